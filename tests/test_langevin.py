"""Inverse Langevin function: against 50-digit arithmetic, identities, derivatives."""

from __future__ import annotations

import warnings
from decimal import Decimal, localcontext

import numpy as np
import pytest
from esmm.pipeline.materials.langevin import (
    chain_energy,
    inverse_langevin,
    inverse_langevin_derivative,
    langevin,
    langevin_derivative,
    log_beta_over_sinh,
)

EPS = np.finfo(float).eps


# ---------------------------------------------------------------- references
def _lang_dec(b: Decimal) -> tuple[Decimal, Decimal]:
    """(L(b), L'(b)) in decimal arithmetic (series for small b)."""
    if b < Decimal("1e-4"):  # truncation ~ b^9, far below 50 digits relative
        b2 = b * b
        lval = b / 3 - b * b2 / 45 + 2 * b * b2 * b2 / 945 - b * b2**3 / 4725
        dval = Decimal(1) / 3 - b2 / 15 + 2 * b2 * b2 / 189 - b2**3 / 675
        return lval, dval
    c = Decimal(1) if b > 200 else (lambda e: (e + 1) / (e - 1))((2 * b).exp())
    return c - 1 / b, 1 / (b * b) - (c * c - 1)


def _linv_dec(x: float) -> Decimal:
    """L^-1(x) to ~45 digits: Newton in 60-digit decimal arithmetic."""
    with localcontext() as ctx:
        ctx.prec = 60
        xd = Decimal(x)  # the exact binary value of x
        if xd == 0:
            return Decimal(0)
        # independent start: 1/(1-x) near 1, 3x otherwise (then bisection-safe Newton)
        b = 1 / (1 - xd) if xd > Decimal("0.5") else 3 * xd
        for _ in range(200):
            lval, dfd = _lang_dec(b)
            nb = b - (lval - xd) / dfd
            if nb <= 0:
                nb = b / 2
            if abs(nb - b) <= Decimal(10) ** -50 * abs(b):
                return nb
            b = nb
        raise AssertionError("reference did not converge")


X_REF = np.concatenate([
    [1e-300, 1e-12, 1e-6, 1e-3, 0.01, 0.1, 0.2, 1 / 3, 0.5, 0.5 + 1e-9, 0.7, 0.9],
    [0.95, 0.97, 0.99, 0.995, 0.999, 0.9999, 0.99999, 0.999999, 1 - 1e-9, 1 - 1e-12,
     1 - 2.0**-50],
])


def test_inverse_langevin_matches_high_precision_reference():
    beta = inverse_langevin(X_REF)
    ref = np.array([float(_linv_dec(float(x))) for x in X_REF])
    rel = np.abs(beta / ref - 1.0)
    assert rel.max() < 1e-13, (X_REF[rel.argmax()], rel.max())


def test_inverse_langevin_identity_and_shapes():
    x = np.concatenate([np.linspace(0.0, 0.999999, 20001), 1 - np.logspace(-6.1, -15, 50)])
    beta = inverse_langevin(x)
    assert np.all(np.isfinite(beta)) and np.all(np.diff(beta) > 0)
    back = langevin(beta)
    # a few ulp (the exponential branch of L just above beta = 1/4 loses ~3 bits)
    assert np.all(np.abs(back - x) <= 3e-14 * x)
    # odd, 2-D shape kept, scalar in -> float out
    grid = x[:600].reshape(20, 30)
    assert np.array_equal(inverse_langevin(-grid), -inverse_langevin(grid))
    assert inverse_langevin(grid).shape == (20, 30)
    assert isinstance(inverse_langevin(0.5), float)
    # domain edges
    out = inverse_langevin([1.0, -1.0, 1.5, np.nan, 0.0])
    assert out[0] == np.inf and out[1] == -np.inf
    assert np.isnan(out[2]) and np.isnan(out[3]) and out[4] == 0.0


def test_small_and_large_asymptotics():
    x = np.array([1e-10, 1e-6, 1e-4])
    # L^-1(x) = 3x + 9x^3/5 + ...
    assert np.allclose(inverse_langevin(x), 3 * x + 9 * x**3 / 5, rtol=1e-15, atol=0)
    y = np.array([1 - 1e-8, 1 - 1e-12])
    # L^-1(x) = 1/(1-x) + O(e^{-2/(1-x)}) very close to 1
    assert np.allclose(inverse_langevin(y), 1 / (1 - y), rtol=1e-14)


