"""Close the loop: fit the base model, diagnose, add effects greedily, report before and after.

:func:`discover` is the library entry point of ``esmm calibrate --discover``.

Procedure (docs/discover.md):

1. Fit the base model (:func:`esmm.pipeline.calibrate.fit.fit_material`, on
   the thinned fitting samples) and measure its error on every sample, and on
   held-out data.
2. Diagnose the residual (:mod:`.diagnose`): size, serial correlation, runs,
   covariates, and the first-order share of each candidate effect.
3. For every candidate that the data can identify: fit each variant (base +
   kept effects + candidate, all parameters free), take the best variant by
   AICc, and if its AICc beats the current model by at least
   ``aicc_threshold`` run the held-out check. An effect is kept only if both
   the AICc and the held-out error say so; among those that pass, the one with
   the lowest AICc is kept. Repeat with what is left, until nothing passes.
4. Report errors before and after, on the fitting data and held out.

Held-out schemes, in order of preference: leave one loading-rate group out
(several rates), leave one file out (several files of a loading mode), leave
one cycle out (one file with several cycles), leave one of five consecutive
blocks of every file out. A file is never held out if it is the only one of
its loading mode (that would test extrapolation between modes, not effects).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from ..blas import single_threaded_blas
from ..errors import ConfigError, FitError
from ..materials.effects import (
    ARTEFACTS,
    EFFECT_NAMES,
    MATERIAL_EFFECTS,
    MaterialEffects,
    qlv_stress,
)
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from .diagnose import Diagnosis, diagnose
from .model import (
    VARIANTS,
    Bounds,
    Errors,
    Estimate,
    Problem,
    Record,
    Spec,
    error_measures,
    estimates,
    information,
    n_effective,
    offset_applicable,
    prepare,
    slack_applicable,
    view_test,
)

#: default ΔAICc an effect must reach (Burnham & Anderson: > 10 = no support for the simpler model)
AICC_THRESHOLD = -10.0
#: default relative reduction of the held-out NRMSE an effect must reach
MIN_HELDOUT_GAIN = 0.05
#: candidates whose first-order signature explains less of the residual than this are not fitted
MIN_SHARE = 0.005
#: most folds of any held-out scheme
MAX_FOLDS = 6


# --------------------------------------------------------------------------- results
@dataclass
class Fitted:
    """One fitted model: its problem, parameters, information and errors."""

    spec: Spec
    problem: Problem
    z: np.ndarray
    info: dict[str, float]
    errors: Errors  # on all samples of the fitting files
    heldout: Errors | None = None
    estimates: list[Estimate] = field(default_factory=list)

    @property
    def state(self):
        return self.problem.state(self.z)


@dataclass
class Candidate:
    """The verdict on one effect (last round it was tried in)."""

    name: str
    kind: str  # "material" or "artefact"
    round: int = 0
    variant: str = ""
    delta_aicc: float | None = None
    delta_bic: float | None = None
    heldout_nrmse: float | None = None
    heldout_gain: float | None = None
    kept: bool = False
    identifiable: bool = True
    applicable: bool = True
    reason: str = ""
    score: float = 0.0
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "kind": self.kind, "round": self.round, "variant": self.variant,
            "delta_aicc": self.delta_aicc, "delta_bic": self.delta_bic,
            "heldout_nrmse": self.heldout_nrmse, "heldout_gain": self.heldout_gain,
            "kept": self.kept, "identifiable": self.identifiable, "applicable": self.applicable,
            "first_order_share": self.score, "reason": self.reason, "params": self.params,
        }


@dataclass
class Fold:
    name: str
    train: list  # per record: None (all fitting samples) or positions (possibly empty)
    test: list  # per record: None (not tested) or a boolean mask over all samples


@dataclass
class DiscoverResult:
    """Everything :func:`discover` found (see docs/discover.md for the JSON)."""

    model: str
    records: list[Record]
    base: Fitted
    final: Fitted
    kept: list[str]
    candidates: dict[str, Candidate]
    not_identifiable: list[str]
    diagnoses: list[Diagnosis]
    scheme: str
    folds: list[str]
    settings: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    base_fit: Any = None  # the FitResult of the base model

    @property
    def material_effects(self) -> MaterialEffects:
        me = self.final.state.material_effects()
        iv = {e.key: [e.lower, e.upper] for e in self.final.estimates
              if e.key.split(".")[0] in MATERIAL_EFFECTS}
        return MaterialEffects(me.viscoelastic, me.mullins, me.damage, iv)

    @property
    def artefacts(self) -> list[str]:
        return [n for n in self.kept if n in ARTEFACTS]

    def base_params(self, which: str = "final") -> dict[str | None, dict[str, float]]:
        f = self.final if which == "final" else self.base
        return f.state.base


# --------------------------------------------------------------------------- identifiability
def identifiability(records: Sequence[Record]) -> dict[str, tuple[bool, bool, str]]:
    """Can the data show each effect? name -> (applicable, identifiable, reason)."""
    out: dict[str, tuple[bool, bool, str]] = {}
    timed = [r for r in records if r.history]
    rates = sorted({v for r in timed for v in r.cov.rates()})
    several_rates = len(rates) >= 2 and rates[-1] / max(rates[0], 1e-300) >= 1.5
    unloading = any(r.cov.has_unloading for r in timed)
    holds = any(r.cov.has_hold and float(np.nanmax(r.cov.hold_time)) >= 5 * float(np.median(np.diff(r.t)))
                for r in timed)
    below = any(np.any(r.cov.below_max > 0.02) for r in timed)
    if not timed:
        out["viscoelastic"] = (True, False, "not identifiable from these data: no time column, so no rate, "
                               "hold or loading history")
    elif not (several_rates or unloading or holds):
        out["viscoelastic"] = (True, False, "not identifiable from these data: one monotonic ramp at one rate "
                               f"({rates[0] if rates else float('nan'):.3g} /s) cannot separate a rate effect from "
                               "the elastic curve; test at a second rate, or add an unloading or a hold")
    else:
        why = [w for w, ok in (("several rates", several_rates), ("unloading", unloading), ("holds", holds)) if ok]
        out["viscoelastic"] = (True, True, "identifiable: " + ", ".join(why))
    if not timed:
        out["mullins"] = (True, False, "not identifiable from these data: without a time column the row order "
                          "is not a loading history")
    elif not below:
        out["mullins"] = (True, False, "not identifiable from these data: every sample is on the primary "
                          "loading path; Mullins softening shows only on unloading or reloading below a "
                          "previous maximum")
    else:
        out["mullins"] = (True, True, "identifiable: unloading or reloading below a previous maximum")
    spans = [float(r.cov.drive.max()) - 1.0 for r in records]
    if max(spans, default=0.0) < 0.01:
        out["damage"] = (True, False, "not identifiable from these data: the deformation stays below 1 %")
    else:
        out["damage"] = (True, True, "identifiable: the primary loading curve reaches "
                         f"an equivalent stretch of {1 + max(spans):.3g}")
    if any(slack_applicable(r) for r in records):
        out["slack"] = (True, True, "applicable: tension tests from the undeformed state")
    else:
        out["slack"] = (False, False, "not applicable: slack is an artefact of tension tests that start "
                        "from zero displacement; these data have none")
    if any(offset_applicable(r) for r in records):
        out["sensor_offset"] = (True, True, "applicable: the data pass through the undeformed state, where the "
                                "true force is zero")
    else:
        out["sensor_offset"] = (True, False, "not identifiable from these data: no sample near the undeformed "
                                "state, where the true force is known to be zero")
    return out


# --------------------------------------------------------------------------- held-out folds
def make_folds(records: Sequence[Record]) -> tuple[str, list[Fold]]:
    """The held-out scheme and its folds (see the module docstring).

    A file (or rate group) is only held out if every loading mode it has is
    still in the training files: predicting a mode never fitted tests the base
    model's extrapolation between modes, not the effects.
    """
    m = len(records)
    folds: list[Fold] = []
    modes = [r.test.mode for r in records]

    def modes_kept(held: list[int]) -> bool:
        rest = {modes[k] for k in range(m) if k not in held}
        return all(modes[k] in rest for k in held)

    rates = [r.cov.loading_rate() for r in records]
    finite = [v for v in rates if math.isfinite(v) and v > 0]
    if m >= 2 and len(finite) == m:
        order = np.argsort(rates)
        groups: list[list[int]] = []
        for k in order:
            if groups and rates[k] / rates[groups[-1][0]] < 1.5:
                groups[-1].append(int(k))
            else:
                groups.append([int(k)])
        if len(groups) >= 2 and all(modes_kept(g) for g in groups):
            for g in groups[:MAX_FOLDS]:
                name = f"rate {np.median([rates[k] for k in g]):.3g}/s ({len(g)} file{'s' if len(g) > 1 else ''})"
                folds.append(_file_fold(name, records, g))
            return "leave one loading rate out", folds
    eligible = [k for k in sorted(range(m), key=lambda k: records[k].name) if modes_kept([k])]
    if len(eligible) >= 2:
        nf = min(len(eligible), MAX_FOLDS)
        for j in range(nf):
            g = eligible[j::nf]
            folds.append(_file_fold(", ".join(records[k].name for k in g), records, g))
        scheme = "leave one file out" if nf == len(eligible) else f"leave files out ({nf} groups)"
        if len(eligible) < m:
            scheme += " (files whose loading mode has another file)"
        return scheme, folds
    if m == 1 and records[0].history and records[0].cov.n_cycles >= 2:
        r = records[0]
        nc = r.cov.n_cycles
        groups = [list(range(c, nc, min(nc, MAX_FOLDS))) for c in range(min(nc, MAX_FOLDS))]
        for g in groups:
            mask = np.isin(r.cov.cycle, g)
            folds.append(_block_fold(f"cycle {', '.join(str(c + 1) for c in g)}", records, {0: mask}))
        return "leave one cycle out", folds
    for j in range(5):
        masks = {}
        for k, r in enumerate(records):
            n = r.test.n
            edges = np.linspace(0, n, 6).round().astype(int)
            mask = np.zeros(n, bool)
            mask[edges[j]:edges[j + 1]] = True
            masks[k] = mask
        folds.append(_block_fold(f"block {j + 1}/5", records, masks))
    return ("leave one of 5 consecutive blocks out" + (" (of every file)" if m > 1 else "")), folds


def _file_fold(name: str, records, held: list[int]) -> Fold:
    train = [np.zeros(0, dtype=int) if k in held else None for k in range(len(records))]
    test = [np.ones(records[k].test.n, bool) if k in held else None for k in range(len(records))]
    return Fold(name, train, test)


def _block_fold(name: str, records, masks: dict[int, np.ndarray]) -> Fold:
    """Hold out the samples in *masks* (record index -> boolean mask over all its samples)."""
    train, test = [], []
    for k, r in enumerate(records):
        mask = masks.get(k)
        if mask is None:
            train.append(None)
            test.append(None)
        else:
            train.append(np.flatnonzero(~mask[r.fit_idx]))
            test.append(mask)
    return Fold(name, train, test)


# --------------------------------------------------------------------------- fitting helpers
def _fit_spec(spec: Spec, current: Fitted | None, records, model, fixed, directions, bounds,
              *, init_from: Fitted | None = None) -> Fitted:
    """Fit *spec* on all fitting samples, initialised from *current* plus a search for the new effect."""
    prob = Problem(model, records, spec, fixed=fixed, directions=directions, bounds=bounds)
    src = init_from or current
    z0 = prob.transfer(src.problem, src.z) if src is not None else prob.default_z()
    new = [n for n in spec.names() if src is None or not getattr(src.spec, n)]
    for n in new:
        z0 = _initialise(prob, z0, n)
    new_idx = [i for i, s in enumerate(prob.slots) if s.effect in new]
    if src is not None:
        # slots of a richer variant of an effect already present (another Prony term, beta)
        old_keys = {s.key for s in src.problem.slots}
        extra = [i for i, s in enumerate(prob.slots) if s.effect is not None and s.effect not in new
                 and s.file is None and s.key not in old_keys]
        if extra:
            z0 = _extend_variant(prob, z0, extra)
            new_idx += extra
    z, _ = prob.solve(z0)
    return _finish(prob, z)


def _extend_variant(prob: Problem, z: np.ndarray, extra: list[int]) -> np.ndarray:
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


def _finish(prob: Problem, z: np.ndarray) -> Fitted:
    res = prob.fit_residuals(z)
    info = information(res, n_effective(res), prob.n_params())
    errs = full_errors(prob, z)
    return Fitted(prob.spec, prob, z, info, errs)


def full_errors(prob: Problem, z: np.ndarray) -> Errors:
    """Errors of every record on all its samples."""
    coefs = prob.offsets(z)
    items = []
    for k, r in enumerate(prob.records):
        p = prob.full_prediction(k, z, coefs[k])
        items.append((r.name, r.y, p))
    return error_measures(items)


def _grid_eval(prob: Problem, z: np.ndarray) -> float:
    prob.z_full = z
    prob.active = np.zeros(0, dtype=int)
    return prob.cost(np.zeros(0))


def _set(prob: Problem, z: np.ndarray, effect: str, values: Mapping[str, float]) -> np.ndarray:
    z = z.copy()
    for i, s in enumerate(prob.slots):
        if s.effect == effect and s.name in values:
            z[i] = values[s.name]
    return np.clip(z, prob.lower, prob.upper)


def _initialise(prob: Problem, z: np.ndarray, name: str) -> np.ndarray:
    """Starting values of effect *name* with everything else held (grid search / NNLS)."""
    b = prob.bounds
    if name == "viscoelastic":
        return _init_prony(prob, z)
    if name == "mullins":
        best, zb = math.inf, z
        betas = (0.0, 0.5) if prob.spec.mullins == 3 else (0.0,)
        for s in (0.2, 0.5, 0.8):
            for mm in (0.01, 0.05, 0.2, 1.0):
                for be in betas:
                    zz = _set(prob, z, "mullins", {"s": s, "m": math.log(mm * b.w_ref), "beta": be})
                    c = _grid_eval(prob, zz)
                    if c < best:
                        best, zb = c, zz
        return zb
    if name == "damage":
        best, zb = math.inf, z
        for q in (0.2, 0.4, 0.6, 0.8, 0.95):
            for sc in (0.05, 0.2, 0.6):
                for k in (1.5, 3.0):
                    zz = _set(prob, z, "damage", {"onset": 1.0 + q * b.xi_span,
                                                  "scale": math.log(sc * b.xi_span), "shape": k})
                    c = _grid_eval(prob, zz)
                    if c < best:
                        best, zb = c, zz
        return zb
    if name == "slack":
        idx = [i for i, s in enumerate(prob.slots) if s.effect == "slack"]
        if not idx:
            return z
        st = prob.state(z)
        best = {i: (math.inf, z[i]) for i in idx}
        for q in np.linspace(0.0, 1.0, 13):
            zz = z.copy()
            for i in idx:
                zz[i] = prob.lower[i] + q * (prob.upper[i] - prob.lower[i]) * 0.6
            st = prob.state(zz)
            for i in idx:
                k = prob.slots[i].file
                blk, _ = prob._block(k, st)
                c = float(blk @ blk)
                if c < best[i][0]:
                    best[i] = (c, zz[i])
        z = z.copy()
        for i in idx:
            z[i] = best[i][1]
        return z
    return z


def _init_prony(prob: Problem, z: np.ndarray) -> np.ndarray:
    """Prony starting values: non-negative least squares over a dictionary of relaxation times."""
    b = prob.bounds
    n_terms = prob.spec.viscoelastic
    taus = np.geomspace(b.tau_min * 2, b.tau_max / 5, 14)
    st = prob.state(z)
    cols, target = [], []
    for k, r in enumerate(prob.records):
        if not prob.n_train[k] or r.t is None:
            continue
        idx = r.fit_idx
        pd = np.nan_to_num(prob.softened(k, st, idx))
        tt = r.t[idx]
        atoms = np.stack([qlv_stress(tt, pd, [1.0], [tau]) - pd for tau in taus], axis=1)
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
    if not cols:
        return z
    A = np.concatenate(cols)
    yv = np.concatenate(target)
    try:
        g, _ = optimize.nnls(A, yv, maxiter=50 * A.shape[1])
    except RuntimeError:
        g = np.zeros(len(taus))
    order = np.argsort(-g)
    chosen = [j for j in order if g[j] > 0][:n_terms]
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
    # stick-breaking fractions
    us, rest = [], 1.0
    for v in gs:
        u = min(max(v / rest, 1e-3), 0.99) if rest > 0 else 0.5
        us.append(u)
        rest *= 1 - u
    vals = {}
    for j in range(n_terms):
        vals[f"u[{j}]"] = us[j]
        vals[f"tau[{j}]"] = math.log(min(max(ts[j], b.tau_min * 1.01), b.tau_max * 0.99))
    return _set(prob, z, "viscoelastic", vals)


def _best_variant(name, variants, current: Fitted, records, model, fixed, directions, bounds, aicc_threshold,
                  *, upgrade: bool = False):
    """Fit the variants of effect *name* in order; stop when one more term stops paying.

    Returns (fit, info, reference info) of the best variant by AICc, the
    information of both models computed on the candidate's effective sample
    sizes (its residual is the better estimate of the noise's correlation).
    """
    best = None
    prev = None
    for v in variants:
        spec = current.spec.with_(name, v)
        try:
            f = _fit_spec(spec, current, records, model, fixed, directions, bounds,
                          init_from=prev[0] if prev is not None else None)
        except FitError:
            break
        res = f.problem.fit_residuals(f.z)
        nu = n_effective(res)
        inf = information(res, nu, f.problem.n_params())
        ref = information(current.problem.fit_residuals(current.z), nu, current.problem.n_params())
        if prev is not None:
            # the richer variant must beat the simpler one on the same footing
            prev_inf = information(prev[0].problem.fit_residuals(prev[0].z), nu, prev[0].problem.n_params())
            if inf["aicc"] - prev_inf["aicc"] > aicc_threshold:
                break
        if best is None or inf["aicc"] - ref["aicc"] < best[1]["aicc"] - best[2]["aicc"]:
            best = (f, inf, ref)
        if not upgrade and inf["aicc"] - ref["aicc"] > 0 and name != "viscoelastic":
            break  # the simplest variant does not help at all: the richer ones will not either
        prev = (f, inf)
    return best


def _try_pairs(singles, current: Fitted, records, model, fixed, directions, bounds, folds, aicc_threshold,
               min_heldout_gain):
    """When no single effect passes, try two at once (effects that only show together, e.g. slack
    hiding a rate effect). Pairs among the three best single candidates by AICc.

    Returns ((a, b), fit, ΔAICc) of the first pair (best AICc first) that passes both tests, or None.
    """
    pool = sorted((n for n, (f, inf, ref) in singles.items() if math.isfinite(inf["aicc"] - ref["aicc"])),
                  key=lambda n: singles[n][1]["aicc"] - singles[n][2]["aicc"])[:3]
    tried = []
    for i in range(len(pool)):
        for j in range(i + 1, len(pool)):
            a, b = pool[i], pool[j]
            spec = current.spec.with_(a, getattr(singles[a][0].spec, a)).with_(b, getattr(singles[b][0].spec, b))
            try:
                f = _fit_spec(spec, current, records, model, fixed, directions, bounds)
            except FitError:
                continue
            res = f.problem.fit_residuals(f.z)
            nu = n_effective(res)
            inf = information(res, nu, f.problem.n_params())
            ref = information(current.problem.fit_residuals(current.z), nu, current.problem.n_params())
            d = inf["aicc"] - ref["aicc"]
            if math.isfinite(d) and d <= aicc_threshold:
                tried.append(((a, b), f, d))
    for (a, b), f, d in sorted(tried, key=lambda t: t[2]):
        f.heldout = heldout(f, folds)
        gain = 1.0 - f.heldout.nrmse / max(current.heldout.nrmse, 1e-300)
        if gain >= min_heldout_gain:
            return (a, b), f, d
    return None


def heldout(fitted: Fitted, folds: Sequence[Fold]) -> Errors:
    """Held-out errors of *fitted*'s model: refit per fold, predict what was left out.

    Per-test artefact parameters (slack, offsets) of a held-out *file* are
    re-estimated on that file with the material fixed (as ``esmm evaluate``
    does); a held-out *block* keeps those fitted on the rest of its file.
    """
    prob = fitted.problem
    per_file: dict[int, tuple[list, list]] = {}
    for fold in folds:
        fp = Problem(prob.model, prob.records, prob.spec, fixed=prob.fixed, directions=prob.directions,
                     bounds=prob.bounds, train=fold.train)
        excluded = {k for k, t in enumerate(fold.train) if t is not None and len(t) == 0}
        active = [i for i, s in enumerate(fp.slots) if s.file is None or s.file not in excluded]
        try:
            z, _ = fp.solve(fitted.z.copy(), active=active, max_nfev=8 * (len(active) + 2), ftol=1e-5)
        except FitError:
            z = fitted.z.copy()
        held_files = sorted(excluded)
        if held_files:
            # re-estimate the held-out files' own artefacts with the material fixed
            fp.set_train([None if k in excluded else np.zeros(0, dtype=int) for k in range(len(fp.records))])
            own = [i for i, s in enumerate(fp.slots) if s.file in excluded]
            if own:
                z, _ = fp.solve(z, active=own, max_nfev=10 * (len(own) + 2), ftol=1e-5)
        coefs = fp.offsets(z)
        for k, mask in enumerate(fold.test):
            if mask is None:
                continue
            p = fp.full_prediction(k, z, coefs[k])
            ys, ps = per_file.setdefault(k, ([], []))
            ys.append(fp.records[k].y[mask])
            ps.append(p[mask])
    items = [(prob.records[k].name, np.concatenate(v[0]), np.concatenate(v[1])) for k, v in sorted(per_file.items())]
    return error_measures(items)


# --------------------------------------------------------------------------- the loop
def discover(
    tests: Sequence[TensileTest],
    *,
    model: str = "esedf",
    base=None,
    fixed: Mapping[str, float] | None = None,
    free: Sequence[str] = (),
    weights: Mapping[str, float] | Sequence[float] | None = None,
    n_starts: int = 4,
    seed: int = 0,
    max_points: int = 400,
    candidates: Sequence[str] = EFFECT_NAMES,
    aicc_threshold: float = AICC_THRESHOLD,
    min_heldout_gain: float = MIN_HELDOUT_GAIN,
    max_effects: int = 4,
    min_share: float = MIN_SHARE,
    reporter: Reporter | None = None,
) -> DiscoverResult:
    """Find what the base model misses in *tests*, add it, and report before and after.

    Parameters
    ----------
    tests : sequence of TensileTest
        The data (any modes; raw or processed; with or without time).
    model : str
        The base model (``esedf``, ``arruda-boyce``).
    base : FitResult, optional
        A base fit already made (its parameters start the base fit here).
    fixed : mapping, optional
        Base parameters held (SI), as ``--fix``.
    free : sequence of str
        Base parameters the model holds by default to fit anyway, as ``--free``.
    weights : mapping or sequence, optional
        Per-file weights, as the calibrate fit.
    n_starts, seed : int
        Starting points of the base fit.
    max_points : int
        Fitting samples per file (thinned; errors use all samples).
    candidates : sequence of str
        Effects to consider (names of :data:`~esmm.pipeline.materials.effects.EFFECT_NAMES`).
    aicc_threshold : float
        An effect must lower the AICc by at least this much (negative number).
    min_heldout_gain : float
        ... and lower the held-out NRMSE by at least this fraction.
    max_effects : int
        Stop after this many effects.
    min_share : float
        Candidates whose first-order signature explains less than this share
        of the residual are rejected without a fit.
    reporter : Reporter, optional

    Returns
    -------
    DiscoverResult
    """
    with single_threaded_blas():
        return _discover(tests, model=model, base=base, fixed=fixed, free=free, weights=weights, n_starts=n_starts,
                         seed=seed, max_points=max_points, candidates=candidates,
                         aicc_threshold=aicc_threshold, min_heldout_gain=min_heldout_gain,
                         max_effects=max_effects, min_share=min_share, reporter=reporter)


def _discover(tests, *, model, base, fixed, free, weights, n_starts, seed, max_points, candidates, aicc_threshold,
              min_heldout_gain, max_effects, min_share, reporter) -> DiscoverResult:
    from ..calibrate.fit import _directions, _weights, fit_material
    from ..materials import MODEL_NAMES, get_model

    rep = ensure(reporter)
    t_start = time.perf_counter()
    if not tests:
        raise FitError("no tensile data to analyse; give at least one file")
    if model not in MODEL_NAMES:
        raise ConfigError(f"--model: unknown model {model!r}; choose one of {', '.join(MODEL_NAMES)}")
    bad = [c for c in candidates if c not in EFFECT_NAMES]
    if bad:
        raise ConfigError(f"unknown effect {bad[0]!r}; the effects are {', '.join(EFFECT_NAMES)}")
    if not aicc_threshold < 0:
        raise ConfigError(f"aicc_threshold must be negative, got {aicc_threshold}")
    if not 0 <= min_heldout_gain < 1:
        raise ConfigError(f"min_heldout_gain must be in [0, 1), got {min_heldout_gain}")
    if max_points < 20:
        raise ConfigError(f"max_points must be at least 20, got {max_points}")
    m = get_model(model)
    w = _weights(tests, weights)
    directions = _directions(tests)
    records = prepare(tests, max_points=max_points, weights=w)

    # 1. base fit on the thinned samples
    rep.step(f"discover: {len(tests)} file(s), {sum(t.n for t in tests)} samples, "
             f"{sum(r.fit_idx.size for r in records)} used for fitting")
    views = [view_test(r) for r in records]
    init = None
    if base is not None:
        init = dict(base.params)
    base_fit = fit_material(views, model=model, n_starts=n_starts, seed=seed, fixed=fixed, free=tuple(free),
                            weights=w, initial=init)
    free = {e.name for e in base_fit.estimates}
    fixed_all = {k: v for k, v in base_fit.params.items() if k not in free}
    fixed_all.update(fixed or {})
    base_params = {None: dict(base_fit.params)}
    if base_fit.directions:
        base_params.update({d: dict(p) for d, p in base_fit.directions.items()})
    # data-derived bounds of the effect parameters
    from ..materials.loading import energy_density

    w_ref = 0.0
    for r in records:
        p = base_params.get(r.key if directions else None, base_params[None])
        with np.errstate(all="ignore"):
            wv = np.asarray(energy_density(m, p, r.test.mode, r.x[r.fit_idx]), float)
        if np.any(np.isfinite(wv)):
            w_ref = max(w_ref, float(np.nanmax(wv[np.isfinite(wv)])))
    bounds = Bounds(records, w_ref or 1.0)
    bprob = Problem(m, records, Spec(), fixed=fixed_all, directions=directions, bounds=bounds)
    z0 = bprob.set_base(bprob.default_z(), base_params)
    z, _ = bprob.solve(z0)
    current = _finish(bprob, z)
    scheme, folds = make_folds(records)
    with rep.task("held-out check of the base model", total=1) as adv:
        current.heldout = heldout(current, folds)
        adv(1)
    current.estimates = estimates(bprob, current.z)
    base_f = current
    rep.step(f"base {model}: RMSE {current.errors.rmse:.4g} Pa, NRMSE {current.errors.nrmse:.2%}, "
             f"held-out NRMSE {current.heldout.nrmse:.2%} ({scheme})")

    ident = identifiability(records)
    cands: dict[str, Candidate] = {}
    for n in EFFECT_NAMES:
        applicable, ok, why = ident[n]
        c = Candidate(n, "material" if n in MATERIAL_EFFECTS else "artefact", identifiable=ok,
                      applicable=applicable)
        if n not in candidates:
            c.reason = "not considered (excluded by the caller)"
        elif not applicable or not ok:
            c.reason = why
        cands[n] = c
    testable = [n for n in candidates if ident[n][0] and ident[n][1]]
    kept: list[str] = []
    diagnoses: list[Diagnosis] = []
    upgrades: list[str] = []
    rnd = 0
    while True:
        rnd += 1
        remaining = [n for n in testable if n not in kept]
        diag = diagnose(current.problem, current.z, candidates=remaining, errors=current.errors)
        diagnoses.append(diag)
        upgradable = [n for n in kept if getattr(current.spec, n) < max(VARIANTS[n])]
        if (not remaining and not upgradable) or len(kept) >= max_effects:
            break
        order = [x for x in diag.ranking if x in remaining] + [x for x in remaining if x not in diag.ranking]
        trials: list[tuple[str, Fitted, dict, dict]] = []  # (name, fit, info, ref info)
        singles: dict[str, tuple[Fitted, dict, dict]] = {}  # every candidate fitted this round
        with rep.task(f"round {rnd}: trying {', '.join(order + [u + ' (more terms)' for u in upgradable])}",
                      total=len(order) + len(upgradable)) as adv:
            for n in order:
                c = cands[n]
                c.round, c.score = rnd, diag.scores.get(n, 0.0)
                if c.score < min_share:
                    why = (f"its first-order signature explains {100 * c.score:.2f} % of the residual "
                           f"(less than {100 * min_share:.1f} %)")
                    if c.delta_aicc is not None or c.reason.startswith("rejected:"):
                        # keep the verdict of the round in which it was fitted
                        c.reason = f"{c.reason.split('; in round')[0]}; in round {rnd}, after {', '.join(kept)}, {why}"
                    else:
                        c.delta_aicc = c.delta_bic = c.heldout_nrmse = c.heldout_gain = None
                        c.reason = f"rejected without a fit: {why}"
                    adv(1)
                    continue
                got = _best_variant(n, VARIANTS[n], current, records, m, fixed_all, directions, bounds,
                                    aicc_threshold)
                adv(1)
                if got is None:
                    c.reason = "the fit with this effect failed"
                    continue
                f, inf, ref = got
                if n == "sensor_offset":
                    bad = _offset_inconsistent(f)
                    if bad:
                        c.variant = f.spec.variant_text(n)
                        c.delta_aicc = inf["aicc"] - ref["aicc"]
                        c.delta_bic = inf["bic"] - ref["bic"]
                        c.params = _effect_params(f, n)
                        c.heldout_nrmse = c.heldout_gain = None
                        c.reason = ("rejected: " + bad + "; the offset compensates for misfit instead of "
                                    "correcting the load cell")
                        continue
                c.variant = f.spec.variant_text(n)
                c.delta_aicc = inf["aicc"] - ref["aicc"]
                c.delta_bic = inf["bic"] - ref["bic"]
                c.params = _effect_params(f, n)
                c.heldout_nrmse = c.heldout_gain = None
                singles[n] = (f, inf, ref)
                if not math.isfinite(c.delta_aicc):
                    c.delta_aicc = None
                    c.reason = "rejected: the information criterion could not be computed for this fit"
                elif c.delta_aicc > aicc_threshold:
                    c.reason = (f"rejected: AICc {c.delta_aicc:+.1f} (needs {aicc_threshold:+.0f} or less): "
                                "the improvement does not pay for the extra parameters")
                else:
                    c.reason = f"AICc {c.delta_aicc:+.1f}; held-out check pending"
                    trials.append((n, f, inf, ref))
            for n in upgradable:
                nxt = [v for v in VARIANTS[n] if v > getattr(current.spec, n)]
                got = _best_variant(n, nxt, current, records, m, fixed_all, directions, bounds, aicc_threshold,
                                    upgrade=True)
                adv(1)
                if got is None:
                    continue
                f, inf, ref = got
                if math.isfinite(inf["aicc"] - ref["aicc"]) and inf["aicc"] - ref["aicc"] <= aicc_threshold:
                    trials.append((n, f, inf, ref))
        # held-out check, best AICc first; the first that passes is kept
        trials.sort(key=lambda t: t[2]["aicc"] - t[3]["aicc"])
        winner = None
        for n, f, inf, ref in trials:
            f.heldout = heldout(f, folds)
            gain = 1.0 - f.heldout.nrmse / max(current.heldout.nrmse, 1e-300)
            d_aicc = inf["aicc"] - ref["aicc"]
            if n in kept:  # a variant upgrade of a kept effect
                if gain >= min_heldout_gain:
                    winner = n
                    upgrades.append(f"round {rnd}: {n} extended to {f.spec.variant_text(n)} (AICc {d_aicc:+.1f}, "
                                    f"held-out NRMSE {current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%})")
                    break
                continue
            c = cands[n]
            c.heldout_nrmse, c.heldout_gain = f.heldout.nrmse, gain
            if gain < min_heldout_gain:
                c.reason = (f"rejected: AICc {d_aicc:+.1f} favours it but the held-out NRMSE goes "
                            f"{current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%} ({-gain:+.1%}; needs "
                            f"-{min_heldout_gain:.0%} or better): it does not predict data it was not fitted to")
                continue
            winner = n
            break
        for n, _f, inf, ref in trials:  # candidates never reached by the held-out check this round
            c = cands[n]
            if n != winner and n not in kept and c.reason.endswith("pending"):
                c.reason = (f"AICc {inf['aicc'] - ref['aicc']:+.1f}, but {winner} explained more in round {rnd}; "
                            "tried again after it")
        if winner is None and len(kept) + 2 <= max_effects:
            pair = _try_pairs(singles, current, records, m, fixed_all, directions, bounds, folds,
                              aicc_threshold, min_heldout_gain)
            if pair is not None:
                (a, b), f, d_aicc = pair
                for n, other in ((a, b), (b, a)):
                    c = cands[n]
                    c.kept = True
                    c.variant = f.spec.variant_text(n)
                    c.heldout_nrmse = f.heldout.nrmse
                    c.heldout_gain = 1.0 - f.heldout.nrmse / max(current.heldout.nrmse, 1e-300)
                    kind = "corrected in the data" if n in ARTEFACTS else "added to the material"
                    c.reason = (f"kept ({kind}) in round {rnd} together with {other}: neither alone passed, "
                                f"together AICc {d_aicc:+.1f} and held-out NRMSE {current.heldout.nrmse:.2%} -> "
                                f"{f.heldout.nrmse:.2%}")
                rep.step(f"round {rnd}: kept {a} and {b} together: NRMSE {current.errors.nrmse:.2%} -> "
                         f"{f.errors.nrmse:.2%}, held-out {current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
                kept += [a, b]
                current = f
                continue
        if winner is None:
            break
        f = next(t[1] for t in trials if t[0] == winner)
        if winner in kept:
            rep.step(upgrades[-1])
            current = f
            continue
        c = cands[winner]
        c.kept = True
        kind = "corrected in the data" if winner in ARTEFACTS else "added to the material"
        c.reason = (f"kept ({kind}) in round {rnd}: AICc {c.delta_aicc:+.1f}, held-out NRMSE "
                    f"{current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
        rep.step(f"round {rnd}: kept {winner} ({c.variant}): NRMSE {current.errors.nrmse:.2%} -> "
                 f"{f.errors.nrmse:.2%}, held-out {current.heldout.nrmse:.2%} -> {f.heldout.nrmse:.2%}")
        kept.append(winner)
        current = f
    # final estimates and the verdicts of the effects not kept
    current.estimates = estimates(current.problem, current.z)
    for n in kept:
        cands[n].params = _effect_params(current, n)
        cands[n].variant = current.spec.variant_text(n)
        for u in upgrades:
            if f": {n} extended" in u:
                cands[n].reason += f"; {u.split(': ', 1)[1]}"
    # a confound the data cannot resolve: on a single monotonic ramp, damage and relaxation look alike
    if "damage" in kept and not cands["viscoelastic"].identifiable and any(r.history for r in records):
        cands["damage"].reason += (
            "; caution: with one monotonic ramp at one rate, damage cannot be told from rate-dependent "
            "relaxation (which is not identifiable here); an unloading-reloading cycle or a second rate "
            "would tell them apart")
    not_ident = [n for n in EFFECT_NAMES if cands[n].applicable and not cands[n].identifiable]
    warnings = [f"{e.key} is not identifiable from these data: 95 % interval [{e.lower:.4g}, {e.upper:.4g}]"
                for e in current.estimates if e.wide and e.key.split(".")[0] in MATERIAL_EFFECTS]
    settings = {"max_points": max_points, "criterion": "AICc", "aicc_threshold": aicc_threshold,
                "min_heldout_gain": min_heldout_gain, "n_starts": n_starts, "seed": seed,
                "candidates": list(candidates), "bounds": bounds.to_dict(), "fixed": fixed_all,
                "directions": directions}
    result = DiscoverResult(
        model=m.name, records=records, base=base_f, final=current, kept=kept, candidates=cands,
        not_identifiable=not_ident, diagnoses=diagnoses, scheme=scheme, folds=[f.name for f in folds],
        settings=settings, warnings=warnings, seconds=time.perf_counter() - t_start, base_fit=base_fit,
    )
    rep.step(f"discover: kept {', '.join(kept) or 'nothing'}; NRMSE {base_f.errors.nrmse:.2%} -> "
             f"{current.errors.nrmse:.2%}, held-out {base_f.heldout.nrmse:.2%} -> {current.heldout.nrmse:.2%} "
             f"({result.seconds:.1f} s)")
    return result


def _noise_sd(y: np.ndarray) -> float:
    """Robust standard deviation of white measurement noise (MAD of first differences / sqrt 2)."""
    d = np.diff(np.asarray(y, float))
    d = d[np.isfinite(d)]
    if d.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _offset_inconsistent(f: Fitted) -> str:
    """Why a fitted load-cell offset contradicts the force read before loading ('' if it does not).

    Where a record starts at rest in the reference state, its first sample *is*
    a reading of the offset (the true force is zero): the fitted offset at the
    start must agree with it within 5 noise standard deviations (and 1 % of
    the file's stress scale).
    """
    coefs = f.problem.offsets(f.z)
    for k, r in enumerate(f.problem.records):
        c = coefs[k]
        if c is None:
            continue
        ref = 0.0 if r.test.mode == "simple_shear" else 1.0
        span = float(np.ptp(r.x)) or 1.0
        if abs(float(r.x[0]) - ref) > 1e-3 * span or not r.history:
            continue
        sd = _noise_sd(r.y)
        tol = 5.0 * sd + 0.01 * r.scale
        if abs(float(c[0]) - float(r.y[0])) > tol:
            unit, fac = ("N", r.area) if r.area else ("Pa", 1.0)
            return (f"in {r.name} it needs an offset of {float(c[0]) * fac:+.3g} {unit} at the start, but the "
                    f"load cell read {float(r.y[0]) * fac:+.3g} {unit} there before loading (noise "
                    f"{sd * fac:.2g} {unit})")
    return ""


def _effect_params(f: Fitted, name: str) -> dict[str, Any]:
    """The fitted parameters of effect *name* in *f* (values only; intervals in the final model)."""
    st = f.state
    if name == "viscoelastic" and st.g is not None:
        return {"g": [float(v) for v in st.g], "tau": [float(v) for v in st.tau],
                "g_inf": float(max(0.0, 1 - float(np.sum(st.g))))}
    if name == "mullins" and st.mullins is not None:
        return dict(zip(("r", "m", "beta"), map(float, st.mullins)))
    if name == "damage" and st.damage is not None:
        return dict(zip(("onset", "scale", "shape"), map(float, st.damage)))
    if name == "slack" and st.slack is not None:
        out = {}
        for k, r in enumerate(f.problem.records):
            if any(s.effect == "slack" and s.file == k for s in f.problem.slots):
                d = float(st.slack[k])
                out[r.name] = {"delta": d, "length_m": d * r.gauge if r.gauge else None}
        return out
    if name == "sensor_offset":
        coefs = f.problem.offsets(f.z)
        out = {}
        for k, r in enumerate(f.problem.records):
            c = coefs[k]
            if c is None:
                continue
            o = float(c[0])  # data = model + offset (what the load cell reads at zero force)
            d = float(c[1]) / (r.T or 1.0) if len(c) > 1 else 0.0
            out[r.name] = {"stress_Pa": o, "drift_Pa_per_s": d,
                           "force_N": o * r.area if r.area else None,
                           "drift_N_per_s": d * r.area if r.area else None}
        return out
    return {}
