"""The force channel's lag behind the stretch (:func:`~esmm.pipeline.tensile.events.force_lag`), against truth.

The records are made here: a rate-independent law (Arruda-Boyce, uniaxial nominal stress) and a
quasi-linear viscoelastic one (Fung's QLV, a Prony relaxation function, the hereditary integral
updated exactly for a piecewise-linear elastic response) under triangular stretch cycles. The force
is filtered with scipy.signal, causally (``lfilter``: the chain's delay) or with zero phase
(``filtfilt``: no delay); the truth is the filter's own group delay at low frequency
(``scipy.signal.group_delay``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.tensile.data import TensileTest
from esmm.pipeline.tensile.events import force_lag
from scipy import signal

FS, RATE, PEAK, CYCLES = 20.0, 0.05, 1.5, 4
MU, N_LINKS = 30e3, 6.0


def _stretch() -> tuple[np.ndarray, np.ndarray]:
    """(time [s], stretch) of *CYCLES* triangular load-unload cycles at a constant stretch rate."""
    period = 2.0 * (PEAK - 1.0) / RATE
    t = np.arange(0.0, CYCLES * period, 1.0 / FS)
    phase = (t % period) / period
    return t, 1.0 + (PEAK - 1.0) * (1.0 - np.abs(2.0 * phase - 1.0))


def _elastic(lam: np.ndarray) -> np.ndarray:
    """Uniaxial nominal stress [Pa] of the Arruda-Boyce law (Arruda & Boyce 1993), its inverse Langevin
    function solved by Newton's method from Cohen's Padé start."""
    lr = np.sqrt((lam**2 + 2.0 / lam) / (3.0 * N_LINKS))
    b = lr * (3.0 - lr**2) / (1.0 - lr**2)
    for _ in range(30):
        b = b - (1.0 / np.tanh(b) - 1.0 / b - lr) / (1.0 / b**2 - 1.0 / np.sinh(b) ** 2)
    return MU * b * (lam - lam**-2) / (3.0 * lr)


def _qlv(t: np.ndarray, pe: np.ndarray, g: tuple[float, ...] = (0.3, 0.3), tau: tuple[float, ...] = (1.0, 10.0)):
    """Fung's QLV stress: P(t) = ∫ G(t − s) dPe/ds ds, G = 1 − Σ g_i (1 − e^{−t/τ_i}); per Prony term the
    hereditary integral h_i is updated exactly for an elastic stress linear within each step."""
    g_inf = 1.0 - sum(g)
    out = g_inf * pe.copy()
    for gi, ti in zip(g, tau):
        h = np.zeros_like(pe)
        for n in range(1, pe.size):
            dt = t[n] - t[n - 1]
            e = np.exp(-dt / ti)
            h[n] = e * h[n - 1] + (pe[n] - pe[n - 1]) * ti / dt * (1.0 - e)
        out += gi * h
    return out


def _direction(lam: np.ndarray) -> np.ndarray:
    """+1 loading, −1 unloading, from the sign of the stretch's change (written here, not esmm's covariates)."""
    d = np.sign(np.gradient(lam)).astype(int)
    return d


def _noisy(rng, p: np.ndarray, level: float = 0.002) -> np.ndarray:
    return p + level * float(np.max(np.abs(p))) * rng.standard_normal(p.size)


def _delay_s(b, a) -> float:
    """The filter's group delay at low frequency [s]."""
    _, gd = signal.group_delay((b, a), w=[1e-3])
    return float(gd[0]) / FS


@pytest.mark.parametrize("order, cutoff", [(2, 0.1), (4, 0.2), (2, 0.05)])
def test_causally_filtered_elastic_record_lags_by_the_filters_group_delay(order, cutoff):
    """A rate-independent record whose force (noise included) went through a causal Butterworth filter:
    the lag found is the filter's group delay at low frequency, within 30 %."""
    rng = np.random.default_rng(11)
    t, lam = _stretch()
    b, a = signal.butter(order, cutoff)
    p = signal.lfilter(b, a, _noisy(rng, _elastic(lam)))
    truth = _delay_s(b, a)
    d = force_lag(lam, p, t, _direction(lam))
    assert d == pytest.approx(truth, rel=0.3), (d, truth)


@pytest.mark.parametrize("kind", ["elastic", "qlv", "filtfilt"])
def test_no_lag_invented(kind):
    """No lag where there is none: an unfiltered elastic record, an unfiltered viscoelastic one (its stress
    peaks before the stretch and falls faster after it) and a zero-phase filtered elastic one all give 0."""
    rng = np.random.default_rng(12)
    t, lam = _stretch()
    pe = _elastic(lam)
    if kind == "elastic":
        p = _noisy(rng, pe)
    elif kind == "qlv":
        p = _noisy(rng, _qlv(t, pe))
    else:
        p = signal.filtfilt(*signal.butter(2, 0.1), _noisy(rng, pe))
    assert force_lag(lam, p, t, _direction(lam)) == 0.0


def test_qlv_record_is_not_symmetric_about_the_stretch_peak():
    """The check above can fail: at equal stretch the viscoelastic stress of this generator is lower after
    the peak than before it, by far more than the noise (so a lag of 0 for it is the rule's decision, not
    a record without asymmetry)."""
    t, lam = _stretch()
    p = _qlv(t, _elastic(lam))
    k = int(np.argmax(lam[: int(round(2.0 * (PEAK - 1.0) / RATE * FS))]))
    j = np.arange(5, 50)
    assert np.all(p[k - j] - p[k + j] > 0.02 * float(p.max()))


def test_discovery_of_a_causally_filtered_elastic_record_adds_no_viscoelasticity():
    """A clean rate-independent record, its force through a causal 2nd-order Butterworth filter (0.1 of
    Nyquist): the delay is found and taken off, and nothing history-dependent is kept. (At this delay, a
    hundredth of a loading run, the search keeps no viscoelasticity without the correction either: the test
    guards the correction's place in the discovery, not a case it alone decides.)"""
    from esmm.pipeline.discover import discover

    rng = np.random.default_rng(13)
    t, lam = _stretch()
    b, a = signal.butter(2, 0.1)
    p = signal.lfilter(b, a, _noisy(rng, _elastic(lam)))
    rec = TensileTest(source=Path("lagged.csv"), mode="uniaxial", stretch=lam, stress=p, time=t)
    res = discover([rec], model="arruda-boyce", n_starts=2, max_points=300, nested=False)
    [r] = res.records
    assert r.lag.get("seconds", 0.0) == pytest.approx(_delay_s(b, a), rel=0.3)
    assert not any(k.startswith("viscoelastic") for k in res.kept), {n: c.reason for n, c in res.candidates.items()}
