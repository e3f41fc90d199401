"""Parameters of a fitted extended model with their 95 % intervals.

The covariance is that of the calibrate fit (:mod:`esmm.pipeline.calibrate.intervals`:
the pseudo-inverse of :math:`J^T J` on the identified subspace, inflated for the
serial correlation of the residual), over every slot *and* the load-cell offset
coefficients, which the fit eliminates in closed form and which enter here as
explicit columns of the Jacobian. Derived quantities (Prony weights from their
stick-broken fractions, the Mullins ``r = 1/s``, offsets in N, slack in m) get
their intervals by the delta method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from ..calibrate.intervals import (
    WIDE_LOG_FACTOR,
    WIDE_REL_WIDTH,
    identified_covariance,
    lag1,
    unbounded,
)
from ..calibrate.problem import NAN_PENALTY
from .model import Problem, Values

#: the serial correlation used for the inflation is clipped to this
RHO_CLIP = 0.99


@dataclass
class Estimate:
    """A reported parameter with its 95 % interval (SI)."""

    key: str
    value: float
    lower: float
    upper: float
    unit: str = ""
    wide: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "ci95": [self.lower, self.upper], "unit": self.unit,
                "not_identifiable": self.wide}


def estimates(problem: Problem, z_full: np.ndarray) -> list[Estimate]:
    """Parameters of *problem* at *z_full* with 95 % intervals (module docstring).

    Parameters
    ----------
    problem : Problem
    z_full : ndarray, shape (n_slots,)

    Returns
    -------
    list of Estimate
        Base and effect parameters, then the derived ones; Prony terms in order
        of their relaxation time.
    """
    prob = problem
    iv, coefs, off_keys = _fit_intervals(prob, z_full)
    st = prob.params.values(z_full)
    _slot_estimates(iv, prob, z_full)
    if st.g is not None:
        _prony_estimates(iv, prob, z_full, st)
    if st.mullins is not None:
        i = next(i for i, s in enumerate(prob.slots) if s.effect == "mullins" and s.name == "s")
        iv.add("mullins.r", iv.unit_grad(i, -1.0 / max(z_full[i], 1e-12) ** 2), st.mullins[0], positive=True)
    _offset_estimates(iv, prob, coefs, off_keys)
    return _prony_by_tau(iv.out)


def slot_covariance(problem: Problem, z_full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fit's joint covariance over the slots of *problem* at *z_full*, and the directions it does not see.

    The covariance of :func:`estimates` (before any derived quantity), restricted to the slots: what a
    test of several parameters together needs where their errors are correlated (per-file slacks that
    trade with one elastic law's onset, :mod:`.artefacts`).

    Returns
    -------
    cov : ndarray, shape (n_slots, n_slots)
    null : ndarray, shape (q, n_slots)
        Rows spanning the unidentified directions (q may be 0), as
        :func:`~esmm.pipeline.calibrate.intervals.identified_covariance`.
    """
    iv, _, _ = _fit_intervals(problem, z_full)
    n = len(problem.slots)
    return iv.cov[:n, :n], iv.null[:, :n]


def _fit_intervals(prob: Problem, z_full: np.ndarray) -> tuple[_Intervals, list, list[tuple[int, int]]]:
    """The covariance of the fit at *z_full* over every slot and the offset coefficients, the offsets, and
    the (record, coefficient) keys of the offset columns (*prob* left with every slot active at *z_full*)."""
    prob.z_full = z_full.copy()
    prob.active = np.arange(len(prob.slots))
    coefs = prob.offsets(z_full)
    r0, J, off_keys = _jacobian(prob, z_full, coefs)
    return _Intervals(prob, z_full, r0, J), coefs, off_keys