def test_derivatives_against_finite_differences():
    beta = np.concatenate([np.logspace(-4, 3, 60), [0.2499, 0.25, 0.2501]])
    h = 1e-6 * np.maximum(beta, 1e-2)
    fd = (langevin(beta + h) - langevin(beta - h)) / (2 * h)
    assert np.allclose(langevin_derivative(beta), fd, rtol=2e-7, atol=0)
    assert langevin_derivative(0.0) == pytest.approx(1 / 3, rel=1e-15)

    x = np.array([1e-3, 0.1, 0.5, 0.9, 0.95, 0.99, 0.999])
    hx = 1e-7 * (1 - x)
    fdx = (inverse_langevin(x + hx) - inverse_langevin(x - hx)) / (2 * hx)
    assert np.allclose(inverse_langevin_derivative(x), fdx, rtol=1e-6)
    assert inverse_langevin_derivative(0.0) == pytest.approx(3.0, rel=1e-15)


def test_log_beta_over_sinh_is_stable():
    b = np.array([0.0, 1e-8, 0.1, 0.2499, 0.25, 1.0, 30.0, 1e3, 1e6, 1e300])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = log_beta_over_sinh(b)
    with localcontext() as ctx:
        ctx.prec = 50
        ref = []
        for v in b[1:6]:
            d = Decimal(float(v))
            ref.append(float((d / ((d.exp() - (-d).exp()) / 2)).ln()))
    assert got[0] == 0.0
    assert np.allclose(got[1:6], ref, rtol=1e-14)
    # large beta: ln(2 beta) - beta (e^{-2 beta} negligible); np.log(np.sinh) would overflow
    big = b[6:]
    assert np.allclose(got[6:], np.log(2 * big) - big, rtol=1e-15)


def test_chain_energy_derivative_is_beta_and_finite_near_locking():
    x = np.array([0.01, 0.3, 0.8, 0.95, 0.999, 0.999999])
    h = 1e-6 * (1 - x)
    fd = (chain_energy(x + h) - chain_energy(x - h)) / (2 * h)
    assert np.allclose(fd, inverse_langevin(x), rtol=1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e = chain_energy(np.array([0.0, 1e-5, 0.999999, 1 - 1e-14]))
    assert e[0] == 0.0
    assert e[1] == pytest.approx(1.5e-10, rel=1e-9)  # 3x^2/2
    # logarithmic divergence: ln(2/(1-x)) - 1 + O(1-x)
    assert e[2] == pytest.approx(np.log(2 / 1e-6) - 1, abs=1e-5)
    assert np.isfinite(e[3])




def test_compiled_inverse_langevin_gives_the_numpy_bits(monkeypatch):
    """The compiled path (long arrays) is the numpy form's arithmetic in loops: the same bits."""
    from esmm.pipeline.materials import langevin as lv

    rng = np.random.default_rng(7)
    x = np.concatenate([
        rng.uniform(0.0, 1.0, 4000), 1.0 - np.exp(-rng.uniform(0.0, 36.0, 4000)),  # up to the locking
        np.exp(-rng.uniform(0.0, 700.0, 2000)), rng.uniform(0.07, 0.09, 2000),  # series branch and its edge
        [0.0, -0.0, 5e-324, 0.5, np.nextafter(0.5, 1.0), 1.0 - 2.0**-53, 1.0, -1.0, 1.5, -2.0, np.nan, np.inf],
    ])
    x[::3] *= -1.0  # odd function: both signs
    assert lv._compiled_kernels() is not None and x.size >= lv._COMPILED_MIN
    with np.errstate(all="ignore"):
        compiled = inverse_langevin(x)
        monkeypatch.setattr(lv, "_COMPILED_MIN", x.size + 1)
        numpy_form = inverse_langevin(x)
    # the same bits (NaN where both give NaN: outside the domain, and at the subnormal 5e-324)
    assert np.array_equal(compiled.view(np.int64)[np.isfinite(numpy_form) | np.isinf(numpy_form)],
                          numpy_form.view(np.int64)[np.isfinite(numpy_form) | np.isinf(numpy_form)])
    assert np.array_equal(np.isnan(compiled), np.isnan(numpy_form))
