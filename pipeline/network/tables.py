r"""Stiffness tables of the Equivalent Spring-Mass Model (the paper's Eq. 8-9).

A spring *i-j* of rest length :math:`L_0` and volume weight
:math:`v_{ij} = V_{ij}/L_0^2` has, at stretch :math:`\lambda = L/L_0`, the
stiffness

.. math::

    k_{ij}(\lambda) = c\,v_{ij}\,\bigl[\mu_{ex}(\lambda)\cos^2\alpha
        + \mu_{ey}(\lambda)\cos^2\beta + \mu_{ez}(\lambda)\cos^2\gamma\bigr],
    \qquad
    \mu_e(\lambda) = \frac{2\,W_T(\lambda)}{(\lambda-1)^2},

where :math:`W_T` is the strain energy of the tissue in incompressible
uniaxial stretch along a material direction, the angles are those of the
spring's rest direction with the fibre frame, and :math:`c` is the volumetric
compensation factor of :mod:`esmm.pipeline.compensation.calibration` (1 when not
calibrated). Two force laws use the same tables; both are central forces
whose magnitude is a function of :math:`\lambda` only,

.. math::

    F_{ij} = \frac{c\,V_{ij}}{L_0}\sum_d \cos^2\theta_d\, f_d(\lambda),
    \qquad
    f_d(\lambda) = \begin{cases}
        \mu_{e,d}(\lambda)\,(\lambda-1) & \text{secant (paper, Eq. 9)}\\
        W_{T,d}'(\lambda) & \text{energy (}F = \partial E/\partial L,\ E = c V_{ij} W_T\text{)}
    \end{cases}

:class:`StiffnessTables` holds, on one uniform stretch grid, the three rows
(x, y, z) of :math:`\mu_e` (``values``), of the nominal uniaxial stress
:math:`W_T'` (``stress``) and of an energy :math:`W_T` that is the exact
integral of the interpolated stress (``energy``), so a consumer can evaluate
both laws, their energies and tangents from the file alone. When the network
has been calibrated (:mod:`esmm.pipeline.compensation.calibration`), ``values``
and ``stress`` already include the stretch correction :math:`g(\lambda)`
(``correction``; the material's own curves are ``values / correction``), so a
consumer never applies it separately; only ``volume_factor`` multiplies.

Lookup (O(1), what a kernel does)::

    s = (lam - lam_min) / dlam
    i = min(max(int(floor(s)), 0), n - 2)
    t = s - i                                    # unclipped
    mu_e   = values[d, i] + (values[d, i+1] - values[d, i]) * clip(t, 0, 1)
    stress = stress[d, i] + (stress[d, i+1] - stress[d, i]) * t

Outside the grid, :math:`\mu_e` is held at its end value (the secant spring
becomes linear with its end secant stiffness) and the stress continues with
the slope of its end segment (a quadratic energy extension: constant tangent
stiffness). Both keep a positive tangent because :func:`build_tables` refuses
a material whose uniaxial stress does not increase over the grid.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from ..checks import choice, number
from ..errors import ConfigError, InputError
from ..materials.loading import nominal_stress
from ..materials.material import DIRECTIONS

#: Names of the force laws, in the order of preference.
LAWS = ("secant", "energy")
#: Default number of grid points.
DEFAULT_N = 1024
#: The default grid never reaches beyond these stretches (a material that locks nearer to 1 ends before
#: them). Stretch 2 (100 % strain) is past the rupture of soft organ tissue in tension and 0.5 past any
#: compression an organ survives, so a grid beyond them tabulates no tissue; on 1 024 points [0.5, 2]
#: gives a step of 0.0015, 270 points over the compensation's calibration range 0.9-1.3. A fit whose
#: locking stretch lies far beyond its data (a chain count at its bound) would otherwise stretch the grid
#: to hundreds and leave no point between 1 and 1.3 (docs/design/tables.md, "Grid rule").
DEFAULT_LAM_MIN = 0.5
DEFAULT_LAM_MAX = 2.0
#: Fraction of the distance between 1 and a locking stretch kept free at each end.
LOCK_MARGIN = 0.02

# The three texts below describe the tables where they are stored (the /tables group of an
# asset, docs/reference/asset-format.md): the grid, the extrapolation and the force laws.
GRID_RULE = (
    "uniform grid of n points from lam_min to lam_max; defaults from the material: "
    f"lam_min = max({DEFAULT_LAM_MIN}, lower admissible stretch + {LOCK_MARGIN:g}*(1 - lower)), "
    f"lam_max = min({DEFAULT_LAM_MAX}, upper admissible stretch - {LOCK_MARGIN:g}*(upper - 1)), "
    "then narrowed to the stretches around 1 where the material's uniaxial stress is finite and "
    "increasing (metadata 'grid' says why each end is where it is); the step is then shortened "
    "(lam_max lowered, by less than one step per point above 1) so that stretch 1 is a grid node"
)
EXTRAPOLATION = (
    "linear interpolation inside the grid; outside, mu_e is held at its end value "
    "and the stress continues with the slope of its end segment"
)
FORCE_LAW = (
    "F = volume_factor * V_ij / L0 * sum_d cos2_d * f_d(lam), lam = L/L0, positive = tension; "
    "secant (paper Eq. 9): f = mu_e(lam) * (lam - 1), i.e. F = k (L - L0) with "
    "k = volume_factor * v_ij * sum_d cos2_d * mu_e_d(lam); energy: f = stress(lam); "
    "mu_e and stress are the datasets (stretch correction included)"
)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class StiffnessTables:
    """:math:`\\mu_e(\\lambda)` and :math:`W_T'(\\lambda)` per fibre direction on a uniform grid.

    Attributes
    ----------
    lam_min, lam_max : float
        Grid ends (stretch, dimensionless); ``lam_min < 1 < lam_max``.
    n : int
        Number of grid points (>= 3).
    values : ndarray, shape (3, n)
        :math:`g_{secant}(\\lambda)\\,\\mu_e(\\lambda)` [Pa] for the x, y, z
        directions (equal rows for an isotropic material), with
        :math:`\\mu_e = 2W_T/(\\lambda-1)^2` the material's modulus and
        :math:`g` the stretch correction (1 unless calibrated): the secant
        law's table, ``k_ij = volume_factor * v_ij * cos2_ij @ values(lam)``.
    stress : ndarray, shape (3, n)
        :math:`g_{energy}(\\lambda)\\,W_T'(\\lambda)` [Pa], with :math:`W_T'` the
        material's nominal uniaxial stress: the energy law's table.
    energy : ndarray, shape (3, n)
        Integral from 1 of the linearly interpolated ``stress`` [Pa = J/m3]
        (:math:`W_T` when uncorrected), so that the energy law's force is
        exactly the derivative of its energy.
    default_law : str
        ``"secant"`` (the paper's Eq. 9) or ``"energy"``.
    volume_factor : float
        Volumetric compensation factor :math:`c` that multiplies every
        :math:`v_{ij}` (1 = uncalibrated).
    correction : ndarray, shape (2, n)
        The stretch correction :math:`g` already applied to ``values`` (row 0)
        and ``stress`` (row 1), in :data:`LAWS` order; all ones when not
        calibrated. The material's own curves are ``values / correction[0]``
        and ``stress / correction[1]`` (:attr:`material_values`,
        :attr:`material_stress`).
    material_toml : str
        The material the tables were built from, as TOML text.
    metadata : dict
        Free-form provenance (``material_name``, ``compensation`` records, ...);
        JSON-serialisable.
    """

    lam_min: float
    lam_max: float
    n: int
    values: np.ndarray
    stress: np.ndarray
    energy: np.ndarray
    default_law: str = "secant"
    volume_factor: float = 1.0
    correction: np.ndarray | None = None
    material_toml: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = int(self.n)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "lam_min", float(self.lam_min))
        object.__setattr__(self, "lam_max", float(self.lam_max))
        object.__setattr__(self, "volume_factor", float(self.volume_factor))
        if n < 3:
            raise ValueError(f"n: need at least 3 grid points, got {n}")
        if not (0.0 < self.lam_min < 1.0 < self.lam_max and math.isfinite(self.lam_max)):
            raise ValueError(
                f"lam_min/lam_max: need 0 < lam_min < 1 < lam_max, got {self.lam_min}, {self.lam_max}"
            )
        if self.correction is None:
            object.__setattr__(self, "correction", np.ones((len(LAWS), n)))
        for name, shape in (("values", (3, n)), ("stress", (3, n)), ("energy", (3, n)),
                            ("correction", (len(LAWS), n))):
            arr = _readonly(getattr(self, name))
            if arr.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: contains non-finite values")
            object.__setattr__(self, name, arr)
        if np.any(self.correction <= 0):
            raise ValueError("correction: must be positive")
        if self.default_law not in LAWS:
            raise ValueError(f"default_law: must be one of {', '.join(LAWS)}, got {self.default_law!r}")
        if not (math.isfinite(self.volume_factor) and self.volume_factor > 0):
            raise ValueError(f"volume_factor: must be a positive number, got {self.volume_factor}")

    # -- grid --------------------------------------------------------------
    @property
    def dlam(self) -> float:
        """Grid step."""
        return (self.lam_max - self.lam_min) / (self.n - 1)

    @property
    def lam(self) -> np.ndarray:
        """The grid, shape (n,)."""
        return np.linspace(self.lam_min, self.lam_max, self.n)

    @property
    def isotropic(self) -> bool:
        """True when the three rows are identical."""
        return bool(
            np.array_equal(self.values[0], self.values[1])
            and np.array_equal(self.values[0], self.values[2])
            and np.array_equal(self.stress[0], self.stress[1])
            and np.array_equal(self.stress[0], self.stress[2])
        )

    def is_corrected(self, law: str | None = None) -> bool:
        """True when the law's stretch-dependent correction is not identically 1."""
        return bool(np.any(self.correction[LAWS.index(self.check_law(law))] != 1.0))

    def _locate(self, lam) -> tuple[np.ndarray, np.ndarray]:
        """Segment index (clamped to [0, n-2]) and unclipped offset t in grid steps."""
        s = (np.asarray(lam, dtype=np.float64) - self.lam_min) / self.dlam
        i = np.clip(np.floor(s), 0, self.n - 2).astype(np.intp)
        return i, s - i

    def check_law(self, law: str | None) -> str:
        """Return *law* (or the default law) after validation."""
        law = self.default_law if law is None else law
        if law not in LAWS:
            raise ConfigError(f"law: unknown force law {law!r}; use one of {', '.join(LAWS)}")
        return law

    # -- the material's own curves ---------------------------------------------
    @cached_property
    def material_values(self) -> np.ndarray:
        """The material's :math:`\\mu_e` on the grid [Pa], shape (3, n) (``values / correction[0]``)."""
        return _readonly(self.values / self.correction[0][None, :])

    @cached_property
    def material_stress(self) -> np.ndarray:
        """The material's :math:`W_T'` on the grid [Pa], shape (3, n) (``stress / correction[1]``)."""
        return _readonly(self.stress / self.correction[1][None, :])

    # -- evaluation --------------------------------------------------------
    def mu_e(self, lam) -> np.ndarray:
        """The material's :math:`\\mu_e` [Pa] interpolated, shape (3, *lam.shape); held off the grid."""
        return self._interp_clamped(self.material_values, lam)

    def stiffness_modulus(self, lam) -> np.ndarray:
        """Interpolated ``values`` (the secant law's corrected modulus) [Pa], shape (3, *lam.shape).

        The spring stiffness is ``k_ij = c * v_ij * cos2_ij @ stiffness_modulus(lam)``;
        held constant off the grid.
        """
        return self._interp_clamped(self.values, lam)

    def _interp_clamped(self, rows: np.ndarray, lam) -> np.ndarray:
        i, t = self._locate(lam)
        tc = np.clip(t, 0.0, 1.0)
        return rows[:, i] + (rows[:, i + 1] - rows[:, i]) * tc

    def force_function(self, lam, *, law: str | None = None) -> np.ndarray:
        """:math:`f_d(\\lambda)` [Pa] of the module docstring (with the correction), shape (3, *lam.shape).

        The spring force magnitude (positive = tension) is
        ``c * V / L0 * sum_d cos2[d] * f[d]``.
        """
        law = self.check_law(law)
        lam = np.asarray(lam, dtype=np.float64)
        if law == "secant":
            return self.stiffness_modulus(lam) * (lam - 1.0)
        i, t = self._locate(lam)
        s = self.stress
        return s[:, i] + (s[:, i + 1] - s[:, i]) * t

    def tangent_function(self, lam, *, law: str | None = None) -> np.ndarray:
        """:math:`df_d/d\\lambda` [Pa] of the interpolant, shape (3, *lam.shape).

        At a grid node the slope of the segment to the right is returned.
        """
        law = self.check_law(law)
        lam = np.asarray(lam, dtype=np.float64)
        i, t = self._locate(lam)
        if law == "energy":
            s = self.stress
            return (s[:, i + 1] - s[:, i]) / self.dlam
        v = self.values
        inside = (t >= 0.0) & (t <= 1.0)
        dmu = np.where(inside, (v[:, i + 1] - v[:, i]) / self.dlam, 0.0)
        return self.stiffness_modulus(lam) + (lam - 1.0) * dmu

    def potential(self, lam, *, law: str | None = None) -> np.ndarray:
        """:math:`\\int_1^\\lambda f_d\\,d\\lambda` [Pa], shape (3, *lam.shape).

        The exact integral of :meth:`force_function` (piecewise polynomial), so
        a spring's energy ``c * V * sum_d cos2[d] * potential[d]`` has
        :math:`\\partial E/\\partial L` equal to its force for either law. For
        the uncorrected energy law this is :math:`W_T(\\lambda)` up to the
        interpolation error. For the secant law it differs from the paper's
        :math:`\\tfrac12 k (L-L_0)^2 = V W_T` (which is not the potential of the
        secant force).
        """
        law = self.check_law(law)
        lam = np.asarray(lam, dtype=np.float64)
        p1 = self._potential_raw(np.asarray(1.0), law)
        return self._potential_raw(lam, law) - p1.reshape((3,) + (1,) * lam.ndim)

    def _potential_raw(self, lam: np.ndarray, law: str) -> np.ndarray:
        h = self.dlam
        i, t = self._locate(lam)
        lam_i = self.lam_min + i * h
        if law == "energy":
            cum = self._cum_energy
            s = self.stress
            tau = t * h
            return cum[:, i] + s[:, i] * tau + (s[:, i + 1] - s[:, i]) * tau**2 / (2.0 * h)
        cum = self._cum_secant
        v = self.values
        tau = np.clip(t, 0.0, 1.0) * h
        a = v[:, i]
        b = (v[:, i + 1] - v[:, i]) / h
        c = lam_i - 1.0
        inside = cum[:, i] + a * c * tau + (a + b * c) * tau**2 / 2.0 + b * tau**3 / 3.0
        # Off the grid the modulus is constant: f = mu_end * (lam - 1).
        lo = t < 0.0
        hi = t > 1.0
        lam_end = np.where(lo, self.lam_min, np.where(hi, self.lam_max, lam))
        shape = (3,) + (1,) * lam.ndim
        mu_end = np.where(lo, v[:, 0].reshape(shape), v[:, -1].reshape(shape))
        ext = 0.5 * mu_end * ((lam - 1.0) ** 2 - (lam_end - 1.0) ** 2)
        return inside + np.where(lo | hi, ext, 0.0)

    @cached_property
    def _cum_energy(self) -> np.ndarray:
        s = self.stress
        seg = 0.5 * (s[:, 1:] + s[:, :-1]) * self.dlam
        return np.concatenate([np.zeros((3, 1)), np.cumsum(seg, axis=1)], axis=1)

    @cached_property
    def _cum_secant(self) -> np.ndarray:
        h = self.dlam
        v = self.values
        a = v[:, :-1]
        b = (v[:, 1:] - v[:, :-1]) / h
        c = self.lam[:-1] - 1.0
        seg = a * c * h + (a + b * c) * h**2 / 2.0 + b * h**3 / 3.0
        return np.concatenate([np.zeros((3, 1)), np.cumsum(seg, axis=1)], axis=1)

    # -- derived -----------------------------------------------------------
    def with_compensation(self, factor: float, *, correction: dict[str, np.ndarray] | None = None,
                          record: dict[str, Any] | None = None) -> StiffnessTables:
        """A copy with ``volume_factor = factor`` and, per law, a new correction row.

        Parameters
        ----------
        factor : float
            The scalar :math:`c`.
        correction : dict, optional
            ``{law: g}`` with ``g`` of shape (n,); laws not given keep their row.
        record : dict, optional
            Stored as ``metadata["compensation"]`` (a calibration report).
        """
        corr = np.array(self.correction, copy=True)
        for law, g in (correction or {}).items():
            g = np.asarray(g, dtype=np.float64)
            if g.shape != (self.n,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
                raise ValueError(f"correction[{law!r}]: need {self.n} positive finite values")
            corr[LAWS.index(self.check_law(law))] = g
        meta = dict(self.metadata)
        if record is not None:
            meta["compensation"] = record
        return self._with_rows(corr, volume_factor=float(factor), metadata=meta)

    def _with_rows(self, corr: np.ndarray, **changes) -> StiffnessTables:
        values = self.material_values * corr[0][None, :]
        stress = self.material_stress * corr[1][None, :]
        return replace(self, values=values, stress=stress,
                       energy=_integrate_from_one(self.lam, stress), correction=corr, **changes)

    def without_compensation(self) -> StiffnessTables:
        """A copy with ``volume_factor = 1`` and no correction (the material's own curves)."""
        meta = {k: v for k, v in self.metadata.items() if k != "compensation"}
        return self._with_rows(np.ones((len(LAWS), self.n)), volume_factor=1.0, metadata=meta)



# ---------------------------------------------------------------------------
# Building from a material
# ---------------------------------------------------------------------------

def _material_directions(material) -> tuple[str | None, str | None, str | None]:
    """The ``direction=`` argument to pass for the x, y, z rows (all None if isotropic)."""
    iso = getattr(material, "is_isotropic", None)
    if iso is None:
        iso = not getattr(material, "directions", None)
    if iso:
        return (None, None, None)
    return tuple(DIRECTIONS)  # type: ignore[return-value]


def _material_curves(material, lam: np.ndarray, direction: str | None):
    """(W, W', mu_e) of *material* in uniaxial stretch *lam* along *direction*."""
    W = np.asarray(material.uniaxial_energy(lam, direction), dtype=np.float64)
    mu = np.asarray(material.mu_e(lam, direction), dtype=np.float64)
    P = np.asarray(nominal_stress(material.model_obj, material.params_for(direction), "uniaxial", lam),
                   dtype=np.float64)
    return W, P, mu


def _admissible(material, direction: str | None) -> tuple[float, float]:
    lo, hi = material.stretch_range(direction)
    return float(lo), float(hi)


def default_grid(material) -> tuple[float, float]:
    """The default (lam_min, lam_max) for *material* from its admissible range (see :data:`GRID_RULE`),
    before :func:`build_tables` narrows it to where the stress increases."""
    lo, hi, _ = _default_ends(material)
    return lo, hi


def _default_ends(material) -> tuple[float, float, dict[str, str]]:
    """The default grid ends and, per end, why it is there (the locking stretch or the bound)."""
    lo_all, hi_all = 0.0, math.inf
    for d in sorted(set(_material_directions(material)), key=str):
        lo, hi = _admissible(material, d)
        lo_all, hi_all = max(lo_all, lo), min(hi_all, hi)
    lock_lo = lo_all + LOCK_MARGIN * (1 - lo_all) if lo_all > 0 else -math.inf
    lock_hi = hi_all - LOCK_MARGIN * (hi_all - 1) if math.isfinite(hi_all) else math.inf
    why = {}
    if lock_lo > DEFAULT_LAM_MIN:
        lam_min, why["lam_min"] = lock_lo, f"{LOCK_MARGIN:.0%} inside the material's locking stretch {lo_all:.4g}"
    else:
        lam_min, why["lam_min"] = DEFAULT_LAM_MIN, (f"the bound {DEFAULT_LAM_MIN:g}, past any compression an organ "
                                                    "survives" + _lock_note(lo_all))
    if lock_hi < DEFAULT_LAM_MAX:
        lam_max, why["lam_max"] = lock_hi, f"{LOCK_MARGIN:.0%} inside the material's locking stretch {hi_all:.4g}"
    else:
        lam_max, why["lam_max"] = DEFAULT_LAM_MAX, (f"the bound {DEFAULT_LAM_MAX:g} (100 % strain), past the "
                                                    "rupture of soft tissue" + _lock_note(hi_all))
    return lam_min, lam_max, why


def _lock_note(lock: float) -> str:
    return "" if lock <= 0 or not math.isfinite(lock) else f" (the material locks only at {lock:.4g})"


def material_toml_text(material) -> str:
    """The material as TOML text, for provenance (empty if it cannot be serialised)."""
    for attr in ("to_toml_string", "to_toml", "dumps"):
        fn = getattr(material, attr, None)
        if callable(fn):
            try:
                out = fn()
            except TypeError:
                continue
            if isinstance(out, str):
                return out
    return ""


@dataclass(frozen=True)
class GridOptions:
    """The options of :func:`build_tables` that do not depend on the material (checked by
    :func:`grid_options`): grid points, default law, grid ends (None: from the material)."""

    n: int = DEFAULT_N
    law: str = "secant"
    lam_min: float | None = None
    lam_max: float | None = None


def grid_options(*, n=DEFAULT_N, law="secant", lam_min=None, lam_max=None,
                 names: Mapping[str, str] | None = None) -> GridOptions:
    """Checked :class:`GridOptions`: ``n >= 3`` points, a law of :data:`LAWS`,
    ``0 < lam_min < 1 < lam_max`` (finite).

    *names* maps an option to the parameter name used in messages (default:
    the option's name; e.g. ``[tables] n`` for a config key).

    Raises
    ------
    ConfigError
        Naming the option.
    """
    def name(key: str) -> str:
        return (names or {}).get(key, key)

    return GridOptions(
        n=number(n, name("n"), lo=3, integer=True), law=choice(law, LAWS, name("law")),
        lam_min=None if lam_min is None else number(lam_min, name("lam_min"), lo=0.0, hi=1.0, lo_open=True,
                                                    hi_open=True),
        lam_max=None if lam_max is None else number(lam_max, name("lam_max"), lo=1.0, lo_open=True))


def build_tables(material, *, n: int = DEFAULT_N, lam_min: float | None = None,
                 lam_max: float | None = None, law: str = "secant") -> StiffnessTables:
    """Tabulate :math:`\\mu_e`, :math:`W_T'` and :math:`W_T` of *material*.

    Parameters
    ----------
    material : esmm.pipeline.materials.material.Material
        The tissue; per-direction parameters give three different rows.
    n : int
        Number of grid points (>= 3).
    lam_min, lam_max : float, optional
        Grid ends; default from the material (see :data:`GRID_RULE`): inside its
        admissible uniaxial range, within [0.5, 2], and narrowed to the stretches
        around 1 where its uniaxial stress is finite and increasing
        (``metadata["grid"]`` records why each end is where it is, and a
        ``warning`` when the grid was narrowed). Given ends must lie in that
        range with ``lam_min < 1 < lam_max``.
    law : {"secant", "energy"}
        The default force law recorded in the tables.

    Returns
    -------
    StiffnessTables

    Raises
    ------
    ConfigError
        Bad grid options.
    InputError
        The material's energy is not finite on a given grid, or its uniaxial
        stress does not increase with stretch there (the network would be
        unstable); narrow the grid. With the default grid: the stress
        increases on no interval around 1.
    """
    grid = grid_options(n=n, law=law, lam_min=lam_min, lam_max=lam_max)
    n, law = grid.n, grid.law
    name = getattr(material, "name", None) or getattr(material, "model", "material")
    dirs = _material_directions(material)
    lo, hi, why = _default_ends(material)
    if grid.lam_min is not None:
        lo, why["lam_min"] = grid.lam_min, "given"
    if grid.lam_max is not None:
        hi, why["lam_max"] = grid.lam_max, "given"
    _check_admissible(material, dirs, lo, hi, name)
    lam, curves = _tabulate(material, dirs, lo, hi, n)
    narrowed: dict[str, str] = {}
    for _ in range(4):   # narrow the default ends to where the stress increases (each pass on a finer grid)
        bad = _first_bad(lam, curves)
        if bad is None:
            break
        side, k, what = bad
        if why[side] == "given" or not _narrowable(lam, side, k):
            raise _curve_error(name, side, lam, k, what, given=why[side] == "given")
        narrowed[side] = what
        lo, hi = (float(lam[k + 2]), hi) if side == "lam_min" else (lo, float(lam[k - 2]))
        lam, curves = _tabulate(material, dirs, lo, hi, n)
    else:
        raise _curve_error(name, side, lam, k, what, given=False)
    stress = np.vstack([curves[d][0] for d in dirs])
    values = np.vstack([curves[d][1] for d in dirs])
    grid_note = {"lam_min": float(lam[0]), "lam_max": float(lam[-1]), "why": why}
    for side, what in narrowed.items():
        end, where = (lam[0], "below") if side == "lam_min" else (lam[-1], "beyond")
        why[side] = f"narrowed: the material's uniaxial {what} just {where} it"
        grid_note["warning"] = (f"{name}: the tables end at stretch {end:.4g} because the material's uniaxial "
                                f"{what} just {where} it; springs stretched past it keep the end's stiffness "
                                "(a stable network there, where the tissue as fitted is not)")
    meta = {"material_name": str(name), "grid": grid_note,
            "units": {"lam": "1", "mu_e": "Pa", "stress": "Pa", "energy": "Pa"}}
    return StiffnessTables(lam_min=lam[0], lam_max=lam[-1], n=n, values=values, stress=stress,
                           energy=_integrate_from_one(lam, stress), default_law=law,
                           material_toml=material_toml_text(material), metadata=meta)


def _check_admissible(material, dirs, lo: float, hi: float, name: str) -> None:
    """Refuse grid ends outside the material's admissible uniaxial range."""
    for d in sorted(set(dirs), key=str):
        a_lo, a_hi = _admissible(material, d)
        if lo <= a_lo or hi >= a_hi:
            raise ConfigError(
                f"lam_min/lam_max: grid [{lo:g}, {hi:g}] leaves the admissible uniaxial range "
                f"({a_lo:.4g}, {a_hi:.4g}) of {name}"
                + (f" along {d}" if d else "") + "; choose a grid inside it"
            )


def _tabulate(material, dirs, lo: float, hi: float, n: int):
    """The grid through 1 on [lo, hi] (hi lowered) and, per direction, the stress and mu_e on it."""
    lo, hi = _grid_through_one(lo, hi, n)
    lam = np.linspace(lo, hi, n)
    lam[int(round((1.0 - lo) / ((hi - lo) / (n - 1))))] = 1.0
    curves: dict[str | None, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for d in dirs:
        if d not in curves:
            W, P, mu = _material_curves(material, lam, d)
            curves[d] = (P, mu, W)
    return lam, curves


def _first_bad(lam: np.ndarray, curves) -> tuple[str, int, str] | None:
    """The node nearest to 1 (on either side) where a curve is not usable, as (side, index, what), or None.

    Not usable: the energy, stress or mu_e not finite, mu_e not positive, or the stress not
    increasing on the segment that ends at that node (counted from 1 outwards).
    """
    i1 = int(np.argmin(np.abs(lam - 1.0)))
    worst: tuple[int, str, int, str] | None = None
    for P, mu, W in curves.values():
        finite = np.isfinite(W) & np.isfinite(P) & np.isfinite(mu)
        for side, order in (("lam_max", range(i1 + 1, lam.size)), ("lam_min", range(i1 - 1, -1, -1))):
            prev = i1
            for k in order:
                what = ("energy is not finite" if not finite[k] else "mu_e is not positive" if mu[k] <= 0 else
                        "stress stops increasing" if (P[k] - P[prev]) * (k - prev) <= 0 else "")
                if what:
                    if worst is None or abs(k - i1) < worst[0]:
                        worst = (abs(k - i1), side, k, what)
                    break
                prev = k
    return None if worst is None else worst[1:]


def _narrowable(lam: np.ndarray, side: str, k: int) -> bool:
    """Whether an end moved two nodes inside *k* still leaves two steps between it and 1."""
    i1 = int(np.argmin(np.abs(lam - 1.0)))
    return (k + 2 <= i1 - 2) if side == "lam_min" else (k - 2 >= i1 + 2)


def _curve_error(name: str, side: str, lam: np.ndarray, k: int, what: str, *, given: bool) -> InputError:
    """The message for a material whose curve is not usable near stretch ``lam[k]``."""
    if given:
        return InputError(f"{name}: uniaxial {what} near stretch {lam[k]:.4g} (a spring network would be "
                          "unstable there); narrow the grid (lam_min/lam_max) or check the material parameters")
    return InputError(f"{name}: uniaxial {what} near stretch {lam[k]:.4g}, too close to 1 for a spring "
                      "network; check the material parameters (a fit far outside its data, or a parameter at "
                      "its bound)")


def grid_note(tables: StiffnessTables) -> str:
    """Why the tables' grid ends where it does, in words ("" when not recorded)."""
    g = tables.metadata.get("grid") if isinstance(tables.metadata, dict) else None
    if not isinstance(g, dict) or not isinstance(g.get("why"), dict):
        return ""
    why = g["why"]
    return "; ".join(f"{end} {g.get(end, 0):.4g}: {why[end]}" for end in ("lam_min", "lam_max") if end in why)


def _grid_through_one(lo: float, hi: float, n: int) -> tuple[float, float]:
    """Grid ends with *lo* kept and *hi* lowered (never raised) so that 1 is a grid node.

    With ``k = ceil((1 - lo) / dlam)`` steps below 1 the step becomes
    ``(1 - lo) / k <= dlam``; the rest state then has exactly zero force for
    both laws (no interpolation across 1).
    """
    h = (hi - lo) / (n - 1)
    k = max(1, math.ceil((1.0 - lo) / h - 1e-9))
    if k > n - 2:
        raise ConfigError(f"n: {n} grid points leave no room above stretch 1 in [{lo:g}, {hi:g}]; "
                          "use more points or a larger lam_max")
    h = (1.0 - lo) / k
    return lo, lo + (n - 1) * h


def _integrate_from_one(lam: np.ndarray, stress: np.ndarray) -> np.ndarray:
    """Exact integral from 1 of the piecewise-linear interpolant of *stress* at the nodes."""
    h = lam[1] - lam[0]
    seg = 0.5 * (stress[:, 1:] + stress[:, :-1]) * h
    cum = np.concatenate([np.zeros((stress.shape[0], 1)), np.cumsum(seg, axis=1)], axis=1)
    i = int(np.clip(np.floor((1.0 - lam[0]) / h), 0, lam.size - 2))
    tau = 1.0 - lam[i]
    at_one = cum[:, i] + stress[:, i] * tau + (stress[:, i + 1] - stress[:, i]) * tau**2 / (2 * h)
    return cum - at_one[:, None]


# ---------------------------------------------------------------------------
# Per-spring factors and tables
# ---------------------------------------------------------------------------

def _network_arrays(network) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.asarray(network.volume_weight, dtype=np.float64)
    cos2 = np.asarray(network.cos2, dtype=np.float64)
    L0 = np.asarray(network.rest_length, dtype=np.float64)
    s = v.shape[0]
    if cos2.shape != (s, 3) or L0.shape != (s,):
        raise InputError(f"network: volume_weight {v.shape}, cos2 {cos2.shape} and rest_length "
                         f"{L0.shape} do not describe the same {s} springs; rebuild the network")
    return v, cos2, L0


def spring_factors(tables: StiffnessTables, network) -> np.ndarray:
    """Per-spring direction weights :math:`a_{ij,d} = c\\,v_{ij}\\cos^2\\theta_d` [m], shape (s, 3).

    ``k_ij(lam) = a[ij] @ tables.stiffness_modulus(lam)`` (secant law); the force magnitude is
    ``L0 * a[ij] @ f(lam)`` for either law (:meth:`StiffnessTables.force_function`).
    """
    v, cos2, _ = _network_arrays(network)
    return (tables.volume_factor * v)[:, None] * cos2


def per_spring_table(tables: StiffnessTables, network, *, dtype=np.float32) -> np.ndarray:
    """Materialised stiffness :math:`k_{ij}(\\lambda_m)` [N/m] on the table grid, shape (s, n)."""
    a = spring_factors(tables, network)
    return (a @ tables.values).astype(dtype, copy=False)
