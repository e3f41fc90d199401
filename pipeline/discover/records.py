"""The tests of a discovery prepared for fitting, and what each can show.

:func:`prepare` turns every :class:`~esmm.pipeline.tensile.TensileTest` into a
:class:`Record`: the record is cut at a rupture (what follows a break is not
the material's response), a force channel that lags the stretch is advanced
(:func:`undo_force_lag`), its measurement noise is modelled without a model of
the material (:func:`~esmm.pipeline.tensile.noise.noise_model`), grip slips are
located, the covariates computed and the fitting samples chosen.

The applicability rules of the artefacts (docs/design/discovery.md, "The extended model") live here:
artefacts are corrected on *machine records* only — files with a time column,
as a testing machine writes them. A curve without time (digitised from a
paper, averaged over specimens: Treloar's, Budday's) has been processed
already; its offsets, slack and slips are not in it any more, or cannot be
told from the material law.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from ..calibrate.problem import stress_scale
from ..tensile.data import TensileTest
from ..tensile.events import SLIP_ALPHA, force_lag, rupture_index, slip_events
from ..tensile.noise import Noise, noise_model, quantum
from .covariates import Covariates, covariates, thin
from .statistics import REPLICATION_LEVEL, resolution, segment_mean


def reference(mode: str) -> float:
    """The reference state of a mode's loading variable (stretch 1, shear 0)."""
    return 0.0 if mode == "simple_shear" else 1.0


@dataclass
class Record:
    """One test prepared for fitting: covariates, thinned indices, scales, noise.

    Attributes
    ----------
    test : TensileTest
        The test as used (cut at a rupture).
    cov : Covariates
    fit_idx : ndarray of int, shape (m,)
        Thinned fitting samples.
    weight : float
    cut : dict
        ``{"index", "stretch", "time", "dropped"}`` when the record was cut at a rupture, else empty.
    """

    test: TensileTest
    cov: Covariates
    fit_idx: np.ndarray
    weight: float = 1.0
    cut: dict[str, Any] = field(default_factory=dict)
    #: ``{"seconds", "dropped"}`` when the force channel lagged the stretch and was advanced, else empty
    lag: dict[str, Any] = field(default_factory=dict)
    #: the converter's step of the stress as recorded (before the lag's interpolation moved the readings off
    #: their grid); None: read from :attr:`test`
    raw_quantum: float | None = None

    def __post_init__(self):
        t = self.test
        self.x = np.asarray(t.stretch, float)
        self.y = np.asarray(t.stress, float)
        self.t = None if not self.cov.has_time else np.asarray(t.time, float)
        self.scale = stress_scale(self.y)
        self.range = float(np.ptp(self.y)) or self.scale
        ref = reference(t.mode)
        x0 = float(np.min(self.x)) if t.mode != "simple_shear" else -1.0
        #: a test that never goes below its reference state (tension only)
        self.tension_only = t.mode != "simple_shear" and x0 >= ref - 1e-3 * (float(np.ptp(self.x)) or 1.0)
        self.area = t.metadata.get("area")
        self.gauge = t.metadata.get("gauge_length")
        self.T = float(self.t[-1] - self.t[0]) if self.t is not None else 0.0
        #: the measurement noise of the stress, from the record alone (size [Pa], correlation, quantisation)
        self.noise: Noise = noise_model(self.y, self.t)
        if self.raw_quantum and not self.noise.quantum:
            self.noise = replace(self.noise, quantum=float(self.raw_quantum))
        #: its per-sample standard deviation [Pa]
        self.sigma = self.noise.sigma
        #: samples where the grip slipped (the stretch is shifted from each on)
        self.slips = slip_events(self.x, self.y, self.cov.direction, noise=self.noise) if self.history and self.tension_only else []
        #: a tension record that reads a compressive force beyond its noise (:func:`reads_compression`): the
        #: model may leave it unclamped (``Spec.compression``)
        self.compressive = self.tension_only and reads_compression(self)

    @property
    def name(self) -> str:
        return self.test.source.name

    @property
    def key(self) -> str | None:
        return self.test.orientation

    @property
    def history(self) -> bool:
        return self.cov.has_time

    @property
    def specimen(self) -> str:
        """The specimen id (metadata ``specimen``, else the file stem): files of one specimen share its scale."""
        return str(self.test.specimen or self.test.source.stem)

    def preload(self) -> tuple[float, float, int] | None:
        """(mean, standard deviation, count) of the stress read at rest before loading, or None.

        The samples at the start whose stretch has not left its first value (a
        machine record that starts before the crosshead moves): their stress is
        the load cell's reading at zero force plus noise.
        """
        if not self.history or self.x.size < 3:
            return None
        tol = 1e-9 * (float(np.ptp(self.x)) or 1.0)
        moved = np.flatnonzero(np.abs(self.x - self.x[0]) > tol)
        n = int(moved[0]) if moved.size else self.x.size
        if n < 2:
            return float(self.y[0]), self.sigma, 1
        seg = self.y[:n]
        return float(np.mean(seg)), float(np.std(seg, ddof=1)), n


