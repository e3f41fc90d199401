"""What a tensile record carries besides stress and stretch: rate, direction, holds, cycles.

:func:`covariates` segments one test into loading / unloading / hold samples,
numbers its cycles, and computes the covariates that the residual diagnosis
relates the residual to (stretch rate, time in a hold, the largest stretch so
far, time since the start, the toe region and the high-stretch end).

:func:`thin` picks the samples used for fitting: evenly spaced in arc length of
the normalised (time, stretch) path, plus every turning point, so a long hold
and a short ramp are both represented and a 90 000-sample relaxation record
costs a few hundred samples. Reported errors are always computed on all samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..materials.effects import equivalent_stretch
from ..materials.loading import invariants
from ..tensile.data import TensileTest
from ..tensile.events import runs as _runs
from ..tensile.noise import lag_profile, quantum

#: |rate| below this fraction of the largest (smoothed) |rate| of the test is a hold
HOLD_FRACTION = 0.03
#: the rate is smoothed over the time in which the stretch, at the test's mean speed, advances by this many of
#: its resolution steps (the larger of its quantisation step and its noise): a window in strain, not in samples
RATE_STEPS = 4.0
#: toe region: the first loading up to this fraction of the test's stretch span
TOE_FRACTION = 0.10
#: high-stretch end: above this fraction of the span, on the primary loading path
HIGH_FRACTION = 0.80
#: "below the previous maximum": more than this fraction of the span below it
BELOW_MAX_FRACTION = 0.02
#: a record's stretch turns back where it retreats from its running extreme by more than this fraction of its span
REVERSAL_FRACTION = 0.05


@dataclass
class Covariates:
    """Per-sample covariates of one test (arrays of shape (n,)).

    Attributes
    ----------
    has_time : bool
        The file has a time column (so sample order is loading history).
    drive : ndarray
        Uniaxial-equivalent stretch ξ ≥ 1 (|γ| → ξ for shear; compression → ξ > 1).
    rate : ndarray
        dλ/dt [1/s] (dγ/dt for shear), smoothed; NaN without time.
    direction : ndarray of int8
        +1 loading (|deformation| growing), -1 unloading, 0 hold.
    hold_time : ndarray
        Time since the current hold began [s] (0 outside holds; NaN without time).
    cycle : ndarray of int
        0 for the first loading, +1 at every reloading after an unloading.
    max_so_far : ndarray
        Running maximum of ``drive``.
    below_max : ndarray
        ``(max_so_far - drive) / span``, ≥ 0.
    elapsed : ndarray
        Time since the first sample [s] (sample index without time).
    toe, high, virgin : ndarray of bool
        Toe region of the first loading; high-stretch end; primary loading path.
    """

    has_time: bool
    drive: np.ndarray
    rate: np.ndarray
    direction: np.ndarray
    hold_time: np.ndarray
    cycle: np.ndarray
    max_so_far: np.ndarray
    below_max: np.ndarray
    elapsed: np.ndarray
    toe: np.ndarray
    high: np.ndarray
    virgin: np.ndarray
    #: samples of the rate's smoothing window (:data:`RATE_STEPS`); a pause shorter than it is not a hold
    window: int = 1

    @property
    def n_cycles(self) -> int:
        return int(self.cycle.max()) + 1 if self.cycle.size else 0

    @property
    def has_unloading(self) -> bool:
        return bool(np.any(self.direction < 0))

    @property
    def has_hold(self) -> bool:
        return self.has_time and bool(np.any(self.direction == 0) and np.nanmax(self.hold_time) > 0)

    def loading_rate(self) -> float:
        """Median |rate| over the moving samples [1/s] (NaN without time)."""
        moving = self.direction != 0
        if not self.has_time or not np.any(moving):
            return float("nan")
        return float(np.median(np.abs(self.rate[moving])))

    def rates(self) -> np.ndarray:
        """Distinct loading rates of the moving segments (rounded to 2 significant digits)."""
        if not self.has_time:
            return np.array([])
        moving = self.direction != 0
        r = np.abs(self.rate[moving])
        r = r[r > 0]
        if r.size == 0:
            return np.array([])
        # one value per segment: median over runs of equal direction
        out = []
        seg = _runs(self.direction)
        for s, e, d in seg:
            if d != 0 and e - s >= max(self.window, 3):
                out.append(float(np.median(np.abs(self.rate[s:e]))))
        return np.unique(np.array([float(f"{v:.2g}") for v in out if v > 0]))




def drive_of(test: TensileTest, x: np.ndarray | None = None) -> np.ndarray:
    """Uniaxial-equivalent stretch ξ of the test's samples (or of *x* in its mode)."""
    x = test.stretch if x is None else x
    i1, _ = invariants(test.mode, np.asarray(x, float))
    return equivalent_stretch(i1)


