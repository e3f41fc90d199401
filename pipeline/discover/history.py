r"""Is a history effect's improvement history? The test against every elastic law at once.

A material history effect (relaxation, Mullins softening, damage, cyclic
softening, a permanent set) changes the predicted stress in two ways: as a
function of the stretch alone, which a different elastic law could also do,
and as a function of the path (a hold that relaxes, an unloading below the
loading, a reload below the previous maximum, a peak that falls from cycle to
cycle), which no elastic law can do. The held-out test
(:func:`~esmm.pipeline.discover.statistics.heldout_test`) asks whether the
candidate predicts better; where the base law is not the material's (a tendon's
fibre recruitment, which no term of the library draws exactly), a history
effect fitted to the elastic misfit predicts held-out data of the same protocol
better too, and is kept for what is an elastic law's error.

:func:`history_test` asks the other question: does the part of the candidate's
signature that no function of the stretch can give explain the part of the
residual that no function of the stretch can give? With e the current model's
residual (data − model) and d the candidate's change of the prediction, both
on every sample, and P the least-squares projection onto smooth functions of
the specimen's stretch (the crosshead's less the slips and the slack the current
model holds; a cubic spline of :data:`KNOTS` intervals over the stretch range,
one per loading mode and direction, shared by the files: one material has one
elastic law), a = e − Pe and b = d − Pd are the path-dependent parts. Under the
null "nothing depends on the path", a is measurement noise (any elastic misfit
is a function of the stretch and is projected out) and S = Σ a·b has mean 0.
Its variance is heteroskedasticity- and autocorrelation-consistent per record
(:func:`~esmm.pipeline.discover.statistics.segment_mean`) on the products
(a − βb)·b, β = S/Σb² the regression coefficient (so that under the
alternative the effect itself does not count as noise): filtered noise counts
as the fewer independent samples it is; 1/f noise whose correlation outlasts
the estimator's window makes the p-value optimistic. The one-sided p of
T = S/se(S) (Student's t, Welch–Satterthwaite degrees of freedom over the
records) is judged at the replication check's level, and the largest
path-dependent change the data support, max |βb|, must reach the record's
resolution (:func:`~esmm.pipeline.tensile.noise.resolution`, as the held-out
test's size): an acquisition chain can leave a path dependence of its own (a
force channel's delay left after its correction), significant on many samples
but below what the machine resolves.

A record that never returns to a stretch it has passed (one ramp at one rate)
carries no path information: b vanishes there and so does its weight, so a
history effect is not kept on such records alone. The one exception is damage
where a loading run softens: a stress that falls beyond the noise while the
stretch rises (:func:`~esmm.pipeline.discover.records.strain_softening`) is a
function of the stretch, but of none that a stable elastic law gives, so damage
is not subject to the test there (:func:`applies`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import interpolate, stats

from .fitted import Fitted
from .records import Record, strain_softening
from .statistics import resolution, segment_mean

#: the material effects subject to the test: each changes the stress along the path, not only with the stretch
HISTORY = ("viscoelastic", "nonlinear_viscoelastic", "mullins", "damage", "cyclic_softening", "permanent_set")
#: intervals of the cubic spline in stretch that stands for every elastic law: an elastic law's stress is smooth
#: on a twentieth of the stretch range, and more intervals only make the test stricter (more is called elastic)
KNOTS = 24


def applies(names: Sequence[str], records: Sequence[Record]) -> bool:
    """Does the test judge a candidate (or a pair) whose effects are *names*?

    Damage is not judged where a record's loading softens (the module's docstring).
    """
    judged = [n for n in names if n in HISTORY]
    if judged == ["damage"] and any(r.history and strain_softening(r) for r in records):
        return False
    return bool(judged)


def history_test(current: Fitted, candidate: Fitted) -> dict[str, float]:
    """The path-dependent part of *candidate*'s change against that of *current*'s residual, on every sample.

    Returns
    -------
    dict
        As :func:`path_dependence`.
    """
    prob = current.problem
    e, d = _changes(current, candidate)
    return path_dependence(prob.specimen_stretches(current.z), e, d, ranges=[r.range for r in prob.records],
                           groups=[(r.test.mode, r.key) for r in prob.records],
                           resolutions=[resolution(r.y, r.sigma) for r in prob.records])


def path_dependence(x: Sequence[np.ndarray], e: Sequence[np.ndarray], d: Sequence[np.ndarray], *,
                    ranges: Sequence[float], groups: Sequence[Any],
                    resolutions: Sequence[float] | None = None) -> dict[str, float]:
    """Does the path-dependent part of a change *d* explain that of a residual *e*? (The module's docstring.)

    Parameters
    ----------
    x, e, d : sequences of ndarray, one per record, each of shape (n_k,) in time order
        The stretch, the residual (data − model) and the change of the prediction; NaN where not predicted.
    ranges : sequence of float
        Each record's stress range (every record counts alike).
    groups : sequence of hashable
        Records of one group share one elastic law (a loading mode and direction).
    resolutions : sequence of float, optional
        What each record resolves [Pa] (:func:`~esmm.pipeline.tensile.noise.resolution`); default its range
        (``peak_resolutions`` then reads in ranges).

    Returns
    -------
    dict
        ``p`` (one-sided), ``t``, ``dof``; ``share``: the fraction of the
        change's sum of squares that depends on the path; ``peak_resolutions``:
        the largest path-dependent change the data support, max |β b| with β
        the regression of a on b, in resolutions of its record.
    """
    members: dict[Any, list[int]] = {}
    for k, g in enumerate(groups):
        members.setdefault(g, []).append(k)
    total = float(sum(np.nansum(np.asarray(dk, float) ** 2) for dk in d))
    parts: list[tuple[np.ndarray, np.ndarray, float, int]] = []  # (a, b, weight, record) per record
    for ks in members.values():
        a, b = _path_parts([x[k] for k in ks], [e[k] for k in ks], [d[k] for k in ks],
                           [1.0 / max(ranges[k], 1e-300) for k in ks])
        parts += [(ak, bk, 1.0 / max(ranges[k], 1e-300) ** 2, k) for ak, bk, k in zip(a, b, ks) if bk.size >= 2]
    path = sum(float(bk @ bk) for _, bk, _, _ in parts)
    # the regression of a on b; its score's variance from what the regression leaves (u), so that under the
    # alternative the effect itself does not count as noise
    sab = sum(w * float(ak @ bk) for ak, bk, w, _ in parts)
    sbb = sum(w * float(bk @ bk) for _, bk, w, _ in parts)
    beta = sab / sbb if sbb > 0 else 0.0
    var = ws_den = 0.0
    res = list(resolutions) if resolutions is not None else list(ranges)
    peak = max((abs(beta) * float(np.max(np.abs(bk))) / max(res[k], 1e-300) for _, bk, _, k in parts), default=0.0)
    for ak, bk, w, _ in parts:
        _, v, nu = segment_mean((ak - beta * bk) * bk)
        c = (w * bk.size) ** 2 * v
        var += c
        ws_den += c * c / nu
    dof = var * var / ws_den if ws_den > 0 else 1.0
    if var > 0 and math.isfinite(var):
        t = sab / math.sqrt(var)
        p = float(stats.t.sf(t, max(dof, 1.0)))
    else:
        t, p = (math.inf, 0.0) if sab > 0 else (0.0, 1.0)
    return {"p": p, "t": float(t), "dof": float(dof), "share": path / total if total > 0 else 0.0,
            "peak_resolutions": float(peak)}


def _changes(current: Fitted, candidate: Fitted) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per record: the current residual (data − model) and the change of the prediction (candidate −
    current), on every sample of the problem's training data; NaN elsewhere and where either model does not
    predict. A fold's problem (the nested selections') sees none of the samples it holds out."""
    p0, p1 = current.problem, candidate.problem
    c0, c1 = p0.offsets(current.z), p1.offsets(candidate.z)
    e, d = [], []
    for k, r in enumerate(p0.records):
        train = _training_samples(r.fit_idx, p0.train[k], r.y.size)
        if not train.any():
            e.append(np.full(r.y.size, np.nan))
            d.append(np.full(r.y.size, np.nan))
            continue
        m0 = p0.full_prediction(k, current.z, c0[k])
        m1 = p1.full_prediction(k, candidate.z, c1[k])
        good = train & np.isfinite(m0) & np.isfinite(m1) & np.isfinite(r.y)
        e.append(np.where(good, r.y - m0, np.nan))
        d.append(np.where(good, m1 - m0, np.nan))
    return e, d


def _training_samples(fit_idx: np.ndarray, positions, n: int) -> np.ndarray:
    """Which of a record's *n* samples belong to a training set given as *positions* within its fitting
    samples *fit_idx* (None: all): a fitting sample's own, and every sample between two training ones."""
    if positions is None:
        return np.ones(n, dtype=bool)
    pos = np.asarray(positions, dtype=int)
    m = fit_idx.size
    if not pos.size or not m:
        return np.zeros(n, dtype=bool)
    infit = np.zeros(m, dtype=bool)
    infit[pos] = True
    j = np.searchsorted(fit_idx, np.arange(n), side="right") - 1  # the fitting sample at or before each
    before = infit[np.clip(j, 0, m - 1)]
    after = infit[np.clip(j + 1, 0, m - 1)]
    exact = (j >= 0) & (fit_idx[np.clip(j, 0, m - 1)] == np.arange(n))
    return np.where(exact, before, np.where(j < 0, after, np.where(j + 1 >= m, before, before & after)))


def _path_parts(xs: list[np.ndarray], es: list[np.ndarray], ds: list[np.ndarray], ws: list[float]
                ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """e − Pe and d − Pd on one group's records (finite samples only, in time order), P the least-squares
    projection onto one cubic spline in stretch shared by the group, each file weighted by its range."""
    keep = [np.isfinite(e) & np.isfinite(d) & np.isfinite(x) for x, e, d in zip(xs, es, ds)]
    x = np.concatenate([xk[m] for xk, m in zip(xs, keep)])
    if x.size < 2 * (KNOTS + 3):
        return [np.zeros(0)] * len(xs), [np.zeros(0)] * len(xs)
    lo, hi = float(x.min()), float(x.max())
    if hi <= lo:
        return [np.zeros(0)] * len(xs), [np.zeros(0)] * len(xs)
    inner = np.linspace(lo, hi, KNOTS + 1)
    knots = np.concatenate([[lo] * 3, inner, [hi] * 3])
    basis = interpolate.BSpline.design_matrix(np.clip(x, lo, hi), knots, 3).toarray()
    e = np.concatenate([ek[m] for ek, m in zip(es, keep)])
    d = np.concatenate([dk[m] for dk, m in zip(ds, keep)])
    w = np.concatenate([np.full(int(m.sum()), wk) for wk, m in zip(ws, keep)])[:, None]
    rhs = np.column_stack([e, d])
    coef, *_ = np.linalg.lstsq(basis * w, rhs * w, rcond=None)
    rest = rhs - basis @ coef
    out_a, out_b, i = [], [], 0
    for m in keep:
        n = int(m.sum())
        out_a.append(rest[i:i + n, 0])
        out_b.append(rest[i:i + n, 1])
        i += n
    return out_a, out_b


__all__ = ["HISTORY", "KNOTS", "applies", "history_test", "path_dependence"]
