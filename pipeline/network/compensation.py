r"""Volumetric compensation: calibrate the network on a virtual tensile test.

The ESMM spring stiffness :math:`k_{ij} = v_{ij}\mu_e(\lambda)` with
:math:`V_{ij} = \sum_{t \ni ij} V_t/6` makes the network far softer than the
tissue: in small strain an affine, isotropically oriented edge set stores
:math:`\tfrac{1}{15}(\operatorname{tr}^2\varepsilon + 2\,\varepsilon:\varepsilon)\,E/2`
per volume, i.e. Lamé constants :math:`\lambda_L = \mu_L = E/15` and a Young's
modulus :math:`E/6` (Poisson ratio 1/4, the Cauchy relation of central-force
networks). Nodal relaxation softens it a little more, and at finite stretch the
off-axis springs are stretched less than the specimen, so a stiffening tissue
is matched worse the further it is stretched (docs/model-tables.md).

:func:`calibrate_compensation` fixes both with one numerical test per mesh:

1. **Scalar factor** :math:`c`: a small-strain test (stretch :math:`1+10^{-4}`)
   gives :math:`c = P_{cont}/P_{net}`; it multiplies every :math:`v_{ij}`
   (``StiffnessTables.volume_factor``). Under displacement control the
   network's stress is exactly proportional to :math:`c`.
2. **Stretch-dependent correction** :math:`g(\lambda)`, :math:`g(1) = 1`: the
   law's table row is multiplied by :math:`g` at each grid node. :math:`g` is
   found by the fixed-point iteration
   :math:`g_{m+1}(\lambda_k) = g_m(\lambda_k)\,P_{cont}(\lambda_k)/P_{net,m}(\lambda_k)`
   at the test stretches (tension up to ``tension``, compression down to
   ``compression``), smooth between them (monotone cubic in log g) and held
   constant beyond them. It
   converges because the axial force at specimen stretch :math:`\lambda` comes
   mostly from springs near the axis, whose stretch is :math:`\lambda`.

Both are properties of the mesh (element shape statistics and size relative to
the specimen) and of the law; the record stored in the tables' metadata says
on what specimen they were found.

:func:`compensate` is the policy ``esmm prepare`` and ``esmm tables`` share:
the calibration range (:data:`DEFAULT_RANGE`, clipped to the grid), the
specimen (:func:`specimen_for`, :data:`DEFAULT_RADIUS_ELEMENTS`) and the cache
of calibrations (:mod:`~esmm.pipeline.network.compensation_policy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, SimulationError
from ..progress import ensure
from ..validate import number
from . import compensation_policy as policy
from .compensation_policy import DEFAULT_RADIUS_ELEMENTS, DEFAULT_RANGE, RADIUS_ELEMENTS_RANGE
from .loadcases import virtual_shear_test
from .tables import LAWS, StiffnessTables
from .tensile_test import (
    Specimen,
    TensileResult,
    continuum_stress,
    cylinder_specimen,
    virtual_tensile_test,
)
from .volume import VolumeSpec

__all__ = ["Compensation", "CompensationResult", "calibrate_compensation", "compensate", "correction_on_grid",
           "specimen_for"]

#: Small-strain stretch (and amount of shear) of the scalar calibration.
SMALL_STRAIN = 1e-4
#: Amounts of simple shear the calibrated network is checked at (with the volume term).
SHEAR_CHECK = (0.1, 0.2, 0.3, 0.4)
#: The small-strain load cases of the scalar factor with the volume term, and their weights: the
#: specimen's axial mode and its two shear planes weigh 1 : 2 : 2, the isotropic average of the
#: five deviatoric modes of a transversely isotropic (cylinder) network (docs/model-tables.md §4b).
SCALAR_CASES = (("tension", 1.0), ("xy", 2.0), ("xz", 2.0))


@dataclass(frozen=True, eq=False)
class CompensationResult:
    """What :func:`calibrate_compensation` found.

    Attributes
    ----------
    law : str
    factor : float
        Scalar :math:`c` on :math:`v_{ij}`.
    knots : ndarray, shape (k,)
        Stretches where :math:`g` was calibrated (including 1).
    g : ndarray, shape (k,)
        :math:`g` at the knots.
    before, scalar, after : TensileResult
        Tests of the raw network (springs alone, :math:`c = 1`; without a
        volume term derived exactly from the scalar run), with :math:`c` only,
        and with :math:`c` and :math:`g` (both with the volume term, if any).
        Tension and compression points are concatenated (compression first).
    iterations : int
        Fixed-point iterations used.
    converged : bool
        True when the largest relative error is below ``tol``.
    specimen : dict
        :meth:`Specimen.describe`.
    volume : dict or None
        The volume term's :meth:`VolumeSpec.describe` (None: springs only).
    small_strain : dict
        The scalar calibration: ``factor``, ``balance`` (c over the tension
        factor), the factor of each load case (``cases``) and their ``weights``.
    checks : dict
        Load cases the calibration was checked on but not fitted to
        (``"shear_xz"``, ``"shear_xy"``: simple shear, errors per amount of shear).
    """

    law: str
    factor: float
    knots: np.ndarray
    g: np.ndarray
    before: TensileResult
    scalar: TensileResult
    after: TensileResult
    iterations: int
    converged: bool
    specimen: dict[str, Any] = field(default_factory=dict)
    volume: dict[str, Any] | None = None
    small_strain: dict[str, Any] = field(default_factory=dict)
    checks: dict[str, Any] = field(default_factory=dict)

    def record(self) -> dict[str, Any]:
        """JSON-serialisable summary (stored in ``tables.metadata["compensation"]``)."""
        def errs(r: TensileResult) -> dict[str, float]:
            return {"max_abs_rel_error": r.max_abs_rel_error, "rms_rel_error": r.rms_rel_error}

        return {
            "method": "virtual uniaxial test on a gmsh cylinder (pipeline/network/compensation.py): "
                      "scalar factor from a small-strain test (with the volume term: the weighted geometric mean "
                      "of small-strain tension and simple shear in two planes), stretch-dependent correction by "
                      "fixed-point iteration on tension and compression",
            "law": self.law, "volume_factor": self.factor,
            "knots": self.knots.tolist(), "g": self.g.tolist(),
            "stretch_range": [float(self.after.stretch.min()), float(self.after.stretch.max())],
            "iterations": self.iterations, "converged": self.converged,
            "errors_before": errs(self.before), "errors_scalar": errs(self.scalar),
            "errors_after": errs(self.after), "specimen": self.specimen,
            "volume_term": self.volume, "small_strain": self.small_strain, "checks": self.checks,
            "volume_ratio_after": None if self.after.volume_ratio is None else
            [float(self.after.volume_ratio.min()), float(self.after.volume_ratio.max())],
        }


def correction_on_grid(tables: StiffnessTables, knots, g) -> np.ndarray:
    """:math:`g` on the tables' grid, shape (n,): smooth (C1) through *knots*, constant beyond.

    ``log g`` is interpolated by a monotone cubic (PCHIP) through the knots and
    one extra knot beyond each end (one knot spacing further, with the end
    value), so that g levels off smoothly at the ends of the calibrated range
    and stays constant beyond. A piecewise-linear g would put a jump of the
    spring tangent stiffness at every knot, which makes Newton's method cycle
    on fine networks.
    """
    from scipy.interpolate import PchipInterpolator

    knots = np.asarray(knots, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    order = np.argsort(knots)
    k, lg = knots[order], np.log(g[order])
    if k.size < 2:
        return np.full(tables.n, float(g[0]) if g.size else 1.0)
    k = np.concatenate([[k[0] - (k[1] - k[0])], k, [k[-1] + (k[-1] - k[-2])]])
    lg = np.concatenate([[lg[0]], lg, [lg[-1]]])
    lam = np.clip(tables.lam, k[0], k[-1])
    return np.exp(PchipInterpolator(k, lg)(lam))


def _stretches(end: float | None, spacing: float, *, tension: bool, tables: StiffnessTables) -> np.ndarray:
    """Test stretches of one side, from 1 to *end* in steps of about *spacing*."""
    if end is None:
        return np.zeros(0)
    if tension:
        if not (1.0 < end <= tables.lam_max):
            raise ConfigError(f"tension: calibration stretch {end:g} must lie in (1, {tables.lam_max:.4g}] "
                              "(the tables' grid)")
    elif not (tables.lam_min <= end < 1.0):
        raise ConfigError(f"compression: calibration stretch {end:g} must lie in "
                          f"[{tables.lam_min:.4g}, 1) (the tables' grid)")
    steps = max(2, int(math.ceil(abs(end - 1.0) / spacing - 1e-9)))
    return 1.0 + (end - 1.0) * np.arange(1, steps + 1) / steps


def calibrate_compensation(tables: StiffnessTables, specimen: Specimen, *, law: str | None = None,
                           material=None, tension: float | None = 1.3, compression: float | None = 0.9,
                           spacing: float = 0.02, tol: float = 0.01, max_iter: int = 8,
                           rtol: float = 1e-8, volume: VolumeSpec | None = None, shear_check=SHEAR_CHECK,
                           reporter=None) -> tuple[StiffnessTables, CompensationResult]:
    """Find the scalar factor and the stretch correction of *law* on *specimen*.

    Parameters
    ----------
    tables : StiffnessTables
        Material tables; their current compensation for *law* is replaced.
    specimen : Specimen
        From :func:`~esmm.pipeline.network.tensile_test.cylinder_specimen`.
    law : {"secant", "energy"}, optional
        Default: ``tables.default_law``.
    material : Material, optional
        Continuum reference; default the tables' own stress along z.
    tension, compression : float or None
        Largest and smallest calibration stretch (None: skip that side; the
        correction is then 1 on that side).
    spacing : float
        Approximate stretch step between test points (= knots of g).
    tol : float
        Stop when every relative stress error (against the target) is below *tol*.
    max_iter : int
        Fixed-point iterations at most; the best correction found is kept.
    rtol : float
        Equilibrium tolerance of the virtual tests (see
        :func:`~esmm.pipeline.network.tensile_test.virtual_tensile_test`).
    volume : VolumeSpec, optional
        The volume term the network will carry (:mod:`~esmm.pipeline.network.volume`);
        every test then includes it, and the scalar factor balances two load
        cases (uniaxial tension and simple shear, module doc).
    shear_check : sequence of float, optional
        Amounts of shear at which the calibrated network is checked against
        the material (with *volume* and *material*; empty: no check).

    Returns
    -------
    (StiffnessTables, CompensationResult)
        The compensated tables (``metadata["compensation"]`` holds the record)
        and the details.
    """
    rep = ensure(reporter)
    law = tables.check_law(law)
    _check_options(tol, max_iter, spacing)
    lam_t = _stretches(tension, spacing, tension=True, tables=tables)
    lam_c = _stretches(compression, spacing, tension=False, tables=tables)
    if lam_t.size + lam_c.size == 0:
        raise ConfigError("tension/compression: give at least one side to calibrate on")
    base = tables.with_compensation(1.0, correction={law: np.ones(tables.n)})

    def reference(lam):
        if material is not None:
            return continuum_stress(material, lam)
        return np.interp(lam, base.lam, base.material_stress[2])

    # 1. scalar factor from small-strain tests (tension; with the volume term also simple shear)
    scalar = _scalar_factor(specimen, base, law, material, volume, reference)
    c, balance = scalar["factor"], scalar["balance"]
    rep.step(f"compensation ({law}): scalar factor c = {c:.4f} from small-strain "
             + ", ".join(f"{k} {v:.4f}" for k, v in scalar["cases"].items()))

    # 2. stretch correction by fixed-point iteration on the curve's shape: the target is the
    # material's stress times the small-strain balance of the load cases.
    knots = np.concatenate([lam_c[::-1], [1.0], lam_t])
    g = np.ones_like(knots)
    best: tuple[float, np.ndarray, TensileResult] | None = None
    first: TensileResult | None = None
    converged = False
    it = 0
    history: dict[str, np.ndarray] = {}
    guesses: dict[str, np.ndarray] = {}
    with rep.task(f"compensation ({law} law)", total=max_iter) as advance:
        for it in range(1, max_iter + 1):
            cur = base.with_compensation(c, correction={law: correction_on_grid(base, knots, g)})
            try:
                res = _both_sides(specimen, cur, lam_t, lam_c, law, reference, guesses, rtol, volume)
            except SimulationError as exc:
                if best is None:
                    raise SimulationError(
                        f"compensation ({law}): the virtual tensile test failed before any "
                        f"correction ({exc}); narrow the calibration range") from None
                rep.warn(f"compensation ({law}): iteration {it} found no equilibrium (the corrected "
                         "network loses stability); keeping the best correction so far. A smaller "
                         "compression range avoids this")
                break
            if first is None:
                first = res
            ratio = balance * res.reference / res.stress          # target over network, per test stretch
            err = float(np.max(np.abs(1.0 / ratio - 1.0)))
            if best is None or err < best[0]:
                best = (err, g.copy(), res)
            advance(1)
            rep.step(f"compensation ({law}) iteration {it}: max |error| {100 * err:.2f} % (against the target)")
            if err <= tol:
                converged = True
                break
            nc = lam_c.size        # res: compression (1 -> end) then tension; knots ascending
            log_r = np.zeros_like(g)
            log_r[:nc] = np.log(ratio[:nc][::-1])
            log_r[nc + 1:] = np.log(ratio[nc:])
            if not np.all(np.isfinite(log_r)):
                break
            g = _update(g, log_r, history)
            g = _limit_ends(knots, g, nc)
    assert best is not None and first is not None
    err, g_best, after = best
    before = _before(first, c, specimen, base, lam_t, lam_c, law, reference, rtol, volume)
    checks = {}
    if volume is not None and material is not None and len(shear_check):
        done = base.with_compensation(c, correction={law: correction_on_grid(base, knots, g_best)})
        for plane in ("xz", "xy"):
            checks[f"shear_{plane}"] = _shear_record(virtual_shear_test(
                specimen.network, done, gamma=shear_check, law=law, material=material, volume=volume,
                plane=plane, rtol=rtol))
    result = CompensationResult(law=law, factor=c, knots=knots, g=g_best, before=before, scalar=first,
                                after=after, iterations=it, converged=converged, specimen=specimen.describe(),
                                volume=None if volume is None else volume.describe(), small_strain=scalar,
                                checks=checks)
    if not converged:
        rep.warn(f"compensation ({law}): stopped after {it} iterations at max |error| "
                 f"{100 * err:.2f} % (tolerance {100 * tol:.2g} %)")
    return _apply(tables, law, c, knots, g_best, result.record()), result


def _check_options(tol, max_iter, spacing) -> None:
    if not (isinstance(tol, float | int) and 0 < tol < 1):
        raise ConfigError(f"tol: must be a fraction in (0, 1), got {tol!r}")
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise ConfigError(f"max_iter: must be a positive integer, got {max_iter!r}")
    if not (isinstance(spacing, float | int) and 0 < spacing <= 0.5):
        raise ConfigError(f"spacing: must be a stretch step in (0, 0.5], got {spacing!r}")


def _scalar_factor(specimen, base, law, material, volume, reference) -> dict[str, Any]:
    """The scalar factor c from small-strain tests, and the tension balance.

    Springs only: ``c = P_cont / P_net`` in uniaxial tension (the network's
    stress is proportional to c). With the volume term the network is
    (nearly) incompressible and one modulus remains, the shear modulus; but a
    cylinder's mesh is not isotropic (its edges favour the axis: the axial
    mode is ~6 % stiffer and the xz shear ~5 % softer than the orientation
    average). So c is the weighted geometric mean of the factors of uniaxial
    tension along the axis and simple shear in the xy and xz planes,
    :data:`SCALAR_CASES`: the isotropic average of the five deviatoric modes
    (each factor is refined once, as the volume term does not scale with c).
    The *balance* ``c / c_tension`` is the specimen's axial stress relative to
    the material's at small strain; the stretch correction keeps it, so that g
    holds the curve's shape only.
    """
    lam = np.array([1.0 + SMALL_STRAIN])

    def factor(case, c):
        t = base.with_compensation(c, correction={law: np.ones(base.n)})
        if case == "tension":
            r = virtual_tensile_test(specimen, t, stretch=lam, law=law, material=material, volume=volume)
            return float(reference(lam)[0] / r.stress[0])
        r = virtual_shear_test(specimen.network, t, gamma=[SMALL_STRAIN], law=law, material=material,
                               volume=volume, plane=case)
        # without a material: P_ab = mu gamma = (E/3) gamma = P_uniaxial(1 + eps) / 3 at gamma = eps
        ref = r.reference[0] if material is not None else reference(lam)[0] / 3.0
        return float(ref / r.stress[0])

    cases = SCALAR_CASES if volume is not None else SCALAR_CASES[:1]
    found = {}
    for case, _ in cases:
        c = factor(case, 1.0)
        found[case] = c * factor(case, c) if volume is not None else c
    weights = np.array([w for _, w in cases])
    c = float(np.exp(np.sum(weights * np.log([found[k] for k, _ in cases])) / weights.sum()))
    if not (math.isfinite(c) and c > 0):
        raise ConfigError(f"specimen: small-strain network stresses give no usable compensation factor "
                          f"({found}); check the tables and the specimen")
    return {"factor": c, "balance": c / found["tension"], "cases": found,
            "weights": {k: w for k, w in cases}}


def _before(first, c, specimen, base, lam_t, lam_c, law, reference, rtol, volume) -> TensileResult:
    """The raw network (springs alone, c = 1, g = 1): exact scaling of *first* without a volume term, else a run."""
    if volume is None:
        return _scaled(first, 1.0 / c, 1.0)      # stress is proportional to c under displacement control
    return _both_sides(specimen, base, lam_t, lam_c, law, reference, {}, rtol, None)


def _shear_record(r) -> dict[str, Any]:
    """Plain data of a simple-shear check."""
    return {"gamma": r.gamma.tolist(), "rel_error": r.rel_error.tolist(), "max_abs_rel_error": r.max_abs_rel_error,
            "volume_ratio": r.volume_ratio.tolist(), "inverted": r.inverted.tolist()}


def _apply(tables: StiffnessTables, law: str, factor: float, knots, g, record: dict[str, Any]) -> StiffnessTables:
    """*tables* with the scalar factor and the correction of *law* (knots, g), and its record."""
    # Other laws' corrections were found relative to the old factor: keep c * g unchanged.
    corr = {law: correction_on_grid(tables, knots, g)}
    for other in LAWS:
        if other != law and tables.is_corrected(other):
            corr[other] = tables.correction[LAWS.index(other)] * (tables.volume_factor / factor)
    return tables.with_compensation(factor, correction=corr, record=_merge_record(tables, law, record))


def specimen_for(network, *, radius_elements: float = DEFAULT_RADIUS_ELEMENTS, reporter=None) -> Specimen:
    """A calibration cylinder meshed like *network*: element size = its median rest length.

    The network's stress response is scale-free (forces scale with V/L0, areas
    with L0^2), so what the compensation depends on is the mesh's shape
    statistics and the specimen's resolution, not its size in metres. The
    specimen has radius ``radius_elements`` element sizes and length 4 radii.
    """
    h = float(np.median(network.rest_length))
    if not (math.isfinite(h) and h > 0):
        raise ConfigError("network: rest lengths are not positive; rebuild the network")
    r = radius_elements * h
    return cylinder_specimen(radius=r, length=4.0 * r, size=h, reporter=reporter)


@dataclass(frozen=True)
class Compensation:
    """What :func:`compensate` made.

    Attributes
    ----------
    tables : StiffnessTables
        The compensated tables (``metadata["compensation"]`` holds the record).
    record : dict
        The calibration record of the law (:meth:`CompensationResult.record`;
        with ``cache = {"key", "hit": True}`` when it was reused).
    reused : Path or None
        The cache file it was reused from (None: calibrated now).
    """

    tables: StiffnessTables
    record: dict[str, Any]
    reused: Path | None = None

    def summary(self) -> str:
        """The virtual tensile test's error, one line (``93.5 % raw -> 0.51 %``)."""
        after = 100 * self.record["errors_after"]["max_abs_rel_error"]
        if self.reused is not None:
            return f"{after:.2f} % (calibration reused from {self.reused})"
        return f"{100 * self.record['errors_before']['max_abs_rel_error']:.1f} % raw -> {after:.2f} %"


