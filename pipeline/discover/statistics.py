"""Statistics of a discovery: residual structure, the pre-screen, the held-out test, error measures.

docs/design/discovery.md, "The held-out test, and its assumptions":

* :func:`noise_test` — the **pre-screen**: the fitted improvement in units of the
  measurement noise (each record's χ² divided by its noise's autocorrelation time
  at the fitting spacing) must exceed the Schwarz penalty ``Δk ln N``. It saves
  the held-out check of candidates that cannot pay for themselves on the data
  they were fitted to; it decides nothing.
* :func:`heldout_test` — what **decides**: on data held out of the fit, a
  one-sided p-value that the candidate predicts better beyond the measurement
  noise (its variance from the record's noise model, the two models' predictions
  fixed), judged at the search-wide level of :mod:`.levels`; a replication check
  across the held-out segments (heteroskedasticity- and autocorrelation-consistent,
  Student's t with Welch–Satterthwaite degrees of freedom, at
  :data:`REPLICATION_LEVEL`); and a size of at least one squared resolution per
  sample (the larger of the noise and :data:`FORCE_ACCURACY` of the reading).

AICc and BIC on effective sample sizes (:func:`information`) are computed and
reported for comparison; they decide nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import signal, stats

from ..calibrate.intervals import lag1
from ..tensile.noise import FORCE_ACCURACY, resolution  # noqa: F401 (part of this module's interface)


def runs_test(r: np.ndarray) -> tuple[int, float]:
    """Wald-Wolfowitz runs test of the residual signs: (runs, z-score; z << 0 = too few runs)."""
    s = np.sign(np.asarray(r, float))
    s = s[s != 0]
    n = s.size
    if n < 3:
        return 0, 0.0
    n1 = int((s > 0).sum())
    n2 = n - n1
    runs = 1 + int(np.count_nonzero(s[1:] != s[:-1]))
    if n1 == 0 or n2 == 0:
        return runs, -math.inf
    mu = 2.0 * n1 * n2 / n + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    return runs, (runs - mu) / math.sqrt(var) if var > 0 else 0.0


#: lag-1 autocorrelation is clipped to this for the effective sample size
RHO_MAX = 0.98
#: ... and a file counts for at least this many effective samples (or its size)
NU_MIN = 5.0


def n_effective(res: Sequence[np.ndarray]) -> list[float]:
    """Effective sample sizes per record: ``n (1-ρ)/(1+ρ)``, ρ = lag-1 autocorrelation in [0, RHO_MAX],
    at least ``min(n, NU_MIN)``."""
    out = []
    for r in res:
        rho = min(max(lag1(r), 0.0), RHO_MAX)
        out.append(max(r.size * (1.0 - rho) / (1.0 + rho), min(float(r.size), NU_MIN)))
    return out


def information(res: Sequence[np.ndarray], n_eff: Sequence[float], k: int) -> dict[str, float]:
    """Gaussian log-likelihood with one noise level per file, AICc and BIC on effective sizes.

    ``logL = -sum_f nu_f/2 (log(2 pi RSS_f/n_f) + 1)``, ``N = sum_f nu_f``,
    ``AICc = -2 logL + 2k + 2k(k+1)/max(N-k-1, 1)``, ``BIC = -2 logL + k log N``.
    """
    ll = 0.0
    N = 0.0
    for r, nu in zip(res, n_eff):
        if r.size == 0:
            continue
        rss = float(np.sum(r[np.isfinite(r)] ** 2)) or 1e-300
        ll += -0.5 * nu * (math.log(2 * math.pi * rss / r.size) + 1.0)
        N += nu
    # small-sample correction; its denominator is floored at 1 so that the criterion
    # stays finite (and heavily penalising) when the effective size is tiny
    corr = 2.0 * k * (k + 1) / max(N - k - 1, 1.0)
    return {"loglik": ll, "aicc": -2 * ll + 2 * k + corr, "bic": -2 * ll + k * math.log(max(N, 1.0)),
            "n_eff": N, "k": k}


def noise_chi2(res: Sequence[np.ndarray], sigma: Sequence[float], tau: Sequence[float] | None = None) -> float:
    """χ² = Σ_f Σ_k r_fk² / (σ_f² τ_f) of residuals (model - data, Pa) against each record's noise σ_f.

    τ_f (default 1) is the integrated autocorrelation time of the record's noise
    at its fitting samples' spacing: n correlated samples carry the information
    of n/τ independent ones.
    """
    tot = 0.0
    for f, (r, s) in enumerate(zip(res, sigma)):
        r = r[np.isfinite(r)]
        tot += float(r @ r) / max(s, 1e-300) ** 2 / (tau[f] if tau is not None else 1.0)
    return tot


#: the fitted improvement [noise variances] below which a candidate with no parameter of its own is the current model
SAME_MODEL_CHI2 = 1.0


def noise_test(res0: Sequence[np.ndarray], res1: Sequence[np.ndarray], sigma: Sequence[float],
               dk: int, tau: Sequence[float] | None = None) -> dict[str, float]:
    """The pre-screen: the fitted improvement of a candidate (res1) over the current model (res0) in noise units.

    Returns ``{"dchi2", "penalty", "dbic"}``: ``dbic = -Δχ² + Δk ln N`` (negative: the
    improvement pays for the parameters), N the number of fitting samples, Δχ²
    with each record's χ² divided by its noise's autocorrelation time *tau*.
    Only a pre-screen (it saves the held-out check of candidates that cannot
    pay for themselves on the data they were fitted to); it decides nothing.

    A candidate without a free parameter of its own (Δk = 0: an offset read at
    rest, held) must still change the fit by :data:`SAME_MODEL_CHI2` noise
    variance: below that it is the current model, and what its held-out errors
    differ by is where the folds' refits, each started from its own model's fit,
    stopped, not the model.
    """
    n = sum(int(np.isfinite(r).sum()) for r in res1)
    d = noise_chi2(res0, sigma, tau) - noise_chi2(res1, sigma, tau)
    pen = max(dk, 0) * math.log(max(n, 2)) if dk != 0 else SAME_MODEL_CHI2
    return {"dchi2": d, "penalty": pen, "dbic": pen - d}


def autocorrelation_time(d: np.ndarray) -> float:
    """Integrated autocorrelation time τ of a series (Geyer's initial positive sequence), in [1, n].

    ``τ = 1 + 2 Σ_t ρ_t``, summed while the sums of consecutive pairs ρ_{2m} + ρ_{2m+1}
    stay positive (and decreasing). The mean of *n* correlated samples has the
    variance of n/τ independent ones.
    """
    d = np.asarray(d, float)
    n = d.size
    if n < 4:
        return 1.0
    x = d - d.mean()
    v = float(x @ x)
    if v <= 0:
        return 1.0
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / v
    tau, prev = -1.0, math.inf
    for m in range(n // 2):
        pair = float(acf[2 * m] + acf[2 * m + 1])
        if pair <= 0:
            break
        pair = min(pair, prev)
        tau += 2.0 * pair
        prev = pair
    return float(min(max(tau, 1.0), n))


def segment_mean(d: np.ndarray) -> tuple[float, float, float]:
    """(mean, variance of the mean, degrees of freedom) of a serially correlated series *d*.

    The variance of the mean is heteroskedasticity- and autocorrelation-consistent:
    var(d) τ / n with τ the integrated autocorrelation time
    (:func:`autocorrelation_time`); its degrees of freedom are those of n/τ
    effective samples, n/τ − 1 (at least 1): a smooth series of n samples counts
    as few.
    """
    d = np.asarray(d, float)
    n = d.size
    if n == 0:
        return 0.0, 0.0, 1.0
    if n == 1:
        return float(d[0]), math.inf, 1.0
    tau = autocorrelation_time(d)
    return float(d.mean()), float(np.var(d, ddof=1)) * tau / n, max(n / tau - 1.0, 1.0)


def heldout_test(segments: Sequence[HeldoutSegment]) -> dict[str, float]:
    """The held-out comparison of a candidate with the current model: two one-sided p-values and a size.

    Per held-out sample the loss difference is d = e₀² − e₁² (current minus
    candidate squared error; e = prediction − data), > 0 where the candidate
    predicts better, in units of the file's stress range² (files of any stress
    level count alike). With Δ = p₀ − p₁ the difference of the two
    predictions, d = Δ² + 2Δe₁. Per file, d is averaged over its held-out
    samples, each segment (one fold's contiguous held-out samples of one file)
    weighing by its samples; G = the mean over files, each counting equally.

    * ``p`` — **beyond the measurement noise** (decides, at the search-wide
      level). Both models were fitted on other data, so Δ is fixed and the
      only randomness of d is the held-out data's noise ε, in 2Δε: its
      variance σ² ΔᵀRΔ/n² per segment, R the noise model's correlation
      (:func:`noise_variance`; σ and ρ(k) = e^{−k/ℓ} from the record alone,
      :mod:`esmm.pipeline.tensile.noise`); T = G/se(G), normal reference.
      Under the null "the candidate predicts no better" this p-value is valid
      whatever the models' misfit, given the noise model.
    * ``p_replication`` — **replicated across the held-out data** (a check at
      :data:`REPLICATION_LEVEL`). The same G, its variance now that of the mean
      of 2Δe₁ with e₁ the candidate's whole held-out residual, heteroskedasticity-
      and autocorrelation-consistent per segment (:func:`segment_mean`),
      Student's t with the Welch–Satterthwaite degrees of freedom,
      ν = (Σ v)² / Σ (v²/ν_s), ν_s = n_s/τ_s − 1. What the candidate leaves
      unexplained counts as variation here (the Diebold–Mariano view): an
      improvement that is small next to the misfit left, or carried by a few
      segments, does not replicate.
    * **Size.** ``resolution_units``: the mean over files of the fall of the
      held-out mean squared error in units of each file's resolution squared,
      r_f = max(σ_f, :data:`FORCE_ACCURACY` × RMS of its stress) — the larger of
      its noise and the accuracy of a testing machine's force channel; the
      search requires at least one. A candidate that changes the prediction by
      less than what the measurement can resolve is not established by it,
      however many samples make the change significant. ``noise_units``: the same
      in units of σ_f² alone (reported).

    Parameters
    ----------
    segments : sequence of HeldoutSegment

    Returns
    -------
    dict
        ``p``, ``t``; ``p_replication``, ``t_replication``, ``dof``; ``gain`` (G,
        the fall of the held-out MSE per range²); ``noise_units``,
        ``resolution_units``; ``relative`` (the fall as a fraction of the current
        model's held-out MSE); ``samples``.
    """
    per_file: dict[str, list] = {}
    for sg in segments:
        good = np.isfinite(sg.p0) & np.isfinite(sg.p1) & np.isfinite(sg.y)
        if not good.any():
            continue
        rng = max(sg.range, 1e-300)
        delta = (sg.p0[good] - sg.p1[good]) / rng
        e1 = (sg.p1[good] - sg.y[good]) / rng
        mu, v, nu = segment_mean(delta * e1)
        e0 = delta + e1
        per_file.setdefault(sg.file, []).append(_Seg(
            int(good.sum()), float(np.mean(delta * delta)) + 2.0 * mu, 4.0 * v, nu,
            4.0 * noise_variance(delta, sg.sigma / rng, sg.length), float(np.mean(e0 * e0)),
            (rng / max(sg.sigma, 1e-300)) ** 2, (rng / max(sg.resolution, sg.sigma, 1e-300)) ** 2))
    return _combine(per_file)


@dataclass
class _Seg:
    """A held-out segment's summary (see :func:`heldout_test`)."""

    n: int
    mean: float  # mean of d [range²]
    var_hac: float  # variance of that mean, HAC of 2Δe1
    dof: float  # its degrees of freedom
    var_noise: float  # variance of that mean under the noise model
    mse0: float  # the current model's held-out MSE [range²]
    per_noise: float  # range² / σ²
    per_resolution: float  # range² / r²


def _combine(per_file: dict[str, list[_Seg]]) -> dict[str, float]:
    """The statistics and the size from per-file lists of segment summaries (:func:`heldout_test`)."""
    if not per_file:
        return {"p": 1.0, "t": 0.0, "p_replication": 1.0, "t_replication": 0.0, "dof": 0.0, "gain": 0.0,
                "noise_units": 0.0, "resolution_units": 0.0, "relative": 0.0, "samples": 0}
    F = len(per_file)
    gain = units = res_units = mse0 = var_hac = var_noise = ws_den = 0.0
    total = 0
    for segs in per_file.values():
        n_f = sum(sg.n for sg in segs)
        total += n_f
        m_f = sum(sg.n * sg.mean for sg in segs) / n_f
        gain += m_f / F
        units += m_f * segs[0].per_noise / F
        res_units += m_f * segs[0].per_resolution / F
        mse0 += sum(sg.n * sg.mse0 for sg in segs) / n_f / F
        for sg in segs:
            w = (sg.n / n_f / F) ** 2
            var_noise += w * sg.var_noise
            c = w * sg.var_hac
            var_hac += c
            ws_den += c * c / sg.dof if math.isfinite(c) else math.inf
    dof = var_hac * var_hac / ws_den if ws_den > 0 and math.isfinite(ws_den) else 1.0
    t_n, p_n = _one_sided(gain, var_noise, math.inf)
    t_h, p_h = _one_sided(gain, var_hac, dof)
    return {"p": p_n, "t": t_n, "p_replication": p_h, "t_replication": t_h, "dof": float(dof), "gain": float(gain),
            "noise_units": float(units), "resolution_units": float(res_units),
            "relative": gain / mse0 if mse0 > 0 else 0.0, "samples": total}


def _one_sided(gain: float, var: float, dof: float) -> tuple[float, float]:
    """(t, one-sided p) of a mean *gain* with variance *var*: normal when *dof* is infinite, else Student's t."""
    se = math.sqrt(var) if math.isfinite(var) and var >= 0 else math.inf
    if se > 0 and math.isfinite(se):
        t = gain / se
    else:
        t = math.inf if (gain > 0 and se == 0) else 0.0
    if not math.isfinite(t):
        return float(t), (0.0 if t > 0 else 1.0)
    p = stats.norm.sf(t) if math.isinf(dof) else stats.t.sf(t, max(dof, 1.0))
    return float(t), float(p)


#: the level of the replication check (one-sided, not adjusted for multiplicity: the search-wide control is
#: carried by the noise test; this check only removes candidates)
REPLICATION_LEVEL = 0.05


def noise_variance(delta: np.ndarray, sigma: float, length: float) -> float:
    """Variance of the mean of Δε for noise ε of SD *sigma* and correlation ρ(k) = e^{−k/length}: σ² ΔᵀRΔ / n².

    ΔᵀRΔ = Σ_k Δ_k² + 2 Σ_k Δ_k Σ_{l<k} ρ^{k−l} Δ_l, the inner sum a first-order recursion.
    """
    n = delta.size
    if n == 0:
        return math.inf
    r = math.exp(-1.0 / length) if length > 0 else 0.0
    quad = float(delta @ delta)
    if r > 0:
        s = signal.lfilter([0.0, r], [1.0, -r], delta)
        quad += 2.0 * float(delta @ s)
    return sigma * sigma * max(quad, 0.0) / (n * n)


@dataclass
class HeldoutSegment:
    """One fold's contiguous held-out samples of one file: data, the two predictions, scale and noise."""

    file: str
    y: np.ndarray
    p0: np.ndarray  # the current model's prediction [Pa]
    p1: np.ndarray  # the candidate's prediction [Pa]
    range: float  # the file's stress range [Pa]
    sigma: float  # the file's noise standard deviation [Pa]
    resolution: float = 0.0  # what the measurement resolves [Pa]: max(sigma, FORCE_ACCURACY x RMS stress)
    length: float = 0.0  # the noise's correlation length [samples]




@dataclass
class Errors:
    """Error measures over files (every file counts equally)."""

    rmse: float
    nrmse: float
    max_abs: float
    per_file: list[dict[str, Any]]
    #: held-out errors only: per record index, (sample indices, data, prediction) in time order
    samples: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"rmse": self.rmse, "nrmse": self.nrmse, "max_abs": self.max_abs, "unit": "Pa",
                "per_file": self.per_file}


def error_measures(items: Sequence[tuple[str, np.ndarray, np.ndarray]],
                   spans: Sequence[tuple[float, float]] | None = None) -> Errors:
    """Errors from ``(name, measured, predicted)`` triples (Pa).

    Per file: RMSE, NRMSE = RMSE / range of its measured stress, max |error|,
    R². Overall: RMSE = sqrt(mean over files of MSE_f) (files count equally,
    as in the fit's objective), NRMSE = that RMSE / range of all measured stress
    pooled, max = largest |error| anywhere. *spans* gives each file's (min, max)
    measured stress when the samples are a part of it (held-out blocks): the
    ranges are then those of the whole files, so held-out and fitted NRMSE compare.
    """
    per = []
    mses, lo, hi, mx = [], math.inf, -math.inf, 0.0
    for j, (name, y, p) in enumerate(items):
        span = spans[j] if spans is not None else None
        y = np.asarray(y, float)
        p = np.asarray(p, float)
        good = np.isfinite(p)
        if not good.any():
            per.append({"file": name, "n": int(y.size), "rmse": math.inf, "nrmse": math.inf,
                        "max_abs": math.inf, "r2": -math.inf})
            mses.append(math.inf)
            continue
        e = np.where(good, p - y, np.nan)
        e = np.nan_to_num(e, nan=float(np.nanmax(np.abs(e))))
        mse = float(np.mean(e**2))
        rng = (span[1] - span[0] if span is not None else float(np.ptp(y))) or 1.0
        ss = float(np.sum((y - y.mean()) ** 2)) or 1.0
        per.append({"file": name, "n": int(y.size), "rmse": math.sqrt(mse), "nrmse": math.sqrt(mse) / rng,
                    "max_abs": float(np.max(np.abs(e))), "r2": 1.0 - float(np.sum(e**2)) / ss})
        mses.append(mse)
        lo, hi = min(lo, float(y.min())), max(hi, float(y.max()))
        if span is not None:
            lo, hi = min(lo, span[0]), max(hi, span[1])
        mx = max(mx, float(np.max(np.abs(e))))
    rmse = math.sqrt(float(np.mean(mses))) if mses else math.nan
    rng = (hi - lo) if hi > lo else 1.0
    return Errors(rmse, rmse / rng, mx, per)
