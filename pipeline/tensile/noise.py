r"""The measurement noise of a tensile record: its size, its correlation and its quantisation step.

A testing machine low-pass filters its force channel (the amplifier, an
anti-aliasing filter, a decimating average), quantises it to its converter's
step and adds amplifier noise that is partly 1/f. The noise a record carries
is therefore correlated from sample to sample, and a noise estimate that
assumes white noise (the lag-1 third difference) comes out many times too
small on such a record. :func:`noise_model` estimates, from the record alone
and without any model of the material:

* the **quantisation step** q: the values' common step (:func:`quantum`);
* the **per-sample standard deviation** σ of the noise, from the robust scale
  of third differences at growing lags L = 1, 2, 4, 8, ...:

  .. math::

      s^2(L) = \frac{\mathrm{sd}_{80}(\Delta_L^3 y)^2}{20},
      \qquad \Delta_L^3 y_k = y_{k+3L} - 3y_{k+2L} + 3y_{k+L} - y_k .

  For noise with autocorrelation ρ, s²(L) = σ²[1 − (15ρ(L) − 6ρ(2L) + ρ(3L))/10]:
  it equals σ² for white noise at every lag, and for correlated noise it rises
  with L to σ² once L exceeds the correlation length. A smooth signal adds a
  term growing like L⁶ (its third derivative; the median removed in blocks of
  48 L samples takes off its slowly varying part, the robust scale the few
  samples at turning points, slips and breaks). σ is the plateau between the
  two rises: a doubling of the lag that raises s by less than
  :data:`FLAT_RATIO`. A profile can hold two plateaus: the converter's white
  floor (its quantisation, an aliased hum) at the shortest lags, below the
  filtered amplifier noise, whose s rises to its own σ once the lag passes its
  correlation length and is flat again there. The per-sample noise is the sum,
  so σ is read at the start of the *last* plateau, one held over two doublings
  (a signal's rise does not flatten again). A record without a plateau (its correlated noise and its
  signal share one time scale) gets the value where s rises least, flagged
  ``separable = False``. A quantised record is floored at q/√12;
* the **correlation**: ρ(k) = exp(−k/ℓ) fitted to the rising part of s²(L)
  (ℓ the correlation length in samples; ℓ·Δt the correlation time in
  seconds), and from it the integrated autocorrelation time of the noise
  sampled every m samples, τ(m) = coth(m/2ℓ) (1 for white noise; ≈ 2ℓ/m for
  m ≪ ℓ): a mean of n such samples has the variance of n/τ independent ones.

docs/design/discovery.md, "What a record says about itself", states the
method and its limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

#: a doubling of the lag that raises the robust scale by less than this factor is flat (the plateau)
FLAT_RATIO = 1.15
#: a plateau after the first is taken only where this many successive doublings are flat (a 4x range of lags)
LATER_PLATEAU = 2
#: the lags used need at least this many third differences per lag span (3 L)
MIN_SPANS = 12
#: the robust scale drops this fraction of the values on either side
TRIM = 0.10
#: standard deviation of a unit normal variable restricted to its central 1 - 2 TRIM
TRIM_SD = math.sqrt(1.0 - 2.0 * 1.2815515655446004 * math.exp(-0.5 * 1.2815515655446004**2)
                    / math.sqrt(2.0 * math.pi) / (1.0 - 2.0 * TRIM))


@dataclass(frozen=True)
class Noise:
    """The noise of one record (see the module docstring).

    Attributes
    ----------
    sigma : float
        Per-sample standard deviation of the noise [units of the record].
    quantum : float
        Quantisation step of the values (0: none found).
    length : float
        Correlation length ℓ [samples], ρ(k) = exp(−k/ℓ); 0 for white noise.
    spacing : float
        Median sampling interval [s] (NaN without time).
    separable : bool
        Whether the lag profile has a plateau (False: noise and signal share a
        time scale and σ is the least-rising point of the profile).
    profile : tuple of (int, float)
        (lag L, s(L)) of the profile.
    """

    sigma: float
    quantum: float = 0.0
    length: float = 0.0
    spacing: float = math.nan
    separable: bool = True
    profile: tuple = field(default=(), compare=False)

    @property
    def correlation_time(self) -> float:
        """ℓ Δt [s] (NaN without time)."""
        return self.length * self.spacing

    def rho(self, k: float | np.ndarray) -> float | np.ndarray:
        """Autocorrelation of the noise at lag *k* samples."""
        if self.length <= 0:
            return np.where(np.asarray(k) == 0, 1.0, 0.0) if np.ndim(k) else float(k == 0)
        return np.exp(-np.abs(k) / self.length)

    def tau(self, m: float) -> float:
        """Integrated autocorrelation time of the noise sampled every *m* samples: coth(m / 2ℓ), ≥ 1."""
        if self.length <= 0 or m <= 0:
            return 1.0
        u = m / (2.0 * self.length)
        return 1.0 / math.tanh(u) if u < 20 else 1.0

    def difference_sd(self, k: float) -> float:
        """Standard deviation of the noise's difference across *k* samples: σ √(2(1 − ρ(k)))."""
        return self.sigma * math.sqrt(max(2.0 * (1.0 - float(self.rho(k))), 0.0))

    def second_difference_sd(self, k: float) -> float:
        """Standard deviation of the noise's y_{j+k} − 2y_j + y_{j−k}: σ √(6 − 8ρ(k) + 2ρ(2k))."""
        return self.sigma * math.sqrt(max(6.0 - 8.0 * float(self.rho(k)) + 2.0 * float(self.rho(2 * k)), 0.0))

    def mean_sd(self, w: int) -> float:
        """Standard deviation of the noise's mean over *w* consecutive samples: σ √(Σ_k (w − |k|) ρ(k)) / w."""
        k = np.abs(np.arange(1 - w, w)).astype(float)
        var = float(np.sum((w - k) * np.asarray(self.rho(k), float)))
        return self.sigma * math.sqrt(max(var, 0.0)) / w

    def to_dict(self) -> dict:
        return {"sd": self.sigma, "quantum": self.quantum, "correlation_samples": self.length,
                "correlation_time_s": self.correlation_time if math.isfinite(self.correlation_time) else None,
                "separable": self.separable, "profile": [[int(L), float(s)] for L, s in self.profile]}


