r"""Drucker stability check of a material over a stretch range.

The incompressible Drucker condition for the homogeneous test modes: the
nominal (first Piola-Kirchhoff) stress must increase with the loading
variable,

.. math::

    \frac{dP}{d\lambda} > 0 \quad \text{(uniaxial, equibiaxial, pure shear; tension and compression)},
    \qquad \frac{dP_{12}}{d\gamma} > 0 \quad \text{(simple shear)},

evaluated with the analytic tangent of
:func:`esmm.pipeline.materials.loading.stress_tangent` on a grid. A fitted
parameter set that violates it gives a spring stiffness that softens with
stretch and an unstable simulation, so the calibration refuses (or flags) it.

The stretch range is clipped to the admissible range of the model (just inside
locking, where the tangent tends to +∞ anyway); simple shear is checked for
:math:`|\gamma| \le \gamma_{max}` with :math:`\gamma_{max} = hi - 1/hi` by
default (the shear whose largest principal stretch is ``hi``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .base import MaterialModel
from .loading import MODES, admissible_range, stress_tangent

__all__ = ["ModeStability", "DruckerReport", "drucker_check"]

#: fraction of the distance to locking kept free when the range is clipped
_LOCK_MARGIN = 1e-4


@dataclass(frozen=True)
class ModeStability:
    """Result of the check in one mode.

    Attributes
    ----------
    mode : str
    lo, hi : float
        The range actually checked (λ, or γ for simple shear).
    clipped : bool
        True when the requested range reached locking and was reduced.
    stable : bool
        dP/dx > 0 at every grid point.
    first_failure : float or None
        The failing grid point nearest the reference state (λ = 1, γ = 0),
        None if stable.
    min_tangent : float
        Smallest dP/dx on the grid [Pa].
    at : float
        Where the smallest tangent occurs.
    """

    mode: str
    lo: float
    hi: float
    clipped: bool
    stable: bool
    first_failure: float | None
    min_tangent: float
    at: float


@dataclass(frozen=True)
class DruckerReport:
    """Drucker check over several modes.

    Attributes
    ----------
    stable : bool
        True when every mode is stable.
    modes : dict[str, ModeStability]
        Per-mode results.
    first_failure : dict[str, float | None]
        Per mode, where the check first fails (nearest the reference state).
    min_tangent : dict[str, tuple[float, float]]
        Per mode, ``(x, dP/dx)`` at the smallest tangent [Pa].
    """

    stable: bool
    modes: dict[str, ModeStability]
    first_failure: dict[str, float | None] = field(default_factory=dict)
    min_tangent: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def summary(self) -> str:
        """One line: stable, or the modes and stretches where it fails."""
        if self.stable:
            ranges = ", ".join(f"{m.mode} {m.lo:.4g}..{m.hi:.4g}" for m in self.modes.values())
            return f"Drucker stable ({ranges})"
        bad = [
            f"{m.mode} at {m.first_failure:.4g} (dP/dx min {m.min_tangent:.3g} Pa at {m.at:.4g})"
            for m in self.modes.values() if not m.stable
        ]
        return "Drucker unstable: " + "; ".join(bad)

    def __str__(self) -> str:
        return self.summary


def drucker_check(
    model: MaterialModel,
    params: Mapping[str, float],
    *,
    modes: Sequence[str] = ("uniaxial", "equibiaxial", "pure_shear"),
    lo: float = 0.5,
    hi: float = 2.0,
    n: int = 401,
    gamma_max: float | None = None,
) -> DruckerReport:
    """Check the Drucker condition dP/dx > 0 on a grid.

    Parameters
    ----------
    model : MaterialModel
    params : Mapping[str, float]
        Parameter values (SI).
    modes : sequence of str
        Modes to check (any of :data:`~esmm.pipeline.materials.loading.MODES`).
    lo, hi : float
        Stretch range, ``0 < lo <= 1 <= hi``; clipped to the admissible range.
    n : int
        Grid points per mode (λ = 1 or γ = 0 is always included).
    gamma_max : float, optional
        Simple-shear range ±γ_max; default ``hi - 1/hi``.

    Returns
    -------
    DruckerReport
    """
    if not (0.0 < lo <= 1.0 <= hi):
        raise ConfigError(f"drucker_check: need 0 < lo <= 1 <= hi, got lo={lo!r}, hi={hi!r}")
    if n < 3:
        raise ConfigError(f"drucker_check: n must be at least 3, got {n!r}")
    results: dict[str, ModeStability] = {}
    for mode in modes:
        if mode not in MODES:
            raise ConfigError(f"drucker_check: unknown mode {mode!r}; use one of {', '.join(MODES)}")
        if mode == "simple_shear":
            g = (hi - 1.0 / hi) if gamma_max is None else float(gamma_max)
            req_lo, req_hi, ref = -g, g, 0.0
        else:
            req_lo, req_hi, ref = lo, hi, 1.0
        a_lo, a_hi = admissible_range(model, params, mode)
        c_lo = max(req_lo, a_lo + _LOCK_MARGIN * (ref - a_lo)) if math.isfinite(a_lo) else req_lo
        c_hi = min(req_hi, a_hi - _LOCK_MARGIN * (a_hi - ref)) if math.isfinite(a_hi) else req_hi
        clipped = c_lo > req_lo or c_hi < req_hi
        half = max(n // 2, 2)
        x = np.unique(np.concatenate([
            np.linspace(c_lo, ref, half), np.linspace(ref, c_hi, n - half + 1),
        ]))
        t = stress_tangent(model, params, mode, x)
        bad = ~(t > 0.0)  # NaN counts as a failure
        i_min = int(np.nanargmin(t)) if np.any(np.isfinite(t)) else 0
        first = None
        if np.any(bad):
            xb = x[bad]
            first = float(xb[np.argmin(np.abs(xb - ref))])
        results[mode] = ModeStability(
            mode=mode, lo=float(c_lo), hi=float(c_hi), clipped=bool(clipped),
            stable=not bool(np.any(bad)), first_failure=first,
            min_tangent=float(t[i_min]), at=float(x[i_min]),
        )
    return DruckerReport(
        stable=all(r.stable for r in results.values()),
        modes=results,
        first_failure={m: r.first_failure for m, r in results.items()},
        min_tangent={m: (r.at, r.min_tangent) for m, r in results.items()},
    )
