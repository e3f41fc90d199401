"""Rate-independent history effects on the elastic stress along a recorded path.

Each function takes the stretch path ``x`` (n,) of a test, the elastic stress ``pe`` and the
elastic energy ``w0`` along it (the undamaged law's), and returns the stress (n,).

* :func:`mullins_discontinuous` discontinuous damage driven by the largest undamaged energy
  reached (Miehe 1995, Eur. J. Mech. A 14:697, "discontinuous damage"; the same structure as de
  Souza Neto, Peric & Owen 1994, J. Mech. Phys. Solids 42:1533): ``P = (1 - D(alpha)) P_e``,
  ``alpha = max W0``, ``D = d_inf (1 - exp(-alpha/eta))``.
* :func:`mullins_pseudo_elastic` Ogden & Roxburgh 1999 (Proc. R. Soc. A 455:2861): the primary
  curve is the elastic one and below a previous maximum ``P = eta P_e``,
  ``eta = 1 - erf((W_max - W0) / (m + beta W_max)) / r``.
* :func:`simo_damage` continuum damage past an onset (Simo 1987, Comput. Methods Appl. Mech. Eng.
  60:153): the equivalent strain ``xi = sqrt(2 W0)``, its running maximum ``Xi``, and
  ``g(Xi) = b + (1 - b)(1 - exp(-z))/z``, ``z = (Xi - Xi_0)/a`` past the threshold ``Xi_0``.
* :func:`continuous_softening` Miehe's continuous damage (Miehe 1995, "continuous damage"): damage
  grows with the arc length of the undamaged energy, ``beta = int |dW0|``,
  ``D = d_inf (1 - exp(-beta/eta))``; at a constant amplitude each cycle adds the same ``beta``, so
  the softening builds from cycle to cycle and saturates (preconditioning).
* :func:`permanent_set` a residual stretch: the multiplicative split ``F = F_e F_p`` with an
  isochoric uniaxial ``F_p`` whose stretch grows with the largest stretch reached,
  ``lambda_p = 1 + f (x_max - 1)**q`` (residual strain growing with the prestrain, as measured on
  filled rubbers by Dorfmann & Ogden 2004, Int. J. Solids Struct. 41:1855). The nominal stress on
  the original section is ``P_e(x/lambda_p)/lambda_p``; below ``lambda_p`` the strip is slack and
  carries nothing.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf


def mullins_discontinuous(pe: np.ndarray, w0: np.ndarray, *, d_inf: float, eta: float) -> np.ndarray:
    alpha = np.maximum.accumulate(np.maximum(w0, 0.0))
    return (1.0 - d_inf * -np.expm1(-alpha / eta)) * pe


def mullins_pseudo_elastic(pe: np.ndarray, w0: np.ndarray, *, r: float, m: float, beta: float) -> np.ndarray:
    w = np.maximum(w0, 0.0)
    wmax = np.maximum.accumulate(w)
    eta = 1.0 - erf((wmax - w) / (m + beta * wmax)) / r
    return eta * pe


def simo_damage(pe: np.ndarray, w0: np.ndarray, *, xi0: float, a: float, b: float) -> np.ndarray:
    xi = np.maximum.accumulate(np.sqrt(2.0 * np.maximum(w0, 0.0)))
    z = np.maximum(xi - xi0, 0.0) / a
    safe = np.where(z > 1e-12, z, 1.0)
    g = np.where(z > 1e-12, b + (1.0 - b) * -np.expm1(-z) / safe, 1.0)
    return g * pe


def continuous_softening(pe: np.ndarray, w0: np.ndarray, *, d_inf: float, eta: float) -> np.ndarray:
    beta = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(w0)))))
    return (1.0 - d_inf * -np.expm1(-beta / eta)) * pe


def permanent_set(x: np.ndarray, stress_fn, *, f: float, q: float) -> np.ndarray:
    """``stress_fn(x_e)`` is the elastic uniaxial stress; ``x`` the stretch path (n,)."""
    x = np.asarray(x, dtype=float)
    lp = 1.0 + f * np.maximum(np.maximum.accumulate(x) - 1.0, 0.0) ** q
    xe = x / lp
    out = np.zeros_like(x)
    taut = xe > 1.0
    out[taut] = stress_fn(xe[taut]) / lp[taut]
    return out
