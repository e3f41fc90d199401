"""Fit a hyperelastic material to tensile tests, jointly across files and loading modes.

The fit minimises the weighted least-squares objective of
:mod:`esmm.pipeline.calibrate.problem` (every file on an equal footing; stress-like
parameters in log space) with :func:`scipy.optimize.least_squares`
(trust-region reflective, bounds), from several starting points, with an
optional robust loss: every start on a thinned copy of long records, the best
polished on all samples.

Uncertainty (:mod:`esmm.pipeline.calibrate.intervals`): the covariance is
:math:`s^2 (J^T J)^{-1}` at the optimum in the optimiser's coordinates, inflated
by :math:`n/n_\\text{eff}` where :math:`n_\\text{eff}` accounts for the serial
correlation of the residuals (lag-1 autocorrelation ρ:
:math:`n_\\text{eff} = n (1-ρ)/(1+ρ)`), because the samples of a machine record
are not independent. 95 % intervals use Student's t; for log-space parameters
they are asymmetric in the parameter itself.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from ..blas import single_threaded_blas
from ..errors import FitError
from ..htmlreport import DIMENSIONLESS, interval_text, quantity_text
from ..materials import get_model
from ..materials.loading import nominal_stress
from ..materials.material import DIRECTIONS, Material
from ..materials.stability import drucker_check
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from .config import check_loss, check_model, check_starts
from .intervals import NULL_WEIGHT, WIDE_LOG_FACTOR, WIDE_REL_WIDTH, identified_covariance, lag1
from .problem import (
    FitProblem,
    ParameterLayout,
    fibre_directions,
    file_weights,
    layout_for,
)

#: a parameter is flagged "not identifiable" when it correlates with another beyond this
#: (or when its interval is wide: :data:`~esmm.pipeline.calibrate.intervals.WIDE_LOG_FACTOR`)
HIGH_CORRELATION = 0.98
#: samples used per file for the multi-start stage (the polish uses all)
START_SAMPLES = 400


# --------------------------------------------------------------------------- data objects
@dataclass(frozen=True)
class ParameterEstimate:
    """A fitted parameter with its 95 % confidence interval (SI units)."""

    name: str
    value: float
    lower: float
    upper: float
    kind: str
    direction: str | None = None  # None = shared (isotropic or not directional)
    at_bound: bool = False
    #: False: a wide or unbounded 95 % interval. A correlation beyond HIGH_CORRELATION is warned but does not
    #: by itself make a parameter undetermined: its marginal interval already carries the correlation.
    identifiable: bool = True

    @property
    def unit(self) -> str:
        """The SI unit of the value: ``"Pa"`` for stress-like parameters, ``"1"`` (dimensionless) otherwise."""
        return "Pa" if self.kind == "stress" else DIMENSIONLESS

    @property
    def key(self) -> str:
        return self.name if self.direction is None else f"{self.name}[{self.direction}]"


@dataclass(frozen=True)
class FileError:
    """Error measures of one file under the fitted material."""

    path: str
    mode: str
    orientation: str | None
    n: int
    weight: float
    rmse: float  # Pa
    nrmse: float  # RMSE / range of measured stress
    r2: float
    max_abs: float  # Pa


@dataclass
class FitResult:
    """The outcome of :func:`fit_material`."""

    model: str
    params: dict[str, float]  # shared/isotropic parameters (SI)
    directions: dict[str, dict[str, float]] | None  # per fibre direction, or None (isotropic)
    estimates: list[ParameterEstimate]
    correlation: np.ndarray  # (p, p) of the free parameters in optimiser coordinates
    free_keys: list[str]
    files: list[FileError]
    rmse: float
    nrmse: float
    r2: float
    warnings: list[str] = field(default_factory=list)
    loss: str = "linear"
    n_starts: int = 0
    cost: float = float("nan")
    seconds: float = 0.0
    drucker: dict[str, Any] = field(default_factory=dict)
    fixed: dict[str, float] = field(default_factory=dict)

    def material(self, *, name: str = "fitted material", source: str = ""):
        """The fitted material as a :class:`~esmm.pipeline.materials.material.Material`."""
        return Material(model=self.model, params=dict(self.params), directions=self.directions,
                        name=name, source=source)

    def held(self) -> list[tuple[str, float, str]]:
        """The parameters held at a value: (name, SI value, unit: ``"Pa"`` or ``"1"``)."""
        kinds = {p.name: p.kind for p in get_model(self.model).parameters}
        return [(k, float(v), "Pa" if kinds.get(k) == "stress" else DIMENSIONLESS) for k, v in self.fixed.items()]

    def params_for(self, direction: str | None) -> dict[str, float]:
        if direction is None or self.directions is None:
            return dict(self.params)
        return dict(self.directions[direction])


# --------------------------------------------------------------------------- fitting
def fit_material(
    tests: Sequence[TensileTest],
    *,
    model: str = "esedf",
    loss: str = "linear",
    f_scale: float = 0.05,
    n_starts: int = 8,
    weights: Mapping[str, float] | Sequence[float] | None = None,
    fixed: Mapping[str, float] | None = None,
    initial: Mapping[str, float] | None = None,
    free: Sequence[str] = (),
    seed: int = 0,
    reporter: Reporter | None = None,
) -> FitResult:
    """Fit one material to all *tests* jointly.

    Parameters
    ----------
    tests : sequence of TensileTest
        The data; any mix of loading modes. Files tagged ``orientation = x|y|z``
        give direction-specific fibre parameters (the model's ``directional``
        parameters); untagged files give an isotropic fit. Tagged and untagged
        files cannot be mixed.
    model : str
        A name from :data:`esmm.pipeline.materials.MODEL_NAMES`.
    loss : {"linear", "soft_l1", "huber", "cauchy", "arctan"}
        Robust loss of :func:`scipy.optimize.least_squares`; ``f_scale`` is its
        soft threshold in units of the normalised residual (fraction of the
        file's stress scale).
    n_starts : int
        Number of starting points (the model defaults, *initial* if given, and a
        scrambled Sobol sample of the bounds).
    weights : mapping of file name or path to weight, or sequence, optional
        Per-file weights (default 1).
    fixed : mapping, optional
        Parameters held at a value (SI units), e.g. ``{"f": 0.0019}``.
    initial : mapping, optional
        A starting point (SI units).
    free : sequence of str
        Parameters the model holds by default (``Parameter.fit`` is False, e.g. the
        ESEDF's fibre fraction f, of which only products are identifiable) to fit anyway.
    seed : int
        Seed of the starting-point sample.

    Returns
    -------
    FitResult
    """
    # Small dense problems: BLAS threads cost more than they save (:mod:`esmm.pipeline.blas`).
    with single_threaded_blas():
        return _fit_material(tests, model=model, loss=loss, f_scale=f_scale, n_starts=n_starts,
                             weights=weights, fixed=fixed, initial=initial, free=free, seed=seed,
                             reporter=reporter)


def _fit_material(tests, *, model, loss, f_scale, n_starts, weights, fixed, initial, free, seed,
                  reporter) -> FitResult:
    rep = ensure(reporter)
    t0 = time.perf_counter()
    prob = _problem(tests, model=model, loss=loss, n_starts=n_starts, weights=weights, fixed=fixed, free=free)
    m = prob.model
    starts = _starting_points(prob.layout, initial, n_starts, seed)
    best = _best_start(prob, starts, loss=loss, f_scale=f_scale, reporter=rep)
    sol = _polish(prob, best.x, loss=loss, f_scale=f_scale)
    result = _summarise(prob, sol, loss, len(starts))
    result.seconds = time.perf_counter() - t0
    result.fixed = dict(prob.layout.fixed)
    for msg in result.warnings:
        rep.warn(msg)
    rep.step(
        f"fitted {m.name} to {len(tests)} file(s), {sum(t.n for t in tests)} samples: "
        f"RMSE {quantity_text(result.rmse, 'Pa')}, NRMSE {result.nrmse:.3%}, R² {result.r2:.4f} "
        f"({result.seconds:.2f} s)"
    )
    return result


def _problem(tests, *, model, loss, n_starts, weights, fixed, free) -> FitProblem:
    """Check the options and build the problem (ConfigError/FitError naming what is wrong)."""
    if not tests:
        raise FitError("no tensile data to fit; give at least one file")
    check_model(model)
    check_loss(loss)
    check_starts(n_starts)
    m = get_model(model)
    w = file_weights(tests, weights)
    layout = layout_for(m, tests, fixed=fixed or {}, directions=fibre_directions(tests), free=free)
    p = len(layout.slots)
    if not p:
        raise FitError("every parameter is fixed; nothing to fit")
    n_total = sum(t.n for t in tests)
    if n_total <= p:
        raise FitError(f"{n_total} sample{'s' if n_total != 1 else ''} cannot determine {p} parameters; give more data")
    return FitProblem(layout, tests, w)


def _least_squares(prob: FitProblem, z0, *, loss: str, f_scale: float, max_nfev: int):
    with np.errstate(over="ignore"):            # a trial step whose cost overflows is rejected by trf itself
        return optimize.least_squares(
            prob.residuals, z0, bounds=(prob.layout.lower, prob.layout.upper), loss=loss, f_scale=f_scale,
            x_scale="jac", method="trf", max_nfev=max_nfev,
        )


def _best_start(prob: FitProblem, starts, *, loss: str, f_scale: float, reporter):
    """Stage 1: every start on a thinned copy of long records; the solution of least cost."""
    p = len(prob.layout.slots)
    prob.use_subset(START_SAMPLES)
    best = None
    with reporter.task(f"fitting {prob.model.name} ({len(starts)} starts)", total=len(starts)) as advance:
        for z0 in starts:
            try:
                sol = _least_squares(prob, z0, loss=loss, f_scale=f_scale, max_nfev=200 * p)
            except (ValueError, FloatingPointError):
                advance(1)
                continue
            if np.isfinite(sol.cost) and (best is None or sol.cost < best.cost):
                best = sol
            advance(1)
    if best is None:
        raise FitError("the fit failed from every starting point; check the data's units and mode")
    return best


def _polish(prob: FitProblem, z0, *, loss: str, f_scale: float):
    """Stage 2: polish on all samples."""
    prob.use_subset(None)
    sol = _least_squares(prob, z0, loss=loss, f_scale=f_scale, max_nfev=400 * len(prob.layout.slots))
    if not np.isfinite(sol.cost):
        raise FitError("the fit diverged; check the data's units and loading mode")
    return sol


def _starting_points(layout: ParameterLayout, initial, n_starts: int, seed: int) -> list[np.ndarray]:
    lo, hi = layout.lower, layout.upper
    defaults = layout.model.defaults()
    starts = [layout.from_params({**defaults, **layout.fixed})]
    if initial:
        starts.insert(0, layout.from_params({**defaults, **dict(initial)}))
    k = max(0, n_starts - len(starts))
    if k:
        sob = stats.qmc.Sobol(d=len(lo), scramble=True, seed=seed)
        u = sob.random(max(2, 1 << math.ceil(math.log2(max(k, 2)))))[:k]
        # keep away from the bounds themselves
        starts += list(lo + (0.05 + 0.9 * u) * (hi - lo))
    return starts[:max(n_starts, 1)]


# --------------------------------------------------------------------------- summary
def _summarise(prob: FitProblem, sol, loss: str, n_starts: int) -> FitResult:
    per_dir = prob.layout.to_params(sol.x)
    files, res, data, rho = _file_errors(prob, per_dir)
    rmse = float(np.sqrt(np.mean(res**2)))
    nrmse = rmse / (float(np.ptp(data)) or 1.0)
    r2 = 1.0 - float(np.sum(res**2)) / (float(np.sum((data - data.mean()) ** 2)) or 1.0)
    estimates, corr, warnings = _estimates(prob, sol, rho)
    if rho > 0.5:
        warnings.append(
            f"residuals are serially correlated (lag-1 {rho:.2f}): the model misses a systematic "
            "effect; the discovery of missing effects may find it (docs/guide/discover.md)"
        )
    if not sol.success:
        warnings.append(f"the optimiser stopped early: {sol.message}")
    directions = _all_directions(prob, per_dir, warnings)
    drucker = _drucker(prob, per_dir)
    if not drucker.get("stable", True):
        warnings.append(f"the fitted material is not Drucker-stable over the data range: {drucker.get('detail', '')}")
    return FitResult(
        model=prob.model.name, params=dict(per_dir[None]), directions=directions, estimates=estimates,
        correlation=corr, free_keys=prob.layout.keys(), files=files, rmse=rmse, nrmse=nrmse, r2=r2,
        warnings=warnings, loss=loss, n_starts=n_starts, cost=float(sol.cost), drucker=drucker,
    )


def _file_errors(prob: FitProblem, per_dir) -> tuple[list[FileError], np.ndarray, np.ndarray, float]:
    """Per-file errors [Pa], the pooled residuals and data, and the mean lag-1 autocorrelation."""
    files: list[FileError] = []
    all_res, all_data, rhos, ns = [], [], [], []
    for k, t in enumerate(prob.tests):
        res = prob.predict(t, prob.params_of(per_dir, t)) - t.stress
        all_res.append(res)
        all_data.append(t.stress)
        rng = float(np.ptp(t.stress)) or 1.0
        rmse = float(np.sqrt(np.mean(res**2)))
        ss_tot = float(np.sum((t.stress - t.stress.mean()) ** 2)) or 1.0
        files.append(FileError(
            path=str(t.source), mode=t.mode, orientation=t.orientation, n=t.n,
            weight=float(prob.weights[k]), rmse=rmse, nrmse=rmse / rng,
            r2=1.0 - float(np.sum(res**2)) / ss_tot, max_abs=float(np.max(np.abs(res))),
        ))
        rhos.append(lag1(res))
        ns.append(t.n)
    rho = float(np.clip(np.average(rhos, weights=ns), 0.0, 0.999))
    return files, np.concatenate(all_res), np.concatenate(all_data), rho


def _estimates(prob: FitProblem, sol, rho: float) -> tuple[list[ParameterEstimate], np.ndarray, list[str]]:
    """Parameter estimates with 95 % intervals, their correlation, and identifiability warnings."""
    z, J = sol.x, sol.jac
    rvec = prob.residuals(z)
    n, p = J.shape
    dof = max(n - p, 1)
    s2 = float(np.dot(rvec, rvec)) / dof
    warnings: list[str] = []
    try:
        cov, null = identified_covariance(J, s2, (1 + rho) / (1 - rho))
        if null.shape[0]:
            warnings.append("the Jacobian is (nearly) singular at the optimum: some parameter "
                            "combination has no effect on these data")
        unbounded = _unbounded_columns(null, p)
    except np.linalg.LinAlgError:
        cov = np.zeros((p, p))
        unbounded = np.ones(p, bool)
    sd = np.sqrt(np.clip(np.diag(cov), 0, np.inf))
    sd = np.where(unbounded, np.inf, sd)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    tq = float(stats.t.ppf(0.975, dof))
    estimates = [_estimate(s, z[i], tq * sd[i], warnings) for i, s in enumerate(prob.layout.slots)]
    keys = prob.layout.keys()
    for i in range(p):
        for j in range(i + 1, p):
            if abs(corr[i, j]) > HIGH_CORRELATION:
                warnings.append(
                    f"{keys[i]} and {keys[j]} are correlated at {corr[i, j]:+.3f}: the data "
                    "determine a combination of them, not each one"
                )
    return estimates, corr, warnings


def _unbounded_columns(null: np.ndarray, p: int) -> np.ndarray:
    """Which of the *p* coordinates have weight in the unidentified directions *null*."""
    null_weight = np.sum(null**2, axis=0) if null.shape[0] else np.zeros(p)
    return null_weight > NULL_WEIGHT


def _estimate(s, zi: float, half: float, warnings: list[str]) -> ParameterEstimate:
    """One slot's estimate and 95 % interval (half-width *half* in optimiser coordinates)."""
    at_bound = bool(min(zi - s.lo, s.hi - zi) <= 1e-6 * max(1.0, abs(s.hi - s.lo)))
    if s.log:
        val = math.exp(zi)
        lo_v = math.exp(zi - half) if math.isfinite(half) else 0.0
        hi_v = math.exp(min(zi + half, 700)) if math.isfinite(half) else math.inf
        wide = (not math.isfinite(half)) or (hi_v / max(lo_v, 1e-300) > WIDE_LOG_FACTOR)
    else:
        val = float(zi)
        lo_v, hi_v = val - half, val + half
        wide = (not math.isfinite(half)) or (2 * half > WIDE_REL_WIDTH * max(abs(val), 1e-12))
    unit = "Pa" if s.kind == "stress" else DIMENSIONLESS
    if wide:
        bounded = math.isfinite(half) and (half < 46.0 or not s.log)  # 20 decades
        span = interval_text(lo_v, hi_v, unit, like=val) if bounded else "unbounded"
        warnings.append(f"{s.key} is not identifiable from these data: 95 % interval {span} around "
                        f"{quantity_text(val, unit)}")
    if at_bound:
        warnings.append(f"{s.key} = {quantity_text(val, unit)} sits at its bound; the optimum may lie outside "
                        "the allowed range")
    return ParameterEstimate(s.name, val, lo_v, hi_v, s.kind, s.direction, at_bound, identifiable=not wide)


def _all_directions(prob: FitProblem, per_dir, warnings: list[str]) -> dict[str, dict[str, float]] | None:
    """Parameters of every fibre direction (None if isotropic); untested ones get the tested mean."""
    if not prob.layout.directions:
        return None
    directions = {d: dict(per_dir[d]) for d in prob.layout.directions}
    missing = [d for d in DIRECTIONS if d not in directions]
    if missing:
        tested = list(directions.values())
        mean = {k: float(np.mean([q[k] for q in tested])) for k in tested[0]}
        for d in missing:
            directions[d] = dict(mean)
        warnings.append(
            f"no data for fibre direction(s) {', '.join(missing)}: their parameters are the "
            "mean of the tested directions, not a fit"
        )
    return directions


def _drucker(prob: FitProblem, per_dir) -> dict[str, Any]:
    """Drucker stability of the fitted material over the stretch range of the data (shear excluded)."""
    stretched = [t for t in prob.tests if t.mode != "simple_shear"]
    lo = min(float(np.min(t.stretch)) for t in stretched) if stretched else 1.0
    hi = max(float(np.max(t.stretch)) for t in stretched) if stretched else 1.0
    lo, hi = min(lo, 1.0), max(hi, 1.0)
    out: dict[str, Any] = {"range": [lo, hi], "stable": True, "by_direction": {}}
    for d, params in per_dir.items():
        if prob.layout.directions and d is None:
            continue
        try:
            rep = drucker_check(prob.model, params, lo=lo, hi=hi)
        except Exception as exc:  # noqa: BLE001 - a check must not break a fit
            out["detail"] = f"check failed: {exc}"
            continue
        stable = bool(getattr(rep, "stable", True))
        out["by_direction"][d or "iso"] = stable
        if not stable:
            out["stable"] = False
            out["detail"] = str(getattr(rep, "summary", rep))
    return out


def predict(result: FitResult, test: TensileTest) -> np.ndarray:
    """Nominal stress [Pa] of *test*'s samples under the fitted material."""
    m = get_model(result.model)
    p = result.params_for(test.orientation if result.directions else None)
    with np.errstate(all="ignore"):
        return np.asarray(nominal_stress(m, p, test.mode, test.stretch), float)