def quantum(y: np.ndarray) -> float:
    """The quantisation step of *y*: the smallest step between samples of which nearly all steps are multiples,
    or the spacing of the levels the reading rests on (:func:`level_step`) where that is more than four times
    larger (the grid is then the written digits', finer than the converter's).

    Returns 0 when the values are not on a grid (fewer than 90 % of the
    non-zero steps within 10 % of a multiple of the smallest), or when fewer
    than 10 steps are non-zero. The 10 %: a converter's levels written with a
    few decimals are rounded a second time, so its steps are unequal by up to
    one written digit (a 12-bit step of 0.0122 N written to 0.001 N steps by
    0.012 and 0.013 N); values off any grid put a fifth of their steps within
    10 % of a multiple, far from nine tenths.
    """
    y = np.asarray(y, float)
    y = y[np.isfinite(y)]
    if y.size < 3:
        return 0.0
    tol = 1e-9 * (float(np.max(np.abs(y))) or 1.0)
    d = np.abs(np.diff(y))
    d = d[d > tol]
    if d.size < 10:
        return 0.0
    q = float(np.min(d))
    r = d / q
    on_grid = np.abs(r - np.round(r)) <= 0.1
    grid = q if float(np.mean(on_grid)) >= 0.9 else 0.0
    levels = level_step(y, grid=grid)
    # a grid much finer than the levels the reading rests on is the written digits', not the converter's
    return levels if levels > 4.0 * grid else grid


#: a record whose readings sit on plateaus (runs of three or more equal values) for at least this fraction of
#: its samples reads its converter's levels, not its noise
PLATEAU_SHARE = 0.5