def calibration_stretches(tables: StiffnessTables, calibration_range=None) -> tuple[float, float]:
    """Compression and tension ends of a calibration on *tables*: *calibration_range*
    (default :data:`DEFAULT_RANGE`) clipped to two grid steps inside the grid.

    Raises
    ------
    ConfigError
        *calibration_range* is not two finite numbers with ``LO < 1 < HI``.
    """
    lo, hi = DEFAULT_RANGE if calibration_range is None else calibration_range
    lo, hi = number(lo, "calibration_range"), number(hi, "calibration_range")
    if not lo < 1.0 < hi:
        raise ConfigError(f"calibration_range: need LO < 1 < HI, got {lo:g} {hi:g}", parameter="calibration_range")
    return max(lo, tables.lam_min + 2 * tables.dlam), min(hi, tables.lam_max - 2 * tables.dlam)


def compensate(tables: StiffnessTables, network, *, material=None, calibration_range=None,
               radius_elements: float | None = None, volume: VolumeSpec | None = None,
               reporter=None) -> Compensation:
    """Calibrate the volumetric compensation of *tables* for their default law, or reuse a calibration.

    One virtual tensile test on a cylinder meshed like *network*
    (:func:`specimen_for`), by :func:`calibrate_compensation`; a calibration
    with the same content address (:mod:`~esmm.pipeline.network.compensation_policy`)
    is reused instead of run again.

    Parameters
    ----------
    tables : StiffnessTables
    network : SpringNetwork
        Its median rest length is the specimen's element size.
    material : Material, optional
        Continuum reference (default: the tables' own stress).
    calibration_range : (float, float), optional
        Compression and tension ends (default :data:`DEFAULT_RANGE`), clipped to the grid.
    radius_elements : float, optional
        Specimen radius in element sizes (default :data:`DEFAULT_RADIUS_ELEMENTS`,
        accepted :data:`RADIUS_ELEMENTS_RANGE`).
    volume : VolumeSpec, optional
        The volume term the asset carries (the calibration runs with it; its
        parameters enter the cache key).
    reporter
        Progress reporter.

    Returns
    -------
    Compensation

    Raises
    ------
    ConfigError
        A bad range or radius (named ``calibration_range``, ``radius_elements``).
    SimulationError
        The virtual tensile test failed before any correction.
    """
    law = tables.default_law
    lo, hi = calibration_stretches(tables, calibration_range)
    r = number(DEFAULT_RADIUS_ELEMENTS if radius_elements is None else radius_elements, "radius_elements",
               lo=RADIUS_ELEMENTS_RANGE[0], hi=RADIUS_ELEMENTS_RANGE[1])
    key = policy.cache_key(tables, law, lo, hi, r, volume=None if volume is None else volume.describe())
    hit = policy.load(key)
    if hit is not None:
        record = dict(hit["record"], cache={"key": key, "hit": True})
        out = _apply(tables, law, hit["factor"], hit["knots"], hit["g"], record)
        return Compensation(out, record, policy.cache_path(key))
    specimen = specimen_for(network, radius_elements=r, reporter=reporter)
    out, calib = calibrate_compensation(tables, specimen, law=law, material=material, tension=hi,
                                        compression=lo, volume=volume, reporter=reporter)
    record = calib.record()
    policy.store(key, factor=calib.factor, knots=calib.knots.tolist(), g=calib.g.tolist(),
                             record=record)
    return Compensation(out, record)


