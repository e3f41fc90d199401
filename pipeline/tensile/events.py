"""Events in a tensile record that a model must not fit: measurement noise, ruptures, grip slips, a force lag.

Shared by the calibrate fit and the discovery (:mod:`esmm.pipeline.discover`): what a record says
about itself, without any model of the material.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .noise import Noise, noise_model, robust_sd

#: a rupture falls faster than this many times the test's mean secant stiffness (largest stress / span)
SUDDEN_STEEPNESS = 10.0
#: a sudden drop below this fraction of the stress before it is a rupture (a slip loses less)
RUPTURE_FRACTION = 0.5
#: the probability of one false slip anywhere in a clean record (Bonferroni over its loading samples)
SLIP_ALPHA = 0.01
#: a lag longer than this fraction of the runs at a reversal is not an acquisition delay (filters delay by a few
#: samples)
LAG_OF_RUN = 0.05


def runs(a: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, stop, value) of the runs of equal values."""
    if a.size == 0:
        return []
    edges = np.flatnonzero(np.diff(a)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [a.size]])
    return [(int(s), int(e), int(a[s])) for s, e in zip(starts, stops)]


def noise_sd(y: np.ndarray) -> float:
    """Per-sample standard deviation of the measurement noise of a record *y* (time order) [units of *y*].

    From :func:`~esmm.pipeline.tensile.noise.noise_model`: robust to filtered,
    decimated, quantised and partly 1/f noise (third differences at growing
    lags, the plateau between the noise's correlation and the signal). At least
    1e-12 of the record's largest |y|.
    """
    return noise_model(y).sigma


def _falls(x: np.ndarray, y: np.ndarray, k0: int, k1: int, slope: float) -> bool:
    """From sample k0 to k1 the stretch advanced (never back) while the stress fell at a slope
    steeper than *slope* [Pa per unit stretch]."""
    seg = x[k0:k1 + 1]
    dx = float(seg[-1] - seg[0])
    return bool(np.all(np.diff(seg) >= 0.0) and dx > 0.0 and (y[k0] - y[k1]) >= slope * dx)


def rupture_index(x: np.ndarray, y: np.ndarray, sigma: float = 0.0) -> int | None:
    """The first sample of a rupture, or None.

    The stress falls below :data:`RUPTURE_FRACTION` of its largest value so far
    and never comes back above it, while the stretch advances; then

    * a **break**: the fall (from the last maximum before it) is steeper than
      :data:`SUDDEN_STEEPNESS` times the test's mean secant stiffness (a
      softening law that steep would be unstable at any sampling): the record is
      cut at the top of the fall;
    * a **complete failure**: a progressive fall (fibres failing one after the
      other: damage, kept) that reaches zero stress (within 5 noise standard
      deviations *sigma*): the record is cut there — what follows is the load
      cell's reading of a broken specimen.

    Everything from the returned sample on is not the material's response. A
    fall while the stretch is held (relaxation) or goes back (unloading) is
    never a rupture.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    n = x.size
    if n < 3:
        return None
    top = np.maximum.accumulate(y)
    later_max = np.maximum.accumulate(y[::-1])[::-1]
    below = (y <= RUPTURE_FRACTION * top) & (top > 0) & (later_max <= RUPTURE_FRACTION * top)
    hits = np.flatnonzero(below)
    if not hits.size:
        return None
    j = int(hits[0])
    k = j - 1
    while k > 0 and y[k - 1] >= y[k]:  # back to the top of the fall
        k -= 1
    secant = float(np.max(np.abs(y))) / (float(np.ptp(x)) or 1.0)
    if _falls(x, y, k, j, SUDDEN_STEEPNESS * secant):
        return k + 1
    zero = np.flatnonzero(y[j:] <= 5.0 * sigma)
    if zero.size and _falls(x, y, k, j + int(zero[0]), 0.0):
        return j + int(zero[0])
    return None


def slip_events(x: np.ndarray, y: np.ndarray, direction: np.ndarray, *, noise: Noise | None = None,
                alpha: float = SLIP_ALPHA) -> list[int]:
    """Samples where the grip slipped: the bottom of each sudden, sustained drop of stress during loading.

    A slip: during a loading run, the stress falls monotonically from sample k
    to m while the stretch advances, and

    * the fall loses more than z s'_h (below), and it is sudden against the record's own noise: the
      second difference
      across it, g = (y_m − y_k) − (y_k − y_{k−h}) with h = m − k (the fall plus the
      rise the trend would have made over the same samples), is below
      −z s_h, where s_h is the larger of the robust standard deviation of the
      same second difference at lag h over every loading sample of the record
      and the noise model's (:meth:`~esmm.pipeline.tensile.noise.Noise.second_difference_sd`):
      whatever the noise's correlation, filtering or quantisation, a fall over
      h samples is judged against the noise's falls over h samples, as the
      record shows them and as its noise model predicts them; z is the normal
      quantile of *alpha* / (loading samples): the chance of one false slip
      anywhere in a clean record is at most *alpha* (Bonferroni);
    * it is not a toggle: when the rise over the h samples before the fall is
      itself a jump (it differs from the rise over the h samples before those
      by more than z s'_h, s'_h the larger of the record's robust standard
      deviation of lag-2h differences, less their median, and the noise
      model's), the fall must take the curve below where that jump started (a
      converter toggling between two levels, a spike, rises and falls back to
      where it was; a slip falls below it);
    * it is sustained: the mean stress over the h + 1 samples after the fall
      stays below the level before it by more than half the fall (a spike falls
      back at once);
    * every threshold is raised by what the converter's rounding alone can do (the quantum q on a
      difference, 2q on a second difference): a fall of one level is the rounding's, never a slip;
    * the specimen still carries load after it (the stress at its bottom above z s'_h), and the same run
      then loads again (:func:`_loads_again`: means of the run's thirds after the fall at the single-test
      level, a slip late in a ramp found). A fall after which the stress never comes back is a rupture,
      cut before slips are sought (:func:`rupture_index`).

    Two falls closer than either's duration are one slip (the filter's ringing
    splits a fall). No window counts samples: the fall's own duration sets the lag.

    Parameters
    ----------
    x, y : ndarray, shape (n,)
        Stretch and stress in time order.
    direction : ndarray of int, shape (n,)
        +1 loading, -1 unloading, 0 hold (:class:`~esmm.pipeline.discover.covariates.Covariates`).
    noise : Noise, optional
        The record's noise model (default: :func:`~esmm.pipeline.tensile.noise.noise_model` of *y*).
    alpha : float
        Probability of a false slip in a clean record.

    Returns
    -------
    list of int
        The last sample of each slip's fall.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    d = np.asarray(direction)
    loading = [(s, e) for s, e, v in runs(d) if v > 0 and e - s >= 4]
    n_load = sum(e - s for s, e in loading)
    if n_load < 8:
        return []
    zz = (float(stats.norm.isf(alpha / n_load)), float(stats.norm.isf(alpha)))  # the fall's, the reload's
    noise = noise if noise is not None else noise_model(y)
    scales: dict[int, float] = {}
    falls: list[tuple[int, int]] = []
    for s, e in loading:
        k = s
        while k < e - 1:
            m = k
            while m + 1 < e and y[m + 1] < y[m]:
                m += 1
            if m > k and _is_slip(x, y, s, e, k, m, zz, scales, loading, noise):
                if falls and k - falls[-1][1] <= max(m - k, falls[-1][1] - falls[-1][0]):
                    falls[-1] = (falls[-1][0], m)  # one slip whose fall the filter's ringing split in two
                else:
                    falls.append((k, m))
            k = m + 1
    return [int(m) for _, m in falls]


