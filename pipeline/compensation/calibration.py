r"""Volumetric compensation: calibrate the network on a virtual tensile test.

The ESMM spring stiffness :math:`k_{ij} = v_{ij}\mu_e(\lambda)` with
:math:`V_{ij} = \sum_{t \ni ij} V_t/6` makes the network far softer than the
tissue: in small strain an affine, isotropically oriented edge set stores
:math:`\tfrac{1}{15}(\operatorname{tr}^2\varepsilon + 2\,\varepsilon:\varepsilon)\,E/2`
per volume, i.e. Lamé constants :math:`\lambda_L = \mu_L = E/15` and a Young's
modulus :math:`E/6` (Poisson ratio 1/4, the Cauchy relation of central-force
networks). Nodal relaxation softens it a little more, and at finite stretch the
off-axis springs are stretched less than the specimen, so a stiffening tissue
is matched worse the further it is stretched (docs/design/tables.md).

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
   With a volume term (and a material), g is then refitted on tension,
   compression and simple shear in two planes together, by Levenberg-Marquardt
   on the springs' power shares (:mod:`.stretch_fit`; docs/design/tables.md, "The compensation"): fitted
   on the axial test alone it leaves the network soft in shear and in bulkier
   meshes at finite strain.

Both are properties of the mesh (element shape statistics and size relative to
the specimen) and of the law; the record stored in the tables' metadata says
on what specimen they were found.

:func:`compensate` is the policy ``esmm prepare`` and ``esmm tables`` share:
the calibration range (:data:`DEFAULT_RANGE`, clipped to the grid), the
specimen (:func:`specimen_for`, :data:`DEFAULT_RADIUS_ELEMENTS`) and the cache
of calibrations (:mod:`~esmm.pipeline.compensation.policy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..checks import number
from ..errors import ConfigError, SimulationError
from ..network.tables import DEFAULT_LAM_MAX, LAWS, StiffnessTables
from ..network.volume import VolumeSpec
from ..progress import ensure
from . import policy, stretch_fit
from .loadcases import virtual_shear_test
from .policy import DEFAULT_RADIUS_ELEMENTS, DEFAULT_RANGE, RADIUS_ELEMENTS_RANGE
from .virtual_tensile import (
    Specimen,
    TensileResult,
    continuum_stress,
    cylinder_specimen,
    virtual_tensile_test,
)

__all__ = ["Compensation", "CompensationResult", "calibrate_compensation", "compensate", "correction_on_grid",
           "specimen_for"]

#: Small-strain stretch (and amount of shear) of the scalar calibration.
SMALL_STRAIN = 1e-4
#: Amounts of simple shear the calibrated network is checked at (with the volume term).
SHEAR_CHECK = (0.1, 0.2, 0.3, 0.4)
#: The small-strain load cases of the scalar factor with the volume term, and their weights: the
#: specimen's axial mode and its two shear planes weigh 1 : 2 : 2, the isotropic average of the
#: five deviatoric modes of a transversely isotropic (cylinder) network (docs/design/tables.md, "The compensation").
SCALAR_CASES = (("tension", 1.0), ("xy", 2.0), ("xz", 2.0))
#: The load cases the stretch correction is fitted on with the volume term (without it: the first two).
JOINT_CASES = ("tension", "compression", "shear_xy", "shear_xz")
#: Largest change of log g at a knot in one step of the joint fit (a trust region: g moves by 25 % at most).
MAX_STEP = math.log(1.25)
#: Evaluations of the joint fit at most (each runs the axial test and two shear tests).
JOINT_MAX_ITER = 24


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
        Simple shear of the calibrated network (``"shear_xz"``, ``"shear_xy"``:
        errors per amount of shear; with the volume term).
    fitted_on : list of str
        The load cases g was fitted on (:data:`JOINT_CASES`, or its first two:
        the axial test alone).
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
    fitted_on: list[str] = field(default_factory=list)

    def record(self) -> dict[str, Any]:
        """JSON-serialisable summary (stored in ``tables.metadata["compensation"]``)."""
        def errs(r: TensileResult) -> dict[str, float]:
            return {"max_abs_rel_error": r.max_abs_rel_error, "rms_rel_error": r.rms_rel_error}

        return {
            "method": "virtual load tests on a gmsh cylinder (pipeline/compensation/calibration.py): "
                      "scalar factor from a small-strain test (with the volume term: the weighted geometric mean "
                      "of small-strain tension and simple shear in two planes), stretch-dependent correction "
                      + ("by Gauss-Newton on power shares over tension, compression and simple shear in two planes "
                         "(pipeline/compensation/stretch_fit.py)" if len(self.fitted_on) > 2 else
                         "by fixed-point iteration on tension and compression"),
            "fitted_on": self.fitted_on,
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
        From :func:`~esmm.pipeline.compensation.virtual_tensile.cylinder_specimen`.
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
        :func:`~esmm.pipeline.compensation.virtual_tensile.virtual_tensile_test`).
    volume : VolumeSpec, optional
        The volume term the network will carry (:mod:`~esmm.pipeline.network.volume`);
        every test then includes it, and the scalar factor balances two load
        cases (uniaxial tension and simple shear, module doc).
    shear_check : sequence of float, optional
        Amounts of simple shear (xy and xz planes) the stretch correction is
        fitted on together with tension and compression, when *volume* and
        *material* are given (:mod:`.stretch_fit`; empty: the axial test alone).

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
    reference = _reference(material, base)

    # 1. scalar factor from small-strain tests (tension; with the volume term also simple shear)
    scalar = _scalar_factor(specimen, base, law, material, volume, reference)
    c = scalar["factor"]
    rep.step(f"compensation ({law}): scalar factor c = {c:.4f} from small-strain "
             + ", ".join(f"{k} {v:.4f}" for k, v in scalar["cases"].items()))

    # 2. stretch correction on the curve's shape: the target is the material's stress times the
    # small-strain balance of each load case. With the volume term and a material, g is fitted on
    # tension, compression and simple shear together; otherwise on the axial test alone.
    knots = np.concatenate([lam_c[::-1], [1.0], lam_t])
    joint = volume is not None and material is not None and len(shear_check) > 0
    fit = _fit_joint if joint else _fit_axial        # the joint fit falls back to the axial one (it warns)
    run = _Run(specimen, base, c, scalar, knots, lam_t, lam_c, law, material, reference, rtol, volume,
               np.asarray(shear_check, dtype=np.float64), tol, max_iter, rep)
    f = fit(run)
    before = _before(f.first, c, specimen, base, lam_t, lam_c, law, reference, rtol, volume)
    result = _result(run, f, before)
    if not f.converged:
        rep.warn(f"compensation ({law}): stopped after {f.iterations} iterations at max |error| "
                 f"{100 * f.err:.2f} % (tolerance {100 * tol:.2g} %)")
    return _apply(tables, law, c, f.knots, f.g, result.record()), result


@dataclass(frozen=True, eq=False)
class _Fit:
    """What a fit of g returns to :func:`calibrate_compensation`."""

    knots: np.ndarray
    g: np.ndarray
    err: float
    after: TensileResult
    first: TensileResult
    iterations: int
    converged: bool
    shear: dict[str, Any]
    fitted_on: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class _Run:
    """What a fit of g works on (the arguments of :func:`calibrate_compensation`, resolved)."""

    specimen: Specimen
    base: StiffnessTables
    c: float
    scalar: dict[str, Any]
    knots: np.ndarray
    lam_t: np.ndarray
    lam_c: np.ndarray
    law: str
    material: Any
    reference: Any
    rtol: float
    volume: VolumeSpec | None
    shear: np.ndarray
    tol: float
    max_iter: int
    rep: Any

    def tables(self, g: np.ndarray) -> StiffnessTables:
        return self.base.with_compensation(self.c, correction={self.law: correction_on_grid(self.base, self.knots, g)})

    def failed(self, it: int, exc: Exception, first: bool) -> None:
        """Raise when nothing was found yet, else warn that the best correction so far is kept."""
        if first:
            raise SimulationError(f"compensation ({self.law}): the virtual tensile test failed before any "
                                  f"correction ({exc}); narrow the calibration range") from None
        self.rep.warn(f"compensation ({self.law}): iteration {it} found no equilibrium (the corrected network "
                      "loses stability); keeping the best correction so far. A smaller compression range avoids this")


def _reference(material, base: StiffnessTables):
    """The target stress [Pa] as a function of the stretch: the material's, else the tables' own along z."""
    def reference(lam):
        if material is not None:
            return continuum_stress(material, lam)
        return np.interp(lam, base.lam, base.material_stress[2])

    return reference


def _result(run: _Run, f: _Fit, before: TensileResult) -> CompensationResult:
    """The details of a calibration: the fit *f* of *run*, with the uncorrected test *before*."""
    checks = {f"shear_{plane}": _shear_record(r) for plane, r in f.shear.items()}
    volume = run.volume
    return CompensationResult(law=run.law, factor=run.c, knots=f.knots, g=f.g, before=before, scalar=f.first,
                              after=f.after, iterations=f.iterations, converged=f.converged,
                              specimen=run.specimen.describe(), volume=None if volume is None else volume.describe(),
                              small_strain=run.scalar, checks=checks, fitted_on=list(f.fitted_on))


def _fit_axial(run: _Run, guesses: dict[str, np.ndarray] | None = None):
    """g by the fixed-point iteration on the axial test alone (module doc, step 2).

    *guesses* (side -> equilibrium path) is updated in place: the next tests start from it.
    """
    g = np.ones_like(run.knots)
    best, first, converged, it = None, None, False, 0
    history: dict[str, np.ndarray] = {}
    guesses = {} if guesses is None else guesses
    nc = run.lam_c.size        # res: compression (1 -> end) then tension; knots ascending
    with run.rep.task(f"compensation ({run.law} law)", total=run.max_iter) as advance:
        for it in range(1, run.max_iter + 1):
            try:
                res = _both_sides(run.specimen, run.tables(g), run.lam_t, run.lam_c, run.law, run.reference,
                                  guesses, run.rtol, run.volume)
            except SimulationError as exc:
                run.failed(it, exc, best is None)
                break
            first = res if first is None else first
            ratio = run.scalar["balance"] * res.reference / res.stress      # target over network
            err = float(np.max(np.abs(1.0 / ratio - 1.0)))
            if best is None or err < best[0]:
                best = (err, g.copy(), res)
            advance(1)
            run.rep.step(f"compensation ({run.law}) iteration {it}: max |error| {100 * err:.2f} % (against the target)")
            if err <= run.tol:
                converged = True
                break
            log_r = np.zeros_like(g)
            log_r[:nc] = np.log(ratio[:nc][::-1])
            log_r[nc + 1:] = np.log(ratio[nc:])
            if not np.all(np.isfinite(log_r)):
                break
            g = _limit_ends(run.knots, _update(g, log_r, history), nc)
    err, g_best, after = best
    return _Fit(run.knots, g_best, err, after, first, it, converged, {}, JOINT_CASES[:2])


@dataclass(frozen=True, eq=False)
class _JointTests:
    """The load cases of the joint fit at one g: results, log errors y, Jacobian J, weights w."""

    axial: TensileResult
    shear: dict[str, Any]
    y: np.ndarray
    J: np.ndarray
    w: np.ndarray

    @property
    def objective(self) -> float:
        """Weighted RMS of the log errors."""
        return float(np.sqrt(np.sum(self.w * self.y ** 2) / np.sum(self.w)))

    @property
    def max_error(self) -> float:
        return float(np.max(np.abs(np.exp(-self.y) - 1.0)))


def _joint_tests(run: _Run, g: np.ndarray, guesses: dict) -> _JointTests:
    """Run tension, compression and simple shear (xy, xz) at *g*; rows of the fit (:mod:`.stretch_fit`)."""
    tables = run.tables(g)
    ax = _both_sides(run.specimen, tables, run.lam_t, run.lam_c, run.law, run.reference, guesses, run.rtol,
                     run.volume)
    nc = run.lam_c.size
    path = np.concatenate([guesses[k] for k in ("c", "t") if k in guesses])   # before the shear tests add theirs
    modes = ["compression"] * nc + ["tension"] * run.lam_t.size
    y = [np.log(run.scalar["balance"] * ax.reference / ax.stress)]
    w = [stretch_fit.test_weights(m, a) for m, a in (("compression", ax.stretch[:nc]), ("tension", ax.stretch[nc:]))]
    J = [stretch_fit.power_shares(x, run.specimen.network, tables, run.law, stretch_fit.velocity_gradient(m, a),
                                  run.knots) for x, m, a in zip(path, modes, ax.stretch, strict=True)]
    shear = {}
    for plane in ("xy", "xz"):
        r = virtual_shear_test(run.specimen.network, tables, gamma=run.shear, law=run.law, material=run.material,
                               volume=run.volume, plane=plane, rtol=run.rtol, predictors=guesses.get(plane))
        guesses[plane] = r.path
        shear[plane] = r
        y.append(np.log(run.c / run.scalar["cases"][plane] * r.reference / r.stress))
        w.append(stretch_fit.test_weights(plane, r.gamma))
        J += [stretch_fit.power_shares(x, run.specimen.network, tables, run.law,
                                       stretch_fit.velocity_gradient(plane, a), run.knots)
              for x, a in zip(r.path, r.gamma, strict=True)]
    return _JointTests(ax, shear, np.concatenate(y), np.asarray(J), np.concatenate(w))


def _fit_joint(run: _Run):
    """g by Gauss-Newton on tension, compression and simple shear together (:mod:`.stretch_fit`).

    Starts from the axial fixed point (:func:`_fit_axial`: cheap, and close,
    since tension and compression already hold much of the fit's weight).
    Levenberg-Marquardt: a step that lowers the weighted RMS log error by 1 %
    is kept and the damping divided by 3; one that finds no equilibrium or
    does not is dropped and the damping multiplied by 4. The fit is
    stationary (converged) after three dropped steps in a row or when every
    test is within ``tol`` of its target; it stops after :data:`JOINT_MAX_ITER`
    evaluations at most.
    """
    guesses: dict[str, np.ndarray] = {}
    axial = _fit_axial(run, guesses)
    run, g_best = _shear_knots(run, axial.g)
    held = int(np.flatnonzero(run.knots == 1.0)[0])
    try:
        best = _joint_tests(run, g_best, guesses)
    except SimulationError as exc:
        run.rep.warn(f"compensation ({run.law}): the simple-shear tests found no equilibrium ({exc}); "
                     "the stretch correction is fitted on tension and compression only")
        return axial
    damping, dropped, it = stretch_fit.DAMPING, 0, 1
    with run.rep.task(f"compensation ({run.law} law, tension, compression and shear)", total=JOINT_MAX_ITER) as advance:
        while it < JOINT_MAX_ITER and best.max_error > run.tol and dropped < 3:
            step = stretch_fit.gauss_newton_step(best.J, best.y, best.w, held, damping=damping)
            g = _limit_ends(run.knots, g_best * np.exp(np.clip(step, -MAX_STEP, MAX_STEP)), held)
            it += 1
            try:
                ev = _joint_tests(run, g, guesses)
            except SimulationError:
                ev = None
            advance(1)
            if ev is not None and np.all(np.isfinite(ev.y)) and ev.objective < 0.99 * best.objective:
                best, g_best, damping, dropped = ev, g, max(damping / 3.0, 1e-3), 0
            else:
                damping, dropped = damping * 4.0, dropped + 1
            run.rep.step(f"compensation ({run.law}) joint iteration {it}: weighted RMS error "
                         f"{100 * best.objective:.2f} %, max {100 * best.max_error:.2f} % (tension, compression, "
                         "shear; against the targets)")
    converged = dropped >= 3 or best.max_error <= run.tol
    return _Fit(run.knots, g_best, best.max_error, best.axial, axial.first, axial.iterations + it, converged,
                best.shear, JOINT_CASES)


def _shear_knots(run: _Run, g: np.ndarray) -> tuple[_Run, np.ndarray]:
    """Knots below the compression end down to the largest shear's compressive principal stretch.

    Simple shear gamma compresses springs down to ``1 / (gamma/2 + sqrt(1 + gamma^2/4))``
    (0.82 at 0.4), beyond the axial test's end (0.9): without knots there, g would be
    held constant below the end and the shear tests would pull on the end knot,
    which the compression test also needs. g starts there at its end value.
    """
    gmax = float(run.shear.max())
    low = max(1.0 / (gmax / 2 + math.sqrt(1 + gmax ** 2 / 4)), run.base.lam_min + 2 * run.base.dlam)
    end, step = run.knots[0], (run.knots[1] - run.knots[0]) if run.knots.size > 1 else 0.02
    extra = end - step * np.arange(1, int(math.ceil((end - low) / step - 1e-9)) + 1)
    extra = extra[::-1]
    if extra.size == 0:
        return run, g
    return replace(run, knots=np.concatenate([extra, run.knots])), np.concatenate([np.full(extra.size, g[0]), g])


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
        """The virtual tests' errors, one line (``93.5 % raw -> 0.51 %``; with the shear it was fitted on)."""
        after = 100 * self.record["errors_after"]["max_abs_rel_error"]
        shear = "".join(f", {k.replace('_', ' ')} {100 * v['max_abs_rel_error']:.1f} %"
                        for k, v in sorted(self.record.get("checks", {}).items()))
        if self.reused is not None:
            return f"{after:.2f} %{shear} (calibration reused from {self.reused})"
        return f"{100 * self.record['errors_before']['max_abs_rel_error']:.1f} % raw -> {after:.2f} %{shear}"


def calibration_stretches(tables: StiffnessTables, calibration_range=None) -> tuple[float, float]:
    """Compression and tension ends of a calibration on *tables*: *calibration_range*
    (default :data:`DEFAULT_RANGE`) clipped to two grid steps inside the grid.

    Raises
    ------
    ConfigError
        *calibration_range* is not two finite numbers with ``LO < 1 < HI``, or the grid is
        too coarse to hold two steps on each side of 1.
    """
    lo, hi = DEFAULT_RANGE if calibration_range is None else calibration_range
    lo, hi = number(lo, "calibration_range"), number(hi, "calibration_range")
    if not lo < 1.0 < hi:
        raise ConfigError(f"calibration_range: need LO < 1 < HI, got {lo:g} {hi:g}", parameter="calibration_range")
    lo, hi = max(lo, tables.lam_min + 2 * tables.dlam), min(hi, tables.lam_max - 2 * tables.dlam)
    if not lo < 1.0 < hi:   # two grid steps on each side of 1 do not fit: a grid far wider than the tissue
        raise ConfigError(f"the tables' grid (stretch {tables.lam_min:.4g}..{tables.lam_max:.4g} in steps of "
                          f"{tables.dlam:.3g}) is too coarse to calibrate the compensation near stretch 1; give "
                          f"the grid's end (prepare config [tables] lam_max, e.g. {DEFAULT_LAM_MAX:g}, the default of a material that does not lock) or more "
                          f"points ([tables] n)")
    return lo, hi


def compensate(tables: StiffnessTables, network, *, material=None, calibration_range=None,
               radius_elements: float | None = None, volume: VolumeSpec | None = None,
               reporter=None) -> Compensation:
    """Calibrate the volumetric compensation of *tables* for their default law, or reuse a calibration.

    One virtual tensile test on a cylinder meshed like *network*
    (:func:`specimen_for`), by :func:`calibrate_compensation`; a calibration
    with the same content address (:mod:`~esmm.pipeline.compensation.policy`)
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
