"""Fitting a candidate against the current model, the pre-screen, and the held-out test that decides.

A :class:`Trial` is a candidate model (current model + one candidate, every
parameter refitted) with

* its **pre-screen** (:func:`~esmm.pipeline.discover.statistics.noise_test`):
  the fitted improvement in units of the measurement noise, each record's χ²
  divided by its noise's autocorrelation time at the fitting samples' spacing;
  a candidate that cannot pay for its parameters on the data it was fitted to
  is not checked further. It decides nothing;
* once checked, its **held-out test**
  (:func:`~esmm.pipeline.discover.statistics.heldout_test`): a one-sided
  p-value of "the candidate predicts held-out data no better", from a
  heteroskedasticity- and autocorrelation-consistent statistic, and the size
  of the improvement in squared resolutions (the larger of the noise and the
  force channel's accuracy). The search keeps a candidate when the p-value is
  below the level its family-wise control gives it (:mod:`.levels`) and the
  size is at least :data:`MIN_RESOLUTION_UNITS`.

Material effects and strain-energy terms are judged on the material scheme's
folds, per-file artefacts on the artefact scheme's (:mod:`.heldout`). AICc
and BIC on effective sample sizes are computed for the report; they decide
nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import FitError
from ..materials.effects import ARTEFACTS
from ..materials.terms import TERMS
from .fitted import Fitted, fit_spec
from .heldout import FoldSet, cached_heldout
from .model import ALTERNATIVE_VARIANTS, Spec
from .records import drift_applicable, offset_applicable, rest_reading
from .statistics import (
    REPLICATION_LEVEL,
    HeldoutSegment,
    heldout_test,
    information,
    n_effective,
    noise_test,
    resolution,
)

#: a candidate must lower the held-out mean squared error by at least this many squared resolutions per sample
#: (:func:`~esmm.pipeline.discover.statistics.heldout_test`: the larger of the noise and the force accuracy)
MIN_RESOLUTION_UNITS = 1.0


@dataclass
class Trial:
    """A candidate model of one round and how it compares with the current model."""

    name: str
    fit: Fitted
    noise: dict[str, float]  # the pre-screen against the current model
    info: dict[str, float]
    ref: dict[str, float]  # the current model's AICc/BIC, on the candidate's effective sample sizes
    heldout: dict[str, Any] = field(default_factory=dict)  # heldout_test, once checked
    #: the simplest variant of the same candidate that passed the pre-screen, when this richer one was chosen
    #: over it: checked on held-out data when this one fails there (it does not condemn what it contains)
    fallback: Trial | None = None

    @property
    def dbic(self) -> float:
        """Noise-referenced BIC difference (negative: the fitted improvement pays for the parameters)."""
        return self.noise["dbic"]

    @property
    def d_aicc(self) -> float:
        return self.info["aicc"] - self.ref["aicc"]

    @property
    def d_bic(self) -> float:
        return self.info["bic"] - self.ref["bic"]

    @property
    def screened(self) -> bool:
        """The pre-screen passed: the fitted improvement pays for the parameters."""
        return math.isfinite(self.dbic) and self.dbic < 0

    def summary(self) -> dict[str, Any]:
        return {"dchi2": self.noise["dchi2"], "penalty": self.noise["penalty"], "dbic_noise": self.dbic,
                "delta_aicc": self.d_aicc, "delta_bic": self.d_bic, **{f"heldout_{k}": v for k, v in
                                                                        self.heldout.items()}}


def sigmas(f: Fitted) -> list[float]:
    return [r.sigma for r in f.problem.records]


def noise_taus(f: Fitted) -> list[float]:
    """Per record: the integrated autocorrelation time of its noise at its fitting samples' median spacing."""
    out = []
    for r in f.problem.records:
        m = float(np.median(np.diff(r.fit_idx))) if r.fit_idx.size > 1 else 1.0
        out.append(r.noise.tau(m))
    return out


