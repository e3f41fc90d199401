"""Held-out errors: which data a model is tested on without being fitted to them, and how.

Three fold sets (docs/design/discovery.md, "Held-out data: the folds, and what is refitted"):

* the **material scheme** (:func:`make_folds`), in order of preference: leave one
  loading-rate group out (several strain rates); leave one of five consecutive
  blocks of every file out when the files are different specimens that each
  hold or unload after their first loading; leave one file out (several files
  of a loading mode); leave one cycle out (one file with several cycles, its
  first loading always fitted); leave one of five consecutive blocks of every
  file out. A file is never held out if it is the only one of its loading mode
  (that would test extrapolation between modes, not effects).
* the **artefact scheme** (:func:`artefact_folds`): five consecutive blocks of
  every file, the first loading always fitted, and the samples at rest before
  loading in five blocks of their own. A per-file artefact (slack, grip
  slips, a specimen's stress scale, a load-cell offset and drift) is estimated
  on the training samples *of the same file* and judged on its held-out
  samples (an offset read at rest is read from the fold's training samples at
  rest, :func:`read_pins`); on a held-out file it could only be estimated from
  that file's own data, which the base model has no such freedom to use.
* the **slip scheme** (:func:`slip_folds`, carried by the artefact scheme where
  a record has a grip slip; grip slips alone are judged on it): five
  interleaved sets of short blocks, so that every slip has training samples
  after it in every fold.

Effects and artefacts are judged with the held-out samples of a ramp's blocks that lie above the largest
stretch of the fold's training samples not scored (:meth:`FoldSet.within`): there the elastic law is
extrapolated, which is a strain-energy term's business, judged on every sample.

What a fold refits: every parameter on the fold's training samples; a record
without training samples (a held-out file) keeps its per-file parameters at
their neutral values (no slack, no slip, scale 1, no offset), and so does a
grip slip that no training sample follows: nothing is estimated on held-out
data.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..errors import FitError
from .fitted import Fitted
from .records import Record, rest_reading, rest_samples
from .statistics import Errors, error_measures

#: a fold's refit from the full-data optimum: at most this many evaluations per parameter (plus two) ...
FOLD_NFEV = 5
#: ... to this relative tolerance of the cost
FOLD_FTOL = 1e-5
#: most folds of any held-out scheme
MAX_FOLDS = 5
#: blocks of the block schemes
BLOCKS = 5
#: a record is cut in blocks after its first loading only when at least this many samples follow it
#: (BLOCKS blocks of ten samples or more); else the whole record is cut
MIN_AFTER = 10 * BLOCKS
#: the slip scheme's blocks are at least this many noise correlation lengths long (:func:`slip_folds`)
SLIP_BLOCK_CORRELATIONS = 10


@dataclass
class Fold:
    name: str
    train: list  # per record: None (all fitting samples) or positions (possibly empty)
    test: list  # per record: None (not tested) or a boolean mask over all samples
    #: a block of the block or slip scheme holds out samples above the largest stretch of its record's training
    #: samples (:func:`within_training_stretch`)
    beyond: bool = False
    #: held-out samples above the largest stretch of their record's training samples are not scored
    #: (:func:`within_training_stretch`; :meth:`FoldSet.within`)
    within_training: bool = False


@dataclass
class FoldSet:
    """A held-out scheme: its name (``scheme``), its folds, and the key under which errors are cached."""

    key: str  # "material", "artefact" or "slip"
    scheme: str
    folds: list[Fold]
    #: the artefact scheme's: the folds grip slips are judged on (:func:`slip_folds`), None without slips
    slip: FoldSet | None = None

    def within(self) -> FoldSet:
        """The same folds, their blocks scored within the stretch each fold was fitted to
        (:func:`within_training_stretch`): what an effect or an artefact is judged on. A strain-energy term is
        judged on the folds as they are, where a held-out block above the training's stretch tests how the law
        extrapolates, which is the term's business."""
        slip = self.slip.within() if self.slip is not None else None
        if all(f.within_training == f.beyond for f in self.folds) and slip is self.slip:
            return self
        return FoldSet(self.key + "+within", self.scheme + "; held-out samples above the stretch the fold was "
                       "fitted to not scored", [replace(f, within_training=f.beyond) for f in self.folds], slip)


