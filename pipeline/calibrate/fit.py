"""Fit a hyperelastic material to tensile tests, jointly across files and loading modes.

The fit minimises a weighted least-squares objective with
:func:`scipy.optimize.least_squares` (trust-region reflective, bounds), from
several starting points, with an optional robust loss. Every file contributes
on an equal footing whatever its number of samples or stress level:

.. math::

    r_{f,k} = \\sqrt{w_f / n_f}\\; \\frac{P_\\text{model}(x_{f,k}; \\theta) - P_{f,k}}{s_f},
    \\qquad s_f = \\max_k |P_{f,k}| ,

with :math:`w_f` the per-file weight (default 1), :math:`n_f` its sample count
and :math:`s_f` its stress scale. Stress-like parameters are optimised in log
space (they span decades: the paper's liver has μ ≈ 3e-6 MPa next to A2 ≈ 452).

Uncertainty: the covariance is :math:`s^2 (J^T J)^{-1}` at the optimum in the
optimiser's coordinates, inflated by :math:`n/n_\\text{eff}` where
:math:`n_\\text{eff}` accounts for the serial correlation of the residuals
(lag-1 autocorrelation ρ: :math:`n_\\text{eff} = n (1-ρ)/(1+ρ)`), because the
samples of a machine record are not independent. 95 % intervals use Student's t;
for log-space parameters they are asymmetric in the parameter itself.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from ..errors import ConfigError, FitError
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest

DIRECTIONS = ("x", "y", "z")
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")

#: a parameter is flagged "not identifiable" when its 95 % interval is wider than
#: this factor (upper/lower for log parameters) or this relative width (linear ones)
WIDE_LOG_FACTOR = 10.0
WIDE_REL_WIDTH = 1.0
#: ... or when it correlates with another beyond this
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
        from ..materials.material import Material

        return Material(model=self.model, params=dict(self.params), directions=self.directions,
                        name=name, source=source)

    def params_for(self, direction: str | None) -> dict[str, float]:
        if direction is None or self.directions is None:
            return dict(self.params)
        return dict(self.directions[direction])


# --------------------------------------------------------------------------- layout
@dataclass
class _Slot:
    name: str
    direction: str | None
    kind: str
    log: bool
    lo: float  # bounds in optimiser coordinates
    hi: float


class _Problem:
    """Maps an optimiser vector to per-direction parameter dicts, and evaluates residuals."""

    def __init__(self, model, tests: Sequence[TensileTest], weights: Sequence[float],
                 fixed: Mapping[str, float], directions: list[str] | None,
                 free: Sequence[str] = ()):
        from ..materials.loading import invariants

        self.model = model
        self.tests = list(tests)
        self.weights = np.asarray(weights, float)
        self.fixed = dict(fixed)
        self.directions = directions
        specs = {p.name: p for p in model.parameters}
        unknown = (set(self.fixed) | set(free)) - set(specs)
        if unknown:
            raise ConfigError(
                f"--fix/--free: unknown parameter(s) {', '.join(sorted(unknown))} for model "
                f"{model.name!r}; its parameters are {', '.join(specs)}"
            )
        # Chain locking: the model must stay finite on every sample.
        self.i1_max = 3.0
        for t in self.tests:
            i1, _ = invariants(t.mode, t.stretch)
            self.i1_max = max(self.i1_max, float(np.nanmax(i1)))
        # Parameters the model marks as not identifiable from homogeneous tests
        # (``fit=False``) are held at their default unless freed.
        for p in model.parameters:
            if not getattr(p, "fit", True) and p.name not in self.fixed and p.name not in free:
                self.fixed[p.name] = float(p.default)
        self.slots: list[_Slot] = []
        for p in model.parameters:
            if p.name in self.fixed:
                continue
            dirs = directions if (directions and getattr(p, "directional", False)) else [None]
            for d in dirs:
                lo, hi = float(p.lower), float(p.upper)
                if p.name == "N" and math.isfinite(model.max_I1({p.name: 1.0, **_defaults(model)})):
                    lo = max(lo, self._n_lower())
                log = (p.kind == "stress" and hi > 0) or (lo > 0 and hi / lo > 1e3)
                if log:
                    # stress-like parameters live in log space; a zero lower bound becomes
                    # a floor twelve decades below the default (or the upper bound)
                    floor = 1e-12 * (p.default if p.default > 0 else hi)
                    lo = max(lo, floor)
                    # a dimensionless range of many decades, e.g. N in (1, 1e8), is
                    # searched in log space too
                    self.slots.append(_Slot(p.name, d, p.kind, True, math.log(lo), math.log(hi)))
                else:
                    self.slots.append(_Slot(p.name, d, p.kind, False, lo, hi))
        self.specs = specs
        # per-file scale and sqrt(w/n)
        self.scale = np.array([max(float(np.max(np.abs(t.stress))), 1e-30) for t in self.tests])
        self.factor = np.sqrt(self.weights / np.array([t.n for t in self.tests], float))
        self.subset: list[np.ndarray | None] = [None] * len(self.tests)

    def _n_lower(self) -> float:
        """Smallest N with the chain not locked at the largest I1 in the data (AB family)."""
        base = _defaults(self.model)
        lo, hi = 1e-6, 1e6
        for _ in range(200):
            mid = math.sqrt(lo * hi)
            if self.model.max_I1({**base, "N": mid}) > self.i1_max * (1 + 1e-6):
                hi = mid
            else:
                lo = mid
            if hi / lo < 1 + 1e-9:
                break
        return hi * (1 + 1e-6)

    # -- coordinates
    def to_params(self, z: np.ndarray) -> dict[str | None, dict[str, float]]:
        base = dict(self.fixed)
        per_dir: dict[str | None, dict[str, float]] = {}
        shared = {}
        directional: dict[str, dict[str, float]] = {}
        for s, v in zip(self.slots, z):
            val = math.exp(v) if s.log else float(v)
            if s.direction is None:
                shared[s.name] = val
            else:
                directional.setdefault(s.direction, {})[s.name] = val
        base.update(shared)
        if self.directions:
            for d in self.directions:
                per_dir[d] = {**base, **directional.get(d, {})}
        per_dir[None] = base
        return per_dir

    def from_params(self, values: Mapping[str, float]) -> np.ndarray:
        z = []
        for s in self.slots:
            v = float(values[s.name])
            z.append(math.log(v) if s.log else v)
        return np.clip(np.array(z), [s.lo for s in self.slots], [s.hi for s in self.slots])

    @property
    def lower(self) -> np.ndarray:
        return np.array([s.lo for s in self.slots])

    @property
    def upper(self) -> np.ndarray:
        return np.array([s.hi for s in self.slots])

    def keys(self) -> list[str]:
        return [s.name if s.direction is None else f"{s.name}[{s.direction}]" for s in self.slots]

    # -- model
    def predict(self, test: TensileTest, params: Mapping[str, float], idx=None) -> np.ndarray:
        from ..materials.loading import nominal_stress

        x = test.stretch if idx is None else test.stretch[idx]
        with np.errstate(all="ignore"):
            return np.asarray(nominal_stress(self.model, params, test.mode, x), float)

    def residuals(self, z: np.ndarray) -> np.ndarray:
        per_dir = self.to_params(z)
        out = []
        for k, t in enumerate(self.tests):
            idx = self.subset[k]
            p = per_dir[t.orientation if self.directions else None]
            pred = self.predict(t, p, idx)
            data = t.stress if idx is None else t.stress[idx]
            n = t.n if idx is None else len(idx)
            f = math.sqrt(self.weights[k] / n)
            r = f * (pred - data) / self.scale[k]
            out.append(r)
        r = np.concatenate(out)
        bad = ~np.isfinite(r)
        if bad.any():  # outside the model's domain (chain locked): a large, smooth-ish penalty
            r[bad] = 1e3
        return r

    def use_subset(self, max_samples: int | None) -> None:
        for k, t in enumerate(self.tests):
            if max_samples is None or t.n <= max_samples:
                self.subset[k] = None
            else:
                self.subset[k] = np.unique(np.linspace(0, t.n - 1, max_samples).round().astype(int))


def _defaults(model) -> dict[str, float]:
    return {p.name: float(p.default) for p in model.parameters}


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
    from ..blas import single_threaded_blas

    # Small dense problems: BLAS threads cost more than they save (docs/calibrate.md).
    with single_threaded_blas():
        return _fit_material(tests, model=model, loss=loss, f_scale=f_scale, n_starts=n_starts,
                             weights=weights, fixed=fixed, initial=initial, free=free, seed=seed,
                             reporter=reporter)


def _fit_material(tests, *, model, loss, f_scale, n_starts, weights, fixed, initial, free, seed,
                  reporter) -> FitResult:
    from ..materials import MODEL_NAMES, get_model

    rep = ensure(reporter)
    t0 = time.perf_counter()
    if not tests:
        raise FitError("no tensile data to fit; give at least one file")
    if model not in MODEL_NAMES:
        raise ConfigError(f"--model: unknown model {model!r}; choose one of {', '.join(MODEL_NAMES)}")
    if loss not in LOSSES:
        raise ConfigError(f"--loss: unknown loss {loss!r}; choose one of {', '.join(LOSSES)}")
    if n_starts < 1:
        raise ConfigError(f"--starts must be at least 1, got {n_starts}")
    m = get_model(model)
    w = _weights(tests, weights)
    directions = _directions(tests)
    prob = _Problem(m, tests, w, fixed or {}, directions, free)
    if not prob.slots:
        raise FitError("every parameter is fixed; nothing to fit")
    p = len(prob.slots)
    n_total = sum(t.n for t in tests)
    if n_total <= p:
        raise FitError(f"{n_total} samples cannot determine {p} parameters; give more data")

    starts = _starting_points(prob, m, initial, n_starts, seed)
    lo, hi = prob.lower, prob.upper
    # Stage 1: every start on a thinned copy of long records.
    prob.use_subset(START_SAMPLES)
    best = None
    with rep.task(f"fitting {model} ({len(starts)} starts)", total=len(starts)) as advance:
        for z0 in starts:
            try:
                sol = optimize.least_squares(
                    prob.residuals, z0, bounds=(lo, hi), loss=loss, f_scale=f_scale,
                    x_scale="jac", method="trf", max_nfev=200 * p,
                )
            except (ValueError, FloatingPointError):
                advance(1)
                continue
            if np.isfinite(sol.cost) and (best is None or sol.cost < best.cost):
                best = sol
            advance(1)
    if best is None:
        raise FitError("the fit failed from every starting point; check the data's units and mode")
    # Stage 2: polish on all samples.
    prob.use_subset(None)
    sol = optimize.least_squares(
        prob.residuals, best.x, bounds=(lo, hi), loss=loss, f_scale=f_scale,
        x_scale="jac", method="trf", max_nfev=400 * p,
    )
    if not np.isfinite(sol.cost):
        raise FitError("the fit diverged; check the data's units and loading mode")

    result = _summarise(prob, m, sol, loss, len(starts))
    result.seconds = time.perf_counter() - t0
    result.fixed = dict(prob.fixed)
    for msg in result.warnings:
        rep.warn(msg)
    rep.step(
        f"fitted {model} to {len(tests)} file(s), {n_total} samples: "
        f"RMSE {result.rmse:.4g} Pa, NRMSE {result.nrmse:.3%}, R² {result.r2:.4f} "
        f"({result.seconds:.2f} s)"
    )
    return result


def _weights(tests, weights) -> list[float]:
    if weights is None:
        return [1.0] * len(tests)
    if isinstance(weights, Mapping):
        out = []
        for t in tests:
            w = weights.get(str(t.source), weights.get(t.source.name, weights.get(t.source.stem, 1.0)))
            out.append(float(w))
    else:
        out = [float(v) for v in weights]
        if len(out) != len(tests):
            raise ConfigError(f"--weights: {len(out)} weights for {len(tests)} files")
    for t, v in zip(tests, out):
        if not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"--weights: the weight of {t.source.name} must be a positive number, got {v}")
    return out


def _directions(tests) -> list[str] | None:
    tags = [t.orientation for t in tests]
    if all(o is None for o in tags):
        return None
    if any(o is None for o in tags):
        untagged = [t.source.name for t in tests if t.orientation is None]
        raise ConfigError(
            f"some files have an orientation and some do not ({', '.join(untagged[:3])} untagged); "
            "tag every file with orientation = x|y|z, or none for an isotropic fit"
        )
    bad = sorted({o for o in tags if o not in DIRECTIONS})
    if bad:
        raise ConfigError(
            f"orientation {bad[0]!r} is not one of x, y, z; angles are read but an anisotropic "
            "fit needs the fibre-frame axes x|y|z"
        )
    return sorted(set(tags))


def _starting_points(prob: _Problem, model, initial, n_starts: int, seed: int) -> list[np.ndarray]:
    lo, hi = prob.lower, prob.upper
    starts = [prob.from_params({**_defaults(model), **prob.fixed})]
    if initial:
        starts.insert(0, prob.from_params({**_defaults(model), **dict(initial)}))
    k = max(0, n_starts - len(starts))
    if k:
        sob = stats.qmc.Sobol(d=len(lo), scramble=True, seed=seed)
        u = sob.random(max(2, 1 << math.ceil(math.log2(max(k, 2)))))[:k]
        # keep away from the bounds themselves
        starts += list(lo + (0.05 + 0.9 * u) * (hi - lo))
    return starts[:max(n_starts, 1)]


def _lag1(r: np.ndarray) -> float:
    if r.size < 3:
        return 0.0
    r = r - r.mean()
    den = float(np.dot(r, r))
    return 0.0 if den == 0 else float(np.dot(r[:-1], r[1:]) / den)


def _summarise(prob: _Problem, model, sol, loss: str, n_starts: int) -> FitResult:
    z = sol.x
    per_dir = prob.to_params(z)
    # Per-file errors, in Pa.
    files: list[FileError] = []
    all_res, all_data = [], []
    rhos, ns = [], []
    for k, t in enumerate(prob.tests):
        p = per_dir[t.orientation if prob.directions else None]
        pred = prob.predict(t, p)
        res = pred - t.stress
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
        rhos.append(_lag1(res))
        ns.append(t.n)
    res = np.concatenate(all_res)
    data = np.concatenate(all_data)
    rmse = float(np.sqrt(np.mean(res**2)))
    nrmse = rmse / (float(np.ptp(data)) or 1.0)
    r2 = 1.0 - float(np.sum(res**2)) / (float(np.sum((data - data.mean()) ** 2)) or 1.0)

    # Covariance in optimiser coordinates, with serial-correlation inflation.
    J = sol.jac
    rvec = prob.residuals(z)
    n, p = J.shape
    dof = max(n - p, 1)
    s2 = float(np.dot(rvec, rvec)) / dof
    rho = float(np.clip(np.average(rhos, weights=ns), 0.0, 0.999))
    inflation = (1 + rho) / (1 - rho)
    warnings: list[str] = []
    try:
        _, sv, Vt = np.linalg.svd(J, full_matrices=False)
        # Directions of parameter space the data do not see (relative singular value
        # below 1e-7): the parameters with weight in them are unbounded; the others get
        # their interval from the pseudo-inverse restricted to the identified subspace.
        null = sv <= 1e-7 * sv.max() if sv.size and sv.max() > 0 else np.ones_like(sv, bool)
        if null.any():
            warnings.append("the Jacobian is (nearly) singular at the optimum: some parameter "
                            "combination has no effect on these data")
        keep = ~null
        cov = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep] * s2 * inflation
        null_weight = np.sum(Vt[null] ** 2, axis=0) if null.any() else np.zeros(p)
        unbounded = null_weight > 1e-2
    except np.linalg.LinAlgError:
        cov = np.zeros((p, p))
        unbounded = np.ones(p, bool)
    sd = np.sqrt(np.clip(np.diag(cov), 0, np.inf))
    sd = np.where(unbounded, np.inf, sd)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    tq = float(stats.t.ppf(0.975, dof))

    estimates: list[ParameterEstimate] = []
    keys = prob.keys()
    for i, s in enumerate(prob.slots):
        at_bound = bool(min(z[i] - s.lo, s.hi - z[i]) <= 1e-6 * max(1.0, abs(s.hi - s.lo)))
        half = tq * sd[i]
        if s.log:
            val = math.exp(z[i])
            lo_v = math.exp(z[i] - half) if math.isfinite(half) else 0.0
            hi_v = math.exp(min(z[i] + half, 700)) if math.isfinite(half) else math.inf
            wide = (not math.isfinite(half)) or (hi_v / max(lo_v, 1e-300) > WIDE_LOG_FACTOR)
        else:
            val = float(z[i])
            lo_v, hi_v = val - half, val + half
            wide = (not math.isfinite(half)) or (2 * half > WIDE_REL_WIDTH * max(abs(val), 1e-12))
        estimates.append(ParameterEstimate(s.name, val, lo_v, hi_v, s.kind, s.direction, at_bound))
        if wide:
            bounded = math.isfinite(half) and (half < 46.0 or not s.log)  # 20 decades
            span = f"[{lo_v:.4g}, {hi_v:.4g}]" if bounded else "unbounded"
            warnings.append(
                f"{keys[i]} is not identifiable from these data: 95 % interval {span} around {val:.4g}"
            )
        if at_bound:
            warnings.append(f"{keys[i]} = {val:.4g} sits at its bound; the optimum may lie outside the allowed range")
    for i in range(p):
        for j in range(i + 1, p):
            if abs(corr[i, j]) > HIGH_CORRELATION:
                warnings.append(
                    f"{keys[i]} and {keys[j]} are correlated at {corr[i, j]:+.3f}: the data "
                    "determine a combination of them, not each one"
                )
    if rho > 0.5:
        warnings.append(
            f"residuals are serially correlated (lag-1 {rho:.2f}): the model misses a systematic "
            "effect; try --discover"
        )
    if not sol.success:
        warnings.append(f"the optimiser stopped early: {sol.message}")

    params = {k: v for k, v in per_dir[None].items()}
    directions = None
    if prob.directions:
        directions = {d: dict(per_dir[d]) for d in prob.directions}
        missing = [d for d in DIRECTIONS if d not in directions]
        if missing:
            # Directions without data: the mean of the tested ones, flagged.
            tested = list(directions.values())
            mean = {k: float(np.mean([q[k] for q in tested])) for k in tested[0]}
            for d in missing:
                directions[d] = dict(mean)
            warnings.append(
                f"no data for fibre direction(s) {', '.join(missing)}: their parameters are the "
                "mean of the tested directions, not a fit"
            )
    drucker = _drucker(model, prob, per_dir)
    if not drucker.get("stable", True):
        warnings.append(f"the fitted material is not Drucker-stable over the data range: {drucker.get('detail', '')}")
    return FitResult(
        model=model.name, params=params, directions=directions, estimates=estimates,
        correlation=corr, free_keys=keys, files=files, rmse=rmse, nrmse=nrmse, r2=r2,
        warnings=warnings, loss=loss, n_starts=n_starts, cost=float(sol.cost), drucker=drucker,
    )


def _drucker(model, prob: _Problem, per_dir) -> dict[str, Any]:
    try:
        from ..materials.stability import drucker_check
    except ImportError:  # pragma: no cover
        return {}
    lo = min(float(np.min(t.stretch)) for t in prob.tests if t.mode != "simple_shear") if any(
        t.mode != "simple_shear" for t in prob.tests) else 1.0
    hi = max(float(np.max(t.stretch)) for t in prob.tests if t.mode != "simple_shear") if any(
        t.mode != "simple_shear" for t in prob.tests) else 1.0
    lo, hi = min(lo, 1.0), max(hi, 1.0)
    out: dict[str, Any] = {"range": [lo, hi], "stable": True, "by_direction": {}}
    for d, params in per_dir.items():
        if prob.directions and d is None:
            continue
        try:
            rep = drucker_check(model, params, lo=lo, hi=hi)
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
    from ..materials import get_model
    from ..materials.loading import nominal_stress

    m = get_model(result.model)
    p = result.params_for(test.orientation if result.directions else None)
    with np.errstate(all="ignore"):
        return np.asarray(nominal_stress(m, p, test.mode, test.stretch), float)
