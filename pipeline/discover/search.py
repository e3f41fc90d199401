"""Close the loop: fit the base model, diagnose, add effects and strain-energy terms greedily, report.

:func:`discover` is the library entry point of ``esmm calibrate --discover``.

Procedure (docs/design/discovery.md, "The loop"):

1. Prepare the records (cut at ruptures, each record's noise model estimated
   from the record alone, slips located) and fit the base model
   (:func:`esmm.pipeline.calibrate.fit.fit_material`, on the thinned fitting
   samples); measure its error on every sample and on held-out data
   (:mod:`.heldout`).
2. Rounds (:func:`~.rounds.run_round`): diagnose the residual (:mod:`.diagnose`);
   fit every candidate the data can identify (:mod:`.identify`) whose
   first-order gain can pay for one parameter; those that pass the pre-screen
   (:func:`~.statistics.noise_test`) go to the held-out test
   (:func:`~.statistics.heldout_test`), judged at the level the search-wide
   false-positive control gives them (:mod:`.levels`); the first that passes
   is kept. If none passes alone, pairs. Repeat with what is left; then the
   backward elimination.
3. The reported held-out errors before and after are nested
   (:mod:`.nested`): the whole selection is run again inside each outer fold.
4. Report errors before and after, fitted and held out; and when the residual
   left is still systematic, say where it is and what it follows.

AICc and BIC are reported for comparison; they decide nothing.
"""

from __future__ import annotations

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
from .diagnose import Diagnosis
from .estimates import estimates
from .fitted import Fitted, effect_params, finish
from .heldout import cached_heldout, fold_sets
from .levels import ALPHA, Levels
from .model import CANDIDATES, Bounds, Problem, Spec
from .nested import nested_heldout
from .records import Record, fitting_view, prepare
from .rounds import run_search
from .state import Candidate, Criteria, Search
from .trials import MIN_RESOLUTION_UNITS


# --------------------------------------------------------------------------- results
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
    levels: list[Levels] = field(default_factory=list)  # the family-wise levels of each round
    artefact_scheme: str = ""  # the folds per-file artefacts were judged on
    slip_scheme: str = ""  # the folds grip slips were judged on (empty: no record has a slip)
    nested: dict[str, Any] | None = None  # the nested held-out errors before and after (:mod:`.nested`)

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
    alpha: float = ALPHA,
    min_resolution_units: float = MIN_RESOLUTION_UNITS,
    max_effects: int = 6,
    nested: bool = True,
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
    alpha : float
        The probability that the search adds anything to records the current
        model already explains (search-wide, :mod:`.levels`): each candidate's
        held-out p-value must be below its share of it ...
    min_resolution_units : float
        ... and its held-out improvement at least this many squared resolutions per sample (the
        resolution: the larger of the record's noise and the force channel's accuracy,
        :data:`~esmm.pipeline.discover.statistics.FORCE_ACCURACY` of the reading).
    max_effects : int
        Stop after this many kept candidates.
    nested : bool
        Report the held-out errors before and after as nested cross-validation
        (the whole selection run again inside each outer fold, :mod:`.nested`).
    reporter : Reporter, optional

    Returns
    -------
    DiscoverResult
    """
    criteria = Criteria(alpha, min_resolution_units, max_effects)
    with single_threaded_blas():
        return _discover(tests, model=model, base=base, fixed=fixed, free=free, weights=weights, n_starts=n_starts,
                         seed=seed, max_points=max_points, candidates=candidates, criteria=criteria,
                         nested=nested, reporter=reporter)


def _discover(tests, *, model, base, fixed, free, weights, n_starts, seed, max_points, candidates,
              criteria: Criteria, nested: bool, reporter) -> DiscoverResult:
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
        if r.lag:
            rep.step(f"{r.name}: the force lags the stretch by {r.lag['seconds']:.3g} s at its turning points (the "
                     f"acquisition's filter delays): the force was advanced by it, the last {r.lag['dropped']} "
                     "samples dropped")
    # 1. the base model, fitted on the thinned samples, and its held-out error
    base_fit = fit_material([fitting_view(r) for r in records], model=model, n_starts=n_starts, seed=seed,
                            fixed=fixed, free=tuple(free), weights=w,
                            initial=dict(base.params) if base is not None else None)
    start = _base_model(records, base_fit, fixed, directions)
    material, artefact = fold_sets(records)
    with rep.task("held-out check of the base model", total=1) as adv:
        cached_heldout(start, material)
        adv(1)
    start.estimates = estimates(start.problem, start.z)
    rep.step(f"base {model}: RMSE {start.errors.rmse:.4g} Pa, NRMSE {start.errors.nrmse:.2%}, "
             f"held-out NRMSE {start.heldout.nrmse:.2%} ({material.scheme})")
    # 2. add candidates, one per round, while one passes; then the backward elimination
    search = run_search(start, material, artefact, records, candidates, criteria, rep)
    _final_verdicts(search, records)
    result = _result(search, base_fit, t_start, settings={
        "max_points": max_points, "alpha": criteria.alpha, "min_resolution_units": criteria.min_resolution_units,
        "criterion": "held-out test at the search-wide level (pre-screen: noise-referenced BIC)",
        "max_effects": criteria.max_effects, "n_starts": n_starts, "seed": seed, "candidates": list(candidates),
        "noise_sd": {r.name: r.sigma for r in records}})
    if nested:
        result.nested = nested_heldout(search, candidates, criteria, rep)
    result.seconds = time.perf_counter() - t_start
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
    number(criteria.alpha, "alpha", lo=0.0, hi=1.0)
    number(criteria.min_resolution_units, "min_resolution_units", lo=0.0)
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


def _result(s: Search, base_fit: FitResult, t_start: float, *, settings: dict[str, Any]) -> DiscoverResult:
    cur = s.current
    prob = cur.problem
    not_ident = [n for n in CANDIDATES if s.candidates[n].applicable and not s.candidates[n].identifiable]
    warnings = [f"{e.key} is not identifiable from these data: 95 % interval [{e.lower:.4g}, {e.upper:.4g}]"
                for e in cur.estimates if e.wide and e.key.split(".")[0] in MATERIAL_EFFECTS]
    settings = {**settings, "bounds": prob.bounds.to_dict(), "fixed": dict(prob.fixed), "directions": prob.directions}
    return DiscoverResult(
        model=prob.base_model.name, records=prob.records, base=s.base, final=cur, kept=s.kept,
        candidates=s.candidates, not_identifiable=not_ident, diagnoses=s.diagnoses, scheme=s.material.scheme,
        folds=[f.name for f in s.material.folds], settings=settings, warnings=warnings,
        seconds=time.perf_counter() - t_start, base_fit=base_fit,
        outcome=outcome(s.diagnoses[-1], s.kept) if s.diagnoses else "",
        levels=list(s.levels), artefact_scheme=s.artefact.scheme,
        slip_scheme=s.artefact.slip.scheme if s.artefact.slip is not None else "",
    )
