"""Viscoelasticity: reduced relaxation functions, Fung's hereditary integral, and two forms of
stretch-dependent (nonlinear) relaxation.

Quasi-linear viscoelasticity (Fung 1972, in *Biomechanics: its foundations and objectives*; Fung
1993, *Biomechanics: mechanical properties of living tissues*): ``P(t) = int_0^t G(t - s) dP_e(s)/ds ds`` with ``G(0) = 1`` and
``P_e`` the instantaneous elastic stress. It is integrated by **direct convolution on the fine
time grid**: with ``P_e`` taken linear between grid points the integral is exactly
``P_n = G(t_n) P_e(0) + sum_k Gbar_{n-k} (P_e(t_k) - P_e(t_{k-1}))`` where ``Gbar_j`` is the mean
of ``G`` over ``[j dt, (j+1) dt]``, computed from an antiderivative of ``G`` (so a relaxation
time far below the grid step is still integrated right). The sum is evaluated by FFT.

Kernels (each with ``value(t)`` and ``primitive(t)``):

* :class:`Prony` ``G = g_inf + sum_i g_i exp(-t/tau_i)``;
* :class:`FungSpectrum` Fung's continuous (box) spectrum between tau_1 and tau_2,
  ``G = [1 + C (E1(t/tau_2) - E1(t/tau_1))] / [1 + C ln(tau_2/tau_1)]``;
* :class:`PowerLaw` the modified power law ``G = g_inf + (1 - g_inf)(1 + t/t0)**(-n)``
  (Nutting's power-law relaxation with a time ``t0`` that keeps ``G(0) = 1``; Findley, Lai &
  Onaran 1976, *Creep and relaxation of nonlinear viscoelastic materials*).

Stretch-dependent relaxation:

* :func:`schapery` Schapery's single-integral form (Schapery 1969, Polym. Eng. Sci. 9:295) with a
  stretch-dependent amplitude of the relaxing part: ``P = g_inf P_e + int dG(t - s) d[h(x) P_e]/ds ds``,
  ``h = exp(c (x - 1))``;
* :func:`strain_dependent_rate` relaxation whose rate depends on the stretch, as measured on
  ligament by Provenzano et al. 2001 (Ann. Biomed. Eng. 29:908): a generalized Maxwell body whose
  relaxation times are ``tau_i(x) = tau_i exp(c (x - 1))`` (slower relaxation at larger stretch for
  ``c > 0``), integrated exactly step by step with the times frozen over a grid step.
"""

from __future__ import annotations

from itertools import accumulate

import numpy as np
from scipy.signal import fftconvolve
from scipy.special import exp1


class Prony:
    """``G(t) = g_inf + sum_i g[i] exp(-t / tau[i])``, with ``g_inf + sum g = 1``."""

    name = "prony"

    def __init__(self, g, tau):
        self.g = np.asarray(g, dtype=float)
        self.tau = np.asarray(tau, dtype=float)
        self.g_inf = 1.0 - float(self.g.sum())

    def value(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)[..., None]
        return self.g_inf + np.sum(self.g * np.exp(-t / self.tau), axis=-1)

    def primitive(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)[..., None]
        return self.g_inf * t[..., 0] - np.sum(self.g * self.tau * np.exp(-t / self.tau), axis=-1)

    def describe(self) -> dict:
        return {"kernel": self.name, "g": self.g.tolist(), "tau_s": self.tau.tolist(), "g_inf": self.g_inf}


def _phi(x):
    """An antiderivative of E1: ``x E1(x) - exp(-x)`` (-1 at x = 0)."""
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid="ignore"):
        v = x * exp1(x) - np.exp(-x)
    return np.where(x > 0.0, v, -1.0)


