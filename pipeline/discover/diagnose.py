"""Diagnose a residual: its size against the noise, its structure, and which candidate it points to.

For each candidate (an effect, an artefact or a strain-energy term) the
*first-order signature* is the change of the model's prediction when the
candidate is switched on weakly (a finite difference in its strength, at a few
values of its shape parameters). Projected off the directions the current
model's own parameters can already move (its Jacobian), the signature's
regression on the residual, both in units of each record's noise σ, is the
score test of "candidate absent": the χ² that one more parameter along it
would remove at first order (:attr:`Diagnosis.gains`). A candidate whose gain
cannot pay for even one parameter's Schwarz penalty (ln N) is not fitted.
Where the candidate's strength is bounded at zero (a term's modulus, a
relaxation's or softening's strength, a set, a slack, a slip's loss), only the
regression of the admissible sign counts: a residual that asks for a negative
modulus is no evidence for the term, whose fit stops at zero strength.

Plain covariate summaries (residual on loading vs unloading, against rate,
during holds, below the previous maximum, in the toe region, at the
high-stretch end, against time) explain the ranking in words; :func:`structure`
says where a residual is largest and what it follows, for the honest outcome
when nothing explains it.

The residual is called **noise** (:attr:`Diagnosis.white`) when its mean square is within
:data:`WHITE_CHI2` noise variances per sample, or within :data:`WHITE_Z` standard errors of one
(the standard error of a mean of n squared noise samples, √(2τ/n), counts the noise's correlation τ
at the fitting samples' spacing). Its lag-1 autocorrelation and runs test are reported; they do
not decide (filtered noise is correlated however good the model).

The residual here is *measured − model* (what the model misses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibrate.intervals import lag1
from ..materials.terms import TERMS
from .initialise import term_grid
from .model import CANDIDATES, VARIANTS, Problem
from .records import offset_applicable, reference, slack_applicable
from .statistics import runs_test

#: strength used for the finite-difference signatures (in each effect's own coordinate)
_EPS = 1e-3
#: a residual within this many noise variances per sample (RMS 1.2 σ) is at the record's resolution
WHITE_CHI2 = 1.5
#: ... or within this many standard errors of one noise variance per sample (its standard error counts the
#: noise's correlation at the fitting samples' spacing)
WHITE_Z = 3.0


@dataclass
class Diagnosis:
    """The structure of one model's residual."""

    rmse: float
    nrmse: float
    lag1: float  # median over files of the lag-1 autocorrelation
    runs_z: float  # most negative runs-test z over files
    white: bool  # no systematic structure left
    chi2: float = math.nan  # mean squared residual in noise variances per fitting sample
    facts: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)  # share of the residual's χ² (first order)
    gains: dict[str, float] = field(default_factory=dict)  # χ² one parameter along it removes (first order)
    why: dict[str, str] = field(default_factory=dict)
    ranking: list[str] = field(default_factory=list)
    structure: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "rmse": self.rmse, "nrmse": self.nrmse, "lag1": self.lag1, "runs_z": self.runs_z,
            "white": self.white, "chi2_per_sample": self.chi2, "facts": self.facts, "structure": self.structure,
            "ranking": [{"name": n, "score": self.scores.get(n, 0.0), "gain_chi2": self.gains.get(n, 0.0),
                         "why": self.why.get(n, "")} for n in self.ranking],
        }


def _pct(v: float) -> str:
    return f"{100.0 * v:+.1f} %"


