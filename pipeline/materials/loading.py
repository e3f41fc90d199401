r"""Homogeneous incompressible deformations: invariants, energy, nominal stress.

Modes (the names of the tensile-data contract, docs/reference/tensile-input.md):

============== ===================================== ========================= =========================
mode           principal stretches (x = λ or γ)      :math:`I_1`               :math:`I_2`
============== ===================================== ========================= =========================
uniaxial       :math:`\lambda, \lambda^{-1/2}, \lambda^{-1/2}` :math:`\lambda^2 + 2/\lambda`   :math:`2\lambda + \lambda^{-2}`
equibiaxial    :math:`\lambda, \lambda, \lambda^{-2}`   :math:`2\lambda^2+\lambda^{-4}` :math:`\lambda^4 + 2\lambda^{-2}`
pure_shear     :math:`\lambda, 1, \lambda^{-1}`         :math:`\lambda^2+1+\lambda^{-2}` same as :math:`I_1`
simple_shear   :math:`F = I + \gamma\,e_1\otimes e_2`   :math:`3+\gamma^2`        :math:`3+\gamma^2`
============== ===================================== ========================= =========================

``uniaxial``, ``equibiaxial`` and ``pure_shear`` (planar tension) take the
stretch λ > 0 (λ < 1 is compression); ``simple_shear`` takes the amount of
shear γ (any sign).

Nominal stress (first Piola-Kirchhoff, force per reference area, in the loading
direction; lateral faces traction-free, the pressure eliminated by
incompressibility) is the derivative of the energy per reference volume
:math:`W(x) = \hat W(I_1(x), I_2(x))`:

* uniaxial, pure shear, simple shear: :math:`P = dW/dx`
  (uniaxial: :math:`P = 2(\lambda-\lambda^{-2})(W_1 + W_2/\lambda)`;
  pure shear: :math:`P = 2(\lambda-\lambda^{-3})(W_1+W_2)`;
  simple shear, shear stress: :math:`P_{12} = 2\gamma(W_1+W_2)`);
* equibiaxial, the stress in *each* of the two loaded directions:
  :math:`P = \tfrac12\,dW/d\lambda = 2(\lambda-\lambda^{-5})(W_1+\lambda^2W_2)`.

Accuracy near the reference state: the increments :math:`I_1-3`,
:math:`I_2-3` are computed in factored form (e.g. uniaxial
:math:`I_1 - 3 = (\lambda-1)^2(\lambda+2)/\lambda`), and small energies are
integrated from the analytic derivatives,
:math:`W = \int_0^1 [W_1 (I_1-3) + W_2 (I_2-3)](3 + t(I_1-3), 3 + t(I_2-3))\,dt`,
so W and :math:`\mu_e = 2W/(\lambda-1)^2` keep full relative precision as
λ → 1 and :math:`\mu_e` is smooth through λ = 1 (where it equals
:math:`W''(1) = E`, the small-strain Young's modulus).

Values outside the admissible range (beyond locking, λ ≤ 0) are NaN.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from scipy.optimize import brentq

from ..errors import InputError
from .base import MaterialModel

__all__ = [
    "MODES",
    "STRETCH_MODES",
    "invariants",
    "path_kinematics",
    "energy_density",
    "nominal_stress",
    "stress_tangent",
    "admissible_range",
    "mu_e",
]

#: The loading modes.
MODES = ("uniaxial", "equibiaxial", "pure_shear", "simple_shear")
#: Modes whose argument is a stretch (the other, simple_shear, takes γ).
STRETCH_MODES = ("uniaxial", "equibiaxial", "pure_shear")

#: divisor k in P = (dW/dx) / k
_STRESS_DIVISOR = {"uniaxial": 1.0, "equibiaxial": 2.0, "pure_shear": 1.0, "simple_shear": 1.0}

# Gauss-Legendre rule on [0, 1] for the small-energy integral. Used where the
# locking singularity is at least _NEAR_MARGIN increments away (quadrature
# error ~ 1e-20) and I1 - 3 < _NEAR_U; above that the direct W(3 + u) has a
# relative round-off of about 3 eps / u < 1e-12 and is used instead.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
_GL_T = 0.5 * (_GL_X + 1.0)
_GL_W01 = 0.5 * _GL_W
_NEAR_U = 1e-3  # I1 - 3 below which the integral form is used
_NEAR_MARGIN = 5.0


def _check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"unknown loading mode {mode!r}; use one of {', '.join(MODES)}")
    return mode


def _kinematics(mode: str, x):
    """Invariant increments and their x-derivatives.

    Returns
    -------
    tuple of ndarray, each shape of ``x``
        ``(u, v, du, dv, d2u, d2v)`` with u = I1 - 3, v = I2 - 3 (factored,
        cancellation-free), du = dI1/dx, ..., d2v = d²I2/dx². Entries for
        inadmissible x (λ ≤ 0) are NaN.
    """
    x = np.asarray(x, dtype=float)
    if mode == "simple_shear":
        u = x * x
        du = 2.0 * x
        d2 = np.full_like(x, 2.0)
        return u, u, du, du, d2, d2
    lam = np.where(x > 0.0, x, np.nan)
    d = lam - 1.0
    il = 1.0 / lam
    if mode == "uniaxial":
        u = d * d * (lam + 2.0) * il
        v = d * d * (2.0 * lam + 1.0) * il * il
        du = 2.0 * lam - 2.0 * il * il
        dv = 2.0 - 2.0 * il**3
        d2u = 2.0 + 4.0 * il**3
        d2v = 6.0 * il**4
    elif mode == "equibiaxial":
        y = lam * lam
        e = (lam - 1.0) * (lam + 1.0)
        u = e * e * (2.0 * y + 1.0) / (y * y)
        v = e * e * (y + 2.0) / y
        du = 4.0 * lam - 4.0 * il**5
        dv = 4.0 * lam**3 - 4.0 * il**3
        d2u = 4.0 + 20.0 * il**6
        d2v = 12.0 * y + 12.0 * il**4
    else:  # pure_shear
        g = lam - il
        u = g * g
        v = u
        du = 2.0 * lam - 2.0 * il**3
        dv = du
        d2u = 2.0 + 6.0 * il**4
        d2v = d2u
    return u, v, du, dv, d2u, d2v


def path_kinematics(mode: str, x) -> tuple:
    """The kinematics of a loading path, for evaluating many parameter sets on it.

    Parameters
    ----------
    mode : str
        One of :data:`MODES`.
    x : array_like, shape (n,)
        Stretch λ, or γ for ``simple_shear``.

    Returns
    -------
    tuple of ndarray, each shape (n,)
        ``(u, v, du, dv, d2u, d2v)``: the invariant increments ``I1 - 3``,
        ``I2 - 3`` and their first and second derivatives along the path; pass
        it as ``kinematics`` to :func:`nominal_stress` and :func:`energy_density`
        (what they compute from ``x`` otherwise, the same numbers).
    """
    return _kinematics(_check_mode(mode), x)


def invariants(mode: str, x):
    """First and second invariants of C for a homogeneous deformation.

    Parameters
    ----------
    mode : str
        One of :data:`MODES`.
    x : array_like, shape (...)
        Stretch λ (> 0), or γ for ``simple_shear``.

    Returns
    -------
    (I1, I2) : tuple of ndarray, shape (...)
    """
    u, v, *_ = _kinematics(_check_mode(mode), x)
    return 3.0 + u, 3.0 + v


def _integrated(model, params, u, v, su, sv):
    """∫_0^1 [W1 su + W2 sv](3 + t u, 3 + t v) dt for 1-D arrays (small u, v)."""
    i1 = 3.0 + u[:, None] * _GL_T[None, :]
    i2 = 3.0 + v[:, None] * _GL_T[None, :]
    w1, w2 = model.dW(i1, i2, params)
    return (w1 @ _GL_W01) * su + (w2 @ _GL_W01) * sv


def _near_mask(model: MaterialModel, params, u, v) -> np.ndarray:
    room = model.max_I1(params) - 3.0
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(u) & np.isfinite(v) & (np.maximum(np.abs(u), np.abs(v)) < _NEAR_U)
            & (_NEAR_MARGIN * np.abs(u) <= room)
        )


def energy_density(model: MaterialModel, params: Mapping[str, float], mode: str, x, *, kinematics=None):
    """Strain energy per unit reference volume along a loading path.

    Parameters
    ----------
    model : MaterialModel
    params : Mapping[str, float]
        Parameter values (SI).
    mode : str
        One of :data:`MODES`.
    x : array_like, shape (...)
        Stretch λ, or γ for ``simple_shear``.
    kinematics : tuple, optional
        :func:`path_kinematics` of *x* (1-D), computed once for many parameter sets.

    Returns
    -------
    ndarray, shape (...)
        W [Pa]; NaN outside the admissible range, ``inf`` at locking.
    """
    shape = np.shape(x)
    if kinematics is None:
        kinematics = _kinematics(_check_mode(mode), np.ravel(np.asarray(x, dtype=float)))
    u, v = kinematics[0], kinematics[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.array(model.energy(3.0 + u, 3.0 + v, params), dtype=float)
    near = _near_mask(model, params, u, v)
    if np.any(near):
        un, vn = u[near], v[near]
        w[near] = _integrated(model, params, un, vn, un, vn)
    return w.reshape(shape) if shape else float(w[0])


def nominal_stress(model: MaterialModel, params: Mapping[str, float], mode: str, x, *, kinematics=None):
    """Nominal (first Piola-Kirchhoff) stress in the loading direction.

    Parameters
    ----------
    model : MaterialModel
    params : Mapping[str, float]
        Parameter values (SI).
    mode : str
        One of :data:`MODES`.
    x : array_like, shape (...)
        Stretch λ, or γ for ``simple_shear`` (then the shear stress P12).
    kinematics : tuple, optional
        :func:`path_kinematics` of *x*, computed once for many parameter sets.

    Returns
    -------
    ndarray, shape (...)
        P [Pa]; NaN outside the admissible range. Vectorised (its cost is
        dominated by the inverse Langevin function).
    """
    mode = _check_mode(mode)
    u, v, du, dv, _, _ = _kinematics(mode, x) if kinematics is None else kinematics
    with np.errstate(invalid="ignore"):
        w1, w2 = model.dW(3.0 + u, 3.0 + v, params)
        p = (w1 * du + w2 * dv) / _STRESS_DIVISOR[mode]
    return p


def stress_tangent(model: MaterialModel, params: Mapping[str, float], mode: str, x):
    """Derivative of :func:`nominal_stress` with respect to λ (or γ).

    Analytic: :math:`(W_{11}I_1'^2 + 2W_{12}I_1'I_2' + W_{22}I_2'^2 + W_1I_1'' + W_2I_2'')/k`.

    Parameters
    ----------
    model, params, mode, x
        As :func:`nominal_stress`.

    Returns
    -------
    ndarray, shape (...)
        dP/dx [Pa]; NaN outside the admissible range.
    """
    mode = _check_mode(mode)
    u, v, du, dv, d2u, d2v = _kinematics(mode, x)
    i1, i2 = 3.0 + u, 3.0 + v
    with np.errstate(invalid="ignore"):
        w1, w2 = model.dW(i1, i2, params)
        w11, w12, w22 = model.d2W(i1, i2, params)
        t = w11 * du * du + 2.0 * w12 * du * dv + w22 * dv * dv + w1 * d2u + w2 * d2v
    return t / _STRESS_DIVISOR[mode]


def mu_e(model: MaterialModel, params: Mapping[str, float], lam):
    r"""Equivalent spring modulus :math:`\mu_e(\lambda) = 2W(\lambda)/(\lambda-1)^2`, uniaxial.

    W is the energy of incompressible uniaxial stretch λ. At λ = 1 the value is
    the limit :math:`W''(1) = 6\,[W_1 + W_2](3, 3) = E`; near it the energy is
    integrated from the analytic derivatives with the exact factors
    :math:`(I_1-3)/(\lambda-1)^2 = (\lambda+2)/\lambda` and
    :math:`(I_2-3)/(\lambda-1)^2 = (2\lambda+1)/\lambda^2`, so there is no 0/0
    and the curve is smooth (analytic) through λ = 1.

    Parameters
    ----------
    model : MaterialModel
    params : Mapping[str, float]
        Parameter values (SI).
    lam : array_like, shape (...)
        Stretch, in the admissible range (compression λ < 1 allowed).

    Returns
    -------
    ndarray, shape (...)
        μ_e [Pa]; NaN outside the admissible range.
    """
    shape = np.shape(lam)
    lam_a = np.ravel(np.asarray(lam, dtype=float))
    u, v, *_ = _kinematics("uniaxial", lam_a)
    d = lam_a - 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.array(model.energy(3.0 + u, 3.0 + v, params), dtype=float)
        out = 2.0 * w / (d * d)
    near = _near_mask(model, params, u, v)
    if np.any(near):
        ln = lam_a[near]
        su = (ln + 2.0) / ln
        sv = (2.0 * ln + 1.0) / (ln * ln)
        out[near] = 2.0 * _integrated(model, params, u[near], v[near], su, sv)
    return out.reshape(shape) if shape else float(out[0])


def admissible_range(model: MaterialModel, params: Mapping[str, float], mode: str):
    """Open interval of λ (or γ) where the energy is finite (from locking).

    Parameters
    ----------
    model, params
        As :func:`nominal_stress`.
    mode : str
        One of :data:`MODES`.

    Returns
    -------
    (lo, hi) : tuple of float
        Exclusive bounds. Without locking: ``(0, inf)`` for the stretch modes,
        ``(-inf, inf)`` for simple shear. If the reference state itself is
        locked (max_I1 ≤ 3) the interval is empty: ``(1, 1)`` or ``(0, 0)``.
    """
    mode = _check_mode(mode)
    m = model.max_I1(params)
    if math.isinf(m):
        return (-math.inf, math.inf) if mode == "simple_shear" else (0.0, math.inf)
    if not m > 3.0:
        return (0.0, 0.0) if mode == "simple_shear" else (1.0, 1.0)
    if mode == "simple_shear":
        g = math.sqrt(m - 3.0)
        return (-g, g)
    if mode == "pure_shear":
        a = m - 1.0  # lam^2 + lam^-2 = a
        y = 0.5 * (a + math.sqrt((a - 2.0) * (a + 2.0)))
        hi = math.sqrt(y)
        return (1.0 / hi, hi)

    def excess(lam):
        u, *_ = _kinematics(mode, lam)
        return float(u) - (m - 3.0)

    if mode == "uniaxial":
        lo_bracket, hi_bracket = 2.0 / m, math.sqrt(m)
        # There the excess is 4/m^2 and 2/sqrt(m): lost in rounding against m for a huge chain number
        # (m = 1.3e6, a discovered tendon fit). Then 1/m and sqrt(m) + 1, where it is about m and
        # 2 sqrt(m); the first bracket is kept where it works, so that every range found before is the
        # same to the last bit.
        if not excess(lo_bracket) > 0.0:
            lo_bracket = 1.0 / m
        if not excess(hi_bracket) > 0.0:
            hi_bracket = math.sqrt(m) + 1.0
    else:  # equibiaxial
        lo_bracket, hi_bracket = m ** -0.25, math.sqrt(m / 2.0)
    kw = dict(xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200)
    lo = brentq(excess, lo_bracket, 1.0, **kw)
    hi = brentq(excess, 1.0, hi_bracket, **kw)
    return (lo, hi)