class FungSpectrum:
    """Fung's reduced relaxation function of a box spectrum of times between tau1 and tau2."""

    name = "fung"

    def __init__(self, c: float, tau1: float, tau2: float):
        self.c, self.tau1, self.tau2 = float(c), float(tau1), float(tau2)
        self.den = 1.0 + self.c * np.log(self.tau2 / self.tau1)
        self.g_inf = 1.0 / self.den

    def value(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        with np.errstate(invalid="ignore"):
            d = exp1(t / self.tau2) - exp1(t / self.tau1)
        d = np.where(t > 0.0, d, np.log(self.tau2 / self.tau1))
        return (1.0 + self.c * d) / self.den

    def primitive(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return (t + self.c * (self.tau2 * _phi(t / self.tau2) - self.tau1 * _phi(t / self.tau1))) / self.den

    def describe(self) -> dict:
        return {"kernel": self.name, "C": self.c, "tau1_s": self.tau1, "tau2_s": self.tau2, "g_inf": self.g_inf}


class PowerLaw:
    """``G(t) = g_inf + (1 - g_inf)(1 + t/t0)**(-n)``, 0 < n < 1."""

    name = "power"

    def __init__(self, g_inf: float, t0: float, n: float):
        self.g_inf, self.t0, self.n = float(g_inf), float(t0), float(n)

    def value(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return self.g_inf + (1.0 - self.g_inf) * (1.0 + t / self.t0) ** (-self.n)

    def primitive(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        a = 1.0 - self.n
        return self.g_inf * t + (1.0 - self.g_inf) * self.t0 * ((1.0 + t / self.t0) ** a) / a

    def describe(self) -> dict:
        return {"kernel": self.name, "g_inf": self.g_inf, "t0_s": self.t0, "n": self.n}


def cell_means(kernel, dt: float, n: int) -> np.ndarray:
    """``Gbar_j`` = mean of G over ``[j dt, (j+1) dt]``, j = 0..n-1, shape (n,)."""
    edges = kernel.primitive(np.arange(n + 1, dtype=float) * dt)
    return np.diff(edges) / dt


def hereditary(kernel, dt: float, pe: np.ndarray) -> np.ndarray:
    """``int_0^t G(t - s) dP_e/ds ds`` on a uniform grid, ``pe`` piecewise linear, shape (n,)."""
    pe = np.asarray(pe, dtype=float)
    n = pe.size
    gbar = cell_means(kernel, dt, n)
    dpe = np.diff(pe)
    out = kernel.value(np.arange(n) * dt) * pe[0]
    if n > 1:
        out[1:] += fftconvolve(dpe, gbar[: n - 1])[: n - 1]
    return out


def schapery(kernel, dt: float, pe: np.ndarray, x: np.ndarray, c: float) -> np.ndarray:
    """Schapery's single integral with amplitude ``h(x) = exp(c (x - 1))`` on the relaxing part.

    ``P = g_inf P_e + int (G - g_inf)(t - s) d[h P_e]/ds ds`` (the transient kernel ``G - g_inf``
    is convolved through :func:`hereditary` as ``G`` minus its constant part).
    """
    hp = np.exp(c * (np.asarray(x, dtype=float) - 1.0)) * pe
    g_inf = kernel.g_inf
    transient = hereditary(kernel, dt, hp) - g_inf * hp
    return g_inf * pe + transient


def strain_dependent_rate(g, tau, dt: float, pe: np.ndarray, x: np.ndarray, c: float) -> np.ndarray:
    """Generalized Maxwell body with ``tau_i(x) = tau_i exp(c (x - 1))`` (module docstring).

    ``P = g_inf P_e + sum_i q_i``, ``dq_i/dt = -q_i / tau_i(x) + g_i dP_e/dt``; over a step with
    ``tau`` frozen at the step's mean stretch and ``P_e`` linear, exactly
    ``q_n = a q_{n-1} + g_i dP_e tau/dt (1 - a)``, ``a = exp(-dt/tau)``.
    """
    pe = np.asarray(pe, dtype=float)
    x = np.asarray(x, dtype=float)
    g = np.asarray(g, dtype=float)
    out = (1.0 - g.sum()) * pe
    xm = 0.5 * (x[1:] + x[:-1])
    dpe = np.diff(pe)
    for gi, ti in zip(g, tau):
        r = dt / (ti * np.exp(c * (xm - 1.0)))
        a = np.exp(-r)
        b = gi * dpe * np.where(r > 1e-12, -np.expm1(-r) / np.where(r > 0, r, 1.0), 1.0)
        q = np.fromiter(accumulate(zip(a, b), lambda qq, ab: ab[0] * qq + ab[1], initial=gi * pe[0]),
                        dtype=float, count=pe.size)
        out += q
    return out
