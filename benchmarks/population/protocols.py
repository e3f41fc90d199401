"""Test protocols as labs run them, and the crosshead's real motion.

A protocol is one or more files, each a list of waypoints ``(t [s], x)`` joined by straight lines:
``x`` is the stretch of the loaded direction (the amount of shear for simple shear), so that a
segment's slope is the strain rate. Kinds (``KINDS``):

* ``ramp``        rest, one monotonic ramp to the peak, a short stop;
* ``failure``     a ramp that goes on until the specimen ruptures, the crosshead moving on for a
                  moment after it (the rupture itself is made in :mod:`.cases`);
* ``cycles``      load-unload cycles at one amplitude (3-10);
* ``rising``      cycles of rising amplitude (3-6 levels, 1-3 cycles each);
* ``multirate``   2-3 files of one specimen, 1-3 cycles each, strain rates a factor 3-10 apart;
* ``relaxation``  a fast ramp (5-50 times the family's rate, taking at least 1-5 s, as a
                  crosshead does a "step") and a long hold (60-900 s), then unloading;
* ``staircase``   2-4 such ramp-and-hold steps (30-300 s holds) at rising levels;
* ``replicates``  2-3 specimens of one material under one ramp or cycle protocol.

Displacement control throughout (holds are relaxation, never creep). The machine follows the
piecewise-linear command with a finite acceleration (a moving average over the acceleration
time, i.e. a trapezoidal velocity profile) and a velocity that is not quite steady: a periodic
ripple (the ball screw's rotation) and a little low-pass random noise, both proportional to the
commanded speed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

KINDS = ("ramp", "failure", "cycles", "rising", "multirate", "relaxation", "staircase", "replicates")


@dataclass
class Protocol:
    """The files' waypoints (t, x) and what was drawn (``info``)."""

    kind: str
    files: list[list[tuple[float, float]]]
    info: dict = field(default_factory=dict)

    def duration(self, k: int) -> float:
        return self.files[k][-1][0]

    def shortest_segment(self) -> float:
        """The shortest moving segment over all files [s] (what the acquisition must resolve)."""
        out = np.inf
        for wp in self.files:
            for (t0, x0), (t1, x1) in zip(wp[:-1], wp[1:]):
                if x1 != x0:
                    out = min(out, t1 - t0)
        return float(out)


def _path(x0: float, targets, rate: float, *, rest: float, holds=None, end: float = 0.0):
    """Waypoints from x0 through the targets at |dx/dt| = rate, with holds after some targets."""
    wp = [(0.0, x0), (rest, x0)]
    t, x = rest, x0
    for i, xt in enumerate(targets):
        t += abs(xt - x) / rate
        x = xt
        wp.append((t, x))
        h = holds[i] if holds is not None else 0.0
        if h > 0.0:
            t += h
            wp.append((t, x))
    if end > 0.0:
        wp.append((t + end, x))
    return wp


def _cycle(x0: float, hi: float, lo: float | None) -> list[float]:
    """One cycle's targets: to the peak and back (through the opposite peak when ``lo`` is given)."""
    return [hi, x0] if lo is None else [hi, lo, x0]