def level_step(y: np.ndarray, *, grid: float = 0.0) -> float:
    """The spacing of the converter's levels in a record that rests on them, else 0.

    A converter whose step is larger than the noise before it reads the same
    level for many samples; a digital filter after it (quantisation at the
    converter, then filtering and decimation) turns each change of level into a
    short filtered transition, so the written values are off any grid and
    their own steps say nothing of the level spacing. The plateaus do: where
    runs of three or more equal readings (within *grid*, the written
    resolution) hold at least :data:`PLATEAU_SHARE` of the samples, the step is
    the lower quartile of the changes between successive resting plateaus (the
    longest, four fifths of the plateaus' samples) larger than three written
    digits (a change of several levels at once is rarer than of one; at least
    five such changes). The error of such a record against a
    smooth signal is the rounding's, up to half this step: the noise estimate
    of third differences, which sees mostly zeros, is far below it. Where the
    resting plateaus step mostly by one *grid* (their median change within 1.5
    grids), the grid is the converter's own (quantised at the output, a ramp
    climbing its levels one at a time) and 0 is returned: the grid stands, where
    the quartile of the larger changes alone (a fast toe, slips) would read a
    multiple of the step.
    """
    tol = max(0.5 * grid, 1e-9 * (float(np.max(np.abs(y))) or 1.0))
    same = np.abs(np.diff(y)) <= tol
    edges = np.diff(np.concatenate(([0], same.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    lengths = stops - starts + 1  # samples in each run of equal readings
    keep = lengths >= 3
    if float(np.sum(lengths[keep])) < PLATEAU_SHARE * y.size:
        return 0.0
    # the resting plateaus: the longest, holding four fifths of the plateaus' samples (a filter that settles
    # slowly after a change of level leaves short runs at values between)
    idx = np.flatnonzero(keep)
    order = idx[np.argsort(-lengths[idx], kind="stable")]
    cover = np.cumsum(lengths[order])
    rest = np.sort(order[: int(np.searchsorted(cover, 0.8 * cover[-1])) + 1])
    levels = y[starts[rest]]
    d = np.abs(np.diff(levels))
    moves = d[d > tol]
    if grid > 0.0 and moves.size >= 5 and float(np.median(moves)) <= 1.5 * grid:
        return 0.0  # the plateaus step by the grid itself: the grid is the converter's, not the written digits'
    d = d[d > max(3.0 * grid, tol)]
    return float(np.percentile(d, 25)) if d.size >= 5 else 0.0


def _robust_scale(y: np.ndarray, L: int) -> float:
    """s(L): robust standard deviation of the normalised lag-L third differences, medians removed in blocks.

    The robust scale is the standard deviation of the central 80 % of the values
    divided by its value for a unit normal variable (:data:`TRIM_SD`): it ignores
    the 10 % largest on either side (turning points, slips, breaks) and, unlike the
    median absolute deviation, varies smoothly when the values are quantised.
    """
    e = (y[3 * L:] - 3.0 * y[2 * L:-L] + 3.0 * y[L:-2 * L] - y[:-3 * L]) / math.sqrt(20.0)
    block = max(48 * L, 64)
    nb = max(e.size // block, 1)
    parts = np.array_split(e, nb)
    return robust_sd(np.concatenate([p - np.median(p) for p in parts]))


def robust_sd(e: np.ndarray) -> float:
    """Standard deviation of *e* from its central 80 %: robust to a tenth of outliers on either side,
    smooth in quantised values (0 with fewer than 2 values)."""
    e = np.asarray(e, float)
    if e.size < 2:
        return 0.0
    lo, hi = np.quantile(e, [TRIM, 1.0 - TRIM])
    core = e[(e >= lo) & (e <= hi)]
    return float(np.std(core)) / TRIM_SD if core.size > 1 else 0.0


def lag_profile(y: np.ndarray) -> list[tuple[int, float]]:
    """(L, s(L)) for L = 1, 2, 4, ... while the record holds :data:`MIN_SPANS` spans of 3 L samples."""
    y = np.asarray(y, float)
    out = []
    L = 1
    while 3 * L * MIN_SPANS <= y.size:
        out.append((L, _robust_scale(y, L)))
        L *= 2
    return out


def _plateau(profile: list[tuple[int, float]]) -> tuple[int, bool]:
    """Index of the plateau's lag in *profile* and whether a flat step was found.

    The profile is read through its running maximum: positively correlated
    noise makes s(L) rise with L, and a dip after a rise (a quantised record's
    rounding pattern at one lag) is not the noise falling. The plateau is the
    last run of flat doublings (module docstring: a white floor at the shortest
    lags lies below the filtered noise's σ), read at the run's first flat step
    as a single plateau always was; a run after the first must hold over
    :data:`LATER_PLATEAU` doublings (a single flat step at long lags can be the
    signal's, or a few events', between two rises).
    """
    s = np.maximum.accumulate(np.array([v for _, v in profile]))
    if s.size == 1:
        return 0, True
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = s[1:] / s[:-1]
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)
    flat = ratio < FLAT_RATIO
    if not flat.any():
        return int(np.argmin(ratio)) + 1, False
    starts = np.flatnonzero(flat & ~np.concatenate(([False], flat[:-1])))   # the first step of each flat run
    long = [int(k) for k in starts[1:] if flat[k:k + LATER_PLATEAU].sum() == LATER_PLATEAU]
    j = long[-1] if long else int(starts[0])
    return (j if j == 0 else j + 1), True


def _length(profile: list[tuple[int, float]], j: int, sigma: float) -> float:
    """Correlation length ℓ [samples] from the lag where s²(L) reaches half of σ² (0: white).

    For exponentially correlated noise s²(L)/σ² = 1 − (15e^{−u} − 6e^{−2u} + e^{−3u})/10,
    u = L/ℓ, which is ½ at u = :data:`HALF_U`; the half-point is interpolated in
    log L between the profile's lags. Filtered noise is smoother than
    exponential (its profile rises faster), so this ℓ is a scale, not an exact
    fit; its integrated autocorrelation time is within a factor of about two.
    """
    lags = np.array([L for L, _ in profile[: j + 1]], float)
    s2 = np.array([v for _, v in profile[: j + 1]]) ** 2 / sigma**2
    if s2[0] >= 0.5:
        # already above half at lag 1: ℓ below one sample, from the lag-1 value itself
        return _invert_shape(min(float(s2[0]), 0.999))
    k = int(np.flatnonzero(s2 >= 0.5)[0]) if np.any(s2 >= 0.5) else s2.size - 1
    lo, hi = max(k - 1, 0), k
    a, b = math.log(max(s2[lo], 1e-12)), math.log(max(s2[hi], 1e-12))
    if hi == lo or b <= a:
        return float(lags[hi]) / HALF_U
    w = (math.log(0.5) - a) / (b - a)
    half = math.exp(math.log(lags[lo]) + w * (math.log(lags[hi]) - math.log(lags[lo])))
    return half / HALF_U


def _shape(u: float) -> float:
    """s²(L)/σ² of exponentially correlated noise, u = L/ℓ."""
    return 1.0 - (15.0 * math.exp(-u) - 6.0 * math.exp(-2.0 * u) + math.exp(-3.0 * u)) / 10.0


def _invert_shape(v: float) -> float:
    """ℓ [samples] such that the exponential shape at lag 1 is *v* (0 when v is about 1: white)."""
    if v >= 0.999:
        return 0.0
    u = optimize.brentq(lambda u: _shape(u) - v, 1e-9, 50.0)
    return 1.0 / u


#: u = L/ℓ where the exponential shape is one half
HALF_U = float(optimize.brentq(lambda u: _shape(u) - 0.5, 1e-6, 20.0))


def noise_model(y: np.ndarray, t: np.ndarray | None = None) -> Noise:
    """The noise of a record *y* (time order), and its correlation (module docstring).

    Parameters
    ----------
    y : ndarray, shape (n,)
        The measured channel (stress [Pa] or force [N]) in sample order.
    t : ndarray, shape (n,), optional
        Time [s], for the correlation time.

    Returns
    -------
    Noise
    """
    y = np.asarray(y, float)
    keep = np.isfinite(y)
    y = y[keep]
    top = float(np.max(np.abs(y))) if y.size else 1.0
    floor = 1e-12 * top or 1e-300
    dt = math.nan
    if t is not None and y.size > 1:
        tt = np.asarray(t, float)[keep]
        steps = np.diff(tt)
        steps = steps[np.isfinite(steps) & (steps > 0)]
        dt = float(np.median(steps)) if steps.size else math.nan
    q = quantum(y)
    profile = lag_profile(y)
    if not profile:
        return Noise(max(q / math.sqrt(12.0), floor), q, 0.0, dt, False, ())
    j, flat = _plateau(profile)
    sigma = max(v for _, v in profile[: j + 1])
    q_sd = q / math.sqrt(12.0)
    if sigma <= q_sd:  # below the converter's resolution: the quantisation error is the noise
        return Noise(max(q_sd, floor), q, 0.0, dt, flat, tuple(profile))
    return Noise(max(sigma, floor), q, _length(profile, j, sigma), dt, flat, tuple(profile))


def noise_sd(y: np.ndarray) -> float:
    """Per-sample standard deviation σ of the noise of a record *y* (time order), from :func:`noise_model`.

    Robust to correlated (filtered, decimated) and quantised noise; see the
    module docstring. Returns at least 1e-12 of the record's largest |y|.
    """
    return noise_model(y).sigma


__all__ = ["Noise", "noise_model", "noise_sd", "quantum", "level_step", "lag_profile", "robust_sd", "FLAT_RATIO", "FORCE_ACCURACY",
           "resolution"]


#: the relative accuracy of a testing machine's force channel: ISO 7500-1 class 0.5 (the indicated force within
#: 0.5 % of the reading over the calibrated range); a model change below it is not resolved by the measurement
FORCE_ACCURACY = 0.005


def resolution(y: np.ndarray, sigma: float) -> float:
    """What a record resolves [Pa]: the larger of its noise σ and :data:`FORCE_ACCURACY` × the RMS of *y*."""
    y = np.asarray(y, float)
    y = y[np.isfinite(y)]
    return max(float(sigma), FORCE_ACCURACY * (float(np.sqrt(np.mean(y * y))) if y.size else 0.0))