def _update(g: np.ndarray, log_r: np.ndarray, history: dict[str, np.ndarray]) -> np.ndarray:
    """One fixed-point step on log g, with a per-knot secant step length.

    The plain step is ``log g += log r``. The stress at a knot responds to its
    own ``log g`` with a sensitivity ``beta`` (``-dlog r / dlog g``, estimated
    from the last two iterations): below 1 where the neighbouring knots carry
    much of the load (slow, one-signed convergence: the step is lengthened to
    ``log r / beta`` with beta >= 0.25), above 1 where they amplify it (the
    error changed sign: the step is shortened, beta <= 4). Steps are limited to
    a factor 3 per iteration.
    """
    log_g = np.log(g)
    beta = np.ones_like(g)
    if history:
        dg = log_g - history["log_g"]
        dr = log_r - history["log_r"]
        ok = np.abs(dg) > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            est = np.where(ok, -dr / dg, 1.0)
        est = np.where(np.isfinite(est) & (est > 0), est, 1.0)
        flipped = np.sign(log_r) != np.sign(history["log_r"])
        beta = np.where(flipped, np.clip(est, 1.0, 4.0), np.clip(est, 0.25, 1.0))
    history["log_g"], history["log_r"] = log_g, log_r
    step = np.clip(log_r / beta, -math.log(3.0), math.log(3.0))
    return np.exp(log_g + step)


