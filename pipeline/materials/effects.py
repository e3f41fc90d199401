r"""Material effects beyond hyperelasticity, and the data object that carries them.

Five *material* effects extend a hyperelastic base model with nominal stress
:math:`P_e(\lambda)` (see docs/design/discovery.md, "The extended model", for the reasons behind each choice):

``viscoelastic`` — quasi-linear viscoelasticity (Fung, 1981)
    .. math::

        P(t) = \int_0^t G(t-s)\,\frac{dP_e(s)}{ds}\,ds,
        \qquad G(t) = g_\infty + \sum_{i=1}^{n} g_i e^{-t/\tau_i},
        \qquad g_\infty = 1 - \sum_i g_i \ge 0 .

    :math:`G(0) = 1`: the base model's parameters are the **instantaneous**
    (glassy) response; the long-term (equilibrium) response is
    :math:`g_\infty P_e`. With :math:`h_i(t) = \int_0^t e^{-(t-s)/\tau_i}\,dP_e`,
    :math:`P = g_\infty P_e + \sum_i g_i h_i`, and for :math:`P_e` linear between
    samples :math:`t_k, t_{k+1} = t_k + \Delta`:

    .. math::

        h_i(t_{k+1}) = e^{-\Delta/\tau_i} h_i(t_k)
        + \frac{\tau_i}{\Delta}\left(1 - e^{-\Delta/\tau_i}\right)
          \left(P_e(t_{k+1}) - P_e(t_k)\right),

    exact, O(n) per evaluation (:func:`qlv_stress`). The record is assumed to
    start from rest: :math:`h_i(t_0) = P_e(t_0)` (a step to the first sample).

``mullins`` — Ogden & Roxburgh (1999) pseudo-elasticity
    .. math::

        P = \eta\,P_e, \qquad
        \eta = 1 - \frac{1}{r}\,
        \operatorname{erf}\!\left(\frac{W_{max} - W}{m + \beta W_{max}}\right),

    with :math:`W` the base model's strain energy [Pa] and :math:`W_{max}` its
    maximum so far in the test. On the primary (virgin) loading path
    :math:`W = W_{max}` and :math:`\eta = 1`.

``damage`` — irreversible softening past an onset (Weibull)
    .. math::

        P = (1 - D)\,P_e, \qquad
        D = (1 - b)\left(1 - \exp\!\left[-\left(\frac{(\xi_{max} - \lambda_d)_+}{s}\right)^{k}\right]\right),

    with :math:`\xi` the uniaxial-equivalent stretch (the uniaxial stretch
    :math:`\ge 1` with the same :math:`I_1`; it *is* the stretch in uniaxial
    tension) and :math:`\xi_{max}` its maximum so far. Unlike Mullins softening,
    damage also lowers the primary loading curve. The floor b ∈ [0, 1) is the
    fraction damage leaves however far the specimen is stretched (b = 0 unless the
    data ask for it): Simo's (1987, Comput. Methods Appl. Mech. Eng. 60:153)
    damage function tends to such a residual fraction, which a form that decays to
    zero bends down too far at large stretch.

``viscoelastic`` with ``kappa`` — stretch-dependent relaxation (nonlinear viscoelasticity)
    .. math::

        P = P_e - s(\xi)\,\bigl(P_e - P_\text{QLV}\bigr),
        \qquad s(\xi) = \min\!\left(e^{\kappa(\xi - 1)},\ 1/\textstyle\sum_i g_i\right),

    the QLV relaxation of Fung with a *strength* that depends on the current
    uniaxial-equivalent stretch ξ (κ = 0: QLV). The internal variables and the
    relaxation times are those of QLV; only the amount that relaxes changes with
    stretch — in tendon and ligament it falls with strain (Provenzano et al. 2001),
    in elastomers such as VHB it grows. :func:`relaxation_strength`.

``viscoelastic`` with ``kappa_tau`` — stretch-dependent relaxation rate (nonlinear viscoelasticity)
    .. math::

        \tau_i(\xi) = \tau_i\,e^{-\kappa_\tau(\xi - 1)},
        \qquad \dot h_i = \dot P_e - h_i/\tau_i(\xi),
        \qquad P = g_\infty P_e + \sum_i g_i h_i ,

    the Prony branches of QLV with relaxation *times* that depend on the current
    uniaxial-equivalent stretch (κ_τ = 0: QLV). The amount that relaxes at
    equilibrium is that of QLV; how fast it relaxes changes with stretch — the
    form ligament and tendon show (the relaxation rate falls as strain rises:
    Provenzano et al. 2001, Hingorani et al. 2004, Duenwald et al. 2009), which
    the strength form above cannot give. :func:`qlv_rate_stress`.

``cyclic_softening`` — continuous damage from cycling (Miehe 1995)
    .. math::

        P = \bigl[1 - d_\infty\bigl(1 - e^{-\alpha/\eta_c}\bigr)\bigr]\,P_e,
        \qquad \alpha(t) = \int_0^t \left|\frac{dW}{ds}\right| ds,

    α the accumulated variation of the base strain energy: it keeps growing
    while a specimen is cycled at a constant amplitude, which Mullins softening
    (a function of :math:`W_{max}` only) cannot do. The softening saturates at
    :math:`d_\infty` (preconditioning). :func:`cyclic_factor`.

``permanent_set`` — residual strain that grows with the largest stretch
    .. math::

        \lambda_s = 1 + s_p\,(\lambda_{max} - 1)^q,\qquad
        P = P_e(\lambda/\lambda_s)/\lambda_s ,

    the stress-free stretch :math:`\lambda_s` moves with the largest stretch
    reached (multiplicative split, the set configuration incompressible, hence
    the nominal-area factor :math:`1/\lambda_s`); below it a pulled strip is
    slack (force 0). The exponent q is 1 (a residual strain proportional to
    the largest strain) unless the data ask for another: filled rubbers'
    residual strain grows faster than the prestrain (Dorfmann & Ogden 2004,
    Int. J. Solids Struct. 41:1855). Stretch modes in tension only.
    :func:`set_stretch`.

Effects compose as
:math:`P = \mathrm{VE}\bigl[(1-D)\,\eta\,c\;P_e(\lambda/\lambda_s)/\lambda_s\bigr]`,
c the cyclic-softening factor: damage and softening act on the elastic response
at the elastic stretch, which then relaxes.

:class:`MaterialEffects` is the plain data object that the discovery writes
(``discover.json``, ``[material.effects.*]`` in ``params.toml``) and that the
asset writer and the simulator read. The state a simulator must carry per
spring is listed by :meth:`MaterialEffects.state_variables`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import erf

from ..errors import ConfigError
from ..units import from_si, parse_quantity, to_si

__all__ = [
    "MATERIAL_EFFECTS",
    "ARTEFACTS",
    "EFFECT_NAMES",
    "ViscoelasticEffect",
    "MullinsEffect",
    "DamageEffect",
    "MaterialEffects",
    "qlv_stress",
    "qlv_decay",
    "qlv_step",
    "mullins_factor",
    "damage_factor",
    "equivalent_stretch",
    "CyclicSofteningEffect",
    "PermanentSetEffect",
    "cyclic_factor",
    "set_stretch",
    "relaxation_strength",
    "relaxation_times",
    "qlv_rate_decay",
    "qlv_rate_stress",
]

#: Effects that become part of the material.
MATERIAL_EFFECTS = ("viscoelastic", "mullins", "damage", "cyclic_softening", "permanent_set")
#: Effects that are measurement artefacts (corrected in the data, per test).
ARTEFACTS = ("slack", "sensor_offset", "specimen_scale", "grip_slip")
#: Every effect name used in the discovery's JSON.
EFFECT_NAMES = MATERIAL_EFFECTS + ARTEFACTS

SCHEMA = "esmm.material-effects/1"
#: the composition written with the newer effects (the older string is kept when only QLV, Mullins, damage)
COMPOSITION = "P = VE[(1 - D) * eta * c * P_e(lam/lam_s)/lam_s]"


# --------------------------------------------------------------------------- kernels
def _qlv_decay_py(t, tau, xi, kappa_tau, a, b):  # pragma: no cover - compiled by numba (checked in tests/test_discover.py)
    """Per step k and term i: the decay ``a = exp(-Δ r/τ)`` and the ramp factor ``b = τ/(Δ r) (1 - a)``, with
    ``r = exp(kappa_tau (xi_mid - 1))``, ``xi_mid = (xi[k-1] + xi[k]) / 2``, the step's relaxation rate
    relative to ``1/τ`` (:func:`qlv_rate_decay`; 1 for QLV, ``kappa_tau = 0``, *xi* then not read).

    Row 0 and steps without advance (Δ ≤ 0) get ``a = b = 1``: the recursion
    then adds the stress step to ``h`` unchanged (``1·h + 1·Δp = h + Δp`` exactly).
    """
    n, m = t.shape[0], tau.shape[0]
    for i in range(m):
        a[0, i] = 1.0
        b[0, i] = 1.0
    for k in range(1, n):
        dt = t[k] - t[k - 1]
        rate = math.exp(kappa_tau * (0.5 * (xi[k - 1] + xi[k]) - 1.0)) if kappa_tau != 0.0 else 1.0
        for i in range(m):
            if dt > 0.0:
                x = dt * rate / tau[i]
                a[k, i] = math.exp(-x)
                b[k, i] = -math.expm1(-x) / x if x > 1e-12 else 1.0 - 0.5 * x
            else:
                a[k, i] = 1.0
                b[k, i] = 1.0


def _qlv_recursion_py(pe, g, a, b, out, state):  # pragma: no cover - compiled by numba
    """The QLV recursion on the factors of :func:`_qlv_decay_py` (module docstring)."""
    n, m = pe.shape[0], g.shape[0]
    ginf = 1.0 - g.sum()
    h = np.full(m, pe[0])
    out[0] = pe[0]
    for k in range(1, n):
        dp = pe[k] - pe[k - 1]
        acc = ginf * pe[k]
        for i in range(m):
            h[i] = a[k, i] * h[i] + b[k, i] * dp
            acc += g[i] * h[i]
        out[k] = acc
    state[:] = h


@functools.cache
def _qlv_kernels():
    """(decay, recursion) compiled (numba, imported on first use: reading an asset or a material must
    not pay numba's start-up); the plain-Python ones without numba."""
    try:
        from numba import njit
    except ImportError:  # pragma: no cover
        return _qlv_decay_py, _qlv_recursion_py
    jit = njit(cache=True, nogil=True)
    return jit(_qlv_decay_py), jit(_qlv_recursion_py)


def qlv_decay(t, tau) -> tuple[np.ndarray, np.ndarray]:
    """The factors of the QLV recursion for sample times *t* and relaxation times *tau*.

    What :func:`qlv_stress` computes first: give it back as its ``decay`` to
    evaluate many elastic histories on the same times and relaxation times.

    Parameters
    ----------
    t : array_like, shape (n,)
        Time [s], non-decreasing.
    tau : array_like, shape (m,)
        Relaxation times [s], positive.

    Returns
    -------
    (a, b) : tuple of ndarray, each shape (n, m)
    """
    t = np.ascontiguousarray(t, dtype=float)
    return _decay(t, tau, t, 0.0)


def _decay(t: np.ndarray, tau, xi: np.ndarray, kappa_tau: float) -> tuple[np.ndarray, np.ndarray]:
    """The factors of :func:`_qlv_decay_py` for contiguous times *t* and stretches *xi*."""
    tau = np.ascontiguousarray(np.atleast_1d(tau), dtype=float)
    a = np.empty((t.size, tau.size))
    b = np.empty((t.size, tau.size))
    if t.size:
        _qlv_kernels()[0](t, tau, xi, float(kappa_tau), a, b)
    return a, b


def qlv_stress(t, pe, g, tau, *, return_state: bool = False, decay: tuple | None = None):
    """Quasi-linear viscoelastic stress history (exact for piecewise-linear ``pe``).

    Parameters
    ----------
    t : array_like, shape (n,)
        Time [s], non-decreasing.
    pe : array_like, shape (n,)
        Elastic (instantaneous) stress history [Pa].
    g : array_like, shape (m,)
        Prony weights, ``g_i >= 0``, ``sum(g) <= 1``.
    tau : array_like, shape (m,)
        Relaxation times [s], positive.
    return_state : bool
        Also return the internal variables ``h_i`` at the last sample.
    decay : tuple, optional
        ``qlv_decay(t, tau)``, computed once for many histories (then *t* and
        *tau* are not read again).

    Returns
    -------
    P : ndarray, shape (n,)
        Stress [Pa]; NaN where ``pe`` is NaN (and after it: the history is lost).
    h : ndarray, shape (m,)
        Only if *return_state*.
    """
    pe = np.ascontiguousarray(pe, dtype=float)
    g = np.ascontiguousarray(np.atleast_1d(g), dtype=float)
    out = np.empty_like(pe)
    state = np.empty_like(g)
    if pe.size == 0:
        return (out, state) if return_state else out
    a, b = qlv_decay(t, tau) if decay is None else decay
    _qlv_kernels()[1](pe, g, a, b, out, state)
    return (out, state) if return_state else out


def relaxation_times(xi, tau, kappa_tau: float):
    """The relaxation times at stretch *xi*, ``tau_i exp(-kappa_tau (xi - 1))``, shape ``xi.shape + tau.shape``."""
    xi = np.asarray(xi, float)
    return np.asarray(tau, float) * np.exp(-kappa_tau * (xi[..., None] - 1.0))


def qlv_rate_decay(t, tau, xi, kappa_tau: float) -> tuple[np.ndarray, np.ndarray]:
    r"""The factors of the QLV recursion with stretch-dependent relaxation times.

    Over each sample interval :math:`[t_k, t_{k+1}]`, :math:`\Delta = t_{k+1} - t_k`, the
    relaxation rate is held at the stretch of the interval's middle and the elastic
    stress is linear, so the branch equation :math:`\dot h_i = \dot P_e - h_i/\tau_i(\xi)`
    has constant coefficients and is integrated exactly:

    .. math::

        \tau_{i,k} = \tau_i\,e^{-\kappa_\tau(\bar\xi_k - 1)},\quad
        \bar\xi_k = \tfrac12(\xi_k + \xi_{k+1}),\qquad
        a_{k+1,i} = e^{-\Delta/\tau_{i,k}},\quad
        b_{k+1,i} = \frac{\tau_{i,k}}{\Delta}\left(1 - a_{k+1,i}\right),

    and :math:`h_i(t_{k+1}) = a\,h_i(t_k) + b\,(P_e(t_{k+1}) - P_e(t_k))` as in QLV.
    Where the stretch is held (the holds, where relaxation is measured) this is the
    exact solution; on a ramp the midpoint rule for :math:`\int dt/\tau_i(\xi(t))` makes
    the step error third order in Δ (second order over a record), where the
    stretch at either end of the interval would lag or lead it by half a step
    (first order). With ``kappa_tau = 0`` the factors are those of
    :func:`qlv_decay`, bit for bit.

    Parameters
    ----------
    t : array_like, shape (n,)
        Time [s], non-decreasing.
    tau : array_like, shape (m,)
        Relaxation times at ξ = 1 [s], positive.
    xi : array_like, shape (n,)
        Uniaxial-equivalent stretch of each sample (:func:`equivalent_stretch`).
    kappa_tau : float
        Stretch sensitivity of the relaxation rate (> 0: faster relaxation at larger stretch).

    Returns
    -------
    (a, b) : tuple of ndarray, each shape (n, m)
        To pass as ``decay`` to :func:`qlv_stress`.
    """
    t = np.ascontiguousarray(t, dtype=float)
    xi = np.ascontiguousarray(xi, dtype=float)
    if xi.shape != t.shape:
        raise ConfigError(f"stretch-dependent relaxation rate: xi has {xi.size} samples, t {t.size}")
    return _decay(t, tau, xi, kappa_tau)


def qlv_rate_stress(t, pe, xi, g, tau, kappa_tau: float, *, return_state: bool = False):
    r"""Viscoelastic stress history with stretch-dependent relaxation times.

    .. math::

        P = g_\infty P_e + \sum_i g_i h_i,\qquad
        \dot h_i = \dot P_e - \frac{h_i}{\tau_i\,e^{-\kappa_\tau(\xi - 1)}},\qquad
        h_i(t_0) = P_e(t_0),

    each Prony branch a Maxwell element whose relaxation time follows the current
    uniaxial-equivalent stretch ξ; integrated by :func:`qlv_rate_decay` (exact on
    each interval for a rate held at the interval's middle stretch and a linear
    :math:`P_e`). ``kappa_tau = 0`` is :func:`qlv_stress` (Fung's QLV), bit for bit.

    Parameters
    ----------
    t : array_like, shape (n,)
        Time [s], non-decreasing.
    pe : array_like, shape (n,)
        Elastic (instantaneous) stress history [Pa].
    xi : array_like, shape (n,)
        Uniaxial-equivalent stretch of each sample.
    g, tau : array_like, shape (m,)
        Prony weights (``sum(g) <= 1``) and relaxation times at ξ = 1 [s].
    kappa_tau : float
        Stretch sensitivity of the relaxation rate.
    return_state : bool
        Also return the internal variables ``h_i`` at the last sample.

    Returns
    -------
    P : ndarray, shape (n,)
    h : ndarray, shape (m,)
        Only if *return_state*.
    """
    return qlv_stress(t, pe, g, tau, return_state=return_state, decay=qlv_rate_decay(t, tau, xi, kappa_tau))


def qlv_step(h, pe_old: float, pe_new: float, dt: float, g, tau):
    """Advance the Prony internal variables by one time step (for simulators).

    Parameters
    ----------
    h : ndarray, shape (m,) or (n_springs, m)
        Internal variables at the start of the step [Pa] (updated copy returned).
    pe_old, pe_new : float or ndarray, shape (n_springs,)
        Elastic stress (or force) at the start and end of the step.
    dt : float
        Step [s], positive.
    g, tau : array_like, shape (m,)
        Prony weights and times.

    Returns
    -------
    h_new : ndarray, same shape as *h*
    p_new : float or ndarray
        Viscoelastic stress at the end of the step, ``g_inf pe_new + sum g_i h_i``.
    """
    g = np.asarray(g, float)
    tau = np.asarray(tau, float)
    x = dt / tau
    a = np.exp(-x)
    b = np.where(x > 1e-12, -np.expm1(-x) / np.maximum(x, 1e-300), 1.0 - 0.5 * x)
    dp = np.asarray(pe_new, float) - np.asarray(pe_old, float)
    h_new = a * np.asarray(h, float) + b * np.expand_dims(dp, -1)
    p_new = (1.0 - g.sum()) * np.asarray(pe_new, float) + (h_new * g).sum(axis=-1)
    return h_new, p_new


def mullins_factor(W, W_max, r: float, m: float, beta: float = 0.0):
    """Ogden-Roxburgh softening factor η (1 on the primary loading path).

    Parameters
    ----------
    W, W_max : array_like, shape (n,)
        Strain energy now and its maximum so far [Pa].
    r : float
        > 1; the largest softening is 1/r (η ≥ 1 - 1/r).
    m : float
        Energy scale of the softening [Pa], > 0.
    beta : float
        ≥ 0; makes the scale grow with ``W_max``.

    Returns
    -------
    ndarray, shape (n,)
    """
    W = np.asarray(W, float)
    W_max = np.asarray(W_max, float)
    return 1.0 - (1.0 / r) * erf((W_max - W) / (m + beta * W_max))


def damage_factor(xi_max, onset: float, scale: float, shape: float, floor: float = 0.0):
    """Remaining fraction ``1 - D`` of the stress after damage (Weibull in ξ_max).

    Parameters
    ----------
    xi_max : array_like, shape (n,)
        Largest uniaxial-equivalent stretch so far.
    onset : float
        λ_d: no damage below it.
    scale : float
        s > 0, stretch scale of the damage growth.
    shape : float
        k ≥ 1, Weibull shape (k = 1: exponential; large k: abrupt).
    floor : float
        b ∈ [0, 1): the fraction left at large stretch (0: the stress decays to zero).

    Returns
    -------
    ndarray, shape (n,)
    """
    x = np.maximum(np.asarray(xi_max, float) - onset, 0.0) / scale
    f = np.exp(-(x**shape))
    return f if floor == 0.0 else floor + (1.0 - floor) * f


def cyclic_factor(alpha, d_inf: float, eta: float):
    """Remaining stress fraction after cyclic (continuous) softening, ``1 - d_inf (1 - exp(-alpha/eta))``.

    Parameters
    ----------
    alpha : array_like, shape (n,)
        Accumulated variation of the base strain energy, ``cumsum |dW|`` [Pa].
    d_inf : float
        Saturation softening, in [0, 1).
    eta : float
        Energy scale of the softening [Pa], > 0.

    Returns
    -------
    ndarray, shape (n,)
    """
    return 1.0 - d_inf * -np.expm1(-np.asarray(alpha, float) / eta)


def accumulated_energy(W):
    """α = accumulated |ΔW| along a history, starting at 0, shape of *W* (NaN steps count 0)."""
    W = np.asarray(W, float)
    d = np.abs(np.diff(W, prepend=W[:1]))
    return np.cumsum(np.where(np.isfinite(d), d, 0.0))


def set_stretch(lam_max, fraction: float, exponent: float = 1.0):
    """The stress-free (set) stretch ``1 + fraction (lam_max - 1)**exponent`` after the largest stretch
    *lam_max* (≥ 1)."""
    strain = np.maximum(np.asarray(lam_max, float) - 1.0, 0.0)
    return 1.0 + fraction * (strain if exponent == 1.0 else strain ** exponent)


def relaxation_strength(xi, kappa: float, g_sum: float):
    """Scale s(ξ) of the relaxed part, ``min(exp(kappa (xi - 1)), 1/sum g)``, shape of *xi*.

    With ``P = P_e - s (P_e - P_QLV)`` the long-term fraction ``1 - s sum g`` stays in [0, 1].
    """
    cap = 1.0 / g_sum if g_sum > 0 else np.inf
    with np.errstate(over="ignore"):
        return np.minimum(np.exp(kappa * (np.asarray(xi, float) - 1.0)), cap)


def equivalent_stretch(I1):
    """The uniaxial stretch λ ≥ 1 with ``λ² + 2/λ = I1`` (the damage driver ξ).

    Exact (trigonometric root of the cubic ``λ³ - I1 λ + 2 = 0``); equals λ in
    uniaxial tension, and is ``> 1`` in compression and shear as well.

    Parameters
    ----------
    I1 : array_like, shape (n,)
        First invariant, ≥ 3.

    Returns
    -------
    ndarray, shape (n,)
    """
    I1 = np.maximum(np.asarray(I1, float), 3.0)
    c = np.clip(-((3.0 / I1) ** 1.5), -1.0, 1.0)
    return 2.0 * np.sqrt(I1 / 3.0) * np.cos(np.arccos(c) / 3.0)


# --------------------------------------------------------------------------- data object
@dataclass(frozen=True)
class ViscoelasticEffect:
    """Prony series of the QLV reduced relaxation function (SI: seconds).

    ``g[i]`` weight and ``tau[i]`` time of term *i*, sorted by ``tau``. The base
    material parameters are the instantaneous response (G(0) = 1); the
    long-term response is ``g_inf`` times it. ``kappa`` (default 0: Fung's QLV)
    makes the relaxed amount depend on the uniaxial-equivalent stretch
    (:func:`relaxation_strength`); ``kappa_tau`` (default 0) makes the
    relaxation times depend on it instead (:func:`qlv_rate_stress`). The two
    are alternative forms: at most one is non-zero.
    """

    g: tuple[float, ...]
    tau: tuple[float, ...]
    kappa: float = 0.0
    kappa_tau: float = 0.0

    def __post_init__(self):
        g = tuple(float(v) for v in self.g)
        tau = tuple(float(v) for v in self.tau)
        if len(g) != len(tau) or not g:
            raise ConfigError("viscoelastic effect: g and tau need the same, non-zero number of terms")
        if any(not (v >= 0.0 and math.isfinite(v)) for v in g) or sum(g) > 1.0 + 1e-9:
            raise ConfigError(f"viscoelastic effect: weights g must be >= 0 with sum <= 1, got {list(g)}")
        if any(not (v > 0.0 and math.isfinite(v)) for v in tau):
            raise ConfigError(f"viscoelastic effect: relaxation times tau must be positive seconds, got {list(tau)}")
        if not math.isfinite(float(self.kappa)):
            raise ConfigError(f"viscoelastic effect: kappa must be a finite number, got {self.kappa!r}")
        object.__setattr__(self, "kappa", float(self.kappa))
        if not math.isfinite(float(self.kappa_tau)):
            raise ConfigError(f"viscoelastic effect: kappa_tau must be a finite number, got {self.kappa_tau!r}")
        object.__setattr__(self, "kappa_tau", float(self.kappa_tau))
        if self.kappa and self.kappa_tau:
            raise ConfigError("viscoelastic effect: give kappa (the relaxed amount depends on stretch) or kappa_tau "
                              "(the relaxation times do), not both")
        order = sorted(range(len(g)), key=lambda i: tau[i])
        object.__setattr__(self, "g", tuple(g[i] for i in order))
        object.__setattr__(self, "tau", tuple(tau[i] for i in order))

    @property
    def g_inf(self) -> float:
        """Long-term fraction of the instantaneous stress, ``1 - sum(g)``."""
        return max(0.0, 1.0 - sum(self.g))

    def relaxation(self, t):
        """Reduced relaxation function G(t) (G(0) = 1), shape of *t*."""
        t = np.asarray(t, float)
        return self.g_inf + sum(gi * np.exp(-t / ti) for gi, ti in zip(self.g, self.tau))

    def stress(self, t, pe, xi=None):
        """The stress history for the elastic history *pe* (:func:`qlv_stress`; with ``kappa`` or
        ``kappa_tau`` also the uniaxial-equivalent stretch *xi* of each sample, :func:`relaxation_strength`,
        :func:`qlv_rate_stress`)."""
        if (self.kappa or self.kappa_tau) and xi is None:
            raise ConfigError("viscoelastic effect: stretch-dependent relaxation needs the equivalent stretch xi")
        if self.kappa_tau:
            return qlv_rate_stress(t, pe, xi, np.array(self.g), np.array(self.tau), self.kappa_tau)
        p = qlv_stress(t, pe, np.array(self.g), np.array(self.tau))
        if self.kappa == 0.0:
            return p
        pe = np.asarray(pe, float)
        return pe - relaxation_strength(xi, self.kappa, sum(self.g)) * (pe - p)


@dataclass(frozen=True)
class MullinsEffect:
    """Ogden-Roxburgh softening: ``r`` (> 1), ``m`` [Pa] (> 0), ``beta`` (≥ 0)."""

    r: float
    m: float
    beta: float = 0.0

    def __post_init__(self):
        if not (self.r > 1.0 and math.isfinite(self.r)):
            raise ConfigError(f"mullins effect: r must be a number > 1, got {self.r!r}")
        if not (self.m > 0.0 and math.isfinite(self.m)):
            raise ConfigError(f"mullins effect: m must be a positive stress, got {self.m!r}")
        if not (self.beta >= 0.0 and math.isfinite(self.beta)):
            raise ConfigError(f"mullins effect: beta must be >= 0, got {self.beta!r}")

    def factor(self, W, W_max):
        """η for energies *W* and maxima *W_max* [Pa]."""
        return mullins_factor(W, W_max, self.r, self.m, self.beta)


@dataclass(frozen=True)
class DamageEffect:
    """Weibull damage in the largest uniaxial-equivalent stretch so far.

    ``onset`` λ_d (≥ 1), ``scale`` s (> 0, stretch units), ``shape`` k (≥ 1), ``floor`` b
    (in [0, 1): the fraction of the stress damage leaves at large stretch; default 0).
    """

    onset: float
    scale: float
    shape: float = 1.0
    floor: float = 0.0

    def __post_init__(self):
        if not (0.0 <= self.floor < 1.0):
            raise ConfigError(f"damage effect: floor must be in [0, 1), got {self.floor!r}")
        if not (self.onset >= 1.0 and math.isfinite(self.onset)):
            raise ConfigError(f"damage effect: onset must be a stretch >= 1, got {self.onset!r}")
        if not (self.scale > 0.0 and math.isfinite(self.scale)):
            raise ConfigError(f"damage effect: scale must be > 0, got {self.scale!r}")
        if not (self.shape >= 1.0 and math.isfinite(self.shape)):
            raise ConfigError(f"damage effect: shape must be >= 1, got {self.shape!r}")

    def factor(self, xi_max):
        """Remaining stress fraction ``1 - D`` for the largest stretches *xi_max*."""
        return damage_factor(xi_max, self.onset, self.scale, self.shape, self.floor)


@dataclass(frozen=True)
class CyclicSofteningEffect:
    """Continuous softening with the accumulated energy variation: ``d_inf`` in [0, 1), ``eta`` [Pa] > 0."""

    d_inf: float
    eta: float

    def __post_init__(self):
        if not (0.0 <= self.d_inf < 1.0):
            raise ConfigError(f"cyclic_softening effect: d_inf must be in [0, 1), got {self.d_inf!r}")
        if not (self.eta > 0.0 and math.isfinite(self.eta)):
            raise ConfigError(f"cyclic_softening effect: eta must be a positive energy, got {self.eta!r}")

    def factor(self, alpha):
        """Remaining fraction for the accumulated energy variations *alpha* [Pa]."""
        return cyclic_factor(alpha, self.d_inf, self.eta)


@dataclass(frozen=True)
class PermanentSetEffect:
    """Residual strain: the set stretch is ``1 + fraction (lam_max - 1)**exponent``, ``fraction`` in [0, 1),
    ``exponent`` in [0.5, 3] (1: proportional to the largest strain)."""

    fraction: float
    exponent: float = 1.0

    def __post_init__(self):
        if not (0.0 <= self.fraction < 1.0):
            raise ConfigError(f"permanent_set effect: fraction must be in [0, 1), got {self.fraction!r}")
        if not (0.5 <= self.exponent <= 3.0):
            raise ConfigError(f"permanent_set effect: exponent must be in [0.5, 3], got {self.exponent!r}")

    def set_stretch(self, lam_max):
        """λ_s after the largest stretches *lam_max*."""
        return set_stretch(lam_max, self.fraction, self.exponent)


@dataclass(frozen=True)
class MaterialEffects:
    """The material effects kept by a discovery (each None when absent).

    Attributes
    ----------
    viscoelastic : ViscoelasticEffect or None
    mullins : MullinsEffect or None
    damage : DamageEffect or None
    intervals : dict
        Optional 95 % intervals, ``{"viscoelastic.g[0]": [lo, hi], ...}`` (SI).
    cyclic_softening : CyclicSofteningEffect or None
    permanent_set : PermanentSetEffect or None

    Notes
    -----
    Composition: ``P = VE[(1 - D(ξ_max)) · η(W, W_max) · c(α) · P_e(λ/λ_s)/λ_s]`` (module
    docstring). :meth:`stress` evaluates it along a recorded history, given the
    elastic stress at the elastic stretch (the caller applies λ_s).
    """

    viscoelastic: ViscoelasticEffect | None = None
    mullins: MullinsEffect | None = None
    damage: DamageEffect | None = None
    intervals: dict[str, list[float]] = field(default_factory=dict)
    cyclic_softening: CyclicSofteningEffect | None = None
    permanent_set: PermanentSetEffect | None = None

    @property
    def names(self) -> list[str]:
        """Names of the effects present, in :data:`MATERIAL_EFFECTS` order."""
        return [n for n in MATERIAL_EFFECTS if getattr(self, n) is not None]

    def __bool__(self) -> bool:
        return bool(self.names)

    def state_variables(self) -> dict[str, str]:
        """What a simulator must carry per spring (or per material point) for these effects."""
        out = {}
        if self.viscoelastic is not None:
            out["prony_h"] = (f"{len(self.viscoelastic.g)} Prony internal variables h_i [Pa or N] and "
                              "the previous elastic stress; advance with qlv_step")
        if self.mullins is not None:
            out["W_max"] = "largest strain energy density reached so far [Pa] (or the largest stretch)"
        if self.damage is not None or self.permanent_set is not None:
            out["xi_max"] = "largest uniaxial-equivalent stretch reached so far (the set stretch follows from it)"
        if self.cyclic_softening is not None:
            out["alpha"] = "accumulated variation of the strain energy sum |dW| [Pa] and the previous W"
        if self.viscoelastic is not None and self.viscoelastic.kappa:
            out["prony_h"] += "; the relaxed part is scaled by relaxation_strength(xi, kappa, sum g)"
        if self.viscoelastic is not None and self.viscoelastic.kappa_tau:
            out["prony_h"] += "; the relaxation times follow the stretch xi (relaxation_times(xi, tau, kappa_tau))"
        return out

    def stress(self, t, pe, *, W=None, xi=None, history: bool = True):
        """Stress along a recorded history with every effect applied.

        Parameters
        ----------
        t : array_like, shape (n,) or None
            Time [s] (needed for viscoelasticity).
        pe : array_like, shape (n,)
            Elastic stress of the base material [Pa].
        W : array_like, shape (n,), optional
            Base strain energy [Pa] (needed for Mullins and cyclic softening).
        xi : array_like, shape (n,), optional
            Uniaxial-equivalent stretch (needed for damage and stretch-dependent relaxation).
        history : bool
            True: the samples are in loading order (maxima so far are running
            maxima). False: every sample is on the primary loading path.

        Notes
        -----
        With ``permanent_set`` the caller gives *pe* and *W* at the elastic
        stretch λ/λ_s, *pe* already divided by λ_s (:func:`set_stretch`): the set
        changes the kinematics, which only the caller's model can evaluate.
        """
        p = np.asarray(pe, float).copy()
        if self.damage is not None:
            if xi is None:
                raise ConfigError("damage effect: the equivalent stretch xi is needed")
            xi = np.asarray(xi, float)
            p *= self.damage.factor(np.maximum.accumulate(xi) if history else xi)
        if self.mullins is not None and history:
            if W is None:
                raise ConfigError("mullins effect: the strain energy W is needed")
            W = np.asarray(W, float)
            p *= self.mullins.factor(W, np.maximum.accumulate(W))
        if self.cyclic_softening is not None and history:
            if W is None:
                raise ConfigError("cyclic_softening effect: the strain energy W is needed")
            p *= self.cyclic_softening.factor(accumulated_energy(W))
        if self.viscoelastic is not None:
            if t is None:
                raise ConfigError("viscoelastic effect: the time of each sample is needed")
            p = self.viscoelastic.stress(t, p, xi)
        return p

    # ---------------------------------------------------------------- I/O
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (schema ``esmm.material-effects/1``, SI units)."""
        new = self.cyclic_softening or self.permanent_set or (self.viscoelastic and (self.viscoelastic.kappa
                                                                                    or self.viscoelastic.kappa_tau))
        d: dict[str, Any] = {"schema": SCHEMA, "composition": COMPOSITION if new else "P = QLV[(1 - D) * eta * P_e]"}
        if self.viscoelastic is not None:
            v = self.viscoelastic
            d["viscoelastic"] = {"g": list(v.g), "tau": list(v.tau), "g_inf": v.g_inf,
                                 "reference": "instantaneous", "unit_tau": "s"}
            if v.kappa:
                d["viscoelastic"]["kappa"] = v.kappa
            if v.kappa_tau:
                d["viscoelastic"]["kappa_tau"] = v.kappa_tau
        if self.mullins is not None:
            d["mullins"] = {"r": self.mullins.r, "m": self.mullins.m, "beta": self.mullins.beta,
                            "unit_m": "Pa", "energy": "base strain energy density W [Pa]"}
        if self.damage is not None:
            d["damage"] = {"onset": self.damage.onset, "scale": self.damage.scale,
                           "shape": self.damage.shape, **({"floor": self.damage.floor} if self.damage.floor else {}),
                           "driver": "largest uniaxial-equivalent stretch so far"}
        if self.cyclic_softening is not None:
            d["cyclic_softening"] = {"d_inf": self.cyclic_softening.d_inf, "eta": self.cyclic_softening.eta,
                                     "unit_eta": "Pa", "driver": "accumulated variation of W, sum |dW|"}
        if self.permanent_set is not None:
            ps = self.permanent_set
            power = {} if ps.exponent == 1.0 else {"exponent": ps.exponent}
            d["permanent_set"] = {"fraction": ps.fraction, **power, "driver": "largest stretch so far: lam_s = 1 + "
                                  f"fraction (lam_max - 1){'**exponent' if power else ''}"}
        if self.intervals:
            d["intervals"] = {k: list(map(float, v)) for k, v in self.intervals.items()}
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, where: str = "material effects") -> MaterialEffects:
        """Inverse of :meth:`to_dict` (unknown effect names are refused)."""
        if not d:
            return cls()
        if not isinstance(d, Mapping):
            raise ConfigError(f"{where}: expected a table of effects, got {type(d).__name__}")
        known = set(MATERIAL_EFFECTS) | {"schema", "composition", "intervals"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(
                f"{where}: unknown effect {unknown[0]!r}; material effects are {', '.join(MATERIAL_EFFECTS)}"
            )
        try:
            v = d.get("viscoelastic")
            visco = ViscoelasticEffect(tuple(v["g"]), tuple(v["tau"]), float(v.get("kappa", 0.0)),
                                       float(v.get("kappa_tau", 0.0))) if v else None
            mu = d.get("mullins")
            mull = MullinsEffect(float(mu["r"]), float(mu["m"]), float(mu.get("beta", 0.0))) if mu else None
            da = d.get("damage")
            dam = DamageEffect(float(da["onset"]), float(da["scale"]), float(da.get("shape", 1.0)),
                               float(da.get("floor", 0.0))) if da else None
            cy = d.get("cyclic_softening")
            cyc = CyclicSofteningEffect(float(cy["d_inf"]), float(cy["eta"])) if cy else None
            ps = d.get("permanent_set")
            pset = PermanentSetEffect(float(ps["fraction"]), float(ps.get("exponent", 1.0))) if ps else None
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: incomplete or malformed effect entry ({exc}); see docs/reference/configuration.md") from None
        # strict JSON writes an unbounded side as null: lower -inf, upper +inf
        intervals = {str(k): [(-math.inf, math.inf)[j] if a is None else float(a) for j, a in enumerate(val)]
                     for k, val in (d.get("intervals") or {}).items()}
        return cls(visco, mull, dam, intervals, cyc, pset)

    def to_toml_table(self, *, stress_unit: str = "Pa") -> dict[str, Any]:
        """The ``[material.effects]`` table: dimensional values as strings with units."""
        t: dict[str, Any] = {}
        if self.viscoelastic is not None:
            v = self.viscoelastic
            t["viscoelastic"] = {
                "reference": "instantaneous",
                "g": [float(x) for x in v.g],
                "tau": [f"{x:.6g} s" for x in v.tau],
            }
            if v.kappa:
                t["viscoelastic"]["kappa"] = float(v.kappa)
            if v.kappa_tau:
                t["viscoelastic"]["kappa_tau"] = float(v.kappa_tau)
        if self.mullins is not None:
            m = self.mullins
            t["mullins"] = {"r": float(m.r), "m": f"{from_si(m.m, stress_unit, 'stress'):.6g} {stress_unit}",
                            "beta": float(m.beta)}
        if self.damage is not None:
            da = self.damage
            t["damage"] = {"onset": float(da.onset), "scale": float(da.scale), "shape": float(da.shape),
                           **({"floor": float(da.floor)} if da.floor else {})}
        if self.cyclic_softening is not None:
            c = self.cyclic_softening
            t["cyclic_softening"] = {"d_inf": float(c.d_inf),
                                     "eta": f"{from_si(c.eta, stress_unit, 'stress'):.6g} {stress_unit}"}
        if self.permanent_set is not None:
            ps = self.permanent_set
            t["permanent_set"] = {"fraction": float(ps.fraction),
                                  **({} if ps.exponent == 1.0 else {"exponent": float(ps.exponent)})}
        return t

    @classmethod
    def from_toml_table(cls, t: Mapping[str, Any] | None, *, stress_unit: str | None = None,
                        where: str = "[material.effects]") -> MaterialEffects:
        """Read a ``[material.effects]`` table (strings with units, or SI numbers)."""
        if not t:
            return cls()
        if not isinstance(t, Mapping):
            raise ConfigError(f"{where}: must be a table of effect tables")

        def qty(val, kind, key):
            if isinstance(val, str):
                try:
                    return parse_quantity(val, kind, where=f"{where} {key}")
                except Exception as exc:  # noqa: BLE001 - convert to ConfigError
                    raise ConfigError(str(exc)) from None
            if isinstance(val, bool) or not isinstance(val, int | float):
                raise ConfigError(f"{where} {key}: expected a number or a string with a unit, got {val!r}")
            if kind == "stress" and stress_unit:
                return to_si(float(val), stress_unit, "stress")
            if kind == "stress":
                raise ConfigError(f"{where} {key}: {val!r} has no unit; write it as \"{val} kPa\"")
            return float(val)

        d: dict[str, Any] = {}
        unknown = sorted(set(t) - set(MATERIAL_EFFECTS))
        if unknown:
            raise ConfigError(
                f"{where}: unknown effect {unknown[0]!r}; material effects are {', '.join(MATERIAL_EFFECTS)}"
            )
        if "viscoelastic" in t:
            v = t["viscoelastic"]
            ref = v.get("reference", "instantaneous")
            if ref != "instantaneous":
                raise ConfigError(f"{where}.viscoelastic: reference must be \"instantaneous\", got {ref!r}")
            d["viscoelastic"] = {"g": [float(x) for x in v.get("g", [])],
                                 "tau": [qty(x, "time", "viscoelastic.tau") for x in v.get("tau", [])],
                                 "kappa": v.get("kappa", 0.0), "kappa_tau": v.get("kappa_tau", 0.0)}
        if "mullins" in t:
            m = t["mullins"]
            d["mullins"] = {"r": m.get("r"), "m": qty(m.get("m"), "stress", "mullins.m"),
                            "beta": m.get("beta", 0.0)}
        if "damage" in t:
            d["damage"] = dict(t["damage"])
        if "cyclic_softening" in t:
            c = t["cyclic_softening"]
            d["cyclic_softening"] = {"d_inf": c.get("d_inf"), "eta": qty(c.get("eta"), "stress", "cyclic_softening.eta")}
        if "permanent_set" in t:
            d["permanent_set"] = dict(t["permanent_set"])
        return cls.from_dict(d, where=where)