def artefact_folds(records: Sequence[Record]) -> tuple[str, list[Fold]]:
    """The artefact scheme: five consecutive blocks of every file, the first loading always fitted, and the
    samples read at rest before loading cut in five blocks of their own, one held out in each fold.

    A load cell's offset is read at rest (:func:`~esmm.pipeline.discover.records.rest_reading`), not fitted:
    where those samples lay in the first loading, always fitted (a staircase, a relaxation, cycles), no fold
    held out what shows an offset, and the reading was never checked against data it was not read from. With
    the samples at rest in the blocks, each fold reads the offset from its own training samples at rest
    (:func:`read_pins`) and predicts the held-out ones, where a model without it predicts no force.
    """
    return _block_folds(records, rest=True)


def fold_sets(records: Sequence[Record]) -> tuple[FoldSet, FoldSet]:
    """(material scheme, artefact scheme); one object when both are the block scheme. The artefact
    scheme carries the slip scheme (:func:`slip_folds`) where a record has grip slips."""
    scheme, folds = make_folds(records)
    mat = FoldSet("material", scheme, folds)
    if scheme.startswith("leave one of") and not any(_rest_blocks(r) for r in records):  # the same blocks
        art = mat
    else:
        a_scheme, a_folds = artefact_folds(records)
        art = FoldSet("artefact", a_scheme, a_folds)
    art.slip = slip_folds(records)
    return mat, art


def slip_folds(records: Sequence[Record]) -> FoldSet | None:
    """The slip scheme: leave one of five interleaved sets of short blocks of every file out.

    A slip's extension loss shows only in the samples after it, until the next
    slip: held out in one consecutive block (a slip late in a ramp lies in its
    last block), it could not be estimated from training samples at all
    (:func:`unseen_slip`). Short blocks taken in turn put training samples
    after every slip in every fold, as far as each slip is followed by two
    blocks or more. A block is at least :data:`SLIP_BLOCK_CORRELATIONS` noise
    correlation lengths long (the noise of a held-out block is then nearly
    independent of its neighbours', which the models were fitted to) and a
    fiftieth of the samples after the first loading; a file too short for two
    blocks per fold is cut in five consecutive blocks. None when no record has
    a slip.
    """
    if not any(r.slips for r in records):
        return None
    masks: list[dict[int, np.ndarray]] = [{} for _ in range(BLOCKS)]
    for k, r in enumerate(records):
        n, a = r.test.n, _after_first_loading(r)
        size = max(int(math.ceil(SLIP_BLOCK_CORRELATIONS * max(r.noise.length, 1.0))),
                   int(math.ceil((n - a) / (10 * BLOCKS))))
        pieces = (n - a) // size
        edges = (a + np.linspace(0, n - a, pieces + 1)).round().astype(int) if pieces >= 2 * BLOCKS \
            else (a + np.linspace(0, n - a, BLOCKS + 1)).round().astype(int)
        which = np.arange(edges.size - 1) % BLOCKS
        for j in range(BLOCKS):
            mask = np.zeros(n, bool)
            for i in np.flatnonzero(which == j):
                mask[edges[i]:edges[i + 1]] = True
            masks[j][k] = mask
    folds = [_block_fold(f"blocks {j + 1}, {j + 1 + BLOCKS}, ... of every {BLOCKS}", records, masks[j],
                         blocks=True) for j in range(BLOCKS)]
    return FoldSet("slip", f"leave one of {BLOCKS} interleaved sets of short blocks out", folds)


def make_folds(records: Sequence[Record]) -> tuple[str, list[Fold]]:
    """The held-out scheme and its folds (see the module docstring).

    A file (or rate group) is only held out if every loading mode it has is
    still in the training files: predicting a mode never fitted tests the base
    model's extrapolation between modes, not the effects.
    """
    for scheme in (_rate_folds, _specimen_blocks, _file_folds, _cycle_folds):
        got = scheme(records)
        if got is not None:
            return got
    return _block_folds(records)


