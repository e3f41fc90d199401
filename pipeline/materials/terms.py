r"""Strain-energy terms a discovery may add to a base model (the elastic-law library).

Each term is a pure function of the invariants :math:`I_1, I_2` of
:math:`\mathbf C` (incompressible, :math:`I_3 = 1`) with its first and second
derivatives, written out below and checked against finite differences in
tests/test_materials_terms.py. A composite model
(:mod:`esmm.pipeline.materials.composite`) is a base model plus terms,

.. math::

    W = W_\text{base}(I_1, I_2) + \sum_j W_j(I_1, I_2),

so the stiffness tables of the network, :math:`\mu_e = 2W/(\lambda-1)^2`, follow
from the sum as from any model. Every term vanishes in the reference state
(:math:`W_j(3, 3) = 0`) and has non-negative coefficients; which residual
structure each addresses is in :data:`TERMS` (``addresses``) and in
docs/design/discovery.md. The library follows the model-discovery literature
(constitutive artificial neural networks, Linka & Kuhl 2023; EUCLID, Flaschel et
al. 2021): invariant-based terms, linear in a modulus, with at most one
nonlinear shape parameter each (two for the toes). Every function is written with numpy operations
that broadcast over its parameters as well as over the invariants (a parameter
may be an array of shape (m, 1): m parameter sets at once, as
:attr:`~esmm.pipeline.materials.base.MaterialModel.array_parameters` promises).

``mooney`` — Mooney-Rivlin :math:`I_2` term
    :math:`W = C_2 (I_2 - 3)`; :math:`W_2 = C_2`.
    Adds the :math:`I_2` dependence that makes uniaxial tension softer,
    compression stiffer than an :math:`I_1`-only model (tension-compression
    asymmetry), and equibiaxial/pure-shear responses distinct.

``i2exp`` — exponential in :math:`I_2` (the term CANNs select for brain)
    :math:`W = \frac{a}{2b}\left[e^{b(I_2-3)} - 1\right]`;
    :math:`W_2 = \tfrac a2 e^{b(I_2-3)}`, :math:`W_{22} = \tfrac{ab}2 e^{b(I_2-3)}`.
    In uniaxial compression :math:`I_2` grows faster than :math:`I_1`
    (:math:`I_2 - 3 = 3\varepsilon^2 - 4\varepsilon^3 + \ldots`,
    :math:`I_1 - 3 = 3\varepsilon^2 - 2\varepsilon^3 + \ldots`), so a stiffening
    :math:`I_2` term stiffens compression more than tension.

``i1exp`` — exponential in :math:`I_1` (Demiray 1972)
    :math:`W = \frac{a}{2b}\left[e^{b(I_1-3)} - 1\right]`;
    :math:`W_1 = \tfrac a2 e^{b(I_1-3)}`, :math:`W_{11} = \tfrac{ab}2 e^{b(I_1-3)}`.
    Exponential stiffening of soft tissue.

``yeoh`` — cubic term of Yeoh (1993)
    :math:`W = c_3 (I_1 - 3)^3`; :math:`W_1 = 3c_3(I_1-3)^2`, :math:`W_{11} = 6c_3(I_1-3)`.
    A late upturn (rubber at large stretch) the quadratic ESEDF term cannot follow.

``gent`` — limiting chain extensibility (Gent 1996)
    :math:`W = -\frac{\mu_g J_m}{2}\ln\left(1 - \frac{I_1-3}{J_m}\right)`;
    :math:`W_1 = \frac{\mu_g}{2}\left(1 - \frac{I_1-3}{J_m}\right)^{-1}`,
    :math:`W_{11} = \frac{\mu_g}{2J_m}\left(1 - \frac{I_1-3}{J_m}\right)^{-2}`; locks at
    :math:`I_1 = 3 + J_m`.

``i2log`` — Gent-Thomas logarithmic :math:`I_2` term (Gent & Thomas 1958)
    :math:`W = \frac{3\mu_l}{2}\ln\frac{I_2}{3}`; :math:`W_2 = \frac{3\mu_l}{2I_2}`,
    :math:`W_{22} = -\frac{3\mu_l}{2I_2^2}`. Its stiffness *decreases* with
    deformation: a concave loading curve (foams, filled rubbers at moderate
    stretch). Not polyconvex; the Drucker check of the fit says where it is stable.

``fibreexp`` — exponential isotropized fibres (Holzapfel et al. 2000)
    :math:`W = \frac{k_1}{2k_2}\left[e^{k_2(\bar I_4-1)^2} - 1\right]`,
    :math:`\bar I_4 = I_1/3` (the ESEDF's isotropized fibre invariant);
    with :math:`q = \bar I_4 - 1`: :math:`W_1 = \tfrac{k_1}{3} q\,e^{k_2q^2}`,
    :math:`W_{11} = \tfrac{k_1}{9}(1 + 2k_2q^2)e^{k_2q^2}`. Exponential fibre stiffening.

``toe`` — fibre recruitment (a toe region; after Shearer 2015, Hamedzadeh et al. 2018)
    Fibres of modulus :math:`E_t` straighten at stretches spread over
    :math:`[1, 1+\delta]`, in the uniaxial-equivalent stretch :math:`\xi \ge 1`
    (:math:`\xi^2 + 2/\xi = I_1`, ξ = λ in uniaxial tension), the fraction straight
    at ξ being :math:`F = r^p`, :math:`r = (\xi-1)/\delta` (a Beta(p, 1)
    distribution: p = 1 uniform, Shearer's; p > 1 a recruitment that starts slowly
    and gathers pace, as the Weibull distributions fitted to collagen do). With
    :math:`u = \xi - 1`, the fibre stress is :math:`W'(\xi) = E_t\int_0^u F`:

    .. math::

        W = E_t\begin{cases} \dfrac{\delta^2 r^{p+2}}{(p+1)(p+2)} & u \le \delta \\[4pt]
            \dfrac{(u-\delta p/(p+1))^2}{2} + \dfrac{\delta^2 p}{2(p+1)^2(p+2)} & u > \delta \end{cases}

    so :math:`W'(\xi)` rises as :math:`u^{p+1}` over the toe and linearly (slope
    :math:`E_t`) once every fibre is straight (C² at :math:`1+\delta` for p ≥ 0).
    With :math:`h = d\xi/dI_1 = \xi^2/(2(\xi^3-1))`: :math:`W_1 = W'(\xi)\,h` and
    :math:`W_{11} = [W''h + W'h']\,h`, :math:`h' = -(\xi^4+2\xi)/(2(\xi^3-1)^2)`,
    evaluated in forms without 0/0 near ξ = 1 (:math:`W_{11}` goes as
    :math:`(I_1-3)^{(p-2)/2}` there: unbounded for p < 2, p = 1 included, while the
    stress tangent stays finite; it is set to 0 at :math:`I_1 = 3` exactly). The shape p is the
    one term of the library with a second shape parameter: a uniform recruitment
    fitted to a slow start leaves a residual at the toe's foot that a permanent set,
    a slack or an offset then takes (docs/design/model.md). Files written
    before p existed read as p = 1, the law they were written with.

``toeweibull`` — Weibull fibre recruitment (Hamedzadeh, Gasser & Federico 2018)
    The toe with the straight fraction a Weibull distribution of the straightening
    stretch, :math:`F(u) = 1 - e^{-z}`, :math:`z = (u/\eta)^k`, u = ξ − 1 (η the
    scale, k the shape): recruitment starts as :math:`u^k` and ends in a tail rather
    than at a stretch where every fibre is straight. With :math:`P_a(z)` the
    regularized lower incomplete gamma function, :math:`g_1 = \Gamma(1+1/k)P_{1/k}(z)`,
    :math:`g_2 = \Gamma(1+2/k)P_{2/k}(z)`:

    .. math::

        W'(\xi) = E\int_0^u F = E\,[u - \eta g_1], \qquad
        W = E\int_0^u (u - t) F(t)\,dt = E\,[u^2/2 - u\eta g_1 + \eta^2 g_2/2],

    :math:`W'' = E F`, and W1, W11 through h = dξ/dI1 as for ``toe``. For z < 1 the
    brackets are summed as the series :math:`u\sum_n (-1)^{n+1}z^n/(n!(nk+1))` and
    :math:`u^2\sum_n (-1)^{n+1}z^n/(n!(nk+1)(nk+2))` (no cancellation as u → 0).
    Why a second toe: the Beta(p, 1) recruitment of ``toe`` ends at 1 + δ with a
    kink in the fibres' stiffness; a Weibull recruitment, the distribution fitted to
    collagen, turns into the linear region gradually, and a compact toe fitted to it
    leaves a smooth residual of a few tenths of a per cent of the stress that a
    history effect or an artefact then takes (docs/design/model.md). The two are
    alternatives with the same number of parameters; a discovery keeps one of them.

Parameter names carry the term's prefix, so they never clash with a base
model's (``c2``, ``i2exp_a``, ``i2exp_b``, ...).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import gamma, gammainc

from .base import Parameter, broadcast_zeros
from .effects import equivalent_stretch

__all__ = ["Term", "TERMS", "TERM_NAMES", "get_term"]


@dataclass(frozen=True)
class Term:
    """One strain-energy term: its parameters and pure functions of (I1, I2).

    Attributes
    ----------
    name : str
        Registry name (no ``+``, ``-`` or ``_``: it is part of composite model names).
    parameters : tuple of Parameter
        Its parameters; exactly one ``stress`` parameter (the modulus, in which W is linear).
    equation : str
        Plain text, for reports.
    energy, dW, d2W : callable
        ``f(I1, I2, **params)`` -> W; (W1, W2); (W11, W12, W22) [Pa].
    max_I1 : callable or None
        ``f(**params)`` -> the I1 where W locks (None: never).
    addresses : str
        The residual structure it can explain (for reports and docs).
    alternatives : tuple of str
        Terms that are other forms of the same structure (the two toes): a discovery that keeps one does
        not try the others.
    """

    name: str
    parameters: tuple[Parameter, ...]
    equation: str
    energy: Callable
    dW: Callable
    d2W: Callable
    addresses: str
    max_I1: Callable | None = None
    alternatives: tuple[str, ...] = ()

    @property
    def modulus(self) -> str:
        """The name of its (single) stress parameter."""
        return next(p.name for p in self.parameters if p.kind == "stress")

    @property
    def shape_parameters(self) -> tuple[str, ...]:
        """The names of its dimensionless shape parameters (none for one-parameter terms)."""
        return tuple(p.name for p in self.parameters if p.kind != "stress")


def _z(I1, I2):
    return broadcast_zeros(I1, I2)


# --------------------------------------------------------------------------- mooney
def mooney_energy(I1, I2, c2):
    """W = c2 (I2 - 3) [Pa]."""
    return c2 * (np.asarray(I2, float) - 3.0) + _z(I1, I2)


def mooney_dW(I1, I2, c2):
    """(W1, W2) = (0, c2)."""
    z = _z(I1, I2)
    return z, z + c2


def mooney_d2W(I1, I2, c2):
    """(W11, W12, W22) = 0."""
    z = _z(I1, I2)
    return z, z, z


# --------------------------------------------------------------------------- exponentials
def _expm1_over(b, x):
    """(exp(b x) - 1) / b, accurate for small b x; inf when b x overflows."""
    with np.errstate(over="ignore"):
        return np.expm1(b * x) / b


def i2exp_energy(I1, I2, i2exp_a, i2exp_b):
    """W = a/(2b) [exp(b (I2 - 3)) - 1] [Pa]."""
    return 0.5 * i2exp_a * _expm1_over(i2exp_b, np.asarray(I2, float) - 3.0) + _z(I1, I2)


def i2exp_dW(I1, I2, i2exp_a, i2exp_b):
    """(W1, W2) = (0, a/2 exp(b (I2 - 3)))."""
    with np.errstate(over="ignore"):
        e = np.exp(i2exp_b * (np.asarray(I2, float) - 3.0))
    z = _z(I1, I2)
    return z, z + 0.5 * i2exp_a * e


def i2exp_d2W(I1, I2, i2exp_a, i2exp_b):
    """(W11, W12, W22) = (0, 0, a b/2 exp(b (I2 - 3)))."""
    with np.errstate(over="ignore"):
        e = np.exp(i2exp_b * (np.asarray(I2, float) - 3.0))
    z = _z(I1, I2)
    return z, z, z + 0.5 * i2exp_a * i2exp_b * e


def i1exp_energy(I1, I2, i1exp_a, i1exp_b):
    """W = a/(2b) [exp(b (I1 - 3)) - 1] [Pa]."""
    return 0.5 * i1exp_a * _expm1_over(i1exp_b, np.asarray(I1, float) - 3.0) + _z(I1, I2)


def i1exp_dW(I1, I2, i1exp_a, i1exp_b):
    """(W1, W2) = (a/2 exp(b (I1 - 3)), 0)."""
    with np.errstate(over="ignore"):
        e = np.exp(i1exp_b * (np.asarray(I1, float) - 3.0))
    z = _z(I1, I2)
    return z + 0.5 * i1exp_a * e, z


def i1exp_d2W(I1, I2, i1exp_a, i1exp_b):
    """(W11, W12, W22) = (a b/2 exp(b (I1 - 3)), 0, 0)."""
    with np.errstate(over="ignore"):
        e = np.exp(i1exp_b * (np.asarray(I1, float) - 3.0))
    z = _z(I1, I2)
    return z + 0.5 * i1exp_a * i1exp_b * e, z, z


# --------------------------------------------------------------------------- yeoh
def yeoh_energy(I1, I2, c3):
    """W = c3 (I1 - 3)^3 [Pa]."""
    u = np.asarray(I1, float) - 3.0
    return c3 * u**3 + _z(I1, I2)


def yeoh_dW(I1, I2, c3):
    """(W1, W2) = (3 c3 (I1 - 3)^2, 0)."""
    u = np.asarray(I1, float) - 3.0
    z = _z(I1, I2)
    return z + 3.0 * c3 * u * u, z


def yeoh_d2W(I1, I2, c3):
    """(W11, W12, W22) = (6 c3 (I1 - 3), 0, 0)."""
    u = np.asarray(I1, float) - 3.0
    z = _z(I1, I2)
    return z + 6.0 * c3 * u, z, z


# --------------------------------------------------------------------------- gent
def _gent_room(I1, J):
    """1 - (I1 - 3)/J, NaN at or beyond locking."""
    r = 1.0 - (np.asarray(I1, float) - 3.0) / J
    return np.where(r > 0.0, r, np.nan)


def gent_energy(I1, I2, gent_mu, gent_J):
    """W = -(mu J / 2) ln(1 - (I1 - 3)/J) [Pa]; NaN beyond locking (I1 >= 3 + J)."""
    u = np.asarray(I1, float) - 3.0
    with np.errstate(invalid="ignore"):
        w = -0.5 * gent_mu * gent_J * np.log1p(-u / gent_J)
    return np.where(u < gent_J, w, np.nan) + _z(I1, I2)


def gent_dW(I1, I2, gent_mu, gent_J):
    """(W1, W2) = (mu / (2 (1 - (I1 - 3)/J)), 0)."""
    z = _z(I1, I2)
    return z + 0.5 * gent_mu / _gent_room(I1, gent_J), z


def gent_d2W(I1, I2, gent_mu, gent_J):
    """(W11, W12, W22) = (mu / (2 J (1 - (I1 - 3)/J)^2), 0, 0)."""
    z = _z(I1, I2)
    r = _gent_room(I1, gent_J)
    return z + 0.5 * gent_mu / (gent_J * r * r), z, z


def gent_max_I1(gent_mu, gent_J):
    """Locking at I1 = 3 + J (when the modulus is positive)."""
    return 3.0 + gent_J if gent_mu > 0.0 else np.inf


# --------------------------------------------------------------------------- i2log
def i2log_energy(I1, I2, i2log_mu):
    """W = (3 mu / 2) ln(I2 / 3) [Pa]."""
    v = np.asarray(I2, float) - 3.0
    return 1.5 * i2log_mu * np.log1p(v / 3.0) + _z(I1, I2)


def i2log_dW(I1, I2, i2log_mu):
    """(W1, W2) = (0, 3 mu / (2 I2))."""
    z = _z(I1, I2)
    return z, z + 1.5 * i2log_mu / np.asarray(I2, float)


def i2log_d2W(I1, I2, i2log_mu):
    """(W11, W12, W22) = (0, 0, -3 mu / (2 I2^2))."""
    z = _z(I1, I2)
    i2 = np.asarray(I2, float)
    return z, z, z - 1.5 * i2log_mu / (i2 * i2)


# --------------------------------------------------------------------------- fibreexp
def fibreexp_energy(I1, I2, fexp_k1, fexp_k2):
    """W = k1/(2 k2) [exp(k2 q^2) - 1], q = I1/3 - 1 [Pa]."""
    q = (np.asarray(I1, float) - 3.0) / 3.0
    return 0.5 * fexp_k1 * _expm1_over(fexp_k2, q * q) + _z(I1, I2)


def fibreexp_dW(I1, I2, fexp_k1, fexp_k2):
    """(W1, W2) = (k1 q exp(k2 q^2) / 3, 0)."""
    q = (np.asarray(I1, float) - 3.0) / 3.0
    with np.errstate(over="ignore"):
        e = np.exp(fexp_k2 * q * q)
    z = _z(I1, I2)
    return z + fexp_k1 * q * e / 3.0, z


def fibreexp_d2W(I1, I2, fexp_k1, fexp_k2):
    """(W11, W12, W22) = (k1 (1 + 2 k2 q^2) exp(k2 q^2) / 9, 0, 0)."""
    q = (np.asarray(I1, float) - 3.0) / 3.0
    with np.errstate(over="ignore"):
        e = np.exp(fexp_k2 * q * q)
    z = _z(I1, I2)
    return z + fexp_k1 * (1.0 + 2.0 * fexp_k2 * q * q) * e / 9.0, z, z


# --------------------------------------------------------------------------- toe
def _xi_u(I1):
    """(ξ, u = ξ - 1, s = ξ² + ξ + 1) of the uniaxial-equivalent stretch.

    u from the identity (ξ - 1)²(ξ + 2) = ξ (I1 - 3), which keeps its relative
    precision as ξ → 1 (ξ - 1 itself would cancel).
    """
    I1 = np.asarray(I1, float)
    xi = equivalent_stretch(I1)
    u = np.sqrt(xi * np.maximum(I1 - 3.0, 0.0) / (xi + 2.0))
    return xi, u, xi * xi + xi + 1.0


def toe_energy(I1, I2, toe_E, toe_delta, toe_p=1.0):
    """W = E δ² r^(p+2)/((p+1)(p+2)) on the toe, E[(u - δp/(p+1))²/2 + δ²p/(2(p+1)²(p+2))] beyond [Pa]
    (module docstring)."""
    _, u, _ = _xi_u(I1)
    d, p = toe_delta, toe_p
    r = np.minimum(u / d, 1.0)
    w = np.where(u <= d, d * d * r ** (p + 2.0) / ((p + 1.0) * (p + 2.0)),
                 0.5 * (u - d * p / (p + 1.0)) ** 2 + d * d * p / (2.0 * (p + 1.0) ** 2 * (p + 2.0)))
    return toe_E * w + _z(I1, I2)


def _toe_g(u, E, d, p):
    """W'(ξ) and W''(ξ) of the toe law."""
    r = np.minimum(u / d, 1.0)
    g = np.where(u <= d, E * d * r ** (p + 1.0) / (p + 1.0), E * (u - d * p / (p + 1.0)))
    gp = np.where(u <= d, E * r ** p, E)
    return g, gp