def prepare(tests: Sequence[TensileTest], *, max_points: int = 600,
            weights: Sequence[float] | None = None) -> list[Record]:
    """Records of *tests*: cut at ruptures, the force's lag behind the stretch taken off, covariates, thinned
    fitting samples, noise."""
    out = []
    for i, t in enumerate(tests):
        t, cut = cut_at_rupture(t)
        cov = covariates(t)
        raw = t
        t, lag = undo_force_lag(t, cov)
        q = None
        if lag:  # the converter's step as recorded: the lag's interpolation moves the readings off their grid
            q = quantum(np.asarray(raw.stress, float))
            cov = covariates(t)
        idx = thin(t, max_points, cov=cov)
        out.append(Record(t, cov, idx, 1.0 if weights is None else float(weights[i]), cut, lag, q))
    return out


def undo_force_lag(t: TensileTest, cov: Covariates) -> tuple[TensileTest, dict[str, Any]]:
    """*t* with its force channel advanced by the lag it shows behind the stretch
    (:func:`~esmm.pipeline.tensile.events.force_lag`), and what was done (empty: no lag).

    The stress at time t is read at t + d (linear interpolation); the samples of
    the last d seconds, which have no stress reading any more, are dropped.
    """
    if t.time is None or t.mode == "simple_shear" or t.n < 8:
        return t, {}
    time_, y = np.asarray(t.time, float), np.asarray(t.stress, float)
    d = force_lag(t.stretch, y, time_, cov.direction)
    if d <= 0:
        return t, {}
    keep = np.flatnonzero(time_ + d <= time_[-1])
    shifted = view_test(t, keep)

    def advance(a):
        return None if a is None else np.interp(time_[keep] + d, time_, np.asarray(a, float))

    out = TensileTest(source=t.source, mode=t.mode, stretch=shifted.stretch, stress=advance(t.stress),
                      time=shifted.time, displacement=shifted.displacement, force=advance(t.force),
                      metadata=t.metadata)
    return out, {"seconds": float(d), "dropped": int(t.n - keep.size)}


def cut_at_rupture(t: TensileTest) -> tuple[TensileTest, dict[str, Any]]:
    """*t* without the samples from its rupture on (:func:`~esmm.pipeline.tensile.events.rupture_index`), and what was cut."""
    if t.time is None:
        return t, {}
    k = rupture_index(t.stretch, t.stress, noise_model(t.stress).sigma)
    if k is None or k < 10:
        return t, {}
    cut = {"index": int(k), "stretch": float(t.stretch[k]), "time": float(t.time[k]),
           "stress_before": float(np.max(t.stress[:k])), "dropped": int(t.n - k)}
    return view_test(t, np.arange(k)), cut


def view_test(test: TensileTest, idx: np.ndarray) -> TensileTest:
    """A TensileTest restricted to the samples *idx*."""
    def sub(a):
        return None if a is None else np.asarray(a)[idx]

    return TensileTest(source=test.source, mode=test.mode, stretch=sub(test.stretch), stress=sub(test.stress),
                       time=sub(test.time), displacement=sub(test.displacement), force=sub(test.force),
                       metadata=test.metadata)


def fitting_view(rec: Record, idx: np.ndarray | None = None) -> TensileTest:
    """The record's test restricted to *idx* (default: its fitting samples)."""
    return view_test(rec.test, rec.fit_idx if idx is None else idx)


# --------------------------------------------------------------------------- applicability
def machine_record(rec: Record) -> bool:
    """A record as a testing machine writes it (with time): the only kind whose artefacts are corrected."""
    return rec.history


