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
the training samples). When the search kept nothing, the selection is not run
again: *before* and *after* are then the base model's held-out error.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import FitError
from ..progress import SILENT
from .fitted import Fitted, finish
from .heldout import Fold, FoldSet, fold_sets
from .model import Problem
from .rounds import run_search
from .state import Criteria, Search
from .statistics import error_measures


class Restricted(Problem):
    """A :class:`~esmm.pipeline.discover.model.Problem` whose objective never uses the samples outside
    *outer* (per record: positions within its fitting samples, None for all, empty for none).

    Every problem derived from it (another spec, a fold's training set) keeps
    the restriction: the training set asked for is intersected with *outer*.
    """

    def __init__(self, *args, outer: Sequence | None = None, **kwargs):
        self.outer = list(outer) if outer is not None else None
        super().__init__(*args, **kwargs)

    def set_train(self, train) -> None:
        super().set_train(_intersect_all(self.outer, train, len(self.records)))

    def derived(self, spec=None, *, train=None) -> Restricted:
        return Restricted(self.base_model, self.records, self.spec if spec is None else spec, fixed=self.fixed,
                          directions=self.directions, bounds=self.bounds, train=train,
                          free_scales=self.free_scales, outer=self.outer)


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
            folds.append(Fold(f.name, train, test))
    return FoldSet(fs.key, fs.scheme, folds)


def _expand(fs: FoldSet, keep: list[int], m: int) -> FoldSet:
    """Folds made on the records *keep* as folds over all *m* records (the others neither fitted nor tested)."""
    folds = []
    for f in fs.folds:
        train: list = [np.zeros(0, dtype=int)] * m
        test: list = [None] * m
        for i, k in enumerate(keep):
            train[k], test[k] = f.train[i], f.test[i]
        folds.append(Fold(f.name, train, test))
    return FoldSet(fs.key, fs.scheme, folds)


def inner_fold_sets(search: Search, outer: Fold, j: int) -> tuple[FoldSet, FoldSet]:
    """The inner selection's (material, artefact) folds for outer fold *j*.

    An outer fold that holds out whole files leaves the inner selection the
    other files: its folds are made on them as a discovery on those files alone
    would make them (:func:`~esmm.pipeline.discover.heldout.fold_sets`: with
    one rate left, blocks or cycles of its files). An outer fold of blocks or
    cycles leaves every file: its inner folds are the other outer folds and
    blocks, without the outer held-out samples.
    """
    records = search.base.problem.records
    m = len(records)
    out_files = [k for k in range(m) if outer.train[k] is not None and len(outer.train[k]) == 0]
    if out_files:
        keep = [k for k in range(m) if k not in out_files]
        mat, art = fold_sets([records[k] for k in keep])
        mat_x = _expand(mat, keep, m)
        return mat_x, (mat_x if art is mat else _expand(art, keep, m))
    mat = inner_folds(search.material, outer, j)
    art = mat if search.artefact is search.material else inner_folds(search.artefact, outer, None)
    return mat, art


def _restricted_base(search: Search, outer: Fold) -> Fitted:
    """The base model refitted on the outer fold's training samples (from its fit on all data)."""
    p = search.base.problem
    prob = Restricted(p.base_model, p.records, p.spec, fixed=p.fixed, directions=p.directions, bounds=p.bounds,
                      free_scales=p.free_scales, outer=outer.train)
    try:
        z, _ = prob.solve(search.base.z.copy())
    except FitError:
        z = search.base.z.copy()
    return finish(prob, z)


def _predict(f: Fitted, outer: Fold, j: int, out: dict) -> None:
    """Predictions of *f* on the outer fold's held-out samples (a held-out file's own slots neutral)."""
    prob = f.problem
    z = f.z.copy()
    empty = {k for k, t in enumerate(prob.train) if t is not None and len(t) == 0}
    for i, s in enumerate(prob.slots):
        if s.records and all(k in empty for k in s.records):
            z[i] = 0.0
    coefs = prob.offsets(z)
    for k, mask in enumerate(outer.test):
        if mask is None:
            continue
        p = prob.full_prediction(k, z, coefs[k])
        idx, ys, ps, fs = out.setdefault(k, ([], [], [], []))
        idx.append(np.flatnonzero(mask))
        ys.append(prob.records[k].y[mask])
        ps.append(p[mask])
        fs.append(np.full(int(mask.sum()), j))


def _errors(records, got: dict):
    items, spans = [], []
    for k in sorted(got):
        idx, ys, ps, _ = got[k]
        order = np.argsort(np.concatenate(idx), kind="stable")
        items.append((records[k].name, np.concatenate(ys)[order], np.concatenate(ps)[order]))
        spans.append((float(np.min(records[k].y)), float(np.max(records[k].y))))
    return error_measures(items, spans)


def nested_heldout(result, search: Search, candidates: Sequence[str], criteria: Criteria, rep) -> dict[str, Any]:
    """The nested held-out errors before and after (module docstring), as a JSON-ready dict.

    Keys: ``scheme``, ``before`` and ``after`` (rmse, nrmse, max_abs, per_file;
    Pa), ``kept_per_fold`` (the names each outer fold's selection kept),
    ``selection_rerun`` (False when nothing was kept and the selection was not
    run again), ``seconds``.
    """
    t0 = time.perf_counter()
    mat = search.material
    records = search.base.problem.records
    if not search.kept:
        base = search.base.cv.get("material") or search.base.heldout
        doc = base.to_dict() if base is not None else None
        return {"scheme": mat.scheme, "before": doc, "after": doc, "kept_per_fold": [], "selection_rerun": False,
                "seconds": 0.0}
    before, after, kept = {}, {}, []
    with rep.task("nested held-out errors: the selection run again inside each outer fold",
                  total=len(mat.folds)) as adv:
        for j, outer in enumerate(mat.folds):
            start = _restricted_base(search, outer)
            inner_mat, inner_art = inner_fold_sets(search, outer, j)
            inner = run_search(start, inner_mat, inner_art, list(records), candidates, criteria, SILENT,
                               warm=search.warm)
            _predict(start, outer, j, before)
            _predict(inner.current, outer, j, after)
            kept.append(list(inner.kept))
            adv(1)
    return {"scheme": mat.scheme, "before": _errors(records, before).to_dict(),
            "after": _errors(records, after).to_dict(), "kept_per_fold": kept, "selection_rerun": True,
            "seconds": time.perf_counter() - t0}


__all__ = ["Restricted", "inner_folds", "nested_heldout"]