def _residual_at_offsets(prob: Problem, z_full: np.ndarray, coefs) -> np.ndarray:
    """The normalised residual on the training samples with the fitted offsets added explicitly."""
    st = prob.params.values(z_full)
    out = []
    for k, r in enumerate(prob.records):
        if not prob.n_train[k]:
            continue
        p = prob.forward.add_offsets(k, prob.forward.predict(k, st), coefs[k])
        pos = prob.train[k]
        y = r.y[r.fit_idx]
        if pos is not None:
            p, y = p[pos], y[pos]
        o = prob.factor[k] * (p - y) / r.scale
        out.append(np.where(np.isfinite(o), o, NAN_PENALTY))
    return np.concatenate(out + [prob.constraint_residual(z_full)])


def _jacobian(prob: Problem, z_full: np.ndarray, coefs) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Residual, Jacobian over the slots and the offset coefficients, and the (record, coefficient) keys."""
    with prob.offsets_held():
        r0 = _residual_at_offsets(prob, z_full, coefs)
        cols = [prob.jac(z_full)]  # offsets held: plain derivatives
        off_keys = []
        for k, r in enumerate(prob.records):
            if not prob.n_train[k] or coefs[k] is None:
                continue
            X = prob.forward.free_offset_columns(k, r.fit_idx)
            if X is None:
                continue
            pos = prob.train[k]
            if pos is not None:
                X = X[pos]
            block = np.zeros((r0.size, X.shape[1]))
            start = int(sum(prob.n_train[j] for j in range(k) if prob.n_train[j]))
            block[start:start + X.shape[0]] = prob.factor[k] * X / r.scale
            cols.append(block)
            first = prob.forward.n_offset[k] - X.shape[1]  # a held offset read at rest is coefficient 0
            off_keys += [(k, first + j) for j in range(X.shape[1])]
    return r0, np.concatenate(cols, axis=1), off_keys


class _Intervals:
    """The covariance of one fit, and the estimates added to it one by one (delta method)."""

    def __init__(self, prob: Problem, z_full: np.ndarray, r0: np.ndarray, J: np.ndarray):
        n, p = J.shape
        dof = max(n - p, 1)
        s2 = float(r0 @ r0) / dof
        res = [b for b in prob.fit_residuals(z_full) if b.size]
        rho = float(np.clip(np.average([lag1(b) for b in res], weights=[b.size for b in res]), 0.0, RHO_CLIP)) \
            if res else 0.0
        self.cov, self.null = identified_covariance(J, s2, (1 + rho) / (1 - rho))
        self.tq = float(stats.t.ppf(0.975, dof))
        self.size = p
        self.out: list[Estimate] = []

    def unit_grad(self, i: int, value: float = 1.0) -> np.ndarray:
        g = np.zeros(self.size)
        g[i] = value
        return g

    def add(self, key: str, grad: np.ndarray, value: float, *, positive: bool, unit: str = "") -> None:
        """Add the estimate of a quantity of gradient *grad*; *positive*: its interval is log-normal."""
        var = math.inf if unbounded(grad, self.null) else float(grad @ self.cov @ grad)
        sd = math.sqrt(max(var, 0.0)) if math.isfinite(var) else math.inf
        tq = self.tq
        if positive and value > 0:
            sl = sd / value
            lo = value * math.exp(-tq * sl) if math.isfinite(sl) else 0.0
            hi = value * math.exp(min(tq * sl, 700)) if math.isfinite(sl) else math.inf
            wide = (not math.isfinite(sl)) or hi / max(lo, 1e-300) > WIDE_LOG_FACTOR
        else:
            lo, hi = value - tq * sd, value + tq * sd
            wide = (not math.isfinite(sd)) or 2 * tq * sd > WIDE_REL_WIDTH * max(abs(value), 1e-12)
        self.out.append(Estimate(key, float(value), float(lo), float(hi), unit, bool(wide)))


def _slot_estimates(iv: _Intervals, prob: Problem, z_full: np.ndarray) -> None:
    """Base, damage, Mullins (but s), slack and other direct slots."""
    for i, s in enumerate(prob.slots):
        if s.effect in ("viscoelastic",) or (s.effect == "mullins" and s.name == "s"):
            continue
        v = math.exp(z_full[i]) if s.log else float(z_full[i])
        grad = iv.unit_grad(i, v if s.log else 1.0)
        unit = {"stress": "Pa", "time": "s"}.get(s.kind, "")
        key = s.key if s.file is None else f"{s.key}[{prob.records[s.file].name}]"
        if s.effect in ("slack", "grip_slip"):
            r = prob.records[s.file]
            if r.gauge:
                what = "length" if s.effect == "slack" else f"length{s.name[4:]}"
                iv.add(f"{s.effect}.{what}[{r.name}]", grad * r.gauge, v * r.gauge, positive=False, unit="m")
            iv.add(key, grad, v, positive=False)
            continue
        iv.add(key, grad, v, positive=s.log or s.kind == "stress", unit=unit)


def _prony_estimates(iv: _Intervals, prob: Problem, z_full: np.ndarray, st: Values) -> None:
    """Prony weights g_j (from the stick-broken fractions u), relaxation times and g_inf."""
    idx_u = [i for i, s in enumerate(prob.slots) if s.effect == "viscoelastic" and s.name.startswith("u")]
    idx_t = [i for i, s in enumerate(prob.slots) if s.effect == "viscoelastic" and s.name.startswith("tau")]
    u = z_full[idx_u]
    rank = {int(j): r for r, j in enumerate(np.argsort(st.tau))}  # report sorted by tau, as MaterialEffects
    for j in range(len(u)):
        grad = np.zeros(iv.size)
        for q in range(j + 1):  # dg_j/du_q
            grad[idx_u[q]] = np.prod(1 - u[:j]) if q == j else -u[j] * np.prod([1 - u[m] for m in range(j) if m != q])
        iv.add(f"viscoelastic.g[{rank[j]}]", grad, float(st.g[j]), positive=True)
        iv.add(f"viscoelastic.tau[{rank[j]}]", iv.unit_grad(idx_t[j], st.tau[j]), float(st.tau[j]), positive=True,
               unit="s")
    grad = np.zeros(iv.size)
    for q in range(len(u)):
        grad[idx_u[q]] = -np.prod([1 - u[m] for m in range(len(u)) if m != q])
    iv.add("viscoelastic.g_inf", grad, float(np.prod(1 - u)), positive=False)


def _offset_estimates(iv: _Intervals, prob: Problem, coefs, off_keys) -> None:
    """Load-cell offsets and drifts: in N (N/s) where the file has an area, else in Pa (Pa/s)."""
    for c, (k, j) in enumerate(off_keys):
        r = prob.records[k]
        grad = iv.unit_grad(len(prob.slots) + c)
        v = float(coefs[k][j])
        # data = model + offset: the load cell reads `offset` when the true force is zero
        if r.area:
            g2 = grad * r.area
            if j == 0:
                iv.add(f"sensor_offset.force[{r.name}]", g2, v * r.area, positive=False, unit="N")
            else:
                iv.add(f"sensor_offset.drift[{r.name}]", g2 / (r.T or 1.0), v * r.area / (r.T or 1.0),
                       positive=False, unit="N/s")
        elif j == 0:
            iv.add(f"sensor_offset.stress[{r.name}]", grad, v, positive=False, unit="Pa")
        else:
            iv.add(f"sensor_offset.drift[{r.name}]", grad / (r.T or 1.0), v / (r.T or 1.0),
                   positive=False, unit="Pa/s")


def _prony_by_tau(out: list[Estimate]) -> list[Estimate]:
    """The Prony terms in order of their relaxation time, in place of the order they were added in."""
    def prony(e: Estimate) -> bool:
        return e.key.startswith("viscoelastic.") and "[" in e.key

    it = iter(sorted((e for e in out if prony(e)), key=lambda e: (int(e.key[e.key.index("[") + 1:-1]), e.key)))
    return [next(it) if prony(e) else e for e in out]
