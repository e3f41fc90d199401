"""Diagnose a residual: its size, its structure, and which effect it points to.

For each candidate effect the *first-order signature* is the change of the
model's prediction when the effect is switched on weakly (a finite-difference
derivative with respect to the effect's strength, at a few values of its shape
parameters). The share of the residual that this signature explains (the R²
of a one-coefficient regression with the physically allowed sign; per file for
artefacts) ranks the candidates: it is a score test of "effect absent". Plain
covariate summaries (residual on loading vs unloading, against rate, during
holds, below the previous maximum, in the toe region, at the high-stretch end,
against time) explain the ranking in words.

The residual here is *measured − model* (what the model misses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibrate.intervals import lag1
from ..materials.effects import EFFECT_NAMES
from .model import Problem, offset_applicable, slack_applicable
from .statistics import runs_test

#: strength used for the finite-difference signatures (in each effect's own coordinate)
_EPS = 1e-3


@dataclass
class Diagnosis:
    """The structure of one model's residual."""

    rmse: float
    nrmse: float
    lag1: float  # median over files of the lag-1 autocorrelation
    runs_z: float  # most negative runs-test z over files
    white: bool  # no systematic structure left
    facts: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)
    why: dict[str, str] = field(default_factory=dict)
    ranking: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "rmse": self.rmse, "nrmse": self.nrmse, "lag1": self.lag1, "runs_z": self.runs_z,
            "white": self.white, "facts": self.facts,
            "ranking": [{"name": n, "score": self.scores.get(n, 0.0), "why": self.why.get(n, "")}
                        for n in self.ranking],
        }


def _pct(v: float) -> str:
    return f"{100.0 * v:+.1f} %"