def _lag_scale(y: np.ndarray, h: int, loading: list[tuple[int, int]], second: bool) -> float:
    """Robust standard deviation over the loading samples of y_{j+h} − 2y_j + y_{j−h} (*second*) or of
    y_{j+2h} − y_j less its median (the trend), 0 when too few."""
    if second:
        vals = [y[s + 2 * h:e] - 2.0 * y[s + h:e - h] + y[s:e - 2 * h] for s, e in loading if e - s > 2 * h]
    else:
        vals = [y[s + 2 * h:e] - y[s:e - 2 * h] for s, e in loading if e - s > 2 * h]
    if not vals:
        return 0.0
    g = np.concatenate(vals)
    return robust_sd(g - np.median(g)) if g.size >= 8 else 0.0


def _loads_again(y: np.ndarray, m: int, e: int, z1: float, noise: Noise, floor: float) -> bool:
    """After a fall to sample m, the run [.., e) loads again: the mean of its last third exceeds the mean of its
    first third by more than z1 √2 s_w + q, s_w the noise's sd of a mean of that many samples (its correlation
    counted), z1 the single-test quantile: the fall test already bounds a clean record's false slips; this one
    tells a slip from a fall that levels off or keeps falling, and means, not the largest reading, keep the
    noise's own excursions from passing."""
    n = e - m
    if n < 3:
        return False
    w = n // 3
    rise = float(np.mean(y[e - w:e]) - np.mean(y[m:m + w]))
    return rise > z1 * math.sqrt(2.0) * max(noise.mean_sd(w), floor) + noise.quantum


