"""The acquisition chain of a testing machine, from the true signals to the exported samples.

The true force and crosshead position are computed on a fine grid at the converter's rate
``fs = R f_out`` (R = the oversampling ratio). The force channel then goes the way a
strain-gauge load cell's signal goes (Horowitz & Hill 2015, *The Art of Electronics*, on
amplifier noise; Lyons 2011, *Understanding DSP*, on CIC decimation):

1. amplifier noise: white plus 1/f (flicker) noise with a corner frequency where the two have
   equal power; the 1/f part is Kasdin's (1995, Proc. IEEE 83:802) fractional-differencing filter
   of white noise, ``h_0 = 1, h_k = h_{k-1} (k - 1 + alpha/2)/k`` (alpha = 1);
2. the analog anti-aliasing filter (Butterworth, Bessel or Chebyshev type I, order 1-4), its
   -3 dB point placed at the requested cut-off for every type, simulated by the bilinear transform
   with pre-warping at the fine rate (far above the cut-off);
3. mains hum picked up after the filter (50 or 60 Hz, slightly off nominal), which the converter
   samples and aliases;
4. the ADC: a bipolar converter of ``bits`` bits over the load cell's span (twice its capacity),
   step ``span / 2**bits``; the quantization is applied at the converter (before the digital
   averaging, which then dithers it) or on the exported word;
5. digital decimation to the export rate: a CIC (cascaded moving averages, order 1-3) or a FIR
   low-pass, then every R-th sample, the window ending at the exported instant (so the force lags
   by the filters' delays).

The position channel is a quadrature encoder's count (step 0.05-1 um, a random phase), latched at
the exported instant or averaged through the same decimator. Time stamps are written with the
export's resolution.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import signal

FILTERS = ("butter", "bessel", "cheby1")


def aa_filter(kind: str, order: int, fc: float, fs: float, ripple_db: float = 0.5) -> np.ndarray:
    """Second-order sections of a low-pass whose -3 dB point is ``fc`` [Hz] at sampling rate ``fs``."""
    if kind == "butter":
        return signal.butter(order, fc, fs=fs, output="sos")
    if kind == "bessel":
        return signal.bessel(order, fc, norm="mag", fs=fs, output="sos")
    if kind == "cheby1":
        # scipy's edge is the ripple band's; the -3 dB point is cosh(acosh(1/eps)/N) above it
        # (from |H|^2 = 1/(1 + eps^2 T_N^2)), in the pre-warped analog domain.
        eps = np.sqrt(10.0 ** (ripple_db / 10.0) - 1.0)
        ratio = np.cosh(np.arccosh(1.0 / eps) / order)
        w3 = 2.0 * fs * np.tan(np.pi * fc / fs)
        fp = fs / np.pi * np.arctan(w3 / ratio / (2.0 * fs))
        return signal.cheby1(order, ripple_db, fp, fs=fs, output="sos")
    raise ValueError(f"filter kind {kind!r}: use one of {', '.join(FILTERS)}")


def dc_group_delay(sos: np.ndarray, fs: float, fc: float) -> float:
    """Group delay [s] of the filter at low frequency (a hundredth of its cut-off)."""
    f = np.array([0.01, 0.02]) * fc
    _, h = signal.sosfreqz(sos, worN=f, fs=fs)
    ph = np.unwrap(np.angle(h))
    return float(-(ph[1] - ph[0]) / (2.0 * np.pi * (f[1] - f[0])))


def noise_bandwidth(sos: np.ndarray) -> float:
    """Fraction of white noise's variance the filter passes (mean |H|^2 over the band)."""
    _, h = signal.sosfreqz(sos, worN=16384)
    return float(np.mean(np.abs(h) ** 2))


def kasdin_pink(n: int, rng: np.random.Generator, alpha: float = 1.0) -> np.ndarray:
    """1/f**alpha noise of ``n`` samples: unit white noise through Kasdin's filter (module docstring).

    Its two-sided spectrum is ``1/|2 sin(pi f/fs)|**alpha``, i.e. ``(fs/(2 pi f))**alpha`` times the
    unit white level well below fs.
    """
    k = np.arange(1, n, dtype=float)
    h = np.concatenate(([1.0], np.cumprod((k - 1.0 + 0.5 * alpha) / k)))
    return signal.fftconvolve(rng.standard_normal(n), h)[:n]