def _smooth(y: np.ndarray, w: int) -> np.ndarray:
    if w <= 1 or y.size < 3:
        return y.astype(float)
    w = min(w, y.size)
    k = np.ones(w) / w
    pad = w // 2
    yp = np.pad(y.astype(float), (pad, w - 1 - pad), mode="edge")
    return np.convolve(yp, k, mode="valid")


def covariates(test: TensileTest) -> Covariates:
    """Segment *test* and compute its covariates (see :class:`Covariates`)."""
    x = np.asarray(test.stretch, float)
    n = x.size
    # signed deformation magnitude: distance from the reference state
    ref = 0.0 if test.mode == "simple_shear" else 1.0
    drive = drive_of(test)
    mag = np.abs(x - ref)
    has_time = test.time is not None and n > 1 and float(test.time[-1] - test.time[0]) > 0
    window = 1
    if has_time:
        window = rate_window(x, np.asarray(test.time, float))
        elapsed, rate, direction, hold_time = _timed_segments(x, mag, np.asarray(test.time, float), window)
    else:
        elapsed, rate, direction, hold_time = _untimed_segments(mag)
    cycle = _cycles(direction)
    if has_time:
        max_so_far = np.maximum.accumulate(drive)
    else:
        max_so_far = drive.copy()  # no history: every sample on the primary path
    span = float(np.max(drive) - 1.0) or 1.0
    below = (max_so_far - drive) / span
    virgin = below <= BELOW_MAX_FRACTION
    first_loading = (cycle == 0) & (direction >= 0)
    toe = first_loading & ((drive - 1.0) <= TOE_FRACTION * span) & (x >= ref) if test.mode != "simple_shear" \
        else first_loading & ((drive - 1.0) <= TOE_FRACTION * span)
    high = virgin & ((drive - 1.0) >= HIGH_FRACTION * span)
    return Covariates(
        has_time=has_time, drive=drive, rate=rate, direction=direction, hold_time=hold_time,
        cycle=cycle, max_so_far=max_so_far, below_max=below, elapsed=elapsed, toe=toe, high=high,
        virgin=virgin, window=window,
    )