def toe_dW(I1, I2, toe_E, toe_delta, toe_p=1.0):
    """(W1, W2) = (W'(ξ) ξ²/(2(ξ³-1)), 0), with ξ³ - 1 = u (ξ² + ξ + 1)."""
    xi, u, s = _xi_u(I1)
    d, p = toe_delta, toe_p
    r = np.minimum(u / d, 1.0)
    # on the toe W'/u = E r^p/(p+1): W1 = E r^p ξ²/(2 (p+1) s), no 0/0 at u = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        beyond = toe_E * (u - d * p / (p + 1.0)) * xi * xi / (2.0 * u * s)
    w1 = np.where(u <= d, toe_E * r ** p * xi * xi / (2.0 * (p + 1.0) * s), beyond)
    return w1 + _z(I1, I2), _z(I1, I2)


def toe_d2W(I1, I2, toe_E, toe_delta, toe_p=1.0):
    """(W11, W12, W22) = ([W'' h + W' h'] h, 0, 0), h = dξ/dI1 = ξ²/(2 u s), h' = -(ξ⁴ + 2ξ)/(2 u² s²)."""
    xi, u, s = _xi_u(I1)
    d, E, p = toe_delta, toe_E, toe_p
    g, gp = _toe_g(u, E, d, p)
    with np.errstate(invalid="ignore", divide="ignore"):
        h = xi * xi / (2.0 * u * s)
        # on the toe W'' = E r^p: W'' h + W' h' = (W'' / u) [ξ²/(2s) - (ξ⁴ + 2ξ)/(2 (p+1) s²)], no 0/0 at u = 0
        inner_toe = gp / np.where(u > 0.0, u, 1.0) * (
            xi * xi / (2.0 * s) - (xi**4 + 2.0 * xi) / (2.0 * (p + 1.0) * s * s))
        inner_lin = gp * h - g * (xi**4 + 2.0 * xi) / (2.0 * u * u * s * s)
        w11 = np.where(u <= d, inner_toe, inner_lin) * h
    w11 = np.where(u > 0.0, w11, 0.0)
    z = _z(I1, I2)
    return w11 + z, z, z


