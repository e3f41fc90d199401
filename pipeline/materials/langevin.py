r"""The Langevin function, its exact inverse and the eight-chain energy term.

The Langevin function is :math:`\mathcal{L}(\beta) = \coth\beta - 1/\beta`; its
inverse :math:`\beta = \mathcal{L}^{-1}(x)` maps a relative chain stretch
:math:`x \in [0, 1)` to the dimensionless chain force and diverges as
:math:`\beta \approx 1/(1-x)` when :math:`x \to 1` (locking).

Everything here is vectorised (numpy) and written so that nothing overflows or
cancels catastrophically anywhere in :math:`x \in (-1, 1)`:

* small arguments (:math:`|\beta| < 1/2`) use the Taylor series of
  :math:`\coth\beta - 1/\beta` built from Bernoulli numbers (no ``1/β - 1/β``);
* large arguments use ``exp(-2β)`` (which underflows harmlessly to 0) instead of
  ``sinh``/``cosh`` (which overflow beyond β ≈ 710);
* near the singularity the Newton residual is formed as
  :math:`(1-x) - (1-\mathcal{L}(\beta))`, both terms free of cancellation
  (``1 - x`` is exact in floating point for ``x ≥ 1/2``), so β is obtained to
  full relative precision even at ``x = 1 - 1e-12``.

The inverse is a Halley solve on the initial guess of Jedynak (2015),
:math:`\beta_0 = x(3 - 2.6x + 0.7x^2)/((1-x)(1+0.1x))` (relative error below
about 1.5 % on [0, 1)); two Halley steps reach round-off.

References
----------
R. Jedynak, "Approximation of the inverse Langevin function revisited",
Rheol. Acta 54 (2015) 29-39.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import bernoulli

__all__ = [
    "langevin",
    "langevin_derivative",
    "inverse_langevin",
    "inverse_langevin_derivative",
    "log_beta_over_sinh",
    "chain_energy",
]

_SMALL = 0.25  # |beta| below which the Taylor series are used
_NTERMS = 9  # series terms: (0.25/pi)**(2*9) ~ 2e-20, below double precision

# coth(b) - 1/b = sum_{n>=1} c_n b^(2n-1),  c_n = 2^(2n) B_(2n) / (2n)!
_B = bernoulli(2 * _NTERMS)
_C = np.array([2.0 ** (2 * n) * _B[2 * n] / math.factorial(2 * n) for n in range(1, _NTERMS + 1)])
# derivative coefficients: L'(b) = sum (2n-1) c_n b^(2n-2)
_DC = np.array([(2 * n - 1) * _C[n - 1] for n in range(1, _NTERMS + 1)])
# sinh(b)/b - 1 = sum_{k>=1} b^(2k) / (2k+1)!
_S = np.array([1.0 / math.factorial(2 * k + 1) for k in range(1, _NTERMS + 1)])

_LN2 = math.log(2.0)
_EPS = np.finfo(float).eps


def _poly_even(coef: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Horner evaluation of sum_k coef[k] * z**k (z = b**2)."""
    out = np.full_like(z, coef[-1])
    for c in coef[-2::-1]:
        out = out * z + c
    return out