def rate_window(x: np.ndarray, t: np.ndarray) -> int:
    """Samples of the rate's smoothing window: the time in which the stretch, at the test's mean speed,
    advances by :data:`RATE_STEPS` of its resolution (odd, 1 to n/20).

    The resolution is the larger of the stretch's quantisation step (the
    encoder's, :func:`~esmm.pipeline.tensile.noise.quantum`) and its
    sample-to-sample noise (the robust scale of its lag-1 third differences,
    :func:`~esmm.pipeline.tensile.noise.lag_profile`); the mean speed is the
    path length over the duration, measured on a grid of 200 points (so that
    the noise does not lengthen it).
    """
    n = x.size
    T = float(t[-1] - t[0])
    if n < 8 or T <= 0:
        return 1
    prof = lag_profile(x)
    res = max(quantum(x), prof[0][1] if prof else 0.0)
    grid = np.linspace(0, n - 1, min(n, 200)).round().astype(int)
    speed = float(np.sum(np.abs(np.diff(x[grid])))) / T
    dt = T / (n - 1)
    if speed <= 0 or res <= 0:
        return 1
    w = int(round(RATE_STEPS * res / speed / dt))
    w = max(1, min(w, n // 20))
    return w if w % 2 else w + 1


def _timed_segments(x: np.ndarray, mag: np.ndarray, t: np.ndarray, w: int):
    """(elapsed, rate, direction, hold time) of a record with time: directions from the rate smoothed over
    *w* samples (:func:`rate_window`)."""
    n = x.size
    elapsed = t - t[0]
    with np.errstate(divide="ignore", invalid="ignore"):     # repeated time stamps (a clock coarser than the
        rate = np.gradient(_smooth(x, w), t) if n > 2 else np.zeros(n)          # sampling): no rate there
        mag_rate = np.gradient(_smooth(mag, w), t) if n > 2 else np.zeros(n)
    rate = np.where(np.isfinite(rate), rate, 0.0)
    mag_rate = np.where(np.isfinite(mag_rate), mag_rate, 0.0)
    tol = HOLD_FRACTION * (float(np.max(np.abs(rate))) if n else 0.0)
    direction = np.where(mag_rate > tol, 1, np.where(mag_rate < -tol, -1, 0)).astype(np.int8)
    # a pause shorter than the smoothing window is the rate's noise: it inherits the previous direction
    for s, e, d in _runs(direction):
        if d == 0 and e - s < max(w, 3) and s > 0:
            direction[s:e] = direction[s - 1]
    hold_time = np.zeros(n)
    for s, e, d in _runs(direction):
        if d == 0:
            hold_time[s:e] = t[s:e] - t[s]
    return elapsed, rate, direction, hold_time


def reverses(x: np.ndarray, fraction: float = REVERSAL_FRACTION) -> bool:
    """The stretch turns back at least twice (loads, unloads and loads again, or the reverse), each time by
    more than *fraction* of its span.

    A record without time that does this is a cyclic test written without its
    time column. Its rows are not read as its loading history: without time a
    relaxation's loop and its recovery after unloading look like Mullins
    softening, damage, a permanent set or cyclic softening, so the discovery
    says what the time column would let it try (docs/design/discovery-results.md,
    "Records without time", measures what reading the rows would do). A curve
    that turns once (an averaged loop) or a monotonic sweep from compression to
    tension (Budday's) is not such a test.
    """
    x = np.asarray(x, float)
    span = float(np.ptp(x)) if x.size else 0.0
    if span <= 0:
        return False
    tol = fraction * span
    turns, hi, lo, heading = 0, x[0], x[0], 0
    for v in x[1:]:
        if heading >= 0:
            hi = max(hi, v)
        if heading <= 0:
            lo = min(lo, v)
        if heading >= 0 and v < hi - tol:
            turns, heading, lo = turns + (heading > 0), -1, v
        elif heading <= 0 and v > lo + tol:
            turns, heading, hi = turns + (heading < 0), 1, v
        if turns >= 2:
            return True
    return False


def _untimed_segments(mag: np.ndarray):
    """(elapsed, rate, direction, hold time) of a record without time: directions from the row order."""
    n = mag.size
    dm = np.diff(mag, prepend=mag[0])
    direction = np.where(dm > 0, 1, np.where(dm < 0, -1, 0)).astype(np.int8)
    if n > 1:
        direction[0] = direction[1]
    return np.arange(n, dtype=float), np.full(n, np.nan), direction, np.full(n, np.nan)


def _cycles(direction: np.ndarray) -> np.ndarray:
    """Cycle number per sample: a reloading after an unloading starts a new cycle."""
    cycle = np.zeros(direction.size, dtype=int)
    c, last = 0, 0
    for k in range(direction.size):
        d = int(direction[k])
        if d == 1 and last == -1:
            c += 1
        if d != 0:
            last = d
        cycle[k] = c
    return cycle


def thin(test: TensileTest, max_points: int, *, cov: Covariates | None = None) -> np.ndarray:
    """Indices of at most about *max_points* samples for fitting (sorted, unique).

    Evenly spaced in arc length of the path (t/T, (x - min)/span, log time in
    the current hold) — (index, x) without time — plus the first and last sample and every turning point of
    the stretch (with their neighbours), so that peaks and hold starts are kept.

    Parameters
    ----------
    test : TensileTest
    max_points : int
        Target number of samples (the turning points may add a few).
    cov : Covariates, optional
        Precomputed covariates (for the turning points).

    Returns
    -------
    ndarray of int, shape (m,)
    """
    n = test.n
    if n <= max_points:
        return np.arange(n)
    x = np.asarray(test.stretch, float)
    span = float(np.ptp(x)) or 1.0
    if test.time is not None:
        t = np.asarray(test.time, float)
        tn = (t - t[0]) / (float(t[-1] - t[0]) or 1.0)
    else:
        tn = np.linspace(0.0, 1.0, n)
    xn = (x - x.min()) / span
    if cov is None:
        cov = covariates(test)
    ds = np.hypot(np.diff(tn), np.diff(xn))
    if cov.has_hold:
        # log time within holds: relaxation is fast at first, slow later
        dt0 = float(np.median(np.diff(test.time))) or 1e-3
        T = float(test.time[-1] - test.time[0])
        lh = np.zeros(n)
        for s0, e0, dd in _runs(cov.direction):
            if dd == 0 and e0 - s0 > 1:
                ht = cov.hold_time[s0:e0]
                # each hold weighs by its share of the test's duration
                lh[s0:e0] = np.log1p(ht / dt0) / np.log1p(ht[-1] / dt0) * (ht[-1] / T)
        ds = np.hypot(ds, np.abs(np.diff(lh)) * (cov.direction[1:] == 0))
    s = np.concatenate([[0.0], np.cumsum(ds)])
    targets = np.linspace(0.0, s[-1], max_points)
    idx = np.searchsorted(s, targets, side="left")
    extra = [0, n - 1]
    d = cov.direction
    turns = np.flatnonzero(np.diff(d) != 0)
    for k in turns:
        extra += [int(k) - 1, int(k), int(k) + 1, int(k) + 2]
    # true extremes of the stretch within each moving run
    for s0, e0, dd in _runs(d):
        if dd != 0 and e0 > s0:
            seg = x[s0:e0]
            extra += [s0 + int(np.argmax(seg)), s0 + int(np.argmin(seg))]
    idx = np.concatenate([idx, np.array(extra, dtype=int)])
    idx = np.unique(idx[(idx >= 0) & (idx < n)])
    if idx.size < max_points:  # duplicates where the path is steep: fill evenly in index
        fill = np.linspace(0, n - 1, max_points - idx.size).round().astype(int)
        idx = np.unique(np.concatenate([idx, fill]))
    return idx
