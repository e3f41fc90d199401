"""Starting values of an effect's parameters, with everything else held.

A least-squares fit of an effect started from zero strength rarely finds the
optimum (the slack optimum, for one, is not found from zero): each effect's
parameters are first set by a small grid search of the objective (Mullins,
damage, slack) or, for the Prony series, by non-negative least squares over a
dictionary of relaxation times, before the full fit frees everything.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
from scipy import optimize

from ..materials.effects import qlv_stress
from .model import Problem


def initialise(prob: Problem, z: np.ndarray, name: str) -> np.ndarray:
    """Starting values of effect *name* in *z* with everything else held (grid search / NNLS)."""
    if name == "viscoelastic":
        return _init_prony(prob, z)
    if name == "mullins":
        return _init_mullins(prob, z)
    if name == "damage":
        return _init_damage(prob, z)
    if name == "slack":
        return _init_slack(prob, z)
    return z


def _cost(prob: Problem, z: np.ndarray) -> float:
    """The objective at *z* with nothing free."""
    prob.z_full = z
    prob.active = np.zeros(0, dtype=int)
    return prob.cost(np.zeros(0))


def _set(prob: Problem, z: np.ndarray, effect: str, values: Mapping[str, float]) -> np.ndarray:
    z = z.copy()
    for i, s in enumerate(prob.slots):
        if s.effect == effect and s.name in values:
            z[i] = values[s.name]
    return np.clip(z, prob.lower, prob.upper)


def _grid_search(prob: Problem, z: np.ndarray, effect: str, grid: Iterable[Mapping[str, float]]) -> np.ndarray:
    """*z* with the values of *effect* of least cost among *grid* (*z* itself if none is finite)."""
    best, zb = math.inf, z
    for values in grid:
        zz = _set(prob, z, effect, values)
        c = _cost(prob, zz)
        if c < best:
            best, zb = c, zz
    return zb


def _init_mullins(prob: Problem, z: np.ndarray) -> np.ndarray:
    w_ref = prob.bounds.w_ref
    betas = (0.0, 0.5) if prob.spec.mullins == 3 else (0.0,)
    return _grid_search(prob, z, "mullins", ({"s": s, "m": math.log(mm * w_ref), "beta": be}
                                             for s in (0.2, 0.5, 0.8) for mm in (0.01, 0.05, 0.2, 1.0)
                                             for be in betas))


def _init_damage(prob: Problem, z: np.ndarray) -> np.ndarray:
    span = prob.bounds.xi_span
    return _grid_search(prob, z, "damage", ({"onset": 1.0 + q * span, "scale": math.log(sc * span), "shape": k}
                                            for q in (0.2, 0.4, 0.6, 0.8, 0.95) for sc in (0.05, 0.2, 0.6)
                                            for k in (1.5, 3.0)))


def _init_slack(prob: Problem, z: np.ndarray) -> np.ndarray:
    """Each file's slack on a grid of its range, judged by that file's residual alone."""
    idx = [i for i, s in enumerate(prob.slots) if s.effect == "slack"]
    if not idx:
        return z
    best = {i: (math.inf, z[i]) for i in idx}
    for q in np.linspace(0.0, 1.0, 13):
        zz = z.copy()
        for i in idx:
            zz[i] = prob.lower[i] + q * (prob.upper[i] - prob.lower[i]) * 0.6
        st = prob.state(zz)
        for i in idx:
            blk, _ = prob.residual_block(prob.slots[i].file, st)
            c = float(blk @ blk)
            if c < best[i][0]:
                best[i] = (c, zz[i])
    z = z.copy()
    for i in idx:
        z[i] = best[i][1]
    return z


def _init_prony(prob: Problem, z: np.ndarray) -> np.ndarray:
    """Prony starting values: non-negative least squares over a dictionary of relaxation times."""
    b = prob.bounds
    n_terms = prob.spec.viscoelastic
    taus = np.geomspace(b.tau_min * 2, b.tau_max / 5, 14)
    system = _relaxation_system(prob, z, taus)
    if system is None:
        return z
    A, yv = system
    try:
        g, _ = optimize.nnls(A, yv, maxiter=50 * A.shape[1])
    except RuntimeError:
        g = np.zeros(len(taus))
    chosen = [j for j in np.argsort(-g) if g[j] > 0][:n_terms]
    gs = [float(g[j]) for j in chosen]
    ts = [float(taus[j]) for j in chosen]
    spread = np.geomspace(b.tau_min * 10, b.tau_max / 20, n_terms + 2)[1:-1]
    while len(ts) < n_terms:
        cand = [t for t in spread if all(abs(math.log(t / u)) > 0.5 for u in ts)] or list(spread)
        ts.append(float(cand[0]))
        gs.append(0.05)
    tot = sum(gs)
    if tot > 0.95:
        gs = [v * 0.95 / tot for v in gs]
    vals = {}
    for j, u in enumerate(_stick_breaking(gs)):
        vals[f"u[{j}]"] = u
        vals[f"tau[{j}]"] = math.log(min(max(ts[j], b.tau_min * 1.01), b.tau_max * 0.99))
    return _set(prob, z, "viscoelastic", vals)


def _relaxation_system(prob: Problem, z: np.ndarray, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The weighted linear system (atoms, target) of one Prony term per relaxation time in *taus*.

    Each atom is the relaxation of the softened elastic stress with one unit term;
    the offset columns are projected out. None where no training record has time.
    """
    st = prob.state(z)
    cols, target = [], []
    for k, r in enumerate(prob.records):
        if not prob.n_train[k] or r.t is None:
            continue
        idx = r.fit_idx
        pd = np.nan_to_num(prob.softened(k, st, idx))
        atoms = np.stack([qlv_stress(r.t[idx], pd, [1.0], [tau]) - pd for tau in taus], axis=1)
        y = r.y[idx] - pd
        pos = prob.train[k]
        if pos is not None:
            atoms, y = atoms[pos], y[pos]
        X = prob.offset_columns(k, idx)
        if X is not None and prob.n_offset[k]:
            if pos is not None:
                X = X[pos]
            Q, _ = np.linalg.qr(X)
            atoms = atoms - Q @ (Q.T @ atoms)
            y = y - Q @ (Q.T @ y)
        w = prob.factor[k] / r.scale
        cols.append(atoms * w)
        target.append(y * w)
    return (np.concatenate(cols), np.concatenate(target)) if cols else None


