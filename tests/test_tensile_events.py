"""The noise model of a record and the event detectors on it, against noise of known size and correlation.

The noise is made here with scipy.signal (Butterworth, Chebyshev and AR filters of white noise,
decimation, rounding to a converter's step), independently of the estimator; each estimate is
compared with the filtered noise's own standard deviation and autocorrelation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from esmm.pipeline.tensile.events import rupture_index, slip_events
from esmm.pipeline.tensile.noise import level_step, noise_model, noise_sd, quantum
from scipy import signal

N = 8000


def _signal(n: int = N) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time [s], stretch, stress [Pa]) of a smooth ramp: a stiffening law at constant rate."""
    t = np.linspace(0.0, 100.0, n)
    x = 1.0 + 0.5 * t / t[-1]
    return t, x, 1e5 * (x**2 - 1.0 / x)


def _coloured(rng, n: int, kind: str) -> np.ndarray:
    """Unit-variance noise of the given kind (scipy.signal filters of white noise, transients dropped)."""
    w = rng.standard_normal(n + 4000)
    if kind == "white":
        e = w
    elif kind == "butter2":  # 2nd order Butterworth at 0.1 of Nyquist
        e = signal.lfilter(*signal.butter(2, 0.1), w)
    elif kind == "butter4":  # 4th order at 0.05 of Nyquist: correlated over ~15 samples
        e = signal.lfilter(*signal.butter(4, 0.05), w)
    elif kind == "cheby1":
        e = signal.lfilter(*signal.cheby1(3, 0.5, 0.2), w)
    elif kind == "ar":  # AR(1), rho = 0.9
        e = signal.lfilter([1.0], [1.0, -0.9], w)
    elif kind == "decimated":  # 8x oversampled, FIR-decimated
        e = signal.decimate(rng.standard_normal(8 * (n + 4000)), 8, ftype="fir")
    else:
        raise ValueError(kind)
    e = e[4000:4000 + n]
    return e / e.std()


@pytest.mark.parametrize("kind", ["white", "butter2", "butter4", "cheby1", "ar", "decimated"])
def test_noise_sd_within_20_percent_on_white_and_filtered_noise(kind):
    """σ of white and of filtered noise on a smooth signal: within 20 % of the noise's own SD
    (the lag-1 estimate alone comes out up to 100 times too small on the filtered ones)."""
    rng = np.random.default_rng(7)
    t, _, p = _signal()
    e = 300.0 * _coloured(rng, N, kind)
    m = noise_model(p + e, t)
    assert m.sigma == pytest.approx(float(np.std(e)), rel=0.2), (kind, m.profile)
    assert m.separable


@pytest.mark.parametrize("kind", ["zero-phase", "butter4"])
def test_noise_sd_where_a_quantised_floor_lies_below_filtered_noise(kind):
    """A converter's step after a smoothing filter: its rounding is white and makes a first plateau of the
    lag profile at the shortest lags, below the filtered noise, whose own plateau comes at longer lags;
    σ is the second (the per-sample noise), within 20 % of the recorded error's SD. The first plateau
    alone read 0.31 and 0.37 of it here."""
    rng = np.random.default_rng(3)
    t, _, p = _signal()
    w = 300.0 * rng.standard_normal(N + 4000)
    sos = signal.butter(4, 0.1, output="sos")
    e = (signal.sosfiltfilt(sos, w) if kind == "zero-phase" else signal.sosfilt(sos, w))[4000:]
    q = float(np.std(e))                                         # a step of the filtered noise's size
    y = np.round((p + e) / q) * q
    m = noise_model(y, t)
    first = m.profile[0][1]
    assert m.sigma == pytest.approx(float(np.std(y - p)), rel=0.2), (kind, m.profile)
    assert m.sigma > 1.5 * first, (kind, m.profile)              # the white floor is not the noise