# --------------------------------------------------------------------------- toeweibull
#: series terms for z < 1: 1/18! ~ 2e-16, below double precision
_TW_TERMS = 18


def _tw_parts(I1, eta, k):
    """(ξ, u, s, F, G1 = ∫F/u, G2 = ∫(u-t)F/u²) of the Weibull recruitment (module docstring)."""
    xi, u, s = _xi_u(I1)
    with np.errstate(over="ignore"):  # far into the tail z is inf: F = 1, P(a, z) = 1
        z = (u / eta) ** k
    zs = np.minimum(z, 1.0)
    g1s = np.zeros_like(zs)
    g2s = np.zeros_like(zs)
    term = np.ones_like(zs)
    for n in range(1, _TW_TERMS + 1):
        term = -term * zs / n  # (-1)^n z^n / n!
        g1s = g1s - term / (n * k + 1.0)
        g2s = g2s - term / ((n * k + 1.0) * (n * k + 2.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        a = eta * gamma(1.0 + 1.0 / k) * gammainc(1.0 / k, z) / u
        b = eta * eta * gamma(1.0 + 2.0 / k) * gammainc(2.0 / k, z) / (u * u)
        g1 = np.where(z < 1.0, g1s, 1.0 - a)
        g2 = np.where(z < 1.0, g2s, 0.5 - a + 0.5 * b)
    return xi, u, s, -np.expm1(-z), g1, g2


def toeweibull_energy(I1, I2, tw_E, tw_eta, tw_k):
    """W = E [u²/2 - u η g1 + η² g2/2], u = ξ - 1 [Pa] (module docstring)."""
    _, u, _, _, _, g2 = _tw_parts(I1, tw_eta, tw_k)
    return tw_E * u * u * g2 + _z(I1, I2)


def toeweibull_dW(I1, I2, tw_E, tw_eta, tw_k):
    """(W1, W2) = (W'(ξ) ξ²/(2 u s), 0) = (E G1 ξ²/(2s), 0): no 0/0 at u = 0."""
    xi, _, s, _, g1, _ = _tw_parts(I1, tw_eta, tw_k)
    return tw_E * g1 * xi * xi / (2.0 * s) + _z(I1, I2), _z(I1, I2)


def toeweibull_d2W(I1, I2, tw_E, tw_eta, tw_k):
    """(W11, W12, W22) = ([W'' h + W' h'] h, 0, 0) = (E/u [F ξ²/(2s) - G1 (ξ⁴ + 2ξ)/(2s²)] h, 0, 0)."""
    xi, u, s, f, g1, _ = _tw_parts(I1, tw_eta, tw_k)
    with np.errstate(invalid="ignore", divide="ignore"):
        inner = (f * xi * xi / (2.0 * s) - g1 * (xi**4 + 2.0 * xi) / (2.0 * s * s)) / u
        w11 = tw_E * inner * xi * xi / (2.0 * u * s)
    w11 = np.where(u > 0.0, w11, 0.0)
    z = _z(I1, I2)
    return w11 + z, z, z


# --------------------------------------------------------------------------- registry
def _stress(name: str, default: float, what: str) -> Parameter:
    return Parameter(name, "stress", default, 0.0, 1.0e11, what)


def _shape(name: str, default: float, lo: float, hi: float, what: str, *, optional: bool = False) -> Parameter:
    return Parameter(name, "dimensionless", default, lo, hi, what, optional=optional)


#: name -> Term (one entry per term; see the module docstring for each equation)
TERMS: dict[str, Term] = {
    t.name: t for t in (
        Term("mooney", (_stress("c2", 1.0e3, "Mooney-Rivlin I2 modulus C2"),),
             "c2*(I2-3)", mooney_energy, mooney_dW, mooney_d2W,
             "I2 dependence: tension-compression asymmetry, distinct equibiaxial and pure-shear responses"),
        Term("i2exp", (_stress("i2exp_a", 1.0e3, "I2 exponential modulus a"),
                       _shape("i2exp_b", 1.0, 1e-3, 1e3, "I2 exponential rate b")),
             "a/(2b)*(exp(b*(I2-3))-1)", i2exp_energy, i2exp_dW, i2exp_d2W,
             "stiffening in I2: compression stiffer than tension (brain tissue)"),
        Term("i1exp", (_stress("i1exp_a", 1.0e3, "I1 exponential modulus a"),
                       _shape("i1exp_b", 1.0, 1e-3, 1e3, "I1 exponential rate b")),
             "a/(2b)*(exp(b*(I1-3))-1)", i1exp_energy, i1exp_dW, i1exp_d2W,
             "exponential stiffening in I1 (soft tissue)"),
        Term("yeoh", (_stress("c3", 1.0e2, "Yeoh cubic modulus c3"),),
             "c3*(I1-3)^3", yeoh_energy, yeoh_dW, yeoh_d2W,
             "a late upturn at large stretch"),
        Term("gent", (_stress("gent_mu", 1.0e3, "Gent modulus"),
                      _shape("gent_J", 10.0, 1e-2, 1e4, "Gent locking parameter Jm (locks at I1 = 3 + Jm)")),
             "-(mu*J/2)*ln(1-(I1-3)/J)", gent_energy, gent_dW, gent_d2W,
             "stiffening towards a limiting stretch (chain extensibility)", max_I1=gent_max_I1),
        Term("i2log", (_stress("i2log_mu", 1.0e3, "Gent-Thomas log(I2) modulus"),),
             "(3*mu/2)*ln(I2/3)", i2log_energy, i2log_dW, i2log_d2W,
             "a concave loading curve (stiffness falling with stretch)"),
        Term("fibreexp", (_stress("fexp_k1", 1.0e3, "exponential fibre modulus k1"),
                          _shape("fexp_k2", 1.0, 1e-3, 1e4, "exponential fibre rate k2")),
             "k1/(2k2)*(exp(k2*(I1/3-1)^2)-1)", fibreexp_energy, fibreexp_dW, fibreexp_d2W,
             "exponential fibre stiffening (isotropized fibres)"),
        Term("toe", (_stress("toe_E", 1.0e6, "modulus of the recruited fibres"),
                     _shape("toe_delta", 0.02, 1e-4, 2.0, "width of the recruitment (toe) in stretch"),
                     _shape("toe_p", 1.0, 0.5, 8.0, "shape of the recruitment: fraction straight = ((xi-1)/d)^p",
                            optional=True)),
             "E*{d^2 r^(p+2)/((p+1)(p+2)) on the toe; (xi-1-d p/(p+1))^2/2 + d^2 p/(2(p+1)^2(p+2)) beyond}, "
             "r = (xi-1)/d, xi^2 + 2/xi = I1",
             toe_energy, toe_dW, toe_d2W,
             "a toe region: fibres straightening one after another, then a linear region",
             alternatives=("toeweibull",)),
        Term("toeweibull", (_stress("tw_E", 1.0e6, "modulus of the recruited fibres"),
                            _shape("tw_eta", 0.02, 1e-4, 2.0, "Weibull scale of the straightening stretch"),
                            _shape("tw_k", 2.0, 1.0, 10.0, "Weibull shape of the straightening stretch")),
             "E*(u^2/2 - u*eta*G(1+1/k)*P(1/k,z) + eta^2*G(1+2/k)*P(2/k,z)/2), z = (u/eta)^k, u = xi-1, "
             "xi^2 + 2/xi = I1",
             toeweibull_energy, toeweibull_dW, toeweibull_d2W,
             "a toe region that turns into the linear region gradually (Weibull-distributed fibre recruitment)",
             alternatives=("toe",)),
    )
}

#: the term names, in library order
TERM_NAMES: tuple[str, ...] = tuple(TERMS)


def get_term(name: str) -> Term:
    """The term registered as *name*; KeyError if unknown (the composite model turns it into a ConfigError)."""
    return TERMS[name]
