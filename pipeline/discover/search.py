"""Close the loop: fit the base model, diagnose, add effects and strain-energy terms greedily, report.

:func:`discover` is the library entry point of ``esmm calibrate --discover``.

Procedure (docs/design/discovery.md, "The loop"):

1. Prepare the records (cut at ruptures, noise estimated from each record
   alone, slips located) and fit the base model
   (:func:`esmm.pipeline.calibrate.fit.fit_material`, on the thinned fitting
   samples); measure its error on every sample and on held-out data
   (:mod:`.heldout`).
2. Diagnose the residual (:mod:`.diagnose`): size against the noise, serial
   correlation, covariates, and each candidate's first-order gain.
3. Every candidate the data can identify (:mod:`.identify`) whose first-order
   gain can pay for one parameter is fitted (base + kept + candidate, all
   parameters free) in each of its variants; those whose fitted improvement
   pays for their parameters in noise units (:func:`~.statistics.noise_test`)
   go, best first, to the held-out check (:func:`~.statistics.paired_heldout`);
   the first that passes is kept. If none passes alone, pairs of the best
   three are tried. Repeat with what is left.
4. Report errors before and after, fitted and held out; and when the residual
   left is still systematic, say where it is and what it follows.
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
from ..checks import number
from ..errors import ConfigError, FitError
from ..materials import get_model
from ..materials.effects import ARTEFACTS, MATERIAL_EFFECTS, MaterialEffects
from ..materials.loading import energy_density
from ..materials.terms import TERMS
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from .diagnose import Diagnosis, diagnose
from .estimates import estimates
from .fitted import Fitted, effect_params, finish, fit_spec
from .heldout import Fold, heldout, make_folds
from .identify import identifiability
from .model import CANDIDATES, VARIANTS, Bounds, Problem, Spec
from .records import Record, fitting_view, prepare
from .trials import (
    HELDOUT_Z,
    MIN_NOISE_UNITS,
    Trial,
    best_variant,
    check_heldout,
    compared,
)

#: the most strain-energy terms fitted per round (the best by their first-order gain)
TERMS_PER_ROUND = 3
#: the most candidates checked on held-out data per round (the best by their fitted improvement)
CHECKS_PER_ROUND = 5


def kind_of(name: str) -> str:
    """``material`` (travels with the material), ``artefact`` (corrected per test) or ``elastic`` (a term)."""
    if name in TERMS:
        return "elastic"
    return "artefact" if name in ARTEFACTS else "material"


# --------------------------------------------------------------------------- results
@dataclass
class Candidate:
    """The verdict on one candidate (last round it was tried in)."""

    name: str
    kind: str  # "material", "artefact" or "elastic"
    round: int = 0
    variant: str = ""
    delta_aicc: float | None = None
    delta_bic: float | None = None
    dbic_noise: float | None = None
    dchi2: float | None = None
    heldout_nrmse: float | None = None
    heldout_gain: float | None = None
    heldout_z: float | None = None
    heldout_noise_units: float | None = None
    kept: bool = False
    identifiable: bool = True
    applicable: bool = True
    reason: str = ""
    score: float = 0.0
    gain_chi2: float = 0.0
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "kind": self.kind, "round": self.round, "variant": self.variant,
            "delta_aicc": self.delta_aicc, "delta_bic": self.delta_bic, "dbic_noise": self.dbic_noise,
            "dchi2": self.dchi2, "heldout_nrmse": self.heldout_nrmse, "heldout_gain": self.heldout_gain,
            "heldout_z": self.heldout_z, "heldout_noise_units": self.heldout_noise_units,
            "kept": self.kept, "identifiable": self.identifiable, "applicable": self.applicable,
            "first_order_share": self.score, "first_order_chi2": self.gain_chi2, "reason": self.reason,
            "params": self.params,
        }


@dataclass(frozen=True)
class Criteria:
    """When a candidate is kept, and when the search stops (see :func:`discover`)."""

    heldout_z: float = HELDOUT_Z
    min_noise_units: float = MIN_NOISE_UNITS
    max_effects: int = 6


@dataclass
class Search:
    """The state of the greedy search: the current model, the verdicts so far, what was kept."""

    base: Fitted
    current: Fitted
    folds: list[Fold]
    candidates: dict[str, Candidate]
    testable: list[str]
    crit: Criteria
    kept: list[str] = field(default_factory=list)
    diagnoses: list[Diagnosis] = field(default_factory=list)
    upgrades: list[str] = field(default_factory=list)

    def gain(self, f: Fitted) -> float:
        """Relative reduction of the held-out NRMSE from the current model to *f*."""
        return 1.0 - f.heldout.nrmse / max(self.current.heldout.nrmse, 1e-300)


@dataclass
class DiscoverResult:
    """Everything :func:`discover` found (see docs/reference/outputs.md for the JSON)."""

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
    outcome: str = ""  # what is left, in words (empty when the residual is noise)

    @property
    def material_effects(self) -> MaterialEffects:
        me = self.final.values.material_effects()
        iv = {e.key: [e.lower, e.upper] for e in self.final.estimates
              if e.key.split(".")[0] in MATERIAL_EFFECTS + ("nonlinear_viscoelastic",)}
        return MaterialEffects(me.viscoelastic, me.mullins, me.damage, iv, me.cyclic_softening, me.permanent_set)

    @property
    def final_model(self) -> str:
        """The name of the final elastic law (the base model plus the kept terms, ``esedf+i2exp``)."""
        return self.final.problem.model.name

    @property
    def artefacts(self) -> list[str]:
        return [n for n in self.kept if n in ARTEFACTS]

    @property
    def terms(self) -> list[str]:
        return [n for n in self.kept if n in TERMS]

    @property
    def cuts(self) -> dict[str, dict[str, Any]]:
        """Records cut at a rupture: file name -> where and how much."""
        return {r.name: r.cut for r in self.records if r.cut}

    def base_params(self, which: str = "final") -> dict[str | None, dict[str, float]]:
        f = self.final if which == "final" else self.base
        return f.values.base


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
    candidates: Sequence[str] = CANDIDATES,
    heldout_z: float = HELDOUT_Z,
    min_noise_units: float = MIN_NOISE_UNITS,
    max_effects: int = 6,
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
        Effects, artefacts and strain-energy terms to consider
        (:data:`~esmm.pipeline.discover.model.CANDIDATES`).
    heldout_z : float
        A candidate must predict held-out data better by this many standard errors ...
    min_noise_units : float
        ... and by at least this many noise variances per held-out sample.
    max_effects : int
        Stop after this many kept candidates.
    reporter : Reporter, optional

    Returns
    -------
    DiscoverResult
    """
    criteria = Criteria(heldout_z, min_noise_units, max_effects)
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
    for r in records:
        if r.cut:
            rep.step(f"{r.name}: ruptured at stretch {r.cut['stretch']:.4g} (t = {r.cut['time']:.4g} s); the "
                     f"{r.cut['dropped']} samples after it are not the material's response and are left out")
    # 1. the base model, fitted on the thinned samples, and its held-out error
    base_fit = fit_material([fitting_view(r) for r in records], model=model, n_starts=n_starts, seed=seed,
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
    # 2.-3. add candidates, one per round, while one passes both tests
    search = _start_search(start, folds, records, candidates, criteria)
    rnd = 1
    while _round(search, rnd, rep):
        rnd += 1
    _backward(search, rep)
    _final_verdicts(search, records)
    result = _result(search, base_fit, scheme, t_start, settings={
        "max_points": max_points, "criterion": "noise-referenced BIC, then held-out paired test",
        "heldout_z": criteria.heldout_z, "min_noise_units": criteria.min_noise_units,
        "max_effects": criteria.max_effects, "n_starts": n_starts, "seed": seed, "candidates": list(candidates),
        "noise_sd": {r.name: r.sigma for r in records}})
    rep.step(f"discover: kept {', '.join(search.kept) or 'nothing'}; NRMSE {start.errors.nrmse:.2%} -> "
             f"{search.current.errors.nrmse:.2%}, held-out {start.heldout.nrmse:.2%} -> "
             f"{search.current.heldout.nrmse:.2%} ({result.seconds:.1f} s)")
    return result


def _check(tests, *, model, candidates, criteria: Criteria, max_points) -> None:
    if not tests:
        raise FitError("no tensile data to analyse; give at least one file")
    check_model(model, terms=False)  # the terms are the discovery's candidates, not its base
    bad = [c for c in candidates if c not in CANDIDATES]
    if bad:
        raise ConfigError(f"candidates: unknown effect or term {bad[0]!r}; the candidates are "
                          f"{', '.join(CANDIDATES)}", parameter="candidates")
    number(criteria.heldout_z, "heldout_z", lo=0.0)
    number(criteria.min_noise_units, "min_noise_units", lo=0.0)
    number(criteria.max_effects, "max_effects", lo=0, integer=True)
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
    z, _ = bprob.solve(bprob.params.set_base(bprob.params.default_z(), base_params))
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


def _start_search(start: Fitted, folds: list[Fold], records: list[Record], considered: Sequence[str],
                  crit: Criteria) -> Search:
    """Every candidate, with the reason it is not tried where the data cannot show it."""
    ident = identifiability(records)
    cands: dict[str, Candidate] = {}
    for n in CANDIDATES:
        applicable, ok, why = ident[n]
        c = Candidate(n, kind_of(n), identifiable=ok, applicable=applicable)
        if n not in considered:
            c.reason = "not considered (excluded by the caller)"
        elif not applicable or not ok:
            c.reason = why
        cands[n] = c
    testable = [n for n in considered if ident[n][0] and ident[n][1]]
    return Search(start, start, folds, cands, testable, crit)


# --------------------------------------------------------------------------- one round
def _remaining(s: Search) -> list[str]:
    """Candidates still to try (not kept). Stretch-dependent relaxation brings relaxation with it."""
    return [n for n in s.testable if n not in s.kept]


def _round(s: Search, rnd: int, rep) -> bool:
    """Diagnose, try every candidate (and richer variants of kept effects), keep the first that passes.

    Returns False when the search is over.
    """
    remaining = _remaining(s)
    diag = diagnose(s.current.problem, s.current.z, candidates=remaining, errors=s.current.errors)
    s.diagnoses.append(diag)
    upgradable = [n for n in s.kept if n in VARIANTS and s.current.spec.variant(n) < max(VARIANTS[n])]
    if (not remaining and not upgradable) or len(s.kept) >= s.crit.max_effects:
        return False
    order = _order(s, remaining, diag, rnd)
    with rep.task(f"round {rnd}: trying {', '.join(order + [u + ' (more terms)' for u in upgradable])}",
                  total=len(order) + len(upgradable)) as adv:
        trials, singles = _try_candidates(s, order, rnd, adv)
        trials += _try_upgrades(s, upgradable, adv)
    trials.sort(key=lambda t: t.dbic)
    _nested_after(trials, "nonlinear_viscoelastic", "viscoelastic")
    winner = _heldout_winner(s, trials, rnd)
    for t in trials:  # candidates never reached by the held-out check this round
        c = s.candidates[t.name]
        if t.name != winner and t.name not in s.kept and c.reason.endswith("pending"):
            c.reason = f"fitted improvement {-t.dbic:+.1f} (noise BIC), but {winner} was kept first in round {rnd}"
    if winner is None and not diag.white and len(s.kept) + 2 <= s.crit.max_effects:
        pair = _try_pairs(singles, s)
        if pair is not None:
            _keep_pair(s, pair, rnd, rep)
            return True
    if winner is None:
        return False
    _keep(s, next(t for t in trials if t.name == winner), rnd, rep)
    return True


def _nested_after(trials: list[Trial], rich: str, simple: str) -> None:
    """Check the simpler of two nested candidates first: the richer one (which always fits at least as
    well) is kept only when the simpler one does not pass."""
    names = [t.name for t in trials]
    if rich in names and simple in names and names.index(rich) < names.index(simple):
        trials.insert(names.index(simple), trials.pop(names.index(rich)))


def _order(s: Search, remaining: list[str], diag: Diagnosis, rnd: int) -> list[str]:
    """Candidates to fit this round, best first-order gain first; those that cannot pay are not fitted.

    A candidate whose first-order gain is below the Schwarz penalty of one
    parameter (ln N) cannot pay for itself; of the strain-energy terms only the
    :data:`TERMS_PER_ROUND` best are fitted (they overlap: the score test ranks them).
    """
    n_fit = sum(r.fit_idx.size for r in s.current.problem.records)
    penalty = math.log(max(n_fit, 2))
    order, n_terms = [], 0
    for n in sorted(remaining, key=lambda n: -diag.gains.get(n, 0.0)):
        c = s.candidates[n]
        c.round, c.score, c.gain_chi2 = rnd, diag.scores.get(n, 0.0), diag.gains.get(n, 0.0)
        if c.gain_chi2 < penalty:
            _too_small(c, s.kept, rnd, penalty)
            continue
        if n in TERMS:
            n_terms += 1
            if n_terms > TERMS_PER_ROUND:
                c.reason = (f"not fitted in round {rnd}: {TERMS_PER_ROUND} strain-energy terms with larger "
                            "first-order gains were tried first")
                continue
        order.append(n)
    return order


def _try_candidates(s: Search, order: list[str], rnd: int, advance) -> tuple[list[Trial], dict[str, Trial]]:
    """Fit every candidate of this round; those whose noise test passes go to the held-out check (the trials)."""
    trials: list[Trial] = []
    singles: dict[str, Trial] = {}
    for n in order:
        c = s.candidates[n]
        variants = VARIANTS.get(n, (1,))
        t = best_variant(n, variants, s.current)
        advance(1)
        if t is None:
            c.reason = "the fit with this candidate failed"
            continue
        _record(c, t)
        singles[n] = t
        if not math.isfinite(t.dbic):
            c.reason = "rejected: the fit's improvement could not be computed"
        elif t.dbic >= 0:
            c.reason = (f"rejected: its fitted improvement (Δχ² {t.noise['dchi2']:.1f} noise variances) does not pay "
                        f"for its parameters (penalty {t.noise['penalty']:.1f}): it fits noise")
        else:
            c.reason = f"fitted improvement Δχ² {t.noise['dchi2']:.4g} (penalty {t.noise['penalty']:.1f}); held-out check pending"
            trials.append(t)
    return trials, singles


def _too_small(c: Candidate, kept: list[str], rnd: int, penalty: float) -> None:
    """The verdict on a candidate whose first-order gain cannot pay for one parameter."""
    why = (f"its first-order signature would remove {c.gain_chi2:.3g} noise variances, less than the penalty of "
           f"one parameter ({penalty:.1f})")
    if c.dbic_noise is not None or c.reason.startswith("rejected:"):
        c.reason = f"{c.reason.split('; in round')[0]}; in round {rnd}, after {', '.join(kept) or 'the base'}, {why}"
    else:
        c.reason = f"rejected without a fit: {why}"


def _record(c: Candidate, t: Trial) -> None:
    """Write a fitted candidate's variant, statistics and parameters into its verdict."""
    c.variant = t.fit.spec.variant_text(c.name)
    c.delta_aicc = t.d_aicc if math.isfinite(t.d_aicc) else None
    c.delta_bic = t.d_bic if math.isfinite(t.d_bic) else None
    c.dbic_noise = t.dbic if math.isfinite(t.dbic) else None
    c.dchi2 = t.noise["dchi2"]
    c.params = effect_params(t.fit, c.name)
    c.heldout_nrmse = c.heldout_gain = c.heldout_z = c.heldout_noise_units = None


def _try_upgrades(s: Search, upgradable: list[str], advance) -> list[Trial]:
    """Richer variants (another Prony term, beta, a drift) of the kept effects that pass the noise test."""
    trials = []
    for n in upgradable:
        nxt = [v for v in VARIANTS[n] if v > s.current.spec.variant(n)]
        t = best_variant(n, nxt, s.current, upgrade=True)
        advance(1)
        if t is not None and math.isfinite(t.dbic) and t.dbic < 0:
            trials.append(t)
    return trials


def _heldout_winner(s: Search, trials: list[Trial], rnd: int) -> str | None:
    """The held-out check, best noise test first: the first trial that passes wins (None: none passes).

    At most :data:`CHECKS_PER_ROUND` trials are checked (the held-out check refits every fold).
    """
    for t in trials[CHECKS_PER_ROUND:]:
        c = s.candidates[t.name]
        if t.name not in s.kept:
            c.reason = (f"fitted improvement Δχ² {t.noise['dchi2']:.4g}, but not checked on held-out data in round "
                        f"{rnd}: {CHECKS_PER_ROUND} candidates with larger fitted improvements were checked first")
    for t in trials[:CHECKS_PER_ROUND]:
        ok = check_heldout(t, s.current, s.folds, z=s.crit.heldout_z, noise_units=s.crit.min_noise_units)
        h = t.heldout
        if t.name in s.kept:  # a variant upgrade of a kept effect
            if ok:
                s.upgrades.append(f"round {rnd}: {t.name} extended to {t.fit.spec.variant_text(t.name)} (held-out "
                                  f"NRMSE {s.current.heldout.nrmse:.2%} -> {t.fit.heldout.nrmse:.2%}, z {h['z']:.1f})")
                return t.name
            continue
        c = s.candidates[t.name]
        c.heldout_nrmse, c.heldout_gain = t.fit.heldout.nrmse, s.gain(t.fit)
        c.heldout_z, c.heldout_noise_units = h["z"], h["noise_units"]
        if not ok:
            c.reason = (f"rejected: the fit improves (Δχ² {t.noise['dchi2']:.4g}) but it does not predict data it "
                        f"was not fitted to: held-out NRMSE {s.current.heldout.nrmse:.2%} -> "
                        f"{t.fit.heldout.nrmse:.2%}, sign test {h['z']:+.1f} and mean {h['z_mean']:+.1f} standard errors "
                        f"(one needs {s.crit.heldout_z:g}, the mean at least 1), {h['noise_units']:+.3g} noise "
                        f"variances per sample (needs {s.crit.min_noise_units:g})")
            continue
        return t.name
    return None


def _keep(s: Search, t: Trial, rnd: int, rep) -> None:
    """Make the trial's model (the current model plus its candidate) the current model."""
    f, winner = t.fit, t.name
    if winner in s.kept:
        rep.step(s.upgrades[-1])
        s.current = f
        return
    c = s.candidates[winner]
    c.kept = True
    kind = {"artefact": "corrected in the data", "material": "added to the material",
            "elastic": "added to the strain energy"}[c.kind]
    c.reason = (f"kept ({kind}) in round {rnd}: fitted Δχ² {t.noise['dchi2']:.4g} noise variances; held-out NRMSE "
                f"{s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%} (sign test {t.heldout['z']:.1f}, mean "
                f"{t.heldout['z_mean']:.1f} standard errors)")
    rep.step(f"round {rnd}: kept {winner} ({c.variant}): NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
    s.kept.append(winner)
    s.current = f
    _sync_kept(s, rnd)


def _sync_kept(s: Search, rnd: int) -> None:
    """Name what the current model holds without having been kept by name: the relaxation that
    stretch-dependent relaxation brings with it."""
    for n in s.current.spec.names():
        if n not in s.kept:
            c = s.candidates[n]
            c.kept, c.variant = True, s.current.spec.variant_text(n)
            c.reason = f"kept in round {rnd}: brought in by nonlinear_viscoelastic, which contains it"
            s.kept.append(n)


def _try_pairs(singles: dict[str, Trial], s: Search):
    """When no single candidate passes and the residual is not noise, two at once (effects that mask
    each other's signature: slack hiding a rate effect, specimen scales hiding a relaxation), among the
    two whose held-out error improved most alone and the two that fitted best.

    Returns ((a, b), trial) of the pair that passes both tests with the lowest held-out error, or None.
    """
    current = s.current
    # the two that, alone, came closest to passing (best held-out gains) and the two that fitted best: a
    # masked effect fits well but predicts badly until its partner is in the model
    fitted = [n for n, t in singles.items() if math.isfinite(t.dbic) and t.dbic < 0]
    by_gain = sorted((n for n in fitted if singles[n].heldout), key=lambda n: -singles[n].heldout["noise_units"])
    by_fit = sorted(fitted, key=lambda n: singles[n].dbic)
    pool = list(dict.fromkeys(by_gain[:2] + by_fit[:2]))
    tried = []
    for i in range(len(pool)):
        for j in range(i + 1, len(pool)):
            a, b = pool[i], pool[j]
            spec = current.spec.with_(a, singles[a].fit.spec.variant(a)).with_(b, singles[b].fit.spec.variant(b))
            try:
                t = compared(f"{a}+{b}", fit_spec(spec, current), current)
            except FitError:
                continue
            if math.isfinite(t.dbic) and t.dbic < 0:
                tried.append(((a, b), t))
    passed = [((a, b), t) for (a, b), t in tried
              if check_heldout(t, current, s.folds, z=s.crit.heldout_z, noise_units=s.crit.min_noise_units)]
    return min(passed, key=lambda p: p[1].fit.heldout.nrmse) if passed else None


def _keep_pair(s: Search, pair, rnd: int, rep) -> None:
    """Keep two candidates that only passed together."""
    (a, b), t = pair
    f = t.fit
    for n, other in ((a, b), (b, a)):
        c = s.candidates[n]
        c.kept = True
        c.variant = f.spec.variant_text(n)
        c.heldout_nrmse, c.heldout_gain = f.heldout.nrmse, s.gain(f)
        c.heldout_z, c.heldout_noise_units = t.heldout["z"], t.heldout["noise_units"]
        kind = "corrected in the data" if n in ARTEFACTS else "added to the material"
        c.reason = (f"kept ({kind}) in round {rnd} together with {other}: neither alone passed, together fitted "
                    f"Δχ² {t.noise['dchi2']:.4g} and held-out NRMSE {s.current.heldout.nrmse:.2%} -> "
                    f"{f.heldout.nrmse:.2%} ({t.heldout['z']:.1f} standard errors)")
    rep.step(f"round {rnd}: kept {a} and {b} together: NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {s.current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
    s.kept += [a, b]
    s.current = f
    _sync_kept(s, rnd)


def _backward(s: Search, rep) -> None:
    """Backward elimination: a kept candidate that, given the others, no longer passes both tests goes.

    The forward search adds one candidate at a time, and what was kept early
    (or in a pair) may have been only a proxy for what came later. Each kept
    candidate, latest first, is judged again against the model without it.
    """
    for name in list(reversed(s.kept)):
        if len(s.kept) < 2 or (name == "viscoelastic" and "nonlinear_viscoelastic" in s.kept):
            continue
        spec = s.current.spec.with_(name, 0)
        try:
            reduced = fit_spec(spec, s.current)
        except FitError:
            continue
        reduced.heldout = heldout(reduced, s.folds)
        t = compared(name, s.current, reduced)
        ok = t.dbic < 0 and check_heldout(t, reduced, s.folds, z=s.crit.heldout_z,
                                          noise_units=s.crit.min_noise_units)
        if ok:
            continue
        c = s.candidates[name]
        c.kept = False
        c.reason = (f"kept in round {c.round}, then removed: given {', '.join(n for n in s.kept if n != name)}, it "
                    f"no longer predicts held-out data better (held-out NRMSE {reduced.heldout.nrmse:.2%} without "
                    f"it, {s.current.heldout.nrmse:.2%} with it)")
        rep.step(f"removed {name}: the others explain what it did")
        s.kept.remove(name)
        s.current = reduced
        _sync_kept(s, c.round)


# --------------------------------------------------------------------------- the outcome
def _final_verdicts(s: Search, records: list[Record]) -> None:
    """Final estimates, the kept candidates' parameters and variants, and the confounds to warn about."""
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


def outcome(diag: Diagnosis, kept: list[str]) -> str:
    """What is left after the search, in words: empty when it is noise, else where it is and what it follows."""
    if diag.white:
        return ""
    st = diag.structure
    n_all = max((v["samples"] for v in st.get("segments", {}).values()), default=0)
    # the segment holding most of the residual, among those that are a part of the data, not all of it
    segs = sorted(((k, v) for k, v in st.get("segments", {}).items() if v["samples"] < 0.9 * n_all or n_all == 0),
                  key=lambda kv: -kv[1]["chi2_share"])
    covs = sorted(st.get("covariates", {}).items(), key=lambda kv: -kv[1])
    words = [f"What is left is systematic, not noise: {diag.chi2:.3g} noise variances per sample "
             f"(lag-1 autocorrelation {diag.lag1:.2f})"]
    if segs:
        name, v = segs[0]
        words.append(f"it is largest in the {name} segment ({100 * v['chi2_share']:.0f} % of it, data "
                     f"{'above' if v['mean_noise_sd'] > 0 else 'below'} the model by {abs(v['mean_noise_sd']):.3g} "
                     "noise standard deviations on average)")
    if covs and covs[0][1] > 0:
        words.append(f"it follows the {covs[0][0]} (R² {covs[0][1]:.2f} of binned means"
                     + (f"; then the {covs[1][0]}, {covs[1][1]:.2f}" if len(covs) > 1 else "") + ")")
    words.append("no candidate in the library explains it on held-out data"
                 + (f" beyond {', '.join(kept)}" if kept else ""))
    return "; ".join(words) + "."


def _result(s: Search, base_fit: FitResult, scheme: str, t_start: float, *, settings: dict[str, Any],
            ) -> DiscoverResult:
    cur = s.current
    prob = cur.problem
    not_ident = [n for n in CANDIDATES if s.candidates[n].applicable and not s.candidates[n].identifiable]
    warnings = [f"{e.key} is not identifiable from these data: 95 % interval [{e.lower:.4g}, {e.upper:.4g}]"
                for e in cur.estimates if e.wide and e.key.split(".")[0] in MATERIAL_EFFECTS]
    settings = {**settings, "bounds": prob.bounds.to_dict(), "fixed": dict(prob.fixed), "directions": prob.directions}
    return DiscoverResult(
        model=prob.base_model.name, records=prob.records, base=s.base, final=cur, kept=s.kept,
        candidates=s.candidates, not_identifiable=not_ident, diagnoses=s.diagnoses, scheme=scheme,
        folds=[f.name for f in s.folds], settings=settings, warnings=warnings,
        seconds=time.perf_counter() - t_start, base_fit=base_fit,
        outcome=outcome(s.diagnoses[-1], s.kept) if s.diagnoses else "",
    )
