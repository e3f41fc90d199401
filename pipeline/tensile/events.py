"""Events in a tensile record that a model must not fit: measurement noise, ruptures, grip slips.

Shared by the calibrate fit and the discovery (:mod:`esmm.pipeline.discover`): what a record says
about itself, without any model of the material.
"""

from __future__ import annotations

import numpy as np

#: a rupture falls faster than this many times the test's mean secant stiffness (largest stress / span)
SUDDEN_STEEPNESS = 10.0
#: a sudden drop below this fraction of the stress before it is a rupture (a slip loses less)
RUPTURE_FRACTION = 0.5
#: a slip must lose more than this many noise standard deviations of stress
SLIP_SIGMAS = 6.0


def runs(a: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, stop, value) of the runs of equal values."""
    if a.size == 0:
        return []
    edges = np.flatnonzero(np.diff(a)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [a.size]])
    return [(int(s), int(e), int(a[s])) for s, e in zip(starts, stops)]


def noise_sd(y: np.ndarray) -> float:
    r"""Standard deviation of the white measurement noise of a record, estimated without a model.

    The third difference at lag 1, normalised to unit gain for white noise,
    :math:`e_k = (y_{k+3} - 3y_{k+2} + 3y_{k+1} - y_k)/\sqrt{20}`, annihilates every
    locally quadratic signal, so on a record sampled densely compared with its
    curvature it is pure noise; its robust scale (1.4826 × median absolute
    deviation) ignores the few samples at turning points, slips and breaks. A
    quantised record (most differences exactly zero) is floored at the
    quantisation noise q/√12, q the smallest step between samples.

    Parameters
    ----------
    y : ndarray, shape (n,)
        Stress in sample (time) order [Pa].

    Returns
    -------
    float
        σ [Pa] (at least 1e-12 of the record's largest |y|).
    """
    y = np.asarray(y, float)
    y = y[np.isfinite(y)]
    floor = 1e-12 * (float(np.max(np.abs(y))) if y.size else 1.0) or 1e-300
    if y.size < 8:
        return floor
    mad = _third_difference_sd(y)
    steps = np.abs(np.diff(y))
    steps = steps[steps > 0]
    quant = float(np.min(steps)) / np.sqrt(12.0) if steps.size else 0.0
    return max(mad, quant, floor)


def _third_difference_sd(y: np.ndarray) -> float:
    """1.4826 × MAD of the normalised third differences of *y* (0 with fewer than 8 samples)."""
    if y.size < 8:
        return 0.0
    e = (y[3:] - 3.0 * y[2:-1] + 3.0 * y[1:-2] - y[:-3]) / np.sqrt(20.0)
    return 1.4826 * float(np.median(np.abs(e - np.median(e))))


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


def slip_events(x: np.ndarray, y: np.ndarray, direction: np.ndarray) -> list[int]:
    """Samples where the grip slipped: the bottom of each sudden, sustained drop of stress during loading.

    A slip: during a loading run, the stress falls monotonically while the
    stretch advances, faster than it rose over the five samples before (a
    sawtooth, not a smooth maximum); the fall
    exceeds :data:`SLIP_SIGMAS` local noise standard deviations (the
    third-difference estimate of :func:`noise_sd` over the 50 samples around it:
    a step that large between two noisy samples is 4.2 standard deviations of
    their difference, about one chance in 10^5 per sample) and ends more than 2σ
    below the level three samples before the fall began (a spike falls back to the
    trend, a slip below it); it loses less than a rupture; and the same run later
    climbs back above the stress before the fall (the curve continues, shifted).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    out: list[int] = []
    for s, e, d in runs(np.asarray(direction)):
        if d <= 0:
            continue
        k = s
        while k < e - 1:
            m = k
            while m + 1 < e and y[m + 1] < y[m]:
                m += 1
            if m > k and _is_slip(x, y, s, e, k, m):
                out.append(int(m))
            k = m + 1
    return out


def _is_slip(x, y, s: int, e: int, k: int, m: int) -> bool:
    """Whether the fall from sample k to m of the loading run [s, e) is a slip (see :func:`slip_events`)."""
    lo, hi = max(0, k - 25), min(y.size, m + 26)
    sigma = max(_third_difference_sd(y[lo:hi]), 1e-12 * float(np.max(np.abs(y))))
    k0 = max(s, k - 5)
    rise = (y[k] - y[k0]) / (x[k] - x[k0]) if x[k] > x[k0] else 0.0
    ref = y[max(s, k - 3)]
    return bool(y[k] - y[m] > SLIP_SIGMAS * sigma and ref - y[m] > 2.0 * sigma and y[m] > RUPTURE_FRACTION * y[k]
                and _falls(x, y, k, m, max(rise, 0.0)) and np.any(y[m:e] > y[k]))