def _specimen_blocks(records: Sequence[Record]) -> tuple[str, list[Fold]] | None:
    """Blocks within each file when the files are of different specimens and each goes on after its first loading.

    Predicting a held-out specimen tests the specimen-to-specimen variation as
    much as the effects; where every file holds or unloads after its first
    loading, the effects can be tested within each specimen instead.
    """
    if len(records) < 2 or len({r.specimen for r in records}) < 2:
        return None
    if not all(_after_first_loading(r) for r in records):
        return None
    scheme, folds = _block_folds(records)
    return scheme + " (the files are different specimens)", folds


def _modes_kept(records: Sequence[Record], held: list[int]) -> bool:
    """Whether every loading mode of the *held* records is still among the others."""
    modes = [r.test.mode for r in records]
    rest = {modes[k] for k in range(len(records)) if k not in held}
    return all(modes[k] in rest for k in held)


def _rate_folds(records: Sequence[Record]) -> tuple[str, list[Fold]] | None:
    """Leave one loading-rate group out (rates within a factor 1.5 form a group)."""
    m = len(records)
    rates = [r.cov.loading_rate() for r in records]
    finite = [v for v in rates if math.isfinite(v) and v > 0]
    if m < 2 or len(finite) != m:
        return None
    groups: list[list[int]] = []
    for k in np.argsort(rates):
        if groups and rates[k] / rates[groups[-1][0]] < 1.5:
            groups[-1].append(int(k))
        else:
            groups.append([int(k)])
    if len(groups) < 2 or not all(_modes_kept(records, g) for g in groups):
        return None
    folds = []
    for g in groups[:MAX_FOLDS]:
        name = f"rate {np.median([rates[k] for k in g]):.3g}/s ({len(g)} file{'s' if len(g) > 1 else ''})"
        folds.append(_file_fold(name, records, g))
    return "leave one loading rate out", folds


def _file_folds(records: Sequence[Record]) -> tuple[str, list[Fold]] | None:
    """Leave one file (or one group of files) out, among those whose loading mode has another file."""
    m = len(records)
    eligible = [k for k in sorted(range(m), key=lambda k: records[k].name) if _modes_kept(records, [k])]
    if len(eligible) < 2:
        return None
    nf = min(len(eligible), MAX_FOLDS)
    folds = []
    for j in range(nf):
        g = eligible[j::nf]
        folds.append(_file_fold(", ".join(records[k].name for k in g), records, g))
    scheme = "leave one file out" if nf == len(eligible) else f"leave files out ({nf} groups)"
    if len(eligible) < m:
        scheme += " (files whose loading mode has another file)"
    return scheme, folds


def _cycle_folds(records: Sequence[Record]) -> tuple[str, list[Fold]] | None:
    """Leave one cycle out of a single file with three cycles or more; the first cycle is always fitted.

    The first cycle (the first loading) is what determines the elastic law:
    held out, its prediction would test the law's extrapolation from softened
    cycles, not the effects (a softening from cycle to cycle is then confounded
    with a softer law). Every later cycle is predicted with the history of the
    whole record run through the model.
    """
    if len(records) != 1 or not records[0].history or records[0].cov.n_cycles < 3:
        return None
    r = records[0]
    later = list(range(1, r.cov.n_cycles))
    nf = min(len(later), MAX_FOLDS)
    groups = [later[j::nf] for j in range(nf)]
    folds = [_block_fold(f"cycle {', '.join(str(c + 1) for c in g)}", records, {0: np.isin(r.cov.cycle, g)})
             for g in groups]
    return "leave one cycle out, the first always fitted", folds


