"""The test that a history effect's improvement is history (pipeline/discover/history.py).

Records here are made without esmm's model: an Ogden-type uniaxial stress
written out, cycles of rising amplitude, noise filtered by scipy.signal (a
Butterworth low-pass, as a testing machine's amplifier) or shaped 1/f in
frequency, and a relaxation drawn by a Maxwell element's exact update. The
false-positive rate is measured over independent noise draws.
"""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.discover.history import path_dependence
from scipy import signal

FS = 50.0  # samples per second


def _path(n_cycles: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Time and stretch: triangular cycles of rising amplitude (to 1.1, 1.2, ...) at a constant rate."""
    rate = 0.01  # stretch per second
    pts = [1.0]
    for c in range(1, n_cycles + 1):
        pts += [1.0 + 0.1 * c, 1.0]
    x = [np.array([pts[0]])]
    for a, b in zip(pts[:-1], pts[1:]):
        m = int(round(abs(b - a) / rate * FS))
        x.append(np.linspace(a, b, m + 1)[1:])
    lam = np.concatenate(x)
    return np.arange(lam.size) / FS, lam


def _elastic(lam: np.ndarray) -> np.ndarray:
    """Uniaxial nominal stress of a one-term Ogden solid (mu 1, alpha 5): mu/alpha-scaled, written out."""
    a = 5.0
    return (2.0 / a) * (lam ** (a - 1) - lam ** (-a / 2 - 1))


def _maxwell(t: np.ndarray, s: np.ndarray, tau: float) -> np.ndarray:
    """The overstress h of a Maxwell element driven by the elastic stress s (exact update per step)."""
    h = np.zeros_like(s)
    for i in range(1, s.size):
        dt = t[i] - t[i - 1]
        e = np.exp(-dt / tau)
        h[i] = e * h[i - 1] + (1 - e) * tau / dt * (s[i] - s[i - 1]) if dt > 0 else h[i - 1]
    return h


def _filtered(rng, n: int, sd: float) -> np.ndarray:
    b, a = signal.butter(2, 0.1)
    w = signal.lfilter(b, a, rng.standard_normal(n + 500))[500:]
    return sd * w / w.std()


def _pink(rng, n: int, sd: float) -> np.ndarray:
    f = np.fft.rfftfreq(2 * n, 1 / FS)
    spec = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / np.sqrt(np.maximum(f, f[1]))
    w = np.fft.irfft(spec)[:n]
    return sd * w / w.std()


def _rates(noise, *, misfit: bool, draws: int = 100, level: float = 0.05) -> tuple[float, float]:
    """(how often p <= level, how often the test's whole verdict, p and size, says history) on elastic data."""
    t, lam = _path()
    s = _elastic(lam)
    d = -0.05 * _maxwell(t, s, 20.0)  # a relaxation's change of the prediction
    rng = np.random.default_rng(7)
    sd = 0.01 * np.ptp(s)
    p_hits = hits = 0
    for _ in range(draws):
        e = noise(rng, lam.size, sd)
        if misfit:  # an elastic law's error: a function of the stretch alone, ten times the noise
            e = e + 0.1 * np.ptp(s) * (lam - 1.0) ** 2 * np.sin(8 * lam)
        h = path_dependence([lam], [e], [d], ranges=[np.ptp(s)], groups=[0], resolutions=[sd])
        p_hits += h["p"] <= level
        hits += h["p"] <= level and h["peak_resolutions"] >= 1.0
    return p_hits / draws, hits / draws


ALLOWED = 0.05 + 3 * np.sqrt(0.05 * 0.95 / 100)  # the level and three binomial SDs of 100 draws


@pytest.mark.slow
@pytest.mark.parametrize("misfit", [False, True], ids=["law-right", "law-wrong"])
def test_false_positive_rate_under_filtered_noise(misfit):
    """Elastic data (the law right, or wrong by a function of the stretch ten times the noise), Butterworth-
    filtered noise: p <= 5 % at most at about its level; with the size requirement, the verdict too."""
    p_rate, rate = _rates(_filtered, misfit=misfit)
    assert p_rate <= ALLOWED and rate <= ALLOWED


@pytest.mark.slow
def test_false_positive_rate_under_pink_noise():
    """Under 1/f noise over the whole band the p-value alone is liberal (the noise's correlation outlasts
    what the autocorrelation-consistent variance sees: about 20 % at 5 %), which is why the verdict also
    needs the path-dependent part resolved: the verdict's rate stays at its level."""
    p_rate, rate = _rates(_pink, misfit=True)
    assert rate <= ALLOWED
    assert p_rate > rate  # the size requirement is what holds it (a test that shows the p-value's limit)


def test_a_relaxation_is_found():
    """Data that relax (a Maxwell element, g = 0.05, as the change): found at any reasonable level."""
    t, lam = _path()
    s = _elastic(lam)
    h_true = -0.05 * _maxwell(t, s, 20.0)
    rng = np.random.default_rng(3)
    e = h_true + _filtered(rng, lam.size, 0.01 * np.ptp(s))
    h = path_dependence([lam], [e], [h_true], ranges=[np.ptp(s)], groups=[0], resolutions=[0.01 * np.ptp(s)])
    assert h["p"] < 1e-6 and 0.05 < h["share"] < 1.0 and h["peak_resolutions"] > 1.0


def test_a_change_of_the_law_has_no_path_part():
    """A change that is a function of the stretch alone (a stiffer law) has no path-dependent part."""
    t, lam = _path()
    s = _elastic(lam)
    rng = np.random.default_rng(5)
    e = 0.02 * s + _filtered(rng, lam.size, 0.01 * np.ptp(s))
    h = path_dependence([lam], [e], [0.02 * s], ranges=[np.ptp(s)], groups=[0])
    assert h["share"] < 1e-3
    assert h["p"] > 1e-3


def test_one_ramp_carries_no_path_information():
    """On one monotone ramp every change is a function of the stretch: nothing depends on the path."""
    lam = np.linspace(1.0, 1.5, 2000)
    t = np.arange(lam.size) / FS
    s = _elastic(lam)
    d = -0.05 * _maxwell(t, s, 20.0)
    h = path_dependence([lam], [d.copy()], [d], ranges=[np.ptp(s)], groups=[0])
    assert h["share"] < 1e-3


def test_a_fold_sees_only_its_training_samples():
    """The samples between two training fitting samples belong to the training set; those next to a held-out
    fitting sample do not (a nested fold must not see what it holds out)."""
    from esmm.pipeline.discover.history import _training_samples

    fit_idx = np.array([0, 4, 8, 12, 16])
    got = _training_samples(fit_idx, [0, 1, 3, 4], 19)
    want = np.zeros(19, dtype=bool)
    want[0:5] = True  # between fitting samples 0 and 4, both training
    want[12:19] = True  # 12 and 16 training, and the tail after the last
    assert np.array_equal(got, want)
    assert _training_samples(fit_idx, None, 19).all()
    assert not _training_samples(fit_idx, [], 19).any()


def _ramp_record(x_specimen: np.ndarray, stress_of, seed: int = 0):
    """A prepared record of a ramp at 0.01/s (50 Hz) whose specimen stretch is *x_specimen* of the crosshead's
    (``stress_of`` its nominal stress), with white noise of 0.2 % of the peak."""
    from pathlib import Path

    from esmm.pipeline.discover.records import prepare
    from esmm.pipeline.tensile.data import TensileTest

    x = np.linspace(1.0, 1.3, x_specimen.size)
    p = stress_of(x_specimen)
    rng = np.random.default_rng(seed)
    t = np.arange(x.size) / FS
    test = TensileTest(source=Path("r.csv"), mode="uniaxial", stretch=x,
                       stress=p + rng.normal(0.0, 0.002 * float(np.max(p)), x.size), time=t)
    return prepare([test])[0]


def test_a_slips_fall_is_not_a_softening_and_a_falling_law_is():
    """A grip slip near the end of a ramp gives back 0.08 of stretch, so the stress never regains its
    maximum: the fall is the slip's (detected), not a softening of the material, which
    ``strain_softening`` would otherwise call it (exempting damage from the history test and calling it
    identifiable on a single ramp). A law whose stress falls at rising stretch (the stress of the same
    Ogden solid times 1 - D, D rising past 1.2) without a slip is a softening."""
    from esmm.pipeline.discover.records import strain_softening

    n = 1501
    x = np.linspace(1.0, 1.3, n)
    slipped = x - 0.08 * (x >= 1.25)
    r = _ramp_record(slipped, _elastic)
    assert r.slips, "the slip is detected"
    assert not strain_softening(r)
    damage = 1.0 - 0.9 * np.clip((x - 1.2) / 0.1, 0.0, 1.0) ** 2
    assert strain_softening(_ramp_record(x, lambda v: _elastic(v) * damage))