def _as_float_array(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


def _elementwise(func):
    """Run a 1-D kernel on any shape; 0-d input gives a Python float."""

    def wrapper(x):
        xa = _as_float_array(x)
        out = func(np.atleast_1d(xa).ravel()).reshape(xa.shape)
        return float(out) if out.ndim == 0 else out

    wrapper.__name__ = func.__name__
    wrapper.__doc__ = func.__doc__
    return wrapper


def _kernel(a: np.ndarray):
    """(L(a), 1 - L(a), L'(a)) for a >= 0.

    Below ``_SMALL`` L comes from its Taylor series and
    :math:`L' = 1 - L^2 - 2L/a` (cancellation-free there: L' is about 1/3);
    above, everything is written with :math:`e^{-2a}` so nothing overflows,
    and :math:`L' = 1/a^2 - 4e^{-2a}/(1-e^{-2a})^2` keeps full relative
    precision as :math:`a \\to \\infty`. When both branches occur they are
    evaluated on clipped arguments and selected with ``np.where`` (faster
    than masked assignment); usually all values fall in one branch and only
    that one is computed.
    """
    small = a < _SMALL
    n_small = np.count_nonzero(small)
    if n_small:
        sm = np.minimum(a, _SMALL)
        l_small = sm * _poly_even(_C, sm * sm)
        sm_safe = np.where(sm > 0.0, sm, 1.0)
        dl_small = np.where(sm > 0.0, 1.0 - l_small * (l_small + 2.0 / sm_safe), 1.0 / 3.0)
        if n_small == a.size:
            return l_small, 1.0 - l_small, dl_small
    ab = np.maximum(a, _SMALL)
    e = np.exp(-2.0 * ab)
    ome = -np.expm1(-2.0 * ab)
    inv = 1.0 / ab
    oml_big = inv - 2.0 * e / ome
    dl_big = inv * inv - 4.0 * e / (ome * ome)
    if not n_small:
        return 1.0 - oml_big, oml_big, dl_big
    lang = np.where(small, l_small, 1.0 - oml_big)
    oml = np.where(small, 1.0 - l_small, oml_big)
    dlang = np.where(small, dl_small, dl_big)
    return lang, oml, dlang


@_elementwise
def langevin(beta):
    r"""Langevin function :math:`\mathcal{L}(\beta) = \coth\beta - 1/\beta`.

    Parameters
    ----------
    beta : array_like, shape (...)
        Argument (any real value; odd function).

    Returns
    -------
    ndarray, shape (...)
        :math:`\mathcal{L}(\beta) \in (-1, 1)`, accurate to a few ulp.
    """
    return np.copysign(_kernel(np.abs(beta))[0], beta)


@_elementwise
def langevin_derivative(beta):
    r"""Derivative :math:`\mathcal{L}'(\beta) = 1/\beta^2 - 1/\sinh^2\beta` (> 0).

    Parameters
    ----------
    beta : array_like, shape (...)

    Returns
    -------
    ndarray, shape (...)
        Values in (0, 1/3]; :math:`\mathcal{L}'(0) = 1/3`.
    """
    return _kernel(np.abs(beta))[2]


#: Halley steps from the Jedynak guess (cubic convergence): the worst relative
#: error over [0, 1) goes 1.5e-2 -> 1.0e-7 -> round-off (~7e-15).
_HALLEY_STEPS = 2


def inverse_langevin(x):
    r"""Exact inverse Langevin function :math:`\beta = \mathcal{L}^{-1}(x)`.

    Parameters
    ----------
    x : array_like, shape (...)
        Relative chain stretch, :math:`|x| < 1`. ``|x| == 1`` gives ``inf``
        (with sign); ``|x| > 1`` and NaN give NaN.

    Returns
    -------
    ndarray, shape (...)
        β with a relative error of a few 1e-15 for every representable
        :math:`x \in (-1, 1)` (checked against 60-digit arithmetic in the
        tests). Vectorised: cheap enough to evaluate on every table build.
    """
    xa = _as_float_array(x)
    flat = np.atleast_1d(xa).ravel()
    kernels = _compiled_kernels() if flat.size >= _COMPILED_MIN else None
    if kernels is not None:
        out = _inverse_langevin_compiled(flat, *kernels).reshape(xa.shape)
        return float(out) if out.ndim == 0 else out
    ax = np.abs(flat)
    ok = ax < 1.0
    xs = np.where(ok, ax, 0.5)  # placeholder value outside the domain
    out = _inverse_langevin_pos(xs)
    out = np.where(ok, out, np.where(ax == 1.0, np.inf, np.nan))
    out = np.copysign(out, flat).reshape(xa.shape)
    return float(out) if out.ndim == 0 else out


def _inverse_langevin_pos(x: np.ndarray) -> np.ndarray:
    """L^-1 for 0 <= x < 1 (1-D): Halley steps on the Jedynak (2015) guess."""
    omx = 1.0 - x  # exact for x >= 1/2 (Sterbenz lemma)
    beta = x * (3.0 - 2.6 * x + 0.7 * x * x) / (omx * (1.0 + 0.1 * x))
    near = x > 0.5
    for _ in range(_HALLEY_STEPS):
        lang, oml, dl = _kernel(beta)
        # residual L(b) - x without cancellation in either regime
        r = np.where(near, omx - oml, lang - x)
        inv = 1.0 / np.where(beta > 0.0, beta, 1.0)
        # L'' = -2 L L' - 2 L'/b + 2 L/b^2 (only a correction term: its
        # round-off near b -> 0 or infinity does not affect convergence)
        d2l = np.where(beta > 0.0, -2.0 * dl * (lang + inv) + 2.0 * lang * inv * inv, 0.0)
        beta = beta - 2.0 * r * dl / (2.0 * dl * dl - r * d2l)
    return beta


#: arrays at least this long take the compiled path (shorter ones: numpy; numba is imported on first use)
_COMPILED_MIN = 32


def _guess_loop(x, xs, beta, arg):  # pragma: no cover - compiled by numba (checked in tests/test_langevin.py)
    """|x| folded into the domain (0.5 outside it) into *xs*, the Jedynak guess of
    :func:`_inverse_langevin_pos` on it into *beta*, and ``-2 max(β, 1/4)`` (the argument of
    the exponentials of :func:`_kernel`) into *arg*, element by element."""
    for i in range(x.shape[0]):
        ax = abs(x[i])
        xi = ax if ax < 1.0 else 0.5
        xs[i] = xi
        b = xi * (3.0 - 2.6 * xi + 0.7 * xi * xi) / ((1.0 - xi) * (1.0 + 0.1 * xi))
        beta[i] = b
        arg[i] = -2.0 * (_SMALL if b < _SMALL else b)  # np.maximum: NaN stays NaN


def _halley_loop(x, beta, e, em1, coef, arg):  # pragma: no cover - compiled by numba
    """One Halley step of :func:`_inverse_langevin_pos` on *beta* in place, and the next *arg*.

    The same operations in the same order as the numpy form (:func:`_kernel`
    and the step), with ``e = exp(arg)`` and ``em1 = expm1(arg)`` computed by
    numpy: every value is bit for bit the numpy one.
    """
    n_coef = coef.shape[0]
    for i in range(x.shape[0]):
        xi, b = x[i], beta[i]
        if b < _SMALL:
            z = b * b
            poly = coef[n_coef - 1]
            for j in range(n_coef - 2, -1, -1):
                poly = poly * z + coef[j]
            lang = b * poly
            oml = 1.0 - lang
            dl = 1.0 - lang * (lang + 2.0 / b) if b > 0.0 else 1.0 / 3.0
        else:
            ome = -em1[i]
            inv_b = 1.0 / b
            oml = inv_b - 2.0 * e[i] / ome
            dl = inv_b * inv_b - 4.0 * e[i] / (ome * ome)
            lang = 1.0 - oml
        r = (1.0 - xi) - oml if xi > 0.5 else lang - xi
        inv = 1.0 / (b if b > 0.0 else 1.0)
        d2l = -2.0 * dl * (lang + inv) + 2.0 * lang * inv * inv if b > 0.0 else 0.0
        b = b - 2.0 * r * dl / (2.0 * dl * dl - r * d2l)
        beta[i] = b
        arg[i] = -2.0 * (_SMALL if b < _SMALL else b)


def _finish_loop(x, beta, out):  # pragma: no cover - compiled by numba
    """β with the sign of *x*; ``inf`` at ``|x| == 1``, NaN beyond (as :func:`inverse_langevin`)."""
    for i in range(x.shape[0]):
        ax = abs(x[i])
        b = beta[i] if ax < 1.0 else (math.inf if ax == 1.0 else math.nan)
        out[i] = math.copysign(b, x[i])


@functools.cache
def _compiled_kernels():
    """The loops above compiled by numba (imported on first use, cached on disk); None without numba."""
    try:
        from numba import njit
    except ImportError:  # pragma: no cover
        return None
    jit = njit(cache=True, nogil=True, error_model="numpy")
    return jit(_guess_loop), jit(_halley_loop), jit(_finish_loop)


def _inverse_langevin_compiled(x: np.ndarray, guess, halley, finish) -> np.ndarray:
    """:func:`inverse_langevin` of a 1-D array with its arithmetic in compiled loops.

    The same operations in the same order as the numpy form; the
    exponentials stay numpy's (its vectorised ``exp``/``expm1`` differ from
    the C library's in the last bit for some arguments), so the result is
    identical while a few array passes are made instead of a hundred.
    """
    x = np.ascontiguousarray(x, dtype=float)
    xs, beta, arg, e, em1 = np.empty((5, x.size))
    guess(x, xs, beta, arg)
    for _ in range(_HALLEY_STEPS):
        halley(xs, beta, np.exp(arg, out=e), np.expm1(arg, out=em1), _C, arg)
    finish(x, beta, xs)
    return xs


def inverse_langevin_derivative(x):
    r"""Derivative :math:`d\mathcal{L}^{-1}/dx = 1/\mathcal{L}'(\mathcal{L}^{-1}(x))`.

    Parameters
    ----------
    x : array_like, shape (...)
        :math:`|x| < 1`.

    Returns
    -------
    ndarray, shape (...)
        Positive; 3 at ``x = 0``, about :math:`1/(1-x)^2` near 1.
    """
    return 1.0 / langevin_derivative(inverse_langevin(x))


@_elementwise
def log_beta_over_sinh(beta):
    r"""Stable :math:`\ln(\beta/\sinh\beta)` for any real β (even function).

    Uses :math:`\ln\beta - \beta + \ln 2 - \ln(1 - e^{-2\beta})` for
    :math:`|\beta| \ge 1/2` and :math:`-\ln(1 + \sum_k \beta^{2k}/(2k+1)!)`
    below, so it is finite for β up to the float limit and exact at 0.

    Parameters
    ----------
    beta : array_like, shape (...)

    Returns
    -------
    ndarray, shape (...)
        Values :math:`\le 0`.
    """
    b = np.abs(beta)
    out = np.empty_like(b)
    small = b < _SMALL
    z = b[small] ** 2
    out[small] = -np.log1p(z * _poly_even(_S, z))
    s = b[~small]
    out[~small] = np.log(s) - s + _LN2 - np.log1p(-np.exp(-2.0 * s))
    return out


def chain_energy(x):
    r"""Eight-chain energy term :math:`x\beta + \ln(\beta/\sinh\beta)`, β = L⁻¹(x).

    Its derivative with respect to x is β itself (because
    :math:`\mathcal{L}(\beta) = x`).

    Parameters
    ----------
    x : array_like, shape (...)
        Relative chain stretch, :math:`|x| < 1`.

    Returns
    -------
    ndarray, shape (...)
        Non-negative: :math:`\approx 3x^2/2` for small x and
        :math:`\approx \ln(2/(1-x)) - 1` (a logarithmic divergence) as
        :math:`x\to 1`.
    """
    xa = _as_float_array(x)
    beta = inverse_langevin(xa)
    return np.abs(xa) * np.abs(beta) + log_beta_over_sinh(beta)
