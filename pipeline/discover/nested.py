"""Nested held-out errors: the whole selection run again inside each outer fold.

The held-out errors that decide each candidate were used to choose the model:
reported as the model's error on new data they are optimistic (the winner of
several comparisons is, on average, luckier than it will be next time). The
errors reported *before* and *after* a discovery are nested instead
(:func:`nested_heldout`):

* the **outer folds** are the material scheme's folds (:mod:`.heldout`);
* inside each, the base model is refitted on the outer fold's training samples
  only, and the **whole selection** — rounds, pre-screen, held-out tests on the
  inner folds (:func:`inner_fold_sets`), the family-wise levels, pairs,
  backward elimination — runs on those samples alone (:class:`Restricted`: no
  objective, diagnosis or inner fold ever sees an outer held-out sample);
* the model it chose predicts the outer fold's held-out samples, a held-out
  file with its per-file artefacts neutral (as in :mod:`.heldout`).

*before* is the base model refitted on each outer training set, *after* the
model each inner selection chose; both pool every outer fold's held-out
samples. Which candidates each outer fold kept is reported (a selection that
keeps different things in different folds is less certain than one that
keeps the same).

What the inner selections share with the full search: each record's noise
model, rupture cut, slips and covariates (properties of the record, not of
the model), the identifiability of the candidates (the protocol), and warm
starts (a candidate's fit starts from its fit on all data, then converges on
the training samples). For their cost they fit :data:`NESTED_POINTS`
samples per file (the errors use every sample), and the outer folds run in
parallel processes where the machine has the cores. When the search kept
nothing, the selection is not run again: *before* and *after* are then the
base model's held-out error.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..blas import single_threaded_blas, usable_cores
from ..errors import FitError
from ..progress import SILENT
from .fitted import Fitted, finish
from .heldout import Fold, FoldSet, add_predictions, fold_sets, read_pins, unseen_slip
from .model import Problem, Spec
from .records import prepare
from .rounds import run_search
from .state import Criteria, Search
from .statistics import error_measures

#: fitting samples per file of the inner selections (the full search's, if fewer)
NESTED_POINTS = 200


class Restricted(Problem):
    """A :class:`~esmm.pipeline.discover.model.Problem` whose objective never uses the samples outside
    *outer* (per record: positions within its fitting samples, None for all, empty for none).

    Every problem derived from it (another spec, a fold's training set) keeps
    the restriction: the training set asked for is intersected with *outer*.
    """

    def __init__(self, *args, outer: Sequence | None = None, unread: Sequence | None = None, **kwargs):
        self.outer = list(outer) if outer is not None else None
        super().__init__(*args, **kwargs)
        if unread is not None:  # the outer fold's held-out samples: no offset is read from them
            self.unread = list(unread)
            self.pinned = read_pins(self, [None] * len(self.records))

    def set_train(self, train) -> None:
        super().set_train(_intersect_all(self.outer, train, len(self.records)))

    def derived(self, spec=None, *, train=None, pins=None) -> Restricted:
        new = Restricted(self.base_model, self.records, self.spec if spec is None else spec, fixed=self.fixed,
                         directions=self.directions, bounds=self.bounds, train=train,
                         free_scales=self.free_scales, outer=self.outer, unread=self.unread)
        if pins is not None:
            new.pinned = list(pins)
        return new


def _intersect(a, b):
    """Positions in both *a* and *b* (None: all)."""
    if a is None:
        return None if b is None else np.asarray(b, dtype=int)
    if b is None:
        return np.asarray(a, dtype=int)
    return np.intersect1d(np.asarray(a, dtype=int), np.asarray(b, dtype=int))


def _intersect_all(outer, train, m: int) -> list | None:
    if outer is None:
        return train
    train = [None] * m if train is None else list(train)
    return [_intersect(o, t) for o, t in zip(outer, train)]


def inner_folds(fs: FoldSet, outer: Fold, skip: int | None) -> FoldSet:
    """The folds of *fs* restricted to *outer*'s training samples (fold *skip*, the outer fold itself, dropped);
    folds left without a held-out sample are dropped."""
    folds = []
    for j, f in enumerate(fs.folds):
        if j == skip:
            continue
        train = [_intersect(o, t) for o, t in zip(outer.train, f.train)]
        test = []
        for k, mask in enumerate(f.test):
            keep = None if mask is None else mask & ~outer.test[k] if outer.test[k] is not None else mask
            test.append(keep if keep is not None and keep.any() else None)
        if any(t is not None for t in test):
            folds.append(replace(f, train=train, test=test))
    slip = inner_folds(fs.slip, outer, None) if fs.slip is not None else None
    return FoldSet(fs.key, fs.scheme, folds, slip)


def _expand(fs: FoldSet, keep: list[int], m: int) -> FoldSet:
    """Folds made on the records *keep* as folds over all *m* records (the others neither fitted nor tested)."""
    folds = []
    for f in fs.folds:
        train: list = [np.zeros(0, dtype=int)] * m
        test: list = [None] * m
        for i, k in enumerate(keep):
            train[k], test[k] = f.train[i], f.test[i]
        folds.append(replace(f, train=train, test=test))
    return FoldSet(fs.key, fs.scheme, folds, _expand(fs.slip, keep, m) if fs.slip is not None else None)


def inner_fold_sets(ctx: _Context, outer: Fold, j: int) -> tuple[FoldSet, FoldSet]:
    """The inner selection's (material, artefact) folds for outer fold *j*.

    An outer fold that holds out whole files leaves the inner selection the
    other files: its folds are made on them as a discovery on those files alone
    would make them (:func:`~esmm.pipeline.discover.heldout.fold_sets`: with
    one rate left, blocks or cycles of its files). An outer fold of blocks or
    cycles leaves every file: its inner folds are the other outer folds and
    blocks, without the outer held-out samples.
    """
    records = ctx.base.problem.records
    m = len(records)
    out_files = [k for k in range(m) if outer.train[k] is not None and len(outer.train[k]) == 0]
    if out_files:
        keep = [k for k in range(m) if k not in out_files]
        mat, art = fold_sets([records[k] for k in keep])
        mat_x = _expand(mat, keep, m)
        return mat_x, (mat_x if art is mat else _expand(art, keep, m))
    mat = inner_folds(ctx.material, outer, j)
    art = mat if ctx.artefact is ctx.material else inner_folds(ctx.artefact, outer, None)
    return mat, art


@dataclass
class _Context:
    """What every outer fold's selection shares: the records (thinned to :data:`NESTED_POINTS`), the base
    model on them, the outer folds, the warm starts, the candidates and criteria."""

    base: Fitted
    material: FoldSet
    artefact: FoldSet
    warm: dict
    candidates: tuple[str, ...]
    criteria: Criteria


def _context(search: Search, candidates: Sequence[str], criteria: Criteria) -> _Context:
    """The records thinned to :data:`NESTED_POINTS` fitting samples, and the base model on them."""
    full = search.base.problem
    points = max(min(NESTED_POINTS, max(r.fit_idx.size for r in full.records)), 20)
    records = prepare([r.test for r in full.records], max_points=points, weights=[r.weight for r in full.records])
    prob = Problem(full.base_model, records, Spec(), fixed=full.fixed, directions=full.directions,
                   bounds=full.bounds)
    base = finish(prob, prob.params.transfer(full.params, search.base.z))
    material, artefact = fold_sets(records)
    return _Context(base, material, artefact, search.warm, tuple(candidates), criteria)


def _restricted_base(ctx: _Context, outer: Fold) -> Fitted:
    """The base model refitted on the outer fold's training samples (from its fit on all data)."""
    p = ctx.base.problem
    prob = Restricted(p.base_model, p.records, p.spec, fixed=p.fixed, directions=p.directions, bounds=p.bounds,
                      free_scales=p.free_scales, outer=outer.train, unread=outer.test)
    try:
        z, _ = prob.solve(ctx.base.z.copy())
    except FitError:
        z = ctx.base.z.copy()
    return finish(prob, z)


def _outer(ctx: _Context, j: int) -> tuple[dict, dict, list[str]]:
    """Outer fold *j*: the base refitted and the whole selection run on its training samples; their
    predictions of its held-out samples, and what the selection kept."""
    outer = ctx.material.folds[j]
    start = _restricted_base(ctx, outer)
    inner_mat, inner_art = inner_fold_sets(ctx, outer, j)
    inner = run_search(start, inner_mat, inner_art, list(ctx.base.problem.records), ctx.candidates, ctx.criteria,
                       SILENT, warm=ctx.warm)
    before, after = {}, {}
    _predict(start, outer, j, before)
    _predict(inner.current, outer, j, after)
    return before, after, list(inner.kept)


#: the context of the outer folds run in forked worker processes (set by :func:`_run_folds` before forking)
_SHARED: _Context | None = None


def _worker(j: int):
    with single_threaded_blas():
        return _outer(_SHARED, j)


def _run_folds(ctx: _Context, rep) -> list[tuple[dict, dict, list[str]]]:
    """Every outer fold, in worker processes where the process may use more than one core (forked: they share
    the context without copying it), else one after the other. The cores counted are those this process may
    run on (its affinity), so a run confined to one core by its caller (a batch's or a benchmark's jobs) does
    not fork."""
    global _SHARED
    n = len(ctx.material.folds)
    workers = min(n, usable_cores())
    with rep.task("nested held-out errors: the selection run again inside each outer fold", total=n) as adv:
        if workers > 1 and "fork" in multiprocessing.get_all_start_methods():
            _SHARED = ctx
            try:
                with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
                    out = []
                    for got in pool.map(_worker, range(n)):
                        out.append(got)
                        adv(1)
                    return out
            finally:
                _SHARED = None
        out = []
        for j in range(n):
            out.append(_outer(ctx, j))
            adv(1)
        return out


def _predict(f: Fitted, outer: Fold, j: int, out: dict) -> None:
    """Predictions of *f* on the outer fold's held-out samples (a held-out file's own slots, and the slips no
    training sample follows, neutral)."""
    prob = f.problem
    z = f.z.copy()
    empty = {k for k, t in enumerate(prob.train) if t is not None and len(t) == 0}
    for i, s in enumerate(prob.slots):
        if (s.records and all(k in empty for k in s.records)) or unseen_slip(s, prob.records, prob.train):
            z[i] = 0.0
    add_predictions(prob, z, outer, j, out)


def _errors(records, got: dict):
    items, spans = [], []
    for k in sorted(got):
        idx, ys, ps, _ = got[k]
        order = np.argsort(np.concatenate(idx), kind="stable")
        items.append((records[k].name, np.concatenate(ys)[order], np.concatenate(ps)[order]))
        spans.append((float(np.min(records[k].y)), float(np.max(records[k].y))))
    return error_measures(items, spans)


def nested_heldout(search: Search, candidates: Sequence[str], criteria: Criteria, rep) -> dict[str, Any]:
    """The nested held-out errors before and after (module docstring), as a JSON-ready dict.

    Keys: ``scheme``, ``before`` and ``after`` (rmse, nrmse, max_abs, per_file;
    Pa), ``kept_per_fold`` (the names each outer fold's selection kept),
    ``selection_rerun`` (False when nothing was kept and the selection was not
    run again), ``fitting_samples`` (per file, of the inner selections),
    ``seconds``.
    """
    t0 = time.perf_counter()
    mat = search.material
    if not search.kept:
        base = search.base.cv.get("material") or search.base.heldout
        doc = base.to_dict() if base is not None else None
        return {"scheme": mat.scheme, "before": doc, "after": doc, "kept_per_fold": [], "selection_rerun": False,
                "seconds": 0.0}
    ctx = _context(search, candidates, criteria)
    before, after, kept = {}, {}, []
    for b, a, k in _run_folds(ctx, rep):
        for src, dst in ((b, before), (a, after)):
            for rec, parts in src.items():
                got = dst.setdefault(rec, ([], [], [], []))
                for lst, new in zip(got, parts):
                    lst += new
        kept.append(k)
    records = ctx.base.problem.records
    return {"scheme": ctx.material.scheme, "before": _errors(records, before).to_dict(),
            "after": _errors(records, after).to_dict(), "kept_per_fold": kept, "selection_rerun": True,
            "fitting_samples": [int(r.fit_idx.size) for r in records], "seconds": time.perf_counter() - t0}


__all__ = ["Restricted", "inner_folds", "nested_heldout"]