def _limit_ends(knots: np.ndarray, g: np.ndarray, nc: int, *, growth: float = 1.5) -> np.ndarray:
    """Keep g at the outermost knot of each side from spiking.

    The stress at the last test stretch depends only weakly on g at that very
    stretch (few springs are stretched as far as the specimen), so the plain
    update can drive g there far above its neighbours, and the constant
    extension beyond the last knot would carry that spike to every larger
    stretch. The log-slope of g on the outermost interval is limited to
    *growth* times the log-slope on the interval before it (in absolute value).
    """
    g = g.copy()
    lg = np.log(g)
    sides = []
    if nc >= 2:
        sides.append((0, 1, 2))
    if g.size - 1 - nc >= 2:
        sides.append((g.size - 1, g.size - 2, g.size - 3))
    for end, a, b in sides:
        prev = (lg[a] - lg[b]) / (knots[a] - knots[b])
        last = (lg[end] - lg[a]) / (knots[end] - knots[a])
        lim = growth * abs(prev)
        if abs(last) > lim:
            lg[end] = lg[a] + np.sign(last) * lim * (knots[end] - knots[a])
    return np.exp(lg)


def _merge_record(tables: StiffnessTables, law: str, rec: dict[str, Any]) -> dict[str, Any]:
    """Keep the records of the other law (the scalar factor is shared)."""
    old = tables.metadata.get("compensation")
    merged = dict(old) if isinstance(old, dict) and "laws" in old else {"laws": {}}
    merged["laws"] = dict(merged.get("laws", {}))
    merged["laws"][law] = rec
    merged["volume_factor"] = rec["volume_factor"]
    return merged