def build(kind: str, rng: np.random.Generator, *, x0: float, hi: float, lo: float | None,
          rate: float) -> Protocol:
    """Draw a protocol of ``kind`` between the reference ``x0`` and the peak ``hi`` (``lo``: an
    opposite peak for tension-compression or +-shear cycles)."""
    rest = float(rng.uniform(1.0, 8.0))
    if kind == "ramp":
        end = float(rng.uniform(0.0, 2.0))
        return Protocol(kind, [_path(x0, [hi], rate, rest=rest, end=end)], {"rate_per_s": rate, "peak": hi})
    if kind == "failure":  # the crosshead moves on for a moment after the rupture at hi
        after = float(rng.uniform(0.5, 3.0))
        beyond = hi + np.sign(hi - x0) * rate * after
        return Protocol(kind, [_path(x0, [beyond], rate, rest=rest)],
                        {"rate_per_s": rate, "rupture_x": hi, "after_s": after})
    if kind == "cycles":
        n = int(rng.integers(3, 11))
        return Protocol(kind, [_path(x0, _cycle(x0, hi, lo) * n, rate, rest=rest, end=1.0)],
                        {"rate_per_s": rate, "peak": hi, "cycles": n})
    if kind == "rising":
        k, rep = int(rng.integers(3, 7)), int(rng.integers(1, 4))
        levels = x0 + (hi - x0) * np.linspace(1.0 / k, 1.0, k)
        lows = [None] * k if lo is None else list(x0 + (lo - x0) * np.linspace(1.0 / k, 1.0, k))
        targets = [v for a, b in zip(levels, lows) for v in _cycle(x0, float(a), b) * rep]
        return Protocol(kind, [_path(x0, targets, rate, rest=rest, end=1.0)],
                        {"rate_per_s": rate, "levels": levels.tolist(), "repeats": rep})
    if kind == "multirate":
        m, factor = int(rng.integers(2, 4)), float(rng.uniform(3.0, 10.0))
        n = int(rng.integers(1, 4))
        rates = [rate * factor ** (j - (m - 1) / 2.0) for j in range(m)]
        files = [_path(x0, _cycle(x0, hi, lo) * n, r, rest=rest, end=1.0) for r in rates]
        return Protocol(kind, files, {"rates_per_s": rates, "factor": factor, "cycles": n, "peak": hi})
    if kind == "relaxation":
        fast = min(rate * float(rng.uniform(5.0, 50.0)), abs(hi - x0) / float(rng.uniform(1.0, 5.0)))
        hold = float(rng.uniform(60.0, 900.0))
        return Protocol(kind, [_path(x0, [hi, x0], fast, rest=rest, holds=[hold, 0.0], end=float(rng.uniform(2, 20)))],
                        {"rate_per_s": fast, "peak": hi, "hold_s": hold})
    if kind == "staircase":
        k = int(rng.integers(2, 5))
        fast = min(rate * float(rng.uniform(5.0, 50.0)), abs(hi - x0) / k / float(rng.uniform(1.0, 5.0)))
        holds = list(rng.uniform(30.0, 300.0, k))
        levels = list(x0 + (hi - x0) * np.arange(1, k + 1) / k)
        return Protocol(kind, [_path(x0, levels, fast, rest=rest, holds=holds)],
                        {"rate_per_s": fast, "levels": levels, "holds_s": holds})
    if kind == "replicates":
        m = int(rng.integers(2, 4))
        n = int(rng.integers(0, 4))
        targets = _cycle(x0, hi, lo) * n if n else [hi]
        wp = _path(x0, targets, rate, rest=rest, end=1.0)
        return Protocol(kind, [list(wp) for _ in range(m)], {"rate_per_s": rate, "peak": hi, "cycles": n,
                                                             "specimens": m})
    raise ValueError(f"protocol {kind!r}: use one of {', '.join(KINDS)}")


def command(waypoints, fs: float, n: int) -> np.ndarray:
    """The commanded x on the fine grid ``t = arange(n)/fs`` (held at the last waypoint)."""
    t = np.arange(n) / fs
    tw, xw = zip(*waypoints)
    return np.interp(t, tw, xw)


def motion(x_cmd: np.ndarray, fs: float, *, accel_s: float, ripple: float, ripple_hz: float,
           noise: float, rng: np.random.Generator) -> np.ndarray:
    """The x the crosshead really imposes: finite acceleration and an unsteady speed (docstring)."""
    m = max(1, int(round(accel_s * fs)))
    x = x_cmd
    if m > 1:
        x = signal.lfilter(np.ones(m) / m, [1.0], np.concatenate((np.full(m, x_cmd[0]), x_cmd)))[m:]
    v = np.diff(x)
    t = np.arange(v.size) / fs
    tau = max(0.3, 3.0 / fs)  # the servo's bandwidth: the speed noise is low-pass
    a = np.exp(-1.0 / (tau * fs))
    wobble = signal.lfilter([np.sqrt(1.0 - a * a)], [1.0, -a], rng.standard_normal(v.size))
    v = v * (1.0 + ripple * np.sin(2.0 * np.pi * ripple_hz * t + rng.uniform(0, 2 * np.pi)) + noise * wobble)
    return np.concatenate(([x[0]], x[0] + np.cumsum(v)))