def slack_applicable(rec: Record) -> bool:
    """Slack is a tension-test artefact of a machine record that starts at the reference state."""
    if not machine_record(rec) or not rec.tension_only or rec.test.mode == "simple_shear":
        return False
    span = float(np.ptp(rec.x)) or 0.0
    return span > 0 and float(rec.x[0]) - 1.0 <= 0.05 * span


def offset_applicable(rec: Record) -> bool:
    """A load-cell offset is separable in a machine record that reaches the reference state (P_model = 0)."""
    if not machine_record(rec):
        return False
    ref = reference(rec.test.mode)
    span = float(np.ptp(rec.x)) or 1.0
    return float(np.min(np.abs(rec.x - ref))) <= 0.05 * span


def drift_applicable(rec: Record) -> bool:
    """A drift is separable from the material where the zero-force state is seen early *and* late,
    or where the stress rises during a long hold.

    The first is a test that starts and ends near its reference state (a
    load-unload cycle, or a tension test whose slack specimen reads zero force at
    the end). In a relaxation test a falling drift would be indistinguishable
    from slow relaxation; but no material effect of the library raises the
    stress at a held stretch (relaxation only lowers it), so a hold whose stress
    rises is evidence of a drift (:func:`rising_hold`).
    """
    if rec.t is None or rec.T <= 0:
        return False
    ref = reference(rec.test.mode)
    span = float(np.ptp(rec.x)) or 1.0
    near = np.abs(rec.x - ref) <= 0.05 * span
    tn = (rec.t - rec.t[0]) / rec.T
    return bool(np.any(near & (tn <= 0.25)) and np.any(near & (tn >= 0.75))) or rising_hold(rec)


def rising_hold(rec: Record) -> bool:
    """A hold lasting a quarter of the record or more, whose stress rises over its second half
    by more than 5 noise standard deviations (of |stress|: away from zero)."""
    if rec.t is None or rec.T <= 0:
        return False
    d = rec.cov.direction
    for s0, e0 in _holds(d):
        if rec.t[e0 - 1] - rec.t[s0] < 0.25 * rec.T or e0 - s0 < 8:
            continue
        mid = (s0 + e0) // 2
        tt, yy = rec.t[mid:e0], np.abs(rec.y[mid:e0])
        slope = np.polyfit(tt - tt[0], yy, 1)[0]
        if slope * (tt[-1] - tt[0]) > 5.0 * rec.sigma:
            return True
    return False