def _covariate_table(problem: Problem, z_full: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The normalised residual (measured - model) / stress scale of every fitting sample, and its covariates."""
    st = problem.state(z_full)
    coefs = problem.offsets(z_full)
    E, D, RATE, HOLD, BELOW, TOE, HIGH, VIRG, TN, FILE = [], [], [], [], [], [], [], [], [], []
    for k, r in enumerate(problem.records):
        idx = r.fit_idx
        p = problem.add_offsets(k, problem.predict(k, st), coefs[k])
        e = (r.y[idx] - p) / r.scale
        c = r.cov
        E.append(e)
        D.append(c.direction[idx])
        RATE.append(np.full(idx.size, c.loading_rate()))
        HOLD.append(np.nan_to_num(c.hold_time[idx]) * (c.direction[idx] == 0) if r.history else np.zeros(idx.size))
        BELOW.append(c.below_max[idx] if r.history else np.zeros(idx.size))
        TOE.append(c.toe[idx])
        HIGH.append(c.high[idx])
        VIRG.append(c.virgin[idx])
        TN.append(c.elapsed[idx] / (float(c.elapsed[-1]) or 1.0))
        FILE.append(np.full(idx.size, k))
    e = np.concatenate(E)
    good = np.isfinite(e)
    cat = {n: np.concatenate(v)[good] for n, v in
           dict(d=D, rate=RATE, hold=HOLD, below=BELOW, toe=TOE, high=HIGH, virgin=VIRG, tn=TN, file=FILE).items()}
    e = e[good]
    return e, cat


def _facts(problem: Problem, z_full: np.ndarray) -> dict[str, Any]:
    """Covariate summaries of the normalised residual (measured - model) / stress scale."""
    e, cat = _covariate_table(problem, z_full)
    f: dict[str, Any] = {}

    def mean(mask):
        return float(np.mean(e[mask])) if np.any(mask) else None

    f["loading_mean"] = mean(cat["d"] > 0)
    f["unloading_mean"] = mean(cat["d"] < 0)
    f["hold_mean"] = mean(cat["d"] == 0)
    # rate: mean residual per distinct loading rate (files)
    rates = cat["rate"]
    fin = np.isfinite(rates)
    if fin.any():
        groups = {}
        for v in np.unique(np.round(rates[fin], 6)):
            m = fin & np.isclose(rates, v)
            groups[f"{v:.3g}"] = float(np.mean(e[m & (cat["d"] > 0)])) if np.any(m & (cat["d"] > 0)) else None
        f["loading_mean_by_rate"] = groups
    # holds: change of the residual from the start to the end of holds
    hm = (cat["d"] == 0) & (cat["hold"] > 0)
    if np.count_nonzero(hm) > 5:
        lh = np.log1p(cat["hold"][hm])
        a = np.polyfit(lh, e[hm], 1)[0] if np.ptp(lh) > 0 else 0.0
        f["hold_trend"] = float(a * np.ptp(lh))  # residual change over the holds
    below = cat["below"] > 0.02
    f["below_max_mean"] = mean(below)
    f["virgin_loading_mean"] = mean(cat["virgin"] & (cat["d"] > 0))
    f["toe_mean"] = mean(cat["toe"])
    f["high_end_mean"] = mean(cat["high"])
    if np.ptp(cat["tn"]) > 0:
        f["time_trend"] = float(np.polyfit(cat["tn"], e, 1)[0])
    return f


class _Signatures:
    """The weighted residual of the current model, and the first-order signatures of candidate effects."""

    def __init__(self, prob: Problem, z_full: np.ndarray):
        self.prob, self.z_full = prob, z_full
        st = prob.state(z_full)
        self.coefs = prob.offsets(z_full)
        self.base_pred, self.resid, self.w = [], [], []
        for k, r in enumerate(prob.records):
            p = prob.add_offsets(k, prob.predict(k, st), self.coefs[k])
            self.base_pred.append(p)
            wk = prob.factor[k] / r.scale if prob.factor[k] else math.sqrt(1.0 / r.fit_idx.size) / r.scale
            self.w.append(wk)
            self.resid.append(np.nan_to_num((r.y[r.fit_idx] - p) * wk))
        self.e_all = np.concatenate(self.resid)
        self.ss = float(self.e_all @ self.e_all) or 1e-300

    def shared_score(self, sigs: list[np.ndarray], sign: float) -> float:
        """Share of the residual explained by one signature shared by all files, of the allowed *sign*."""
        s = np.concatenate(sigs)
        den = float(s @ s)
        if den <= 0 or not np.isfinite(den):
            return 0.0
        c = float(s @ self.e_all) / den
        if c * sign <= 0:
            return 0.0
        return float((s @ self.e_all) ** 2 / den / self.ss)

    def per_file_score(self, sigs: list[np.ndarray]) -> float:
        """Share of the residual explained by one positive coefficient per file."""
        tot = 0.0
        for s, e in zip(sigs, self.resid):
            den = float(s @ s)
            if den > 0 and float(s @ e) > 0:
                tot += float(s @ e) ** 2 / den
        return tot / self.ss

    def perturbed(self, effect: str, variant: int, values=None) -> list[np.ndarray] | None:
        """Per file: the change of the prediction with *effect* switched on weakly (slot values *values*)."""
        prob = self.prob
        try:
            p2 = prob.derived(prob.spec.with_(effect, variant))
        except Exception:  # noqa: BLE001 - a candidate that cannot be built scores 0
            return None
        z = p2.transfer(prob, self.z_full)
        z = _set_slack(p2, z) if values is None else _set_slots(p2, z, values)
        st2 = p2.state(z)
        return [np.nan_to_num((prob.add_offsets(k, p2.predict(k, st2), self.coefs[k]) - self.base_pred[k]) * self.w[k])
                for k in range(len(prob.records))]


def _set_slots(p2: Problem, z: np.ndarray, values: dict[tuple[str, str], float]) -> np.ndarray:
    z = z.copy()
    for i, s in enumerate(p2.slots):
        for (eff, name), val in values.items():
            if s.effect == eff and s.name == name:
                z[i] = val
    return z


def _signature_scores(problem: Problem, z_full: np.ndarray, names: list[str]) -> dict[str, float]:
    """Share of the residual explained by each effect's first-order signature."""
    sig = _Signatures(problem, z_full)
    spec = problem.spec
    scorers = {"viscoelastic": _viscoelastic_score, "mullins": _mullins_score, "damage": _damage_score,
               "slack": _slack_score, "sensor_offset": _offset_score}
    out: dict[str, float] = {}
    for n, scorer in scorers.items():
        if n in names and not getattr(spec, n):
            score = scorer(sig)
            if score is not None:
                out[n] = score
    return out


def _viscoelastic_score(sig: _Signatures) -> float:
    b, best = sig.prob.bounds, 0.0
    for tau in np.geomspace(b.tau_min * 2, b.tau_max / 10, 7):
        s = sig.perturbed("viscoelastic", 1, {("viscoelastic", "u[0]"): _EPS, ("viscoelastic", "tau[0]"): math.log(tau)})
        if s is not None:
            # QLV lowers the stress relative to the instantaneous response: data above -> c < 0
            best = max(best, sig.shared_score(s, -1.0), sig.shared_score(s, +1.0))
    return best


def _mullins_score(sig: _Signatures) -> float:
    b, best = sig.prob.bounds, 0.0
    for mm in (0.02, 0.1, 0.5):
        s = sig.perturbed("mullins", 2, {("mullins", "s"): _EPS, ("mullins", "m"): math.log(mm * b.w_ref)})
        if s is not None:
            best = max(best, sig.shared_score(s, +1.0))
    return best


def _damage_score(sig: _Signatures) -> float:
    b, best = sig.prob.bounds, 0.0
    for q in (0.3, 0.6, 0.85):
        for sc in (0.1, 0.4):
            s = sig.perturbed("damage", 3, {("damage", "onset"): 1.0 + q * b.xi_span,
                                            ("damage", "scale"): math.log(sc * b.xi_span / _EPS),
                                            ("damage", "shape"): 1.0})
            if s is not None:
                best = max(best, sig.shared_score(s, +1.0))
    return best


def _slack_score(sig: _Signatures) -> float | None:
    # per file: slack delta = eps * stretch span
    s = sig.perturbed("slack", 1)
    return None if s is None else sig.per_file_score(s)


def _offset_score(sig: _Signatures) -> float:
    """Share explained by an offset (and a drift, where there is time) fitted per file."""
    tot = 0.0
    for k, r in enumerate(sig.prob.records):
        if not offset_applicable(r):
            continue
        cols = [np.ones(r.fit_idx.size)]
        if r.t is not None:
            cols.append((r.t[r.fit_idx] - r.t[0]) / (r.T or 1.0))
        X = np.stack(cols, 1) * sig.w[k]
        c, *_ = np.linalg.lstsq(X, sig.resid[k], rcond=None)
        fit = X @ c
        tot += float(fit @ fit)
    return tot / sig.ss


def _set_slack(p2: Problem, z: np.ndarray) -> np.ndarray:
    z = z.copy()
    for i, s in enumerate(p2.slots):
        if s.effect == "slack":
            r = p2.records[s.file]
            z[i] = _EPS * (float(np.max(r.x)) - 1.0)
    return z


def diagnose(problem: Problem, z_full: np.ndarray, *, candidates: list[str] | None = None,
             errors=None) -> Diagnosis:
    """Size and structure of the residual of *problem* at *z_full*, and the ranked candidates.

    Parameters
    ----------
    problem : Problem
        The current model (its training samples are all fitting samples).
    z_full : ndarray
        Its parameters.
    candidates : list of str, optional
        Effect names to score (default: all not yet in the model).
    errors : Errors, optional
        Error measures on all samples (for the size).
    """
    names = [n for n in (candidates or list(EFFECT_NAMES)) if not getattr(problem.spec, n)]
    res = problem.fit_residuals(z_full)
    rhos = [lag1(r) for r in res if r.size > 2]
    zs = [runs_test(r)[1] for r in res if r.size > 2]
    rho = float(np.median(rhos)) if rhos else 0.0
    runs_z = float(min(zs)) if zs else 0.0
    facts = _facts(problem, z_full)
    scores = _signature_scores(problem, z_full, names)
    why = _explain(problem, facts, scores, names)
    white = rho < 0.3 and runs_z > -3.0
    ranking = sorted(names, key=lambda n: -scores.get(n, 0.0))
    rmse = errors.rmse if errors is not None else float("nan")
    nrmse = errors.nrmse if errors is not None else float("nan")
    return Diagnosis(rmse, nrmse, rho, runs_z, white, facts, scores, why, ranking)


def _explain(problem: Problem, f: dict[str, Any], scores: dict[str, float], names: list[str]) -> dict[str, str]:
    """One sentence per candidate: what in the residual points to it (or not)."""
    out = {}
    share = {n: f"{100 * scores.get(n, 0.0):.0f} % of the residual has its shape" for n in names}
    for n in names:
        bits = [share[n]]
        if n == "viscoelastic":
            lo, un = f.get("loading_mean"), f.get("unloading_mean")
            if lo is not None and un is not None:
                bits.append(f"the data lie {_pct(lo)} above the model on loading and {_pct(un)} on unloading "
                            "(of the stress scale)")
            byr = f.get("loading_mean_by_rate") or {}
            vals = {k: v for k, v in byr.items() if v is not None}
            if len(vals) >= 2:
                bits.append("on loading, by rate [1/s]: " + ", ".join(f"{k}: {_pct(v)}" for k, v in vals.items()))
            if "hold_trend" in f:
                bits.append(f"during holds the residual changes by {_pct(f['hold_trend'])} (relaxation)")
        elif n == "mullins":
            bm, vl = f.get("below_max_mean"), f.get("virgin_loading_mean")
            if bm is not None:
                bits.append(f"below the previous maximum the residual averages {_pct(bm)}, "
                            f"on the primary loading path {_pct(vl or 0.0)}")
        elif n == "damage":
            if f.get("high_end_mean") is not None:
                bits.append(f"at the high-stretch end of the primary loading the residual is {_pct(f['high_end_mean'])}")
        elif n == "slack":
            if not any(slack_applicable(r) for r in problem.records):
                bits = ["not applicable: no tension test starting from the undeformed state"]
            elif f.get("toe_mean") is not None:
                bits.append(f"in the toe region the residual is {_pct(f['toe_mean'])}")
        elif n == "sensor_offset":
            if "time_trend" in f:
                bits.append(f"the residual drifts by {_pct(f['time_trend'])} from start to end")
        out[n] = "; ".join(bits)
    return out
