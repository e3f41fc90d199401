"""Statistics of a discovery: residual structure, information criteria, error measures.

The information criteria count every file by its *effective* sample size
(:func:`n_effective`): the samples of a machine record are serially correlated,
and counting them as independent would make any extra parameter look supported
(docs/discover.md).
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


@dataclass


@dataclass
class Errors:
    """Error measures over files (every file counts equally)."""

    rmse: float
    nrmse: float
    max_abs: float
    per_file: list[dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        return {"rmse": self.rmse, "nrmse": self.nrmse, "max_abs": self.max_abs, "unit": "Pa",
                "per_file": self.per_file}


def error_measures(items: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> Errors:
    """Errors from ``(name, measured, predicted)`` triples (Pa).

    Per file: RMSE, NRMSE = RMSE / range of its measured stress, max |error|,
    R². Overall: RMSE = sqrt(mean over files of MSE_f) (files count equally,
    as in the fit's objective), NRMSE = that RMSE / range of all measured stress
    pooled, max = largest |error| anywhere.
    """
    per = []
    mses, lo, hi, mx = [], math.inf, -math.inf, 0.0
    for name, y, p in items:
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
        rng = float(np.ptp(y)) or 1.0
        ss = float(np.sum((y - y.mean()) ** 2)) or 1.0
        per.append({"file": name, "n": int(y.size), "rmse": math.sqrt(mse), "nrmse": math.sqrt(mse) / rng,
                    "max_abs": float(np.max(np.abs(e))), "r2": 1.0 - float(np.sum(e**2)) / ss})
        mses.append(mse)
        lo, hi = min(lo, float(y.min())), max(hi, float(y.max()))
        mx = max(mx, float(np.max(np.abs(e))))
    rmse = math.sqrt(float(np.mean(mses))) if mses else math.nan
    rng = (hi - lo) if hi > lo else 1.0
    return Errors(rmse, rmse / rng, mx, per)