def _block_folds(records: Sequence[Record], *, rest: bool = False) -> tuple[str, list[Fold]]:
    """Leave one of five consecutive blocks of every file out (*rest*: the samples at rest too, in five
    blocks of their own, :func:`artefact_folds`).

    The first loading up to a record's largest stretch is what determines the
    elastic law; where the record goes on after it (a hold, an unloading), the
    blocks are cut from what follows and the first loading is always fitted:
    holding it out would test the elastic law's extrapolation, not the effects.
    """
    folds = []
    after = [_after_first_loading(r) for r in records]
    at_rest = [_rest_blocks(r) if rest else 0 for r in records]
    for j in range(BLOCKS):
        masks = {}
        for k, r in enumerate(records):
            n, a, q = r.test.n, after[k], at_rest[k]
            a = max(a, q)
            edges = (a + np.linspace(0, n - a, BLOCKS + 1)).round().astype(int)
            mask = np.zeros(n, bool)
            mask[edges[j]:edges[j + 1]] = True
            if q:
                cut = np.linspace(0, q, BLOCKS + 1).round().astype(int)
                mask[cut[j]:cut[j + 1]] = True
            masks[k] = mask
        folds.append(_block_fold(f"block {j + 1}/{BLOCKS}", records, masks, blocks=True))
    scheme = f"leave one of {BLOCKS} consecutive blocks out" + (" (of every file)" if len(records) > 1 else "")
    if any(after):
        scheme += ", the first loading always fitted"
    if any(at_rest):
        scheme += ", the samples at rest in blocks of their own"
    return scheme, folds


def _rest_blocks(r: Record) -> int:
    """The samples at rest before loading that the artefact scheme cuts in blocks of their own (0: none; a
    record at rest for fewer than two samples per block keeps them where the blocks put them: in its first
    block, or in a first loading always fitted)."""
    n = rest_samples(r)
    return n if n >= 2 * BLOCKS and n < r.test.n - MIN_AFTER else 0


def _after_first_loading(r: Record) -> int:
    """The first sample after the first loading to the record's largest stretch (0: the record is all first
    loading, or the rest is too short to be cut in five blocks, or the first loading is one ramp and the rest
    is shorter than one block of the whole).

    A ramp that ends in a short hold or return is a ramp: judged on its tail
    alone (a twentieth of it, say), a held-out check would see nothing of what
    happened on the way up (a slip, a load cell's offset), where a ramp that
    stops at its peak is cut in blocks over all of it. A first loading that
    holds or turns on its way (a staircase) keeps it fitted: cut in blocks, its
    last step is held out and the law extrapolated there, which a relaxation
    fitted to the law's misfit predicts better on a clean record.
    """
    if not r.history:
        return 0
    k = int(np.argmax(r.cov.drive)) + 1
    rest = r.test.n - k
    if _ramp_to_peak(r) and rest < r.test.n / BLOCKS:
        return 0
    return k if rest >= MIN_AFTER else 0


def _ramp_to_peak(r: Record) -> bool:
    """The record loads to its largest stretch in one run, without a hold or a turn on the way (the peak may
    open a hold)."""
    d = np.asarray(r.cov.direction[:int(np.argmax(r.cov.drive)) + 1])
    moving = np.flatnonzero(d != 0)
    return moving.size > 0 and bool(np.all(d[moving[0]:moving[-1] + 1] == 1))


def _file_fold(name: str, records, held: list[int]) -> Fold:
    train = [np.zeros(0, dtype=int) if k in held else None for k in range(len(records))]
    test = [np.ones(records[k].test.n, bool) if k in held else None for k in range(len(records))]
    return Fold(name, train, test)


def _block_fold(name: str, records, masks: dict[int, np.ndarray], *, blocks: bool = False) -> Fold:
    """Hold out the samples in *masks* (record index -> boolean mask over all its samples); *blocks*: a fold of
    the block or slip scheme, whose held-out samples may lie above its training's stretch (:attr:`Fold.beyond`)."""
    train, test = [], []
    for k, r in enumerate(records):
        mask = masks.get(k)
        if mask is None:
            train.append(None)
            test.append(None)
        else:
            train.append(np.flatnonzero(~mask[r.fit_idx]))
            test.append(mask)
    fold = Fold(name, train, test)
    fold.beyond = blocks and within_training_stretch(records, fold) is not fold
    return fold


