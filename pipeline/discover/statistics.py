"""Statistics of a discovery: residual structure, the two tests a candidate must pass, error measures.

A candidate is judged by two statistics whose assumptions real records meet
(docs/design/discovery.md, "The two tests, and their assumptions"):

* :func:`noise_test` — the **fitted** improvement in units of the measurement
  noise, which is estimated from each record alone
  (:func:`~esmm.pipeline.tensile.events.noise_sd`), not from any model's
  residual: ``Δχ² = Σ_f ΔRSS_f / σ_f²`` must exceed the Schwarz (BIC) penalty
  ``Δk ln N`` of the parameters it adds. With the noise variance known, this is
  the BIC of a Gaussian likelihood; its penalty grows as ln N, so it does not
  explode on dense records, and on data the current model already explains to
  the noise level ``Δχ²`` is a χ²(Δk) variable, which exceeds ``Δk ln N`` with
  probability below 0.3 % for N ≥ 400.
* :func:`paired_heldout` — the **held-out** improvement, on data left out of
  the fit: (a) on average, the squared prediction error must fall by at least
  one noise variance per sample (an effect that changes the prediction by less
  than the measurement's own noise is not established by it); and (b)
  beyond chance, by two standard errors (one-sided p ≈ 0.02) of either of two
  paired statistics whose standard errors count their serial correlation
  (integrated autocorrelation time, Geyer's initial positive sequence): the
  mean difference of squared errors (the Diebold-Mariano test of predictive
  accuracy), or a sign test — among the held-out samples where the two
  predictions differ by more than the noise, the candidate is the closer one
  more often than not. The sign test establishes a consistent improvement when
  the mean's standard error is inflated by a few held-out segments of very
  different size (cycles of rising amplitude); the mean establishes a large
  improvement concentrated where the effect acts (the high-stretch end). Either
  passing roughly doubles the false-positive rate of one test (about 4 %), and
  the candidate must also have passed the noise test of its fit. (c) Not only
  more often closer: when the sign test decides, the mean improvement must
  still be at least one of its standard errors — a candidate closer on most
  samples but no better on average changes the prediction without improving it.

AICc and BIC on effective sample sizes (:func:`information`) are computed
and reported for comparison; they do not decide.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..calibrate.intervals import lag1


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


def noise_chi2(res: Sequence[np.ndarray], sigma: Sequence[float]) -> float:
    """χ² = Σ_f Σ_k r_fk² / σ_f² of residuals (model - data, Pa) against each record's noise σ_f."""
    tot = 0.0
    for r, s in zip(res, sigma):
        r = r[np.isfinite(r)]
        tot += float(r @ r) / max(s, 1e-300) ** 2
    return tot


def noise_test(res0: Sequence[np.ndarray], res1: Sequence[np.ndarray], sigma: Sequence[float],
               dk: int) -> dict[str, float]:
    """The fitted improvement of a candidate (res1) over the current model (res0) in noise units.

    Returns ``{"dchi2", "penalty", "dbic"}``: ``dbic = -Δχ² + Δk ln N`` (negative: the
    improvement pays for the parameters), N the number of fitting samples.
    """
    n = sum(int(np.isfinite(r).sum()) for r in res1)
    d = noise_chi2(res0, sigma) - noise_chi2(res1, sigma)
    pen = max(dk, 0) * math.log(max(n, 2))
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


def paired_heldout(pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, float, float]],
                   ) -> dict[str, float]:
    """The held-out improvement of a candidate over the current model (module docstring).

    Parameters
    ----------
    pairs : sequence of (y, p0, p1, range, sigma)
        Per file: held-out data, the current model's and the candidate's
        predictions (time order), the file's stress range and noise σ [Pa].

    Returns
    -------
    dict
        ``noise_units``: mean over files of ΔMSE_f / σ_f² (the held-out
        improvement in noise variances per sample; > 0: the candidate predicts
        better); ``gain``: the same per range² (NRMSE units); ``z``: the sign test —
        among the held-out samples where the two predictions differ by more than
        the noise, how much more often the candidate is the closer one, in
        standard errors (the signs' serial correlation included); ``z_mean``:
        the mean improvement in its standard errors; ``decided``: the samples
        where the predictions differ; ``relative``: the fall of the held-out mean
        squared error as a fraction of the current model's; ``relative_se``: that
        error's own relative standard error (its sampling uncertainty, serial
        correlation included).
    """
    gains, units, var_mean = [], [], 0.0
    sign_sum, sign_var, decided = 0.0, 0.0, 0
    mse0, var0 = 0.0, 0.0
    for y, p0, p1, rng, sig in pairs:
        good = np.isfinite(p0) & np.isfinite(p1) & np.isfinite(y)
        if not good.any():
            continue
        e0, e1 = np.abs(p0[good] - y[good]), np.abs(p1[good] - y[good])
        d = e0 * e0 - e1 * e1
        dn = d / max(rng, 1e-300) ** 2
        gains.append(float(dn.mean()))
        units.append(float(d.mean()) / max(sig, 1e-300) ** 2)
        var_mean += float(np.var(dn)) * autocorrelation_time(dn) / dn.size
        q0 = (e0 / max(rng, 1e-300)) ** 2
        mse0 += float(q0.mean())
        var0 += float(np.var(q0)) * autocorrelation_time(q0) / q0.size
        differ = np.abs(p1[good] - p0[good]) > sig
        if differ.sum() >= 2:
            signs = np.sign(e0[differ] - e1[differ])
            sign_sum += float(signs.sum())
            sign_var += float(signs.size) * autocorrelation_time(signs)
            decided += int(signs.size)
    if not gains:
        return {"gain": 0.0, "noise_units": 0.0, "z": 0.0, "z_mean": 0.0, "decided": 0, "relative": 0.0,
                "relative_se": math.inf}
    m = len(gains)
    gain = float(np.mean(gains))
    se = math.sqrt(var_mean) / m
    return {"gain": gain, "noise_units": float(np.mean(units)),
            "z": sign_sum / math.sqrt(sign_var) if sign_var > 0 else 0.0,
            "z_mean": gain / se if se > 0 else 0.0, "decided": decided,
            "relative": gain * m / mse0 if mse0 > 0 else 0.0,
            "relative_se": math.sqrt(var0) / mse0 if mse0 > 0 else math.inf}


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