def test_noise_correlation_time_of_ar1_noise():
    """AR(1) with ρ = 0.9: correlation length -1/ln 0.9 = 9.5 samples, 0.95 s at 10 Hz; white noise: none."""
    rng = np.random.default_rng(3)
    t, _, p = _signal()
    dt = float(t[1] - t[0])
    m = noise_model(p + 50.0 * _coloured(rng, N, "ar"), t)
    assert m.length == pytest.approx(-1.0 / math.log(0.9), rel=0.25)
    assert m.correlation_time == pytest.approx(m.length * dt)
    # the integrated autocorrelation time at spacing 1 of AR(1) is (1 + ρ)/(1 - ρ) = 19
    assert m.tau(1) == pytest.approx(19.0, rel=0.3)
    assert m.tau(200) == pytest.approx(1.0, abs=0.01)
    w = noise_model(p + 50.0 * _coloured(rng, N, "white"), t)
    assert w.length < 0.5 and w.tau(1) < 1.2


def test_integrated_autocorrelation_time_against_the_sample_mean():
    """A mean of n noise samples taken every m samples has variance σ² τ(m) / n: checked by simulation."""
    rng = np.random.default_rng(11)
    t, _, p = _signal()
    m = noise_model(p + _coloured(rng, N, "ar"), t)
    means = [np.mean(_coloured(rng, N, "ar")[::4][:1000]) for _ in range(400)]
    predicted = m.tau(4) / 1000.0  # unit variance
    assert float(np.var(means)) == pytest.approx(predicted, rel=0.35)


def test_quantised_record_floors_at_the_step():
    """A record on a converter's grid: the step is found; noise below it reads between the rounding
    error's q/√12 (dithered) and q (a staircase whose rounding error alternates from sample to sample)."""
    rng = np.random.default_rng(5)
    t, _, p = _signal()
    q = 40.0
    y = np.round((p + 2.0 * rng.standard_normal(N)) / q) * q
    assert quantum(y) == pytest.approx(q, rel=1e-9)
    assert q / math.sqrt(12.0) <= noise_sd(y) <= q
    # noise comparable to the step (a dithered converter): the rounding error adds q²/12
    y1 = np.round((p + 20.0 * rng.standard_normal(N)) / q) * q
    assert noise_sd(y1) == pytest.approx(math.hypot(20.0, q / math.sqrt(12.0)), rel=0.2)
    # noise much larger than the step: the step is still the grid, sigma the noise's
    y2 = np.round((p + 500.0 * rng.standard_normal(N)) / q) * q
    assert noise_sd(y2) == pytest.approx(math.hypot(500.0, q / math.sqrt(12.0)), rel=0.1)
    assert quantum(p + rng.standard_normal(N)) == 0.0


def test_levels_written_with_few_decimals_are_still_a_grid():
    """A 12-bit step of 0.0122 N written to 0.001 N: the steps read 0.012 and 0.013 N, one grid."""
    rng = np.random.default_rng(6)
    t, _, p = _signal()
    force = np.round(np.round((p / 1e5 + 0.002 * rng.standard_normal(N)) / 0.0122) * 0.0122, 3)
    assert quantum(force) == pytest.approx(0.012, rel=1e-6)


def _quantised_then_filtered(rng, p: np.ndarray, q: float, sd: float) -> np.ndarray:
    """Noise *sd* added, rounded to the converter's step *q*, then a digital low-pass filter (4th-order
    Butterworth at 0.05 of Nyquist, as a decimating filter after the converter)."""
    y = np.round((p + sd * rng.standard_normal(p.size)) / q) * q
    return signal.filtfilt(*signal.butter(4, 0.05), y)


def test_levels_of_a_converter_read_before_a_filter():
    """Quantised at the converter, then filtered: the readings rest on the converter's levels between short
    transitions, off any grid; the level step is read from the plateaus, the noise is floored at its
    rounding error, and no transition between levels is taken for a slip. With noise above the step
    (dithered) there are no plateaus and nothing is read."""
    rng = np.random.default_rng(8)
    t, x, p = _signal()
    q = 2000.0  # a 50 kPa span on ~25 levels
    y = np.round(_quantised_then_filtered(rng, 0.5 * (p - p[0]) / p.max() * 5e4, q, 10.0))  # written to 1 Pa
    assert level_step(y, grid=1.0) == pytest.approx(q, rel=0.05)
    m = noise_model(y, t)
    assert m.quantum == pytest.approx(q, rel=0.05) and m.sigma >= q / math.sqrt(12.0) * 0.95
    assert slip_events(x, y, np.ones(N, dtype=int), noise=m) == []
    dithered = np.round(_quantised_then_filtered(rng, 0.5 * (p - p[0]) / p.max() * 5e4, q, 3000.0))
    assert level_step(dithered, grid=1.0) == 0.0