def _holds(direction: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs where the stretch is held."""
    return [(a, b) for a, b, v in _runs_of(direction) if v == 0]


def _at_rest(rec: Record) -> tuple[float, float, int] | None:
    """:meth:`Record.preload` where the record starts at its reference state, else None."""
    pre = rec.preload()
    span = float(np.ptp(rec.x)) or 1.0
    if pre is None or abs(float(rec.x[0]) - reference(rec.test.mode)) > 1e-3 * span:
        return None
    return pre


def rest_samples(rec: Record) -> int:
    """How many samples the record reads at rest in its reference state before loading (0: none)."""
    pre = _at_rest(rec)
    return 0 if pre is None else pre[2]


def rest_reading(rec: Record, held: np.ndarray | None = None) -> float | None:
    """The stress the load cell read at rest in the reference state before loading (its offset), or None.

    A machine record whose first sample is at the reference state (stretch 1,
    shear 0) starts at zero true force: what the load cell reads there, averaged
    over the samples before the crosshead moves, *is* its offset. It is held,
    not fitted, so an offset can never absorb misfit.

    It is a measurement, so it counts only where it is one: the mean of the
    samples at rest (one sample: its value, its error the record's noise σ) must
    differ from zero beyond its standard error (two-sided
    at :data:`~esmm.pipeline.discover.statistics.REPLICATION_LEVEL`; the variance
    autocorrelation-consistent, :func:`~esmm.pipeline.discover.statistics.segment_mean`,
    plus the converter's quantisation q²/12, which averaging a constant reading
    does not reduce), and reach what the record resolves
    (:func:`~esmm.pipeline.tensile.noise.resolution`). Otherwise the reading is
    the tared zero and 0.0 is returned: under correlated (1/f, filtered) noise
    the mean of a few hundred samples at rest wanders by several noise units, and
    a correction by it shifts every sample; where the elastic law misfits, a
    shift of the right sign predicts held-out samples better by the product of
    the two, whatever the shift's size.

    *held*: a boolean mask over the record's samples; the samples at rest it marks
    are held out and not read (a held-out fold reads the offset from its training
    samples only, :func:`~esmm.pipeline.discover.heldout.artefact_folds`).
    """
    pre = _at_rest(rec)
    if pre is None:
        return None
    mean, _, n = pre
    seg = rec.y[:n]
    if held is not None and np.any(held[:n]):
        seg = seg[~held[:n]]
        if seg.size == 0:  # every reading at rest held out: none to read
            return None
        mean, n = float(np.mean(seg)), seg.size
    if n < 2:  # one reading: its error is the record's noise (its noise model, from all its samples)
        var, dof = rec.sigma ** 2, math.inf
    else:
        _, var, dof = segment_mean(seg)
    se = math.sqrt(var + rec.noise.quantum ** 2 / 12.0)
    p = 2.0 * float(stats.t.sf(abs(mean) / se, dof)) if se > 0 else (0.0 if mean else 1.0)
    if p > REPLICATION_LEVEL or abs(mean) < resolution(rec.y, rec.sigma):
        return 0.0
    return mean


def reads_compression(rec: Record, alpha: float = SLIP_ALPHA) -> bool:
    """The record reads a compressive force beyond its noise: some sample's stress, less the reading at rest
    (the load cell's offset, the mean of the n samples before the crosshead moves, where the record has
    them), is below -z σ √(1 + 1/n), z the normal quantile of *alpha* over the record's samples (Bonferroni:
    a record whose true force never goes below zero is called compressive with probability at most *alpha*
    under white noise).

    Only such a record can tell a specimen that carries compression on the way down from a strip that
    buckles; which of the two it is, the data decide (``Spec.compression``).
    """
    if rec.y.size == 0 or not math.isfinite(rec.sigma) or rec.sigma <= 0:
        return False
    z = float(stats.norm.isf(alpha / rec.y.size))
    pre = _at_rest(rec)
    rest, n = (pre[0], pre[2]) if pre is not None else (0.0, math.inf)
    return bool(np.min(rec.y - rest) < -z * rec.sigma * math.sqrt(1.0 + 1.0 / n))


def slip_applicable(rec: Record) -> bool:
    """Grip slip is corrected where the record shows one (:func:`~esmm.pipeline.tensile.events.slip_events`)."""
    return machine_record(rec) and bool(rec.slips)


def specimen_groups(records: Sequence[Record]) -> list[list[int]]:
    """Record indices grouped by specimen (files of one specimen share a stress scale), in first-seen order."""
    groups: dict[str, list[int]] = {}
    for k, r in enumerate(records):
        groups.setdefault(r.specimen, []).append(k)
    return list(groups.values())


def scale_applicable(records: Sequence[Record]) -> bool:
    """A per-specimen stress scale needs at least two specimens (one scale is the material's modulus).

    Machine records (with time) count their specimens by id, the file stem standing in where the file names
    none (a testing machine writes one file per specimen and test). A processed curve counts only where its
    file names its specimen (metadata ``specimen``): a stress computed on a misstated cross-section is as
    wrong after processing as before, but processed sets often keep one file per loading mode of one
    material (Treloar's, Budday's), and a scale per mode would take up the law's misfit between the modes.
    """
    machine = [r for r in records if r.history]
    named = {str(r.test.metadata["specimen"]) for r in records if r.test.metadata.get("specimen")}
    return len(specimen_groups(machine)) >= 2 or len(named) >= 2


def set_applicable(rec: Record) -> bool:
    """Permanent set shows in a tension record (stretch mode) that unloads towards its reference state."""
    if not rec.history or not rec.tension_only or rec.test.mode == "simple_shear" or not rec.cov.has_unloading:
        return False
    span = float(np.ptp(rec.x)) or 1.0
    after_peak = rec.x[int(np.argmax(rec.x)):]
    return float(np.min(after_peak)) - 1.0 <= 0.5 * span


def reloads_below_max(rec: Record) -> bool:
    """The record loads again below a previous maximum (2 % of the stretch below it or more) after unloading:
    the path down and the path up again between the same stretches, which a rate-independent history (a set,
    Mullins softening) makes coincide and relaxation makes a loop."""
    return rec.history and bool(np.any((rec.cov.direction > 0) & (rec.cov.below_max > 0.02)))


def strain_softening(rec: Record, alpha: float = SLIP_ALPHA) -> bool:
    """While the stretch increases on a loading run, the stress falls below its maximum so far by more than
    the noise can make it, and does not come back: a descending branch that no stable elastic law makes
    (a softening only damage explains).

    "More than the noise can make": the fall exceeds z √2 σ, √2 σ the largest
    standard deviation of the noise's difference across any lag
    (:meth:`~esmm.pipeline.tensile.noise.Noise.difference_sd`) and z the normal
    quantile of *alpha* over the record's samples (Bonferroni: a clean record is
    called softening with probability at most *alpha*). A detected grip slip's
    fall is the slip's (the specimen's stretch falls there, not the stress at a
    rising stretch), and after it the crosshead's stretch is no longer the
    specimen's: the run is judged in its parts between the slips' falls.
    """
    if not rec.tension_only:
        return False
    z = float(stats.norm.isf(alpha / max(rec.y.size, 1)))
    drop = z * math.sqrt(2.0) * rec.sigma
    d = rec.cov.direction
    for s0, e0 in [(a, b) for a, b, v in _runs_of(d) if v > 0]:
        for a, b in _between_slips(rec.y, rec.slips, s0, e0):
            y = rec.y[a:b]
            top = np.maximum.accumulate(y)
            later = np.maximum.accumulate(y[::-1])[::-1]
            if np.any((y < top - drop) & (later < top)):
                return True
    return False


def _between_slips(y: np.ndarray, slips: Sequence[int], s0: int, e0: int) -> list[tuple[int, int]]:
    """The parts of the run [s0, e0) of *y* apart from each slip's fall (from the stress's peak before the
    slip's last sample, *slips*, to that sample: a fall the filter's ringing splits is one), each at least two
    samples long."""
    out, a = [], s0
    for m in sorted(int(v) for v in slips if s0 <= v < e0):
        if m < a:
            continue
        out.append((a, a + int(np.argmax(y[a:m + 1]))))
        a = m + 1
    out.append((a, e0))
    return [(p, q) for p, q in out if q - p >= 2]


def _runs_of(a: np.ndarray) -> list[tuple[int, int, int]]:
    edges = np.flatnonzero(np.diff(a)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [a.size]])
    return [(int(x), int(y), int(a[x])) for x, y in zip(starts, stops)]


def repeated_cycles(rec: Record) -> bool:
    """At least two loading cycles of a timed record reach the same maximum (within 2 % of the span)."""
    if not rec.history or rec.cov.n_cycles < 2:
        return False
    span = float(np.ptp(rec.cov.drive)) or 1.0
    peaks = np.array([float(np.max(rec.cov.drive[rec.cov.cycle == c])) for c in range(rec.cov.n_cycles)])
    d = np.abs(peaks[:, None] - peaks[None, :]) <= 0.02 * span
    return bool(np.any(d.sum(axis=1) >= 2))


def stretch_levels(records: Sequence[Record]) -> int:
    """Distinct levels (within 10 % of the largest span) of the stretch at which the timed records turn or hold."""
    vals = []
    for r in records:
        if not r.history:
            continue
        d = r.cov.direction
        turns = np.flatnonzero(np.diff(d) != 0)
        vals += [float(r.cov.drive[k]) for k in turns] + [float(np.max(r.cov.drive))]
    if not vals:
        return 0
    span = max(float(np.max(r.cov.drive)) - 1.0 for r in records) or 1.0
    levels: list[float] = []
    for v in sorted(vals):
        if v - 1.0 < 0.1 * span:
            continue
        if not levels or v - levels[-1] > 0.1 * span:
            levels.append(v)
    return len(levels)


def largest_span(records: Sequence[Record]) -> float:
    """The largest equivalent-stretch excursion ξ - 1 of any record (at least 1e-3)."""
    return max([float(np.max(r.cov.drive)) - 1.0 for r in records] + [1e-3])


__all__ = ["Record", "prepare", "view_test", "fitting_view", "cut_at_rupture", "reference", "machine_record",
           "slack_applicable", "offset_applicable", "drift_applicable", "rest_reading", "rest_samples", "reads_compression", "slip_applicable", "specimen_groups",
           "scale_applicable", "set_applicable", "strain_softening", "repeated_cycles", "stretch_levels", "largest_span"]