def quantize(v: np.ndarray, span: float, bits: int) -> np.ndarray:
    """A bipolar mid-tread converter over ``[-span/2, span/2)``: steps of ``span / 2**bits``."""
    q = span / 2.0 ** bits
    code = np.clip(np.round(np.asarray(v, dtype=float) / q), -(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
    return code * q


def decimator_taps(method: str, r: int, order: int, fs: float, f_out: float) -> np.ndarray:
    """Impulse response of the digital decimation filter at the converter rate (unit DC gain)."""
    if method == "cic":
        h = np.ones(r)
        for _ in range(order - 1):
            h = np.convolve(h, np.ones(r))
        return h / h.sum()
    if method == "fir":
        h = signal.firwin(8 * r + 1, 0.4 * f_out, fs=fs)
        return h / h.sum()
    raise ValueError(f"decimator {method!r}: use cic or fir")


def decimate(v: np.ndarray, taps: np.ndarray, r: int) -> np.ndarray:
    """Causal filtering, then the samples at indices ``(k+1) r - 1`` (the windows' ends)."""
    v = np.asarray(v, dtype=float)
    # start from rest at the first value, as the controller's filter does after its reset
    y = signal.fftconvolve(np.concatenate((np.full(taps.size - 1, v[0]), v)), taps, mode="valid")
    return y[r - 1:: r]


def encoder(p: np.ndarray, step: float, phase: float) -> np.ndarray:
    """Quadrature encoder count times its step, zeroed at the first sample (the machine's zero)."""
    c = np.floor(np.asarray(p, dtype=float) / step + phase)
    return (c - c[0]) * step


@dataclass
class Chain:
    """The drawn parameters of one machine's acquisition chain (written to truth.json)."""

    f_out: float  # export rate [Hz]
    ratio: int  # ADC oversampling R
    filter: str
    order: int
    cutoff_of_nyquist: float  # -3 dB point / (f_out / 2)
    ripple_db: float
    decimator: str  # cic or fir
    cic_order: int
    bits: int
    quantize_at: str  # "adc" or "output"
    capacity_N: float
    noise_sd_of_capacity: float  # at the export, white part
    pink_corner_Hz: float
    hum_of_noise: float  # 0: no hum
    hum_Hz: float
    encoder_step_m: float
    encoder_phase: float
    position: str  # "latched" or "averaged"
    velocity_ripple: float
    ripple_Hz: float
    velocity_noise: float
    accel_s: float  # the crosshead's acceleration time

    @property
    def fs(self) -> float:
        return self.f_out * self.ratio

    @property
    def cutoff_Hz(self) -> float:
        return self.cutoff_of_nyquist * 0.5 * self.f_out

    @property
    def span_N(self) -> float:
        return 2.0 * self.capacity_N

    def sos(self) -> np.ndarray:
        return aa_filter(self.filter, self.order, self.cutoff_Hz, self.fs, self.ripple_db)

    def describe(self) -> dict:
        d = asdict(self)
        sos = self.sos()
        taps = decimator_taps(self.decimator, self.ratio, self.cic_order, self.fs, self.f_out)
        d.update(fs_Hz=self.fs, cutoff_Hz=self.cutoff_Hz, span_N=self.span_N,
                 lsb_N=self.span_N / 2.0 ** self.bits,
                 filter_delay_s=dc_group_delay(sos, self.fs, self.cutoff_Hz),
                 decimator_delay_s=float(np.sum(taps * np.arange(taps.size)) / self.fs))
        return d


def record_force(force: np.ndarray, ch: Chain, rng: np.random.Generator | None) -> np.ndarray:
    """The exported force [N] (shape (n // R,)) from the true force on the fine grid.

    With ``rng=None`` the chain runs without noise, hum and quantization: the filters' effect
    alone, against which the acquisition error of a record is measured.
    """
    n = force.size
    sos = ch.sos()
    if rng is None:
        v, _ = signal.sosfilt(sos, force, zi=signal.sosfilt_zi(sos) * force[0])
        return decimate(v, decimator_taps(ch.decimator, ch.ratio, ch.cic_order, ch.fs, ch.f_out), ch.ratio)
    sd_o = ch.noise_sd_of_capacity * ch.capacity_N
    sd_w = sd_o / np.sqrt(noise_bandwidth(sos))
    pink_sd = sd_w * np.sqrt(2.0 * np.pi * ch.pink_corner_Hz / ch.fs)
    v = force + sd_w * rng.standard_normal(n) + pink_sd * kasdin_pink(n, rng)
    # the filter starts settled on the first (true) value: the amplifier was on before the test
    zi = signal.sosfilt_zi(sos) * force[0]
    v, _ = signal.sosfilt(sos, v, zi=zi)
    if ch.hum_of_noise > 0.0:
        t = np.arange(n) / ch.fs
        v = v + ch.hum_of_noise * sd_o * np.sin(2.0 * np.pi * ch.hum_Hz * t + rng.uniform(0, 2 * np.pi))
    if ch.quantize_at == "adc":
        v = quantize(v, ch.span_N, ch.bits)
    taps = decimator_taps(ch.decimator, ch.ratio, ch.cic_order, ch.fs, ch.f_out)
    out = decimate(v, taps, ch.ratio)
    if ch.quantize_at == "output":
        out = quantize(out, ch.span_N, ch.bits)
    return out


def record_position(p: np.ndarray, ch: Chain) -> np.ndarray:
    """The exported crosshead displacement [m] (shape (n // R,)) from the true position."""
    counts = encoder(p, ch.encoder_step_m, ch.encoder_phase)
    if ch.position == "latched":
        return counts[ch.ratio - 1:: ch.ratio]
    taps = decimator_taps(ch.decimator, ch.ratio, ch.cic_order, ch.fs, ch.f_out)
    return decimate(counts, taps, ch.ratio)