def _both_sides(specimen, tables, lam_t, lam_c, law, reference, guesses, rtol, volume=None) -> TensileResult:
    """Compression then tension tests; *guesses* (dict side -> path) is updated in place."""
    parts = []
    for side, lam in (("c", lam_c), ("t", lam_t)):
        if lam.size:
            r = virtual_tensile_test(specimen, tables, stretch=lam, law=law, rtol=rtol,
                                     predictors=guesses.get(side), keep_path=True, volume=volume)
            guesses[side] = r.path
            parts.append(r)
    stretch = np.concatenate([p.stretch for p in parts])
    return TensileResult(
        stretch=stretch, stress=np.concatenate([p.stress for p in parts]), reference=reference(stretch),
        lateral_stretch=np.concatenate([p.lateral_stretch for p in parts]),
        iterations=np.concatenate([p.iterations for p in parts]), law=law,
        volume_factor=tables.volume_factor, residual=max(p.residual for p in parts),
        info=parts[0].info, volume_ratio=np.concatenate([p.volume_ratio for p in parts]),
    )


def _scaled(r: TensileResult, s: float, c: float) -> TensileResult:
    """*r* with the network stress multiplied by *s* and volume factor *c*."""
    return TensileResult(stretch=r.stretch, stress=r.stress * s, reference=r.reference,
                         lateral_stretch=r.lateral_stretch, iterations=r.iterations, law=r.law,
                         volume_factor=c, residual=r.residual, info=r.info, volume_ratio=r.volume_ratio)