def _is_slip(x, y, s: int, e: int, k: int, m: int, zz: tuple[float, float], scales: dict, loading,
             noise: Noise) -> bool:
    """Whether the fall from sample k to m of the loading run [s, e) is a slip (see :func:`slip_events`);
    *zz*: the fall's quantile (Bonferroni over the loading samples) and the reload's."""
    z, z1 = zz
    h = m - k
    if k - h < s:
        return False
    if h not in scales:
        scales[h] = (max(_lag_scale(y, h, loading, True), noise.second_difference_sd(h)),
                     max(_lag_scale(y, h, loading, False), noise.difference_sd(2 * h)))
    floor = 1e-12 * float(np.max(np.abs(y)))
    q = noise.quantum  # rounding alone moves a difference by up to q, a second difference by up to 2q
    s2, s1 = z * max(scales[h][0], floor) + 2.0 * q, z * max(scales[h][1], floor) + q
    g = (y[m] - y[k]) - (y[k] - y[k - h])
    if not (g < -s2 and y[k] - y[m] > s1 and y[m] > s1):
        return False
    # a fall back to where a sudden rise started is a toggle or a spike, not a slip
    jump_before = k - 2 * h >= s and abs((y[k] - y[k - h]) - (y[k - h] - y[k - 2 * h])) > s1
    if jump_before and not y[m] - y[k - h] < -s1:
        return False
    after = y[m:min(e, m + h + 1)]
    if not float(np.mean(after)) < y[k] - 0.5 * (y[k] - y[m]):
        return False
    return bool(_falls(x, y, k, m, 0.0) and _loads_again(y, m, e, z1, noise, floor))


def force_lag(x: np.ndarray, y: np.ndarray, t: np.ndarray, direction: np.ndarray) -> float:
    """How long the force channel lags the stretch [s] (0 when it does not), from the record's reversals.

    Where the stretch reverses from loading to unloading at one speed, a
    rate-independent material's stress is symmetric in time about the same
    moment as the stretch (elastic, damage and Mullins laws give the same
    stress on either side of the peak at first order), and a viscoelastic
    stress peaks earlier (it relaxes as the rate falls to zero) and falls
    faster after it: a stress that is symmetric about a *later* moment is the
    acquisition chain's delay (a low-pass filter's and a decimating filter's
    group delays, a force channel read after the position). At each reversal
    (a loading run followed directly by an unloading run) the centre of
    symmetry of each channel is the shift c minimising Σ_τ (y_{c+τ} − y_{c−τ})²
    over τ up to an eighth of the shorter run (every sample of the window
    contributes, so the noise averages out), refined between samples by a
    parabola; the lag is the stress's centre less the stretch's. The record's
    lag is the median over its reversals when it is positive at most of them
    and at least one sampling interval, and shorter than :data:`LAG_OF_RUN` of
    the runs (a filter delays by a few samples); else 0.

    Parameters
    ----------
    x, y, t : ndarray, shape (n,)
        Stretch, stress and time [s] in time order (nearly uniform sampling).
    direction : ndarray of int, shape (n,)
        +1 loading, -1 unloading, 0 hold.
    """
    x, y, t = (np.asarray(a, float) for a in (x, y, t))
    lags, lengths = [], []
    for k, length in _reversals(runs(np.asarray(direction))):
        q = length // 8
        if q < 3:
            continue
        lags.append(_symmetry_centre(y, k, q) - _symmetry_centre(x, k, q))
        lengths.append(length)
    if not lags:
        return 0.0
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    lag = np.array(lags) * dt
    d = float(np.median(lag))
    ok = d >= dt > 0 and float(np.mean(lag > 0)) > 0.5 and d <= LAG_OF_RUN * min(lengths) * dt
    return d if ok else 0.0


def _reversals(rr: list[tuple[int, int, int]]) -> list[tuple[int, int]]:
    """(sample, shorter run's length) of each reversal: a loading run followed by an unloading run, directly or
    through a pause shorter than an eighth of either (the crosshead turning)."""
    out = []
    for i in range(len(rr) - 1):
        s0, e0, v0 = rr[i]
        if v0 <= 0:
            continue
        s1, e1, v1 = rr[i + 1]
        if v1 < 0:
            out.append((e0, min(e0 - s0, e1 - s1)))
        elif v1 == 0 and i + 2 < len(rr) and rr[i + 2][2] < 0:
            s2, e2, _ = rr[i + 2]
            length = min(e0 - s0, e2 - s2)
            if e1 - s1 < length // 8:
                out.append(((s1 + e1) // 2, length))
    return out


def _symmetry_centre(a: np.ndarray, k: int, q: int) -> float:
    """The shift c (samples, relative to *k*, within ±q) about which *a* is most nearly symmetric over ±q samples."""
    n = a.size
    cs = np.arange(max(k - q, q), min(k + q, n - q - 1) + 1)
    if cs.size < 3:
        return 0.0
    taus = np.arange(1, q + 1)
    cost = np.array([float(np.sum((a[c + taus] - a[c - taus]) ** 2)) for c in cs])
    j = int(np.argmin(cost))
    shift = float(cs[j] - k)
    if 0 < j < cost.size - 1:  # a parabola through the three lowest points
        den = cost[j - 1] - 2.0 * cost[j] + cost[j + 1]
        if den > 0:
            shift += 0.5 * (cost[j - 1] - cost[j + 1]) / den
    return shift