def compared(name: str, f: Fitted, current: Fitted) -> Trial:
    """*f* against *current*: the pre-screen, and AICc/BIC on *f*'s effective sample sizes (for the report)."""
    res1 = f.problem.fit_residuals(f.z)
    res0 = current.problem.fit_residuals(current.z)
    dk = f.problem.n_params() - current.problem.n_params()
    nu = n_effective(res1)
    return Trial(name, f, noise_test(res0, res1, sigmas(f), dk, noise_taus(f)),
                 information(res1, nu, f.problem.n_params()), information(res0, nu, current.problem.n_params()))


def best_variant(name: str, variants, current: Fitted, *, upgrade: bool = False,
                 warm: Mapping[Any, Fitted] | None = None) -> Trial | None:
    """Fit the variants of *name* in order; a richer variant must pay for its parameters against the simpler.

    Each fit starts from the fit of the same spec in *warm* when there is one
    (the full search's, for an inner selection), else from the previous variant.
    Alternative variants (:data:`~esmm.pipeline.discover.model.ALTERNATIVE_VARIANTS`: as many
    parameters, neither containing the other) are each fitted from the current model, and none is
    skipped because another does not pay. Returns the best variant by the pre-screen (None if no fit
    succeeded), with the simplest variant that passed the pre-screen as its :attr:`Trial.fallback` when
    that is another (of alternatives, the other form that passed it: the form that fits the training data
    best may be the one that takes up an elastic misfit there and fails on held-out data).
    """
    alternatives = name in ALTERNATIVE_VARIANTS
    best: Trial | None = None
    prev: Trial | None = None
    simplest: Trial | None = None
    for v in variants:
        spec = current.spec.with_(name, v)
        if prev is not None and prev.fit.spec.compression and not alternatives:
            spec = replace(spec, compression=1)  # a richer relaxation keeps the simpler one's choice
        start = (warm or {}).get(spec) or (prev.fit if prev is not None and not alternatives else None)
        try:
            t = _clamp_or_not(name, spec, current, start, warm)
        except FitError:
            if alternatives:
                continue
            break
        f = t.fit
        if prev is not None and not alternatives and compared(name, f, prev.fit).dbic >= 0:
            break
        if best is None or t.dbic < best.dbic:
            best = t
        if t.screened and (simplest is None or (alternatives and simplest is best)):
            simplest = t  # of alternatives: a screened form other than the best, when there is one
        if not upgrade and not alternatives and t.dbic > 0 and name not in ("viscoelastic", "sensor_offset"):
            break  # the simplest variant does not pay: the richer ones will not either
        prev = t
    if best is not None and simplest is not None and simplest is not best:
        best.fallback = simplest
    return best


def adds_nothing(name: str, variant: int, current: Fitted) -> bool:
    """Is *name* in *variant* the current model itself? A load cell's offset on records whose readings at
    rest are all the tared zero (:func:`~esmm.pipeline.discover.records.rest_reading`) is held at zero on
    every record it corrects; without a drift (variant 1, or no record where a drift can be told:
    :func:`~esmm.pipeline.discover.records.drift_applicable`) it has no parameter and changes no
    prediction. Fitted all the same, it can only land elsewhere than the current fit, by the optimiser's
    path, and whatever it "gains" so is the current model's own (a clean pull to failure kept such an
    offset, held out 1.41 → 0.60 %, with every offset at 0 Pa)."""
    if name != "sensor_offset" or current.spec.sensor_offset:
        return False
    corrected = [r for r in current.problem.records if offset_applicable(r)]
    if not corrected or any(rest_reading(r) != 0.0 for r in corrected):
        return False
    return variant == 1 or not any(drift_applicable(r) for r in corrected)