def add_predictions(prob, z: np.ndarray, fold: Fold, j: int, out: dict) -> None:
    """Append to *out* ({record: (sample indices, data, predictions, fold numbers)}) the predictions of
    *prob* at *z* on *fold*'s held-out samples, fold *j*."""
    coefs = prob.offsets(z)
    for k, mask in enumerate(fold.test):
        if mask is None:
            continue
        p = prob.full_prediction(k, z, coefs[k])
        idx, ys, ps, fs = out.setdefault(k, ([], [], [], []))
        idx.append(np.flatnonzero(mask))
        ys.append(prob.records[k].y[mask])
        ps.append(p[mask])
        fs.append(np.full(int(mask.sum()), j))


def heldout(fitted: Fitted, folds: Sequence[Fold]) -> Errors:
    """Held-out errors of *fitted*'s model: refit per fold on its training samples, predict what was left out.

    A held-out *file* keeps its per-file parameters neutral (no slack, slip,
    scale or offset is estimated on it); a held-out *block* is predicted with
    the history of its whole file and the per-file parameters estimated on the
    rest of that file. The held-out samples after a grip slip that no training
    sample follows (:func:`unseen_slip`) are not predicted: the slip's loss is
    unknown to the fold, and a model judged there would be judged on how well it
    stands in for the slip. ``samples`` holds, per record index, (sample indices,
    data, prediction, fold number) in time order.
    """
    prob = fitted.problem
    per_file: dict[int, tuple[list, list, list, list]] = {}
    for j, fold in enumerate(folds):
        z, fp = _fold_fit(fitted, fold)
        scored = _before_unseen_slips(fp, fold)
        if fold.within_training:
            scored = within_training_stretch(fp.records, scored)
        add_predictions(fp, z, scored, j, per_file)
    samples = {}
    for k, (idx, ys, ps, fs) in per_file.items():
        i = np.concatenate(idx)
        order = np.argsort(i, kind="stable")
        samples[k] = (i[order], np.concatenate(ys)[order], np.concatenate(ps)[order], np.concatenate(fs)[order])
    items = [(prob.records[k].name, v[1], v[2]) for k, v in sorted(samples.items())]
    spans = [(float(np.min(prob.records[k].y)), float(np.max(prob.records[k].y))) for k in sorted(samples)]
    out = error_measures(items, spans)
    out.samples = samples
    return out


def _before_unseen_slips(prob, fold: Fold) -> Fold:
    """*fold* with each record's held-out samples cut at its first slip that no training sample follows."""
    first: dict[int, int] = {}
    for s in prob.slots:
        if unseen_slip(s, prob.records, fold.train):
            e = prob.records[s.file].slips[int(s.name[5:-1])]
            first[s.file] = min(e, first.get(s.file, e))
    if not first:
        return fold
    test = list(fold.test)
    for k, e in first.items():
        if test[k] is not None:
            test[k] = test[k].copy()
            test[k][e:] = False
            test[k] = test[k] if test[k].any() else None
    return replace(fold, test=test)


def within_training_stretch(records: Sequence[Record], fold: Fold) -> Fold:
    """*fold* with each record's held-out samples above the largest stretch of its training samples left out,
    in records that load to their peak in one ramp (:func:`_ramp_to_peak`) with time and training samples: a
    held-out file is predicted whole, the blocks of a curve without time are cut in the order of its rows, not
    of its loading, and a new peak of cycles to rising peaks is where damage and Mullins softening show.

    Above the largest stretch the fold was fitted to, a held-out sample tests
    how the elastic law extrapolates, not the effect or the artefact judged: on
    a ramp cut in consecutive blocks the last block is all extrapolation, and an
    exponential law's error there can be a hundred times the record's range,
    which no offset or scale of the specimen can show through. Below it every
    law is anchored (no stress at the reference state), and the samples at rest
    before loading, where a load cell's offset shows, stay.
    """
    test = list(fold.test)
    changed = False
    for k, mask in enumerate(test):
        tr, r = fold.train[k], records[k]
        if mask is None or (tr is not None and len(tr) == 0) or not r.history or not _ramp_to_peak(r):
            continue
        idx = r.fit_idx if tr is None else r.fit_idx[np.asarray(tr, dtype=int)]
        top = float(np.max(r.cov.drive[idx]))
        beyond = mask & (r.cov.drive > top + 1e-9 * max(abs(top), 1.0))
        if beyond.any():
            test[k] = mask & ~beyond if (mask & ~beyond).any() else None
            changed = True
    return replace(fold, test=test) if changed else fold