def test_subsampling_keeps_sigma_on_filtered_noise():
    """The same record subsampled x2 and x4 has the same noise per sample (the lag-1 estimate grows)."""
    rng = np.random.default_rng(9)
    t, _, p = _signal(4 * N)
    y = p + 300.0 * _coloured(rng, 4 * N, "butter2")
    s = [noise_sd(y[::k]) for k in (1, 2, 4)]
    assert max(s) / min(s) < 1.25, s


@pytest.mark.parametrize("kind", ["white", "butter2", "butter4", "decimated"])
def test_no_false_slips_on_clean_ramps(kind):
    """50 clean ramps of 8 000 samples (filtered, quantised noise): at most a few false slips in all
    (the detector's level is one false slip per 100 clean records)."""
    rng = np.random.default_rng(21)
    t, x, p = _signal()
    d = np.ones(N, dtype=int)
    false = 0
    for _ in range(50):
        y = np.round((p + 200.0 * _coloured(rng, N, kind)) / 20.0) * 20.0
        false += len(slip_events(x, y, d))
    assert false <= 3


@pytest.mark.parametrize("kind", ["white", "butter2"])
def test_a_slip_is_found_where_it_happens(kind):
    """A grip slip (the extension lost over a few samples, filtered like the rest) is found at its sample."""
    rng = np.random.default_rng(2)
    t, x, _ = _signal()
    k0 = 5000
    lost = np.where(np.arange(N) >= k0, 0.02, 0.0)
    p = 1e5 * ((x - lost) ** 2 - 1.0 / (x - lost))
    if kind == "butter2":
        p = signal.filtfilt(*signal.butter(2, 0.3), p)
    y = p + 200.0 * _coloured(rng, N, kind)
    found = slip_events(x, y, np.ones(N, dtype=int))
    assert len(found) == 1 and abs(found[0] - k0) <= 8, found


def test_rupture_cut_at_a_break_not_at_a_relaxation():
    t, x, p = _signal(2000)
    y = p.copy()
    y[1500:] = 0.02 * p.max()  # a break: the load cell reads almost nothing after it
    assert rupture_index(x, y, noise_sd(y)) == 1500
    # a hold: the stretch stops, the stress relaxes: never a rupture
    xh = np.concatenate([x[:1000], np.full(1000, x[999])])
    yh = np.concatenate([p[:1000], p[999] * (0.3 + 0.7 * np.exp(-np.arange(1000) / 50.0))])
    assert rupture_index(xh, yh * 0.3, 0.0) is None


def _fall_late_in_a_ramp(rng, after: str, n_after: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """A ramp of 4 000 samples (white noise, 200 Pa) whose stress falls by 4 kPa within one sample,
    *n_after* samples before the run ends; then the law goes on (``slip``: the grip gave back extension),
    the stress holds its level (``level``) or keeps falling (``decline``)."""
    n = 4000
    x = 1.0 + 0.5 * np.arange(n) / n
    p = 1e5 * (x**2 - 1.0 / x)
    k0 = n - n_after
    y = p.copy()
    y[k0:] = {"slip": p[k0:], "level": np.full(n_after, p[k0]),
              "decline": p[k0] - 10.0 * np.arange(n_after)}[after] - 4000.0
    return x, y + 200.0 * rng.standard_normal(n)


def test_a_slip_late_in_a_ramp_is_found_and_a_fall_that_does_not_load_again_is_not():
    """A slip 30 samples before the run ends (the stress rises ~3σ after it) is found in nearly every record
    (the largest reading after the fall against the Bonferroni level found 88 of 100); a sudden fall after
    which the stress levels off or keeps falling is not a slip (at most the reload test's level, 1 %)."""
    rng = np.random.default_rng(3)
    d = np.ones(4000, dtype=int)
    found = {a: sum(bool(slip_events(*_fall_late_in_a_ramp(rng, a), d)) for _ in range(40))
             for a in ("slip", "level", "decline")}
    assert found["slip"] >= 39 and found["level"] <= 2 and found["decline"] <= 2, found