def _clamp_or_not(name: str, spec: Spec, current: Fitted, start: Fitted | None,
                  warm: Mapping[Any, Fitted] | None) -> Trial:
    """*spec* fitted as it is and, for a relaxation (plain or stretch-dependent) proposed where a tension record
    reads compression and the model still clamps it, also unclamped (``Spec.compression``): the trial whose
    fit pays better (BIC). Both have the same parameters; what differs is whether the specimen carries the
    compression that its record reads on the way down, or buckles. The choice is the relaxation's own: other
    candidates are fitted with the model's clamp as it is, so that no gain of a flipped clamp is credited to
    them. Raises FitError when the spec as it is fails."""
    t = compared(name, fit_spec(spec, current, init_from=start), current)
    if name not in ("viscoelastic", "nonlinear_viscoelastic") or spec.compression \
            or not any(r.compressive for r in current.problem.records):
        return t
    other = replace(spec, compression=1)
    try:
        u = compared(name, fit_spec(other, current, init_from=(warm or {}).get(other) or t.fit), current)
    except FitError:
        return t
    return u if u.dbic < t.dbic else t


def judged_on(names: str | list[str], material: FoldSet, artefact: FoldSet) -> FoldSet:
    """The fold set a candidate is judged on: the artefact scheme when every name is a per-file artefact,
    its slip scheme for grip slips alone; scored within the stretch each fold was fitted to
    (:meth:`~esmm.pipeline.discover.heldout.FoldSet.within`) unless a strain-energy term is among them."""
    names = [names] if isinstance(names, str) else names
    if artefact.slip is not None and all(n == "grip_slip" for n in names):
        fs = artefact.slip
    else:
        fs = artefact if all(n in ARTEFACTS for n in names) else material
    return fs if any(n in TERMS for n in names) else fs.within()


def check_heldout(t: Trial, current: Fitted, fs: FoldSet) -> dict[str, Any]:
    """The held-out test of *t* against *current* on the fold set *fs* (fills and returns ``t.heldout``)."""
    e0 = cached_heldout(current, fs)
    e1 = cached_heldout(t.fit, fs)
    t.heldout = {**heldout_test(segments(t.fit, e0, e1)), "scheme": fs.scheme, "fold_set": fs.key}
    return t.heldout


def passes(h: dict[str, Any], level: float, min_units: float = MIN_RESOLUTION_UNITS) -> bool:
    """The decision: the noise test's p-value at most *level*, the replication check's at most
    :data:`~esmm.pipeline.discover.statistics.REPLICATION_LEVEL`, and the improvement at least *min_units*
    squared resolutions (:func:`failing_checks` empty)."""
    return bool(h) and not failing_checks(h, level, min_units)


def failing_checks(h: dict[str, Any], level: float, min_units: float = MIN_RESOLUTION_UNITS) -> list[str]:
    """The checks of the held-out test *h* that fail at *level* and *min_units*, each in words (a NaN fails)."""
    out = []
    if not h["p"] <= level:
        out.append(f"beyond the noise p {h['p']:.2g} > {level:.2g}")
    if not h["p_replication"] <= REPLICATION_LEVEL:
        out.append(f"replicated across the held-out segments p {h['p_replication']:.2g} > {REPLICATION_LEVEL:g}")
    if not h["resolution_units"] >= min_units:
        out.append(f"{h['resolution_units']:.3g} squared resolutions per sample < {min_units:g}")
    return out


def segments(f: Fitted, e0, e1) -> list[HeldoutSegment]:
    """The held-out segments (one fold's contiguous held-out samples of one record) of two models' errors."""
    out = []
    a, b = e0.samples or {}, e1.samples or {}
    for k, (idx0, y0, p0, fold0) in a.items():
        if k not in b:
            continue
        idx1, _, p1, _ = b[k]
        _, i0, i1 = np.intersect1d(idx0, idx1, return_indices=True)
        idx, y, q0, q1, fold = idx0[i0], y0[i0], p0[i0], p1[i1], fold0[i0]
        r = f.problem.records[k]
        res = resolution(r.y, r.sigma)
        cuts = np.flatnonzero((np.diff(idx) > 1) | (np.diff(fold) != 0)) + 1
        for part in np.split(np.arange(idx.size), cuts):
            if part.size:
                out.append(HeldoutSegment(r.name, y[part], q0[part], q1[part], r.range, r.sigma, res,
                                          r.noise.length))
    return out


def finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None