# --------------------------------------------------------------------------- covariates
def _covariate_table(problem: Problem, z_full: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Residual (measured - model) of every fitting sample / stress scale and / noise σ, and its covariates."""
    st = problem.params.values(z_full)
    coefs = problem.offsets(z_full)
    cols: dict[str, list] = {n: [] for n in ("d", "rate", "hold", "below", "toe", "high", "virgin", "tn", "file",
                                             "drive", "cycle", "compression", "timed")}
    E, N = [], []
    for k, r in enumerate(problem.records):
        pos = positions(problem, k)
        idx = r.fit_idx[pos]
        e = (r.y[r.fit_idx] - problem.forward.add_offsets(k, problem.forward.predict(k, st), coefs[k]))[pos]
        c = r.cov
        E.append(e / r.scale)
        N.append(e / r.sigma)
        cols["d"].append(c.direction[idx])
        cols["rate"].append(np.full(idx.size, c.loading_rate()))
        cols["hold"].append(np.nan_to_num(c.hold_time[idx]) * (c.direction[idx] == 0) if r.history
                            else np.zeros(idx.size))
        cols["below"].append(c.below_max[idx] if r.history else np.zeros(idx.size))
        cols["toe"].append(c.toe[idx])
        cols["high"].append(c.high[idx])
        cols["virgin"].append(c.virgin[idx])
        cols["tn"].append(c.elapsed[idx] / (float(c.elapsed[-1]) or 1.0))
        cols["file"].append(np.full(idx.size, k))
        cols["drive"].append(c.drive[idx])
        cols["cycle"].append(c.cycle[idx])
        cols["compression"].append((r.x[idx] < reference(r.test.mode)) & (r.test.mode != "simple_shear"))
        cols["timed"].append(np.full(idx.size, r.history))
    e, en = np.concatenate(E), np.concatenate(N)
    good = np.isfinite(e)
    cat = {n: np.concatenate(v)[good] for n, v in cols.items()}
    return e[good], en[good], cat


def _facts(e: np.ndarray, cat: dict[str, np.ndarray]) -> dict[str, Any]:
    """Covariate summaries of the normalised residual (measured - model) / stress scale."""
    f: dict[str, Any] = {}

    def mean(mask):
        return float(np.mean(e[mask])) if np.any(mask) else None

    f["loading_mean"] = mean(cat["d"] > 0)
    f["unloading_mean"] = mean(cat["d"] < 0)
    f["hold_mean"] = mean(cat["d"] == 0)
    rates = cat["rate"]
    fin = np.isfinite(rates)
    if fin.any():
        groups = {}
        for v in np.unique(np.round(rates[fin], 6)):
            m = fin & np.isclose(rates, v) & (cat["d"] > 0)
            groups[f"{v:.3g}"] = float(np.mean(e[m])) if np.any(m) else None
        f["loading_mean_by_rate"] = groups
    hm = (cat["d"] == 0) & (cat["hold"] > 0)
    if np.count_nonzero(hm) > 5:
        lh = np.log1p(cat["hold"][hm])
        a = np.polyfit(lh, e[hm], 1)[0] if np.ptp(lh) > 0 else 0.0
        f["hold_trend"] = float(a * np.ptp(lh))  # residual change over the holds
    f["below_max_mean"] = mean(cat["below"] > 0.02)
    f["virgin_loading_mean"] = mean(cat["virgin"] & (cat["d"] > 0))
    f["toe_mean"] = mean(cat["toe"])
    f["high_end_mean"] = mean(cat["high"])
    f["compression_mean"] = mean(cat["compression"])
    f["tension_mean"] = mean(~cat["compression"] & (cat["drive"] > 1.0))
    if np.ptp(cat["tn"]) > 0:
        f["time_trend"] = float(np.polyfit(cat["tn"], e, 1)[0])
    return f


def _binned_r2(en: np.ndarray, x: np.ndarray, bins: int = 10) -> float:
    """Share of the residual's sum of squares explained by its means in quantile bins of *x*."""
    ss = float(en @ en)
    if ss <= 0 or np.ptp(x) <= 0:
        return 0.0
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    expl = 0.0
    for b in np.unique(which):
        m = which == b
        expl += float(np.sum(en[m])) ** 2 / int(m.sum())
    return expl / ss


def structure(en: np.ndarray, cat: dict[str, np.ndarray]) -> dict[str, Any]:
    """Where the residual is (segments: mean in noise units, share of χ²) and what it follows (covariates: R²).

    The stretch covariate is taken per file and direction of loading, so its R²
    measures a residual that is a function of the deformation alone (an
    elastic-law misfit); time, cycle, time in a hold and depth below the
    previous maximum measure a history effect.
    """
    ss = float(en @ en) or 1e-300
    timed = cat["timed"]  # loading, unloading and holds are segments of a history
    segs = {"loading": timed & (cat["d"] > 0), "unloading": timed & (cat["d"] < 0), "hold": timed & (cat["d"] == 0),
            "tension": ~cat["compression"] & (cat["drive"] > 1.0), "toe": cat["toe"],
            "high stretch end": cat["high"], "below the previous maximum": cat["below"] > 0.02,
            "compression": cat["compression"]}
    seg_out = {"all": {"samples": int(en.size), "mean_noise_sd": float(np.mean(en)), "chi2_share": 1.0}}
    seg_out |= {n: {"samples": int(m.sum()), "mean_noise_sd": float(np.mean(en[m])),
                   "chi2_share": float(en[m] @ en[m]) / ss} for n, m in segs.items() if m.sum() >= 3}
    elastic = 0.0
    for k in np.unique(cat["file"]):
        m = cat["file"] == k
        if m.sum() >= 10:
            elastic += _binned_r2(en[m], cat["drive"][m] * np.where(cat["compression"][m], -1, 1)) * \
                float(en[m] @ en[m]) / ss
    cov = {"stretch (elastic law)": elastic}
    if timed.any():  # history covariates, on the records that have a history
        share = float(en[timed] @ en[timed]) / ss
        for name, key in (("time", "tn"), ("cycle", "cycle"), ("time in a hold", "hold"),
                          ("depth below the previous maximum", "below")):
            cov[name] = _binned_r2(en[timed], cat[key][timed]) * share
    return {"segments": seg_out, "covariates": cov}


# --------------------------------------------------------------------------- signatures
def positions(prob: Problem, k: int) -> np.ndarray:
    """Positions, within record *k*'s fitting samples, of those in *prob*'s objective (all by default)."""
    t = prob.train[k]
    return np.arange(prob.records[k].fit_idx.size) if t is None else np.asarray(t, dtype=int)


class _Signatures:
    """The noise-normalised residual of the current model, its Jacobian's span, and candidate signatures."""

    def __init__(self, prob: Problem, z_full: np.ndarray):
        self.prob, self.z_full = prob, z_full
        st = prob.params.values(z_full)
        self.coefs = prob.offsets(z_full)
        self.base_pred, resid, self.w = [], [], []
        self.pos = [positions(prob, k) for k in range(len(prob.records))]
        for k, r in enumerate(prob.records):
            p = prob.forward.add_offsets(k, prob.forward.predict(k, st), self.coefs[k])
            self.base_pred.append(p)
            self.w.append(1.0 / r.sigma)
            resid.append(np.nan_to_num((r.y[r.fit_idx] - p) / r.sigma)[self.pos[k]])
        self.e = np.concatenate(resid)
        self.sizes = [p.size for p in self.pos]
        self.Q = self._basis()
        self.e_perp = self.e - self.Q @ (self.Q.T @ self.e)
        self.ss = float(self.e @ self.e) or 1e-300

    def _basis(self) -> np.ndarray:
        """Orthonormal basis of what the current parameters (and offsets) can change, in noise units."""
        prob = self.prob
        prob.z_full, prob.active = self.z_full.copy(), np.arange(len(prob.slots))
        with prob.offsets_held():
            J = prob.jac(self.z_full.copy())
        J = J[: sum(self.sizes)]
        rows = []
        for k, r in enumerate(prob.records):
            conv = r.scale / (prob.factor[k] * r.sigma) if prob.factor[k] else 0.0
            rows.append(np.full(self.sizes[k], conv))
        J = J * np.concatenate(rows)[:, None]
        extra = []
        off = np.concatenate([[0], np.cumsum(self.sizes)])
        for k in range(len(prob.records)):
            X = prob.forward.offset_columns(k, prob.records[k].fit_idx[self.pos[k]])
            if X is not None and self.sizes[k]:
                block = np.zeros((J.shape[0], X.shape[1]))
                block[off[k]:off[k + 1]] = X / prob.records[k].sigma
                extra.append(block)
        A = np.concatenate([J] + extra, axis=1) if extra else J
        A = np.nan_to_num(A)
        if A.shape[1] == 0:
            return np.zeros((A.shape[0], 0))
        U, s, _ = np.linalg.svd(A, full_matrices=False)
        return U[:, s > 1e-9 * (s.max() if s.size else 1.0)]

    def gain(self, sig: np.ndarray, sign: float = 0.0) -> float:
        """χ² removed at first order by one coefficient along *sig* (of the given sign; 0: either)."""
        top = float(np.max(np.abs(sig))) if sig.size else 0.0
        if not (0.0 < top < np.inf):
            return 0.0
        sig = sig / top  # the gain is scale-free; keep the products finite
        s = sig - self.Q @ (self.Q.T @ sig)
        den = float(s @ s)
        if den <= 0 or not np.isfinite(den):
            return 0.0
        num = float(s @ self.e_perp)
        return 0.0 if num * sign < 0 else num * num / den

    def perturbed(self, name: str, variant: int, values=None, per_record: bool = False):
        """The change of the prediction (noise units) with *name* switched on weakly (slot *values*).

        ``per_record``: one signature per record (a list), for artefacts and scales fitted per file.
        """
        prob = self.prob
        try:
            p2 = prob.derived(prob.spec.with_(name, variant))
        except Exception:  # noqa: BLE001 - a candidate that cannot be built scores 0
            return None
        z = p2.params.transfer(prob.params, self.z_full)
        z = _set_slots(p2, z, values or {})
        st2 = p2.params.values(z)
        out = [self._change(p2, st2, k) for k in range(len(prob.records))]
        if per_record:
            return out
        return np.concatenate(out)

    def per_slot(self, name: str, variant: int, values: dict) -> list[np.ndarray]:
        """One signature per per-file slot of *name* (slack, slips, scales), each set to its value in *values*."""
        prob = self.prob
        p2 = prob.derived(prob.spec.with_(name, variant))
        base_z = p2.params.transfer(prob.params, self.z_full)
        sigs = []
        for i, s in enumerate(p2.slots):
            if s.effect != name:
                continue
            z = base_z.copy()
            z[i] = values(p2, i)
            st2 = p2.params.values(z)
            parts = []
            for k in range(len(prob.records)):
                if k in s.records:
                    parts.append(self._change(p2, st2, k))
                else:
                    parts.append(np.zeros(self.sizes[k]))
            sigs.append(np.concatenate(parts))
        return sigs


    def _change(self, p2: Problem, st2, k: int) -> np.ndarray:
        """The change of record k's prediction (noise units, objective samples) from the current model to *p2*."""
        new = self.prob.forward.add_offsets(k, p2.forward.predict(k, st2), self.coefs[k])
        return _finite((new - self.base_pred[k]) * self.w[k])[self.pos[k]]


def _finite(a: np.ndarray) -> np.ndarray:
    """*a* with its non-finite entries (a sample outside the perturbed model's domain) set to 0."""
    return np.where(np.isfinite(a), a, 0.0)


def _set_slots(p2: Problem, z: np.ndarray, values: dict) -> np.ndarray:
    z = z.copy()
    for i, s in enumerate(p2.slots):
        key = (s.effect, s.name)
        if key not in values:
            continue
        v = values[key]  # the elastic law's values are SI, the effects' optimiser coordinates
        z[i] = (math.log(max(v, 1e-300)) if s.log else v) if s.effect is None else v
    return z


def _best(sig: _Signatures, name: str, variant: int, grid, sign: float = 0.0) -> float:
    best = 0.0
    for values in grid:
        s = sig.perturbed(name, variant, values)
        if s is not None:
            best = max(best, sig.gain(s, sign))
    return best


def _score_viscoelastic(sig: _Signatures) -> float:
    b = sig.prob.bounds
    return _best(sig, "viscoelastic", 1, ({("viscoelastic", "u[0]"): _EPS, ("viscoelastic", "tau[0]"): math.log(t)}
                                          for t in np.geomspace(b.tau_min * 2, b.tau_max / 10, 7)), +1.0)


def _score_kappa(sig: _Signatures) -> float:
    """The largest first-order gain of the searched forms: the relaxed amount (kappa, variant 1) or the
    relaxation times (kappa_tau, variant 2) depending on stretch."""
    km = sig.prob.bounds.kappa_max
    names = {1: "kappa", 2: "kappa_tau"}
    return max(_best(sig, "nonlinear_viscoelastic", v, [{("nonlinear_viscoelastic", names[v]): _EPS * km}])
               for v in VARIANTS["nonlinear_viscoelastic"])


def _score_mullins(sig: _Signatures) -> float:
    w = sig.prob.bounds.w_ref
    return _best(sig, "mullins", 2, ({("mullins", "s"): _EPS, ("mullins", "m"): math.log(q * w)}
                                     for q in (0.02, 0.1, 0.5)), +1.0)


def _score_damage(sig: _Signatures) -> float:
    b = sig.prob.bounds
    return _best(sig, "damage", 3, ({("damage", "onset"): 1.0 + q * b.xi_span,
                                     ("damage", "scale"): math.log(sc * b.xi_span / _EPS), ("damage", "shape"): 1.0}
                                    for q in (0.0, 0.3, 0.6, 0.85) for sc in (0.1, 0.4)), +1.0)


def _score_cyclic(sig: _Signatures) -> float:
    w = sig.prob.bounds.w_ref
    return _best(sig, "cyclic_softening", 2, ({("cyclic_softening", "d_inf"): _EPS,
                                               ("cyclic_softening", "eta"): math.log(q * w)} for q in (0.3, 3.0, 30.0)), +1.0)


def _score_set(sig: _Signatures) -> float:
    return _best(sig, "permanent_set", 1, [{("permanent_set", "fraction"): _EPS}], +1.0)


def _score_per_slot(sig: _Signatures, name: str, value, sign: float = 0.0) -> float:
    """Artefacts with one coefficient per file, slip or specimen: the sum of their separate gains
    (*sign* as in :meth:`_Signatures.gain`)."""
    try:
        sigs = sig.per_slot(name, 1, value)
    except Exception:  # noqa: BLE001 - a candidate that cannot be built scores 0
        return 0.0
    return float(sum(sig.gain(s, sign) for s in sigs))


def _score_offset(sig: _Signatures) -> float:
    """χ² removed by an offset (and a drift, where there is time) fitted per file."""
    tot, off = 0.0, np.concatenate([[0], np.cumsum(sig.sizes)])
    for k, r in enumerate(sig.prob.records):
        if not offset_applicable(r):
            continue
        idx = r.fit_idx[sig.pos[k]]
        cols = [np.ones(idx.size)]
        if r.t is not None:
            cols.append((r.t[idx] - r.t[0]) / (r.T or 1.0))
        for c in cols:
            full = np.zeros(sig.e.size)
            full[off[k]:off[k + 1]] = c * sig.w[k]
            tot += sig.gain(full)
    return tot


def _score_term(sig: _Signatures, name: str) -> float:
    term = TERMS[name]
    stiff, shapes = term_grid(sig.prob, name)
    grid = ({(None, term.modulus): 1e-6 * stiff, **{(None, k): x for k, x in v.items()}} for v in shapes)
    return _best(sig, name, 1, grid, +1.0)


def _scores(problem: Problem, z_full: np.ndarray, names: list[str]) -> tuple[dict[str, float], float]:
    """First-order χ² gain of each candidate, and the residual's χ² (noise units)."""
    sig = _Signatures(problem, z_full)
    b = problem.bounds
    scorers = {
        "viscoelastic": _score_viscoelastic, "nonlinear_viscoelastic": _score_kappa, "mullins": _score_mullins,
        "damage": _score_damage, "cyclic_softening": _score_cyclic, "permanent_set": _score_set,
        "sensor_offset": _score_offset,
        "slack": lambda s: _score_per_slot(s, "slack", lambda p2, i: _EPS * b.xi_span, +1.0),
        "grip_slip": lambda s: _score_per_slot(s, "grip_slip", lambda p2, i: _EPS * b.xi_span, +1.0),
        "specimen_scale": lambda s: _score_per_slot(s, "specimen_scale", lambda p2, i: _EPS),
    }
    out: dict[str, float] = {}
    for n in names:
        if problem.spec.variant(n):
            continue
        out[n] = _score_term(sig, n) if n in TERMS else scorers[n](sig)
    return out, sig.ss


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
        Names to score (default: every candidate not yet in the model).
    errors : Errors, optional
        Error measures on all samples (for the size).
    """
    names = [n for n in (candidates or list(CANDIDATES)) if not problem.spec.variant(n)]
    res = problem.fit_residuals(z_full)
    rhos = [lag1(r) for r in res if r.size > 2]
    zs = [runs_test(r)[1] for r in res if r.size > 2]
    rho = float(np.median(rhos)) if rhos else 0.0
    runs_z = float(min(zs)) if zs else 0.0
    e, en, cat = _covariate_table(problem, z_full)
    chi2 = float(en @ en) / max(en.size, 1)
    facts = _facts(e, cat)
    gains, ss = _scores(problem, z_full, names)
    scores = {n: g / ss for n, g in gains.items()}
    why = _explain(problem, facts, scores, names)
    white = chi2 <= max(WHITE_CHI2, 1.0 + WHITE_Z * math.sqrt(2.0 * _noise_tau(problem) / max(en.size, 1)))
    ranking = sorted(names, key=lambda n: -gains.get(n, 0.0))
    rmse = errors.rmse if errors is not None else float("nan")
    nrmse = errors.nrmse if errors is not None else float("nan")
    return Diagnosis(rmse, nrmse, rho, runs_z, white, chi2, facts, scores, gains, why, ranking, structure(en, cat))


def _noise_tau(problem: Problem) -> float:
    """The median over records of their noise's integrated autocorrelation time at the fitting spacing."""
    taus = [r.noise.tau(float(np.median(np.diff(r.fit_idx))) if r.fit_idx.size > 1 else 1.0)
            for r in problem.records]
    return float(np.median(taus)) if taus else 1.0


def _explain(problem: Problem, f: dict[str, Any], scores: dict[str, float], names: list[str]) -> dict[str, str]:
    """One sentence per candidate: what in the residual points to it (or not)."""
    out = {}
    for n in names:
        bits = [f"{100 * scores.get(n, 0.0):.0f} % of the residual has its shape"]
        if n == "viscoelastic":
            lo, un = f.get("loading_mean"), f.get("unloading_mean")
            if lo is not None and un is not None:
                bits.append(f"the data lie {_pct(lo)} above the model on loading and {_pct(un)} on unloading "
                            "(of the stress scale)")
            vals = {k: v for k, v in (f.get("loading_mean_by_rate") or {}).items() if v is not None}
            if len(vals) >= 2:
                bits.append("on loading, by rate [1/s]: " + ", ".join(f"{k}: {_pct(v)}" for k, v in vals.items()))
            if "hold_trend" in f:
                bits.append(f"during holds the residual changes by {_pct(f['hold_trend'])} (relaxation)")
        elif n in ("mullins", "cyclic_softening"):
            bm, vl = f.get("below_max_mean"), f.get("virgin_loading_mean")
            if bm is not None:
                bits.append(f"below the previous maximum the residual averages {_pct(bm)}, "
                            f"on the primary loading path {_pct(vl or 0.0)}")
        elif n == "damage" and f.get("high_end_mean") is not None:
            bits.append(f"at the high-stretch end of the primary loading the residual is {_pct(f['high_end_mean'])}")
        elif n == "slack":
            if not any(slack_applicable(r) for r in problem.records):
                bits = ["not applicable: no tension test starting from the undeformed state"]
            elif f.get("toe_mean") is not None:
                bits.append(f"in the toe region the residual is {_pct(f['toe_mean'])}")
        elif n == "sensor_offset" and "time_trend" in f:
            bits.append(f"the residual drifts by {_pct(f['time_trend'])} from start to end")
        elif n in TERMS:
            if f.get("compression_mean") is not None:
                bits.append(f"in compression the residual averages {_pct(f['compression_mean'])}, in tension "
                            f"{_pct(f.get('tension_mean') or 0.0)}")
            bits.append(f"the term addresses {TERMS[n].addresses}")
        out[n] = "; ".join(bits)
    return out
