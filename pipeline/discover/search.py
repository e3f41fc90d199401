"""Close the loop: fit the base model, diagnose, add effects greedily, report before and after.

:func:`discover` is the library entry point of ``esmm calibrate --discover``.

Procedure (docs/discover.md):

1. Fit the base model (:func:`esmm.pipeline.calibrate.fit.fit_material`, on
   the thinned fitting samples) and measure its error on every sample, and on
   held-out data (:mod:`.heldout`).
2. Diagnose the residual (:mod:`.diagnose`): size, serial correlation, runs,
   covariates, and the first-order share of each candidate effect.
3. For every candidate that the data can identify: fit each variant (base +
   kept effects + candidate, all parameters free), take the best variant by
   AICc, and if its AICc beats the current model by at least
   ``aicc_threshold`` run the held-out check. An effect is kept only if both
   the AICc and the held-out error say so; among those that pass, the one with
   the lowest AICc is kept. Repeat with what is left, until nothing passes.
4. Report errors before and after, on the fitting data and held out.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..blas import single_threaded_blas
from ..calibrate.config import check_model
from ..calibrate.fit import FitResult, fit_material
from ..calibrate.problem import fibre_directions, file_weights
from ..errors import ConfigError, FitError
from ..materials import get_model
from ..materials.effects import ARTEFACTS, EFFECT_NAMES, MATERIAL_EFFECTS, MaterialEffects
from ..materials.loading import energy_density
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from ..validate import number
from .diagnose import Diagnosis, diagnose
from .estimates import estimates
from .fitted import Fitted, effect_params, finish, fit_spec
from .heldout import Fold, heldout, make_folds
from .model import (
    VARIANTS,
    Bounds,
    Problem,
    Record,
    Spec,
    offset_applicable,
    prepare,
    slack_applicable,
    view_test,
)
from .statistics import information, n_effective

#: default ΔAICc an effect must reach (Burnham & Anderson: > 10 = no support for the simpler model)
AICC_THRESHOLD = -10.0
#: default relative reduction of the held-out NRMSE an effect must reach
MIN_HELDOUT_GAIN = 0.05
#: candidates whose first-order signature explains less of the residual than this are not fitted
MIN_SHARE = 0.005


# --------------------------------------------------------------------------- results
@dataclass
class Candidate:
    """The verdict on one effect (last round it was tried in)."""

    name: str
    kind: str  # "material" or "artefact"
    round: int = 0
    variant: str = ""
    delta_aicc: float | None = None
    delta_bic: float | None = None
    heldout_nrmse: float | None = None
    heldout_gain: float | None = None
    kept: bool = False
    identifiable: bool = True
    applicable: bool = True
    reason: str = ""
    score: float = 0.0
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "kind": self.kind, "round": self.round, "variant": self.variant,
            "delta_aicc": self.delta_aicc, "delta_bic": self.delta_bic,
            "heldout_nrmse": self.heldout_nrmse, "heldout_gain": self.heldout_gain,
            "kept": self.kept, "identifiable": self.identifiable, "applicable": self.applicable,
            "first_order_share": self.score, "reason": self.reason, "params": self.params,
        }


@dataclass
class Trial:
    """A candidate model of one round: the fit, its information and that of the current model."""

    name: str
    fit: Fitted
    info: dict[str, float]
    ref: dict[str, float]  # the current model's, on the candidate's effective sample sizes
    nu: list[float]  # the candidate's effective sample sizes

    @property
    def d_aicc(self) -> float:
        return self.info["aicc"] - self.ref["aicc"]

    @property
    def d_bic(self) -> float:
        return self.info["bic"] - self.ref["bic"]


@dataclass(frozen=True)
class Criteria:
    """When an effect is kept, and when the search stops (see :func:`discover`)."""

    aicc_threshold: float = AICC_THRESHOLD
    min_heldout_gain: float = MIN_HELDOUT_GAIN
    max_effects: int = 4
    min_share: float = MIN_SHARE


@dataclass
class Search:
    """The state of the greedy search: the current model, the verdicts so far, what was kept."""

    base: Fitted
    current: Fitted
    folds: list[Fold]
    candidates: dict[str, Candidate]
    testable: list[str]
    kept: list[str] = field(default_factory=list)
    diagnoses: list[Diagnosis] = field(default_factory=list)
    upgrades: list[str] = field(default_factory=list)

    def gain(self, f: Fitted) -> float:
        """Relative reduction of the held-out NRMSE from the current model to *f*."""
        return 1.0 - f.heldout.nrmse / max(self.current.heldout.nrmse, 1e-300)


@dataclass
class DiscoverResult:
    """Everything :func:`discover` found (see docs/discover.md for the JSON)."""

    model: str
    records: list[Record]
    base: Fitted
    final: Fitted
    kept: list[str]
    candidates: dict[str, Candidate]
    not_identifiable: list[str]
    diagnoses: list[Diagnosis]
    scheme: str
    folds: list[str]
    settings: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    base_fit: Any = None  # the FitResult of the base model

    @property
    def material_effects(self) -> MaterialEffects:
        me = self.final.state.material_effects()
        iv = {e.key: [e.lower, e.upper] for e in self.final.estimates
              if e.key.split(".")[0] in MATERIAL_EFFECTS}
        return MaterialEffects(me.viscoelastic, me.mullins, me.damage, iv)

    @property
    def artefacts(self) -> list[str]:
        return [n for n in self.kept if n in ARTEFACTS]

    def base_params(self, which: str = "final") -> dict[str | None, dict[str, float]]:
        f = self.final if which == "final" else self.base
        return f.state.base


# --------------------------------------------------------------------------- identifiability
def identifiability(records: Sequence[Record]) -> dict[str, tuple[bool, bool, str]]:
    """Can the data show each effect? name -> (applicable, identifiable, reason)."""
    out: dict[str, tuple[bool, bool, str]] = {}
    timed = [r for r in records if r.history]
    rates = sorted({v for r in timed for v in r.cov.rates()})
    several_rates = len(rates) >= 2 and rates[-1] / max(rates[0], 1e-300) >= 1.5
    unloading = any(r.cov.has_unloading for r in timed)
    holds = any(r.cov.has_hold and float(np.nanmax(r.cov.hold_time)) >= 5 * float(np.median(np.diff(r.t)))
                for r in timed)
    below = any(np.any(r.cov.below_max > 0.02) for r in timed)
    if not timed:
        out["viscoelastic"] = (True, False, "not identifiable from these data: no time column, so no rate, "
                               "hold or loading history")
    elif not (several_rates or unloading or holds):
        out["viscoelastic"] = (True, False, "not identifiable from these data: one monotonic ramp at one rate "
                               f"({rates[0] if rates else float('nan'):.3g} /s) cannot separate a rate effect from "
                               "the elastic curve; test at a second rate, or add an unloading or a hold")
    else:
        why = [w for w, ok in (("several rates", several_rates), ("unloading", unloading), ("holds", holds)) if ok]
        out["viscoelastic"] = (True, True, "identifiable: " + ", ".join(why))
    if not timed:
        out["mullins"] = (True, False, "not identifiable from these data: without a time column the row order "
                          "is not a loading history")
    elif not below:
        out["mullins"] = (True, False, "not identifiable from these data: every sample is on the primary "
                          "loading path; Mullins softening shows only on unloading or reloading below a "
                          "previous maximum")
    else:
        out["mullins"] = (True, True, "identifiable: unloading or reloading below a previous maximum")
    spans = [float(r.cov.drive.max()) - 1.0 for r in records]
    if max(spans, default=0.0) < 0.01:
        out["damage"] = (True, False, "not identifiable from these data: the deformation stays below 1 %")
    else:
        out["damage"] = (True, True, "identifiable: the primary loading curve reaches "
                         f"an equivalent stretch of {1 + max(spans):.3g}")
    if any(slack_applicable(r) for r in records):
        out["slack"] = (True, True, "applicable: tension tests from the undeformed state")
    else:
        out["slack"] = (False, False, "not applicable: slack is an artefact of tension tests that start "
                        "from zero displacement; these data have none")
    if any(offset_applicable(r) for r in records):
        out["sensor_offset"] = (True, True, "applicable: the data pass through the undeformed state, where the "
                                "true force is zero")
    else:
        out["sensor_offset"] = (True, False, "not identifiable from these data: no sample near the undeformed "
                                "state, where the true force is known to be zero")
    return out


# --------------------------------------------------------------------------- the loop
def discover(
    tests: Sequence[TensileTest],
    *,
    model: str = "esedf",
    base=None,
    fixed: Mapping[str, float] | None = None,
    free: Sequence[str] = (),
    weights: Mapping[str, float] | Sequence[float] | None = None,
    n_starts: int = 4,
    seed: int = 0,
    max_points: int = 400,
    candidates: Sequence[str] = EFFECT_NAMES,
    aicc_threshold: float = AICC_THRESHOLD,
    min_heldout_gain: float = MIN_HELDOUT_GAIN,
    max_effects: int = 4,
    min_share: float = MIN_SHARE,
    reporter: Reporter | None = None,
) -> DiscoverResult:
    """Find what the base model misses in *tests*, add it, and report before and after.

    Parameters
    ----------
    tests : sequence of TensileTest
        The data (any modes; raw or processed; with or without time).
    model : str
        The base model (``esedf``, ``arruda-boyce``).
    base : FitResult, optional
        A base fit already made (its parameters start the base fit here).
    fixed : mapping, optional
        Base parameters held (SI), as :func:`~esmm.pipeline.calibrate.fit.fit_material`'s ``fixed``.
    free : sequence of str
        Base parameters the model holds by default to fit anyway (``fit_material``'s ``free``).
    weights : mapping or sequence, optional
        Per-file weights, as the calibrate fit.
    n_starts, seed : int
        Starting points of the base fit.
    max_points : int
        Fitting samples per file (thinned; errors use all samples).
    candidates : sequence of str
        Effects to consider (names of :data:`~esmm.pipeline.materials.effects.EFFECT_NAMES`).
    aicc_threshold : float
        An effect must lower the AICc by at least this much (negative number).
    min_heldout_gain : float
        ... and lower the held-out NRMSE by at least this fraction.
    max_effects : int
        Stop after this many effects.
    min_share : float
        Candidates whose first-order signature explains less than this share
        of the residual are rejected without a fit.
    reporter : Reporter, optional

    Returns
    -------
    DiscoverResult
    """
    criteria = Criteria(aicc_threshold, min_heldout_gain, max_effects, min_share)
    with single_threaded_blas():
        return _discover(tests, model=model, base=base, fixed=fixed, free=free, weights=weights, n_starts=n_starts,
                         seed=seed, max_points=max_points, candidates=candidates, criteria=criteria,
                         reporter=reporter)


def _discover(tests, *, model, base, fixed, free, weights, n_starts, seed, max_points, candidates,
              criteria: Criteria, reporter) -> DiscoverResult:
    rep = ensure(reporter)
    t_start = time.perf_counter()
    _check(tests, model=model, candidates=candidates, criteria=criteria, max_points=max_points)
    w = file_weights(tests, weights)
    directions = fibre_directions(tests)
    records = prepare(tests, max_points=max_points, weights=w)
    rep.step(f"discover: {len(tests)} file(s), {sum(t.n for t in tests)} samples, "
             f"{sum(r.fit_idx.size for r in records)} used for fitting")
    # 1. the base model, fitted on the thinned samples, and its held-out error
    base_fit = fit_material([view_test(r) for r in records], model=model, n_starts=n_starts, seed=seed,
                            fixed=fixed, free=tuple(free), weights=w,
                            initial=dict(base.params) if base is not None else None)
    start = _base_model(records, base_fit, fixed, directions)
    scheme, folds = make_folds(records)
    with rep.task("held-out check of the base model", total=1) as adv:
        start.heldout = heldout(start, folds)
        adv(1)
    start.estimates = estimates(start.problem, start.z)
    rep.step(f"base {model}: RMSE {start.errors.rmse:.4g} Pa, NRMSE {start.errors.nrmse:.2%}, "
             f"held-out NRMSE {start.heldout.nrmse:.2%} ({scheme})")
    # 2.-3. add effects, one per round, while one passes both tests
    search = _start_search(start, folds, records, candidates)
    rnd = 1
    while _round(search, rnd, criteria, rep):
        rnd += 1
    _final_verdicts(search, records)
    result = _result(search, base_fit, scheme, t_start, settings={
        "max_points": max_points, "criterion": "AICc", "aicc_threshold": criteria.aicc_threshold,
        "min_heldout_gain": criteria.min_heldout_gain, "n_starts": n_starts, "seed": seed,
        "candidates": list(candidates)})
    rep.step(f"discover: kept {', '.join(search.kept) or 'nothing'}; NRMSE {start.errors.nrmse:.2%} -> "
             f"{search.current.errors.nrmse:.2%}, held-out {start.heldout.nrmse:.2%} -> "
             f"{search.current.heldout.nrmse:.2%} ({result.seconds:.1f} s)")
    return result


def _check(tests, *, model, candidates, criteria: Criteria, max_points) -> None:
    if not tests:
        raise FitError("no tensile data to analyse; give at least one file")
    check_model(model)
    bad = [c for c in candidates if c not in EFFECT_NAMES]
    if bad:
        raise ConfigError(f"candidates: unknown effect {bad[0]!r}; the effects are {', '.join(EFFECT_NAMES)}",
                          parameter="candidates")
    number(criteria.aicc_threshold, "aicc_threshold", hi=0.0, hi_open=True)
    number(criteria.min_heldout_gain, "min_heldout_gain", lo=0.0, hi=1.0, hi_open=True)
    number(max_points, "max_points", lo=20, integer=True)


def _base_model(records: list[Record], base_fit: FitResult, fixed, directions) -> Fitted:
    """The base model refitted on the extended problem, with the effects' data-derived bounds."""
    m = get_model(base_fit.model)
    free = {e.name for e in base_fit.estimates}
    fixed_all = {k: v for k, v in base_fit.params.items() if k not in free}
    fixed_all.update(fixed or {})
    base_params = {None: dict(base_fit.params)}
    if base_fit.directions:
        base_params.update({d: dict(p) for d, p in base_fit.directions.items()})
    bounds = Bounds(records, _largest_energy(m, records, base_params, directions) or 1.0)
    bprob = Problem(m, records, Spec(), fixed=fixed_all, directions=directions, bounds=bounds)
    z, _ = bprob.solve(bprob.set_base(bprob.default_z(), base_params))
    return finish(bprob, z)


def _largest_energy(m, records: list[Record], base_params, directions) -> float:
    """The largest strain energy density [Pa] of the base model on the fitting samples (0 if none is finite)."""
    w_ref = 0.0
    for r in records:
        p = base_params.get(r.key if directions else None, base_params[None])
        with np.errstate(all="ignore"):
            wv = np.asarray(energy_density(m, p, r.test.mode, r.x[r.fit_idx]), float)
        if np.any(np.isfinite(wv)):
            w_ref = max(w_ref, float(np.nanmax(wv[np.isfinite(wv)])))
    return w_ref


def _start_search(start: Fitted, folds: list[Fold], records: list[Record], considered: Sequence[str]) -> Search:
    """Every effect's candidate, with the reason it is not tried where the data cannot show it."""
    ident = identifiability(records)
    cands: dict[str, Candidate] = {}
    for n in EFFECT_NAMES:
        applicable, ok, why = ident[n]
        c = Candidate(n, "material" if n in MATERIAL_EFFECTS else "artefact", identifiable=ok,
                      applicable=applicable)
        if n not in considered:
            c.reason = "not considered (excluded by the caller)"
        elif not applicable or not ok:
            c.reason = why
        cands[n] = c
    testable = [n for n in considered if ident[n][0] and ident[n][1]]
    return Search(start, start, folds, cands, testable)


# --------------------------------------------------------------------------- one round
def _round(s: Search, rnd: int, crit: Criteria, rep) -> bool:
    """Diagnose, try every candidate (and richer variants of kept effects), keep the best that passes.

    Returns False when the search is over.
    """
    remaining = [n for n in s.testable if n not in s.kept]
    diag = diagnose(s.current.problem, s.current.z, candidates=remaining, errors=s.current.errors)
    s.diagnoses.append(diag)
    upgradable = [n for n in s.kept if getattr(s.current.spec, n) < max(VARIANTS[n])]
    if (not remaining and not upgradable) or len(s.kept) >= crit.max_effects:
        return False
    order = [x for x in diag.ranking if x in remaining] + [x for x in remaining if x not in diag.ranking]
    with rep.task(f"round {rnd}: trying {', '.join(order + [u + ' (more terms)' for u in upgradable])}",
                  total=len(order) + len(upgradable)) as adv:
        trials, singles = _try_candidates(s, order, diag, rnd, crit, adv)
        trials += _try_upgrades(s, upgradable, crit, adv)
    trials.sort(key=lambda t: t.d_aicc)
    winner = _heldout_winner(s, trials, rnd, crit)
    for t in trials:  # candidates never reached by the held-out check this round
        c = s.candidates[t.name]
        if t.name != winner and t.name not in s.kept and c.reason.endswith("pending"):
            c.reason = (f"AICc {t.d_aicc:+.1f}, but {winner} explained more in round {rnd}; "
                        "tried again after it")
    if winner is None and len(s.kept) + 2 <= crit.max_effects:
        pair = _try_pairs(singles, s, crit)
        if pair is not None:
            _keep_pair(s, pair, rnd, rep)
            return True
    if winner is None:
        return False
    _keep(s, next(t.fit for t in trials if t.name == winner), winner, rnd, rep)
    return True


def _try_candidates(s: Search, order: list[str], diag: Diagnosis, rnd: int, crit: Criteria, advance,
                    ) -> tuple[list[Trial], dict[str, Trial]]:
    """Fit every remaining candidate; those whose AICc passes go to the held-out check (the trials)."""
    trials: list[Trial] = []
    singles: dict[str, Trial] = {}  # every candidate fitted this round
    for n in order:
        c = s.candidates[n]
        c.round, c.score = rnd, diag.scores.get(n, 0.0)
        if c.score < crit.min_share:
            _too_small(c, s.kept, rnd, crit.min_share)
            advance(1)
            continue
        t = _best_variant(n, VARIANTS[n], s.current, crit.aicc_threshold)
        advance(1)
        if t is None:
            c.reason = "the fit with this effect failed"
            continue
        _record(c, t)
        bad = _offset_inconsistent(t.fit) if n == "sensor_offset" else ""
        if bad:
            c.reason = "rejected: " + bad + "; the offset compensates for misfit instead of correcting the load cell"
            continue
        singles[n] = t
        if not math.isfinite(c.delta_aicc):
            c.delta_aicc = None
            c.reason = "rejected: the information criterion could not be computed for this fit"
        elif c.delta_aicc > crit.aicc_threshold:
            c.reason = (f"rejected: AICc {c.delta_aicc:+.1f} (needs {crit.aicc_threshold:+.0f} or less): "
                        "the improvement does not pay for the extra parameters")
        else:
            c.reason = f"AICc {c.delta_aicc:+.1f}; held-out check pending"
            trials.append(t)
    return trials, singles


def _too_small(c: Candidate, kept: list[str], rnd: int, min_share: float) -> None:
    """The verdict on a candidate whose first-order signature explains too little of the residual."""
    why = (f"its first-order signature explains {100 * c.score:.2f} % of the residual "
           f"(less than {100 * min_share:.1f} %)")
    if c.delta_aicc is not None or c.reason.startswith("rejected:"):
        # keep the verdict of the round in which it was fitted
        c.reason = f"{c.reason.split('; in round')[0]}; in round {rnd}, after {', '.join(kept)}, {why}"
    else:
        c.delta_aicc = c.delta_bic = c.heldout_nrmse = c.heldout_gain = None
        c.reason = f"rejected without a fit: {why}"


def _record(c: Candidate, t: Trial) -> None:
    """Write a fitted candidate's variant, information and parameters into its verdict."""
    c.variant = t.fit.spec.variant_text(c.name)
    c.delta_aicc = t.d_aicc
    c.delta_bic = t.d_bic
    c.params = effect_params(t.fit, c.name)
    c.heldout_nrmse = c.heldout_gain = None


def _try_upgrades(s: Search, upgradable: list[str], crit: Criteria, advance) -> list[Trial]:
    """Richer variants (another Prony term, beta) of the kept effects whose AICc passes."""
    trials = []
    for n in upgradable:
        nxt = [v for v in VARIANTS[n] if v > getattr(s.current.spec, n)]
        t = _best_variant(n, nxt, s.current, crit.aicc_threshold, upgrade=True)
        advance(1)
        if t is not None and math.isfinite(t.d_aicc) and t.d_aicc <= crit.aicc_threshold:
            trials.append(t)
    return trials


def _heldout_winner(s: Search, trials: list[Trial], rnd: int, crit: Criteria) -> str | None:
    """The held-out check, best AICc first: the first trial that passes wins (None: none passes)."""
    for t in trials:
        f = t.fit
        f.heldout = heldout(f, s.folds)
        gain = s.gain(f)
        if t.name in s.kept:  # a variant upgrade of a kept effect
            if gain >= crit.min_heldout_gain:
                s.upgrades.append(f"round {rnd}: {t.name} extended to {f.spec.variant_text(t.name)} (AICc "
                                  f"{t.d_aicc:+.1f}, held-out NRMSE {s.current.heldout.nrmse:.2%} -> "
                                  f"{f.heldout.nrmse:.2%})")
                return t.name
            continue
        c = s.candidates[t.name]
        c.heldout_nrmse, c.heldout_gain = f.heldout.nrmse, gain
        if gain < crit.min_heldout_gain:
            c.reason = (f"rejected: AICc {t.d_aicc:+.1f} favours it but the held-out NRMSE goes "
                        f"{s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%} ({-gain:+.1%}; needs "
                        f"-{crit.min_heldout_gain:.0%} or better): it does not predict data it was not fitted to")
            continue
        return t.name
    return None


def _keep(s: Search, f: Fitted, winner: str, rnd: int, rep) -> None:
    """Make *f* (the current model plus *winner*) the current model."""
    if winner in s.kept:
        rep.step(s.upgrades[-1])
        s.current = f
        return
    c = s.candidates[winner]
    c.kept = True
    kind = "corrected in the data" if winner in ARTEFACTS else "added to the material"
    c.reason = (f"kept ({kind}) in round {rnd}: AICc {c.delta_aicc:+.1f}, held-out NRMSE "
                f"{s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
    rep.step(f"round {rnd}: kept {winner} ({c.variant}): NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
    s.kept.append(winner)
    s.current = f


def _keep_pair(s: Search, pair, rnd: int, rep) -> None:
    """Keep two effects that only passed together."""
    (a, b), f, d_aicc = pair
    for n, other in ((a, b), (b, a)):
        c = s.candidates[n]
        c.kept = True
        c.variant = f.spec.variant_text(n)
        c.heldout_nrmse = f.heldout.nrmse
        c.heldout_gain = s.gain(f)
        kind = "corrected in the data" if n in ARTEFACTS else "added to the material"
        c.reason = (f"kept ({kind}) in round {rnd} together with {other}: neither alone passed, "
                    f"together AICc {d_aicc:+.1f} and held-out NRMSE {s.current.heldout.nrmse:.2%} -> "
                    f"{f.heldout.nrmse:.2%}")
    rep.step(f"round {rnd}: kept {a} and {b} together: NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
    s.kept += [a, b]
    s.current = f


# --------------------------------------------------------------------------- the outcome
def _final_verdicts(s: Search, records: list[Record]) -> None:
    """Final estimates, the kept effects' parameters and variants, and the confounds to warn about."""
    s.current.estimates = estimates(s.current.problem, s.current.z)
    cands = s.candidates
    for n in s.kept:
        cands[n].params = effect_params(s.current, n)
        cands[n].variant = s.current.spec.variant_text(n)
        for u in s.upgrades:
            if f": {n} extended" in u:
                cands[n].reason += f"; {u.split(': ', 1)[1]}"
    # a confound the data cannot resolve: on a single monotonic ramp, damage and relaxation look alike
    if "damage" in s.kept and not cands["viscoelastic"].identifiable and any(r.history for r in records):
        cands["damage"].reason += (
            "; caution: with one monotonic ramp at one rate, damage cannot be told from rate-dependent "
            "relaxation (which is not identifiable here); an unloading-reloading cycle or a second rate "
            "would tell them apart")


def _result(s: Search, base_fit: FitResult, scheme: str, t_start: float, *, settings: dict[str, Any],
            ) -> DiscoverResult:
    cur = s.current
    prob = cur.problem
    not_ident = [n for n in EFFECT_NAMES if s.candidates[n].applicable and not s.candidates[n].identifiable]
    warnings = [f"{e.key} is not identifiable from these data: 95 % interval [{e.lower:.4g}, {e.upper:.4g}]"
                for e in cur.estimates if e.wide and e.key.split(".")[0] in MATERIAL_EFFECTS]
    settings = {**settings, "bounds": prob.bounds.to_dict(), "fixed": dict(prob.fixed), "directions": prob.directions}
    return DiscoverResult(
        model=prob.model.name, records=prob.records, base=s.base, final=cur, kept=s.kept, candidates=s.candidates,
        not_identifiable=not_ident, diagnoses=s.diagnoses, scheme=scheme, folds=[f.name for f in s.folds],
        settings=settings, warnings=warnings, seconds=time.perf_counter() - t_start, base_fit=base_fit,
    )


# --------------------------------------------------------------------------- fitting candidates
def _compared(name: str, f: Fitted, current: Fitted) -> Trial:
    """*f* against *current*, both judged on *f*'s effective sample sizes.

    The candidate's residual is the better estimate of the noise's correlation.
    """
    res = f.problem.fit_residuals(f.z)
    nu = n_effective(res)
    return Trial(name, f, information(res, nu, f.problem.n_params()), _information(current, nu), nu)


def _information(f: Fitted, nu: list[float]) -> dict[str, float]:
    return information(f.problem.fit_residuals(f.z), nu, f.problem.n_params())


def _best_variant(name: str, variants, current: Fitted, aicc_threshold: float, *,
                  upgrade: bool = False) -> Trial | None:
    """Fit the variants of effect *name* in order; stop when one more term stops paying.

    Returns the best variant by AICc (None if no fit succeeded).
    """
    best: Trial | None = None
    prev: Trial | None = None
    for v in variants:
        try:
            f = fit_spec(current.spec.with_(name, v), current, init_from=prev.fit if prev is not None else None)
        except FitError:
            break
        t = _compared(name, f, current)
        # the richer variant must beat the simpler one on the same footing
        if prev is not None and t.info["aicc"] - _information(prev.fit, t.nu)["aicc"] > aicc_threshold:
            break
        if best is None or t.d_aicc < best.d_aicc:
            best = t
        if not upgrade and t.d_aicc > 0 and name != "viscoelastic":
            break  # the simplest variant does not help at all: the richer ones will not either
        prev = t
    return best


def _try_pairs(singles: dict[str, Trial], s: Search, crit: Criteria):
    """When no single effect passes, try two at once (effects that only show together, e.g. slack
    hiding a rate effect). Pairs among the three best single candidates by AICc.

    Returns ((a, b), fit, ΔAICc) of the first pair (best AICc first) that passes both tests, or None.
    """
    current = s.current
    pool = sorted((n for n, t in singles.items() if math.isfinite(t.d_aicc)), key=lambda n: singles[n].d_aicc)[:3]
    tried = []
    for i in range(len(pool)):
        for j in range(i + 1, len(pool)):
            a, b = pool[i], pool[j]
            spec = current.spec.with_(a, getattr(singles[a].fit.spec, a)).with_(b, getattr(singles[b].fit.spec, b))
            try:
                t = _compared(f"{a}+{b}", fit_spec(spec, current), current)
            except FitError:
                continue
            if math.isfinite(t.d_aicc) and t.d_aicc <= crit.aicc_threshold:
                tried.append(((a, b), t.fit, t.d_aicc))
    for (a, b), f, d in sorted(tried, key=lambda t: t[2]):
        f.heldout = heldout(f, s.folds)
        if s.gain(f) >= crit.min_heldout_gain:
            return (a, b), f, d
    return None


def _noise_sd(y: np.ndarray) -> float:
    """Robust standard deviation of white measurement noise (MAD of first differences / sqrt 2)."""
    d = np.diff(np.asarray(y, float))
    d = d[np.isfinite(d)]
    if d.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _offset_inconsistent(f: Fitted) -> str:
    """Why a fitted load-cell offset contradicts the force read before loading ('' if it does not).

    Where a record starts at rest in the reference state, its first sample *is*
    a reading of the offset (the true force is zero): the fitted offset at the
    start must agree with it within 5 noise standard deviations (and 1 % of
    the file's stress scale).
    """
    coefs = f.problem.offsets(f.z)
    for k, r in enumerate(f.problem.records):
        c = coefs[k]
        if c is None:
            continue
        ref = 0.0 if r.test.mode == "simple_shear" else 1.0
        span = float(np.ptp(r.x)) or 1.0
        if abs(float(r.x[0]) - ref) > 1e-3 * span or not r.history:
            continue
        sd = _noise_sd(r.y)
        tol = 5.0 * sd + 0.01 * r.scale
        if abs(float(c[0]) - float(r.y[0])) > tol:
            unit, fac = ("N", r.area) if r.area else ("Pa", 1.0)
            return (f"in {r.name} it needs an offset of {float(c[0]) * fac:+.3g} {unit} at the start, but the "
                    f"load cell read {float(r.y[0]) * fac:+.3g} {unit} there before loading (noise "
                    f"{sd * fac:.2g} {unit})")
    return ""
