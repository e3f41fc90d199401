"""Drawing a testing machine's acquisition settings for a case (see :mod:`.acquisition`).

The lab chooses an export rate that gives a usable record (10^3-10^5 samples) and a filter
bandwidth well above the test's own time scale: the analog filter's delay is drawn as a small
fraction (0.05-1 %) of the shortest loading segment, and the export rate follows from it and
from the drawn cut-off (0.05-0.45 of the export Nyquist frequency), within the machine's
1-100 Hz and at most 40 000 samples a file. Where the two wishes conflict (a fast segment in a long test) the rate caps win and
the delay recorded in truth.json is larger. The load cell is the smallest of a catalogue whose
capacity is at least 3-100 times the peak force (labs keep one cell for many tests). The white
noise at the export is 0.001-0.02 % of the cell's capacity; the 1/f corner lies 10^-3 to 0.3 times
the anti-aliasing cut-off, so that the flicker noise in the exported band is at most a few times
the white noise (a corner far above the band would make the record a random walk).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .acquisition import FILTERS, Chain, aa_filter, dc_group_delay
from .draws import loguniform

RATES = (1.0, 2.0, 5.0, 10.0, 20.0, 25.0, 50.0, 100.0)
CAPACITIES = (0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 50.0, 100.0, 250.0, 500.0, 1e3, 2.5e3, 5e3, 1e4, 3e4, 5e4, 1e5)
#: the most fine-grid samples per file (memory and time), and the most exported samples
MAX_FINE, MAX_OUT, MIN_OUT = 3_000_000, 40_000, 1_000


def draw_timing(rng: np.random.Generator, durations: list[float], t_move: float) -> list[Chain]:
    """A chain per file with the timing drawn (levels filled in by :func:`draw_levels`)."""
    kind = str(rng.choice(FILTERS))
    order = int(rng.integers(1, 5))
    u = float(rng.uniform(0.05, 0.45))
    ripple = float(rng.uniform(0.1, 1.0))
    g = dc_group_delay(aa_filter(kind, order, 1.0, 1000.0, ripple), 1000.0, 1.0)  # delay x cut-off
    lag = loguniform(rng, 5e-4, 1e-2)
    f_lag = 2.0 * g / (lag * t_move) / u  # export rate that keeps the drawn delay
    n_target = loguniform(rng, 1000.0, 15000.0)
    ratio0 = int(rng.choice([4, 8, 16, 32, 64]))
    base = Chain(f_out=1.0, ratio=ratio0, filter=kind, order=order, cutoff_of_nyquist=u, ripple_db=ripple,
                 decimator=str(rng.choice(["cic", "fir"])), cic_order=int(rng.integers(1, 4)), bits=16,
                 quantize_at="adc", capacity_N=1.0, noise_sd_of_capacity=0.0, pink_corner_Hz=1.0,
                 hum_of_noise=0.0, hum_Hz=50.0, encoder_step_m=1e-6, encoder_phase=0.0, position="latched",
                 velocity_ripple=0.0, ripple_Hz=1.0, velocity_noise=0.0, accel_s=0.1)
    out = []
    for T in durations:
        want = max(f_lag, n_target / T, MIN_OUT / T)
        f = next((r for r in RATES if r >= want), RATES[-1])
        while f > RATES[0] and T * f > MAX_OUT:
            f = RATES[RATES.index(f) - 1]
        r = ratio0
        while r > 4 and T * f * r > MAX_FINE:
            r //= 2
        out.append(replace(base, f_out=f, ratio=r))
    return out


def draw_levels(rng: np.random.Generator, chains: list[Chain], peak_force: float) -> list[Chain]:
    """Load cell, converter, noise, hum, encoder and crosshead of the case's machine."""
    want = abs(peak_force) * loguniform(rng, 3.0, 100.0)
    cap = next((c for c in CAPACITIES if c >= want), CAPACITIES[-1])
    levels = {
        "bits": int(rng.choice([12, 14, 16, 18], p=[0.15, 0.25, 0.35, 0.25])),
        "quantize_at": str(rng.choice(["adc", "output"])),
        "capacity_N": float(cap),
        "noise_sd_of_capacity": loguniform(rng, 1e-5, 2e-4),
        "pink_corner_Hz": loguniform(rng, 1e-3, 0.3) * chains[0].cutoff_Hz,
        "hum_of_noise": float(rng.uniform(0.5, 3.0)) if rng.uniform() < 0.35 else 0.0,
        "hum_Hz": float(rng.choice([50.0, 60.0]) + rng.uniform(-0.05, 0.05)),
        "encoder_step_m": loguniform(rng, 0.05e-6, 1e-6),
        "encoder_phase": float(rng.uniform()),
        "position": str(rng.choice(["latched", "averaged"])),
        "velocity_ripple": loguniform(rng, 1e-3, 1e-2),
        "ripple_Hz": loguniform(rng, 0.05, 2.0),
        "velocity_noise": loguniform(rng, 5e-4, 5e-3),
        "accel_s": loguniform(rng, 0.02, 0.3),
    }
    return [replace(c, **levels) for c in chains]