def cached_heldout(fitted: Fitted, fs: FoldSet) -> Errors:
    """:func:`heldout` of *fitted* on the fold set *fs*, computed once (kept in ``fitted.cv``); the
    material scheme's errors are also ``fitted.heldout``."""
    got = fitted.cv.get(fs.key)
    if got is None:
        got = fitted.heldout if fs.key == "material" and fitted.heldout is not None \
            and fitted.heldout.samples is not None else heldout(fitted, fs.folds)
        fitted.cv[fs.key] = got
    if fs.key == "material":
        fitted.heldout = got
    return got


def unseen_slip(s, records: Sequence[Record], train: Sequence) -> bool:
    """Whether slot *s* is a grip slip with no training sample between it and the next slip
    (*train*: per record, None for all its fitting samples, or positions among them).

    A slip's extension loss shows only after it; where no training sample lies
    before the next slip, the training data see its loss only added to the
    next one's, and the split between the two would be the whole record's:
    estimated from held-out samples.
    """
    if s.effect != "grip_slip" or s.file is None:
        return False
    r = records[s.file]
    tr = train[s.file]
    idx = r.fit_idx if tr is None else r.fit_idx[np.asarray(tr, dtype=int)]
    j = int(s.name[5:-1])
    end = r.slips[j + 1] if j + 1 < len(r.slips) else r.test.n
    return not np.any((idx >= r.slips[j]) & (idx < end))


def read_pins(prob, held: Sequence[np.ndarray | None]) -> list[float | None]:
    """Per record of *prob*, the load cell's offset read at rest without the samples *held* (per record: a
    boolean mask over its samples, or None) nor those *prob* may not see (``prob.unread``): the reading of
    every sample at rest where none is held out, 0 (none applied) where every one is."""
    out = []
    for k, r in enumerate(prob.records):
        pin, mask, unread = prob.pinned[k], held[k], prob.unread[k]
        if not prob.forward.n_offset[k] or pin is None or (mask is None and unread is None):
            out.append(pin)
            continue
        mask = unread if mask is None else mask if unread is None else mask | unread
        v = rest_reading(r, held=mask)
        out.append(0.0 if v is None else v)
    return out


def _fold_fit(fitted: Fitted, fold: Fold):
    """The whole model refitted on a fold's training samples (warm start), and that fold's problem.

    The slots that act only on records without training samples (a held-out
    file's slack, slips, specimen scale), and the grip slips that no training
    sample follows (:func:`unseen_slip`), are set to their neutral value (0: no
    slack, no slip, scale e^0 = 1) and not fitted: nothing is estimated on
    held-out data (a slot the training samples do not see would otherwise keep
    the value the whole record gave it). (A held-out file's offset is not
    applied either: offsets are estimated on training samples only.)
    """
    prob = fitted.problem
    fp = prob.derived(train=fold.train, pins=read_pins(prob, fold.test))
    excluded = {k for k, t in enumerate(fold.train) if t is not None and len(t) == 0}

    def own(s) -> bool:
        return bool(s.records) and all(k in excluded for k in s.records)

    z0 = fitted.z.copy()
    mine = [i for i, s in enumerate(fp.slots) if own(s) or unseen_slip(s, fp.records, fold.train)]
    z0[mine] = 0.0
    active = [i for i in range(len(fp.slots)) if i not in set(mine)]
    try:
        z, _ = fp.solve(z0, active=active, max_nfev=FOLD_NFEV * (len(active) + 2), ftol=FOLD_FTOL)
    except FitError:
        z = z0
    return z, fp
