"""Starting values of an effect's or a strain-energy term's parameters, with everything else held.

A least-squares fit of an effect started from zero strength rarely finds the
optimum (the slack optimum, for one, is not found from zero): each effect's
parameters are first set by a small grid search of the objective (Mullins,
damage, cyclic softening, permanent set, stretch-dependent relaxation, slack,
the strain-energy terms over decades of their modulus and their shape), in
closed form (specimen scales, slips), or, for the Prony series, by
non-negative least squares over a dictionary of relaxation times, before the
full fit frees everything.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping

import numpy as np
from scipy import optimize

from ..materials.effects import qlv_rate_decay, qlv_stress
from ..materials.loading import invariants
from ..materials.terms import TERMS
from .model import Problem


def initialise(prob: Problem, z: np.ndarray, name: str) -> np.ndarray:
    """Starting values of effect or term *name* in *z* with everything else held (grid search / NNLS)."""
    if name in TERMS:
        return _init_term(prob, z, name)
    init = {"viscoelastic": _init_prony, "mullins": _init_mullins, "damage": _init_damage, "slack": _init_slack,
            "nonlinear_viscoelastic": _init_kappa, "cyclic_softening": _init_cyclic,
            "permanent_set": _init_set, "specimen_scale": _init_scales, "grip_slip": _init_slips}
    return init[name](prob, z) if name in init else z


def _init_kappa(prob: Problem, z: np.ndarray) -> np.ndarray:
    """The stretch dependence (of the relaxed amount, kappa, or of the relaxation times, kappa_tau: the
    spec's variant) on a grid, each with its own Prony terms by NNLS."""
    km = prob.bounds.kappa_max
    rate = prob.spec.nonlinear_viscoelastic == 2
    best, zb = math.inf, z
    for q in (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6):
        zk = _set(prob, z, "nonlinear_viscoelastic", {"kappa_tau" if rate else "kappa": q * km})
        zk, rnorm = _prony_nnls(prob, zk, 0.0, q * km) if rate else _prony_nnls(prob, zk, q * km)
        if rnorm < best:
            best, zb = rnorm, zk
    return zb


def _init_cyclic(prob: Problem, z: np.ndarray) -> np.ndarray:
    w = prob.bounds.w_ref
    return _grid_search(prob, z, "cyclic_softening", ({"d_inf": d, "eta": math.log(e * w)}
                                                      for d in (0.05, 0.15, 0.3) for e in (0.1, 1.0, 10.0, 100.0)))


def _init_set(prob: Problem, z: np.ndarray) -> np.ndarray:
    exponents = (1.0, 2.0) if prob.spec.permanent_set == 2 else (1.0,)
    return _grid_search(prob, z, "permanent_set", ({"fraction": f, "exponent": q}
                                                   for f in (0.0, 0.05, 0.1, 0.2, 0.35, 0.5) for q in exponents))


def _init_scales(prob: Problem, z: np.ndarray) -> np.ndarray:
    """Each specimen's scale in closed form (least squares of its data on the current prediction),
    normalised to a geometric mean of 1."""
    st = prob.params.values(z)
    idx = [i for i, s in enumerate(prob.slots) if s.effect == "specimen_scale"]
    logs = []
    for i in idx:
        num = den = 0.0
        for k in prob.slots[i].group:
            r = prob.records[k]
            p = prob.forward.predict(k, st) / st.scale[k]
            good = np.isfinite(p)
            w = 1.0 / (r.fit_idx.size * r.scale**2)
            num += w * float(p[good] @ r.y[r.fit_idx][good])
            den += w * float(p[good] @ p[good])
        logs.append(math.log(num / den) if num > 0 and den > 0 else 0.0)
    z = z.copy()
    if logs:
        z[idx] = np.asarray(logs) - float(np.mean(logs))
    return np.clip(z, prob.lower, prob.upper)


def _init_slips(prob: Problem, z: np.ndarray) -> np.ndarray:
    """Each slip's extension loss from its stress drop over the loading slope just before it."""
    z = z.copy()
    for i, s in enumerate(prob.slots):
        if s.effect != "grip_slip":
            continue
        r = prob.records[s.file]
        e = r.slips[int(s.name[5:-1])]
        k = e
        while k > 0 and r.y[k - 1] >= r.y[k]:
            k -= 1  # top of the fall
        k0 = max(0, k - 5)
        slope = (r.y[k] - r.y[k0]) / (r.x[k] - r.x[k0]) if r.x[k] > r.x[k0] else 0.0
        z[i] = (r.y[k] - r.y[e]) / slope if slope > 0 else 0.0
    return np.clip(z, prob.lower, prob.upper)


def term_grid(prob: Problem, name: str) -> tuple[float, list[dict[str, float]]]:
    """A secant stiffness of the data [Pa] and the data-derived values of term *name*'s shape parameters
    (every combination; one empty dict for a term without any).

    Exponential rates are set so that the exponent reaches 0.3 to 10 at the
    largest invariant in the data; Gent's Jm from just above the largest
    I1 - 3 to ten times it; the toe width from a tenth of the stretch span to all of it, and its
    recruitment shape uniform or starting slowly (p = 1, 3); the Weibull toe's scale likewise, its shape
    1.5 or 3.
    """
    recs = prob.records
    stiff = max(r.scale for r in recs) / prob.bounds.xi_span
    i1 = max(float(np.nanmax(invariants(r.test.mode, r.x)[0])) for r in recs) - 3.0
    i2 = max(float(np.nanmax(invariants(r.test.mode, r.x)[1])) for r in recs) - 3.0
    widths = [prob.bounds.xi_span * q for q in (0.1, 0.25, 0.5, 1.0)]  # of either toe, in stretch
    shapes = {"i2exp_b": [q / max(i2, 1e-9) for q in (0.3, 1.0, 3.0, 10.0)],
              "i1exp_b": [q / max(i1, 1e-9) for q in (0.3, 1.0, 3.0, 10.0)],
              "gent_J": [i1 * q for q in (1.05, 1.5, 3.0, 10.0)],
              "fexp_k2": [q / max((i1 / 3) ** 2, 1e-12) for q in (0.3, 1.0, 3.0, 10.0)],
              "toe_delta": widths,
              "toe_p": [1.0, 3.0],
              "tw_eta": widths,
              "tw_k": [1.5, 3.0]}
    names = TERMS[name].shape_parameters
    return stiff, [dict(zip(names, v)) for v in itertools.product(*(shapes[n] for n in names))]


def _init_term(prob: Problem, z: np.ndarray, name: str) -> np.ndarray:
    """A strain-energy term: grid over decades of its modulus and over its shape parameter."""
    term = TERMS[name]
    stiff, shapes = term_grid(prob, name)
    # from "off" (the current model: the start is never worse than it) to ten times the data's stiffness
    grid = [{term.modulus: stiff * 10.0**e, **v} for e in (-12, -4, -3, -2, -1, 0, 1) for v in shapes]
    return _grid_search_base(prob, z, grid)


def _grid_search_base(prob: Problem, z: np.ndarray, grid) -> np.ndarray:
    """*z* with the elastic-law values of least cost among *grid* (name -> SI value)."""
    best, zb = math.inf, z
    for values in grid:
        zz = prob.params.set_base(z, {None: values, **{d: values for d in (prob.directions or [])}})
        c = prob.objective(zz)
        if c < best:
            best, zb = c, zz
    return zb


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
        c = prob.objective(zz)
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
        st = prob.params.values(zz)
        for i in idx:
            blk, _ = prob.residual_block(prob.slots[i].file, st)
            c = float(blk @ blk)
            if c < best[i][0]:
                best[i] = (c, zz[i])
    z = z.copy()
    for i in idx:
        z[i] = best[i][1]
    return z


def _init_prony(prob: Problem, z: np.ndarray, kappa: float = 0.0) -> np.ndarray:
    """Prony starting values: non-negative least squares over a dictionary of relaxation times."""
    return _prony_nnls(prob, z, kappa)[0]


def _prony_nnls(prob: Problem, z: np.ndarray, kappa: float, kappa_tau: float = 0.0) -> tuple[np.ndarray, float]:
    """*z* with the Prony terms of least squares over a dictionary of relaxation times (the relaxed part
    scaled by exp(kappa (xi - 1)), or the times by exp(-kappa_tau (xi - 1))), and the residual norm of that fit."""
    b = prob.bounds
    n_terms = prob.spec.viscoelastic
    taus = np.geomspace(b.tau_min * 2, b.tau_max / 5, 14)
    system = _relaxation_system(prob, z, taus, kappa, kappa_tau)
    if system is None:
        return z, math.inf
    A, yv = system
    try:
        g, rnorm = optimize.nnls(A, yv, maxiter=50 * A.shape[1])
    except RuntimeError:
        g, rnorm = np.zeros(len(taus)), math.inf
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
    return _set(prob, z, "viscoelastic", vals), float(rnorm)


def _relaxation_system(prob: Problem, z: np.ndarray, taus: np.ndarray, kappa: float = 0.0, kappa_tau: float = 0.0,
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """The weighted linear system (atoms, target) of one Prony term per relaxation time in *taus*.

    Each atom is the relaxation of the softened elastic stress with one unit term
    (scaled by exp(kappa (ξ - 1)) for a stretch-dependent strength; its time
    scaled by exp(-kappa_tau (ξ - 1)) for a stretch-dependent rate); the fitted
    offset columns are projected out, a held offset taken off the data. None where
    no training record has time.
    """
    st = prob.params.values(z)
    cols, target = [], []
    for k, r in enumerate(prob.records):
        if not prob.n_train[k] or r.t is None:
            continue
        idx = r.fit_idx
        sc = st.scale[k] if st.scale is not None else 1.0
        pd = np.nan_to_num(prob.forward.softened(k, st, idx)) * sc
        atoms = np.stack([qlv_stress(r.t[idx], pd, [1.0], [tau]) - pd for tau in taus], axis=1) if not kappa_tau \
            else _rate_atoms(r.t[idx], pd, prob.forward.elastic(k, st)[2], taus, kappa_tau)
        if kappa:
            atoms = atoms * np.exp(kappa * (prob.forward.elastic(k, st)[2] - 1.0))[:, None]
        y = r.y[idx] - pd - (prob.forward.pinned[k] if prob.forward.n_offset[k] and prob.forward.pinned[k] is not None else 0.0)
        pos = prob.train[k]
        if pos is not None:
            atoms, y = atoms[pos], y[pos]
        X = prob.forward.free_offset_columns(k, idx)
        if X is not None:
            if pos is not None:
                X = X[pos]
            Q, _ = np.linalg.qr(X)
            atoms = atoms - Q @ (Q.T @ atoms)
            y = y - Q @ (Q.T @ y)
        w = prob.factor[k] / r.scale
        cols.append(atoms * w)
        target.append(y * w)
    return (np.concatenate(cols), np.concatenate(target)) if cols else None


def _rate_atoms(t: np.ndarray, pd: np.ndarray, xi: np.ndarray, taus: np.ndarray, kappa_tau: float) -> np.ndarray:
    """One unit Prony term per relaxation time in *taus* with stretch-dependent times, less *pd*, shape (n, len(taus))."""
    with np.errstate(invalid="ignore", over="ignore"):
        a, b = qlv_rate_decay(t, taus, xi, kappa_tau)
    return np.stack([qlv_stress(None, pd, [1.0], None, decay=(np.ascontiguousarray(a[:, [j]]),
                                                              np.ascontiguousarray(b[:, [j]]))) - pd
                     for j in range(taus.size)], axis=1)


def _stick_breaking(gs: list[float]) -> list[float]:
    """Prony weights as stick-broken fractions u_j in [1e-3, 0.99] (g_j = u_j prod_{i<j} (1 - u_i))."""
    us, rest = [], 1.0
    for v in gs:
        u = min(max(v / rest, 1e-3), 0.99) if rest > 0 else 0.5
        us.append(u)
        rest *= 1 - u
    return us


def extend_variant(prob: Problem, z: np.ndarray, extra: list[int]) -> np.ndarray:
    """Start the added slots of a richer variant: a small new Prony term far from the others, a small beta,
    a set's exponent at 1 (the simpler variant's); the other form of a stretch-dependent relaxation as a new
    one (:func:`_init_kappa`)."""
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
        elif s.name == "floor":
            z[i] = 0.0  # the damage the simpler variant fitted, which leaves nothing at large stretch
        elif s.name == "exponent":
            z[i] = 1.0  # the proportional set the simpler variant fitted
    if any(prob.slots[i].effect == "nonlinear_viscoelastic" for i in extra):  # another form of it (kappa_tau)
        z = _init_kappa(prob, np.clip(z, prob.lower, prob.upper))
    return np.clip(z, prob.lower, prob.upper)