def _stick_breaking(gs: list[float]) -> list[float]:
    """Prony weights as stick-broken fractions u_j in [1e-3, 0.99] (g_j = u_j prod_{i<j} (1 - u_i))."""
    us, rest = [], 1.0
    for v in gs:
        u = min(max(v / rest, 1e-3), 0.99) if rest > 0 else 0.5
        us.append(u)
        rest *= 1 - u
    return us


def extend_variant(prob: Problem, z: np.ndarray, extra: list[int]) -> np.ndarray:
    """Start the added slots of a richer variant: a small new Prony term far from the others."""
    z = z.copy()
    b = prob.bounds
    taus = [z[i] for i, s in enumerate(prob.slots) if s.effect == "viscoelastic" and s.name.startswith("tau")
            and i not in extra]
    grid = np.log(np.geomspace(b.tau_min * 2, b.tau_max / 5, 15))
    for i in extra:
        s = prob.slots[i]
        if s.effect == "viscoelastic" and s.name.startswith("tau"):
            far = max(grid, key=lambda g: min([abs(g - t) for t in taus] or [0.0]))
            z[i] = far
            taus.append(far)
        elif s.effect == "viscoelastic":
            z[i] = 0.05
        elif s.name == "beta":
            z[i] = 0.1
    return np.clip(z, prob.lower, prob.upper)
