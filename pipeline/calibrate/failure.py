"""Failure tests as a lab reads them: where the specimen failed, its strength, and its toe and linear moduli.

A pull-to-failure test is what a lab runs most, and what it reports from one is the
ultimate stress, the stretch at failure and the toe and linear moduli. This module
reads them from each record, without any material model, and says which samples are
the intact material that a hyperelastic fit may use (docs/design/calibration.md,
"Failure tests"):

* **Rupture**: :func:`esmm.pipeline.tensile.events.rupture_index`, the detector the
  discovery uses, on the record's own noise (:func:`esmm.pipeline.tensile.events.noise_sd`).
* **The last loading**: the run of rising stretch that ends at the rupture (or at the
  end of the record); decreases of the stretch smaller than :data:`STRETCH_TOL` of its
  span are the encoder's noise, not an unloading.
* **Ultimate stress**: the largest nominal stress of the last loading before the
  rupture; the **stretch at failure** is the stretch there (the stretch at the rupture
  is reported too). The samples after the ultimate stress are failure in progress (the
  stress falls while the specimen is stretched, which no hyperelastic law does) and
  are not fitted: the fit uses the intact part, up to the ultimate stress.
* **Censoring**: a record that ends while loading within :data:`CENSOR_FRACTION` of its
  largest stress, with no rupture, stopped at a force (or extension) limit before the
  specimen failed: its ultimate stress is a lower bound, flagged ``censored``.
* **A stop at a drop**: no rupture, but the stress at the end of the last loading lies
  below its largest value by more than the record's noise and the instrument's accuracy
  allow (:func:`drop_tolerance`) while the stretch advanced past it: failure began
  and the machine's break detection stopped the test. The part after the ultimate
  stress is not fitted.
* **Linear modulus**: the slope dP/dλ (nominal stress per unit stretch, i.e. per unit
  engineering strain) of the steepest straight stretch of the last loading up to the
  ultimate stress: least-squares lines over every window of :data:`LINEAR_WINDOW` of
  that stretch span (stepped by 1 % of it), the steepest one.
* **Toe region**: a continuous two-segment line fitted (least squares, the breakpoint
  on a grid) to the last loading from its start to the top of the linear window; the
  breakpoint is the **toe end** and the first segment's slope the **toe modulus**. A
  curve whose first segment is not softer than the linear region has no toe.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..htmlreport import quantity_text
from ..tensile import events
from ..tensile.data import TensileTest

#: a record ending while loading within this fraction of its largest stress stopped before failing.
#: Two accuracy classes of a class-1 load cell (ISO 7500-1: ±1 % of reading): closer than that the
#: end of the record cannot be told from its maximum by the instrument.
CENSOR_FRACTION = 0.02
#: a drop from the ultimate stress counts when it exceeds this many noise standard deviations ...
DROP_SIGMAS = 10.0
#: ... and the instrument's accuracy (:data:`CENSOR_FRACTION` of the ultimate stress)
#: width of the linear-region windows, as a fraction of the last loading's stretch span up to the ultimate
LINEAR_WINDOW = 0.2
#: decreases of the stretch below this fraction of its span are encoder noise, not an unloading
STRETCH_TOL = 1e-3
#: fewest samples a modulus is computed from (a window of the linear region, the toe fit)
MIN_SAMPLES = 8
#: a rupture before this sample leaves too little intact record to fit (the discovery's rule too)
MIN_INTACT = 10
#: breakpoints tried by the toe fit
TOE_GRID = 200
#: samples used for the moduli (evenly thinned above this)
MAX_SAMPLES = 4000


@dataclass(frozen=True)
class FailureTest:
    """What a record says about failure, in SI (stresses in Pa, moduli in Pa per unit stretch).

    ``kind`` is ``"rupture"`` (the detector found one), ``"drop"`` (the test stopped at a
    drop from its largest stress), ``"censored"`` (stopped at its largest stress: no
    failure) or ``"none"`` (not a failure test: a relaxation, cycles that end unloaded,
    a record without time). Samples ``[0, fit_end)`` are the intact part that is fitted.
    """

    file: str
    kind: str
    n: int
    fit_end: int
    ultimate_index: int | None = None
    ultimate_stress: float | None = None
    ultimate_stretch: float | None = None
    ultimate_force: float | None = None
    rupture_index: int | None = None
    rupture_stretch: float | None = None
    rupture_time: float | None = None
    loading_start: int | None = None
    toe_end_stretch: float | None = None
    toe_modulus: float | None = None
    linear_modulus: float | None = None
    linear_from: float | None = None
    linear_to: float | None = None
    linear_r2: float | None = None
    rupture_early: bool = False  # a rupture before MIN_INTACT samples: left in (nothing intact to fit)

    @property
    def failed(self) -> bool:
        """The specimen failed in this record (a rupture, or a stop at a drop from its peak)."""
        return self.kind in ("rupture", "drop")

    @property
    def censored(self) -> bool:
        return self.kind == "censored"

    @property
    def cut(self) -> int:
        """Samples left out of the fit (from the ultimate stress on)."""
        return self.n - self.fit_end

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(failed=self.failed, censored=self.censored, samples_cut=self.cut)
        return d

    def sentence(self) -> str:
        """What happened, in plain words with units."""
        if self.kind == "none":
            return f"{self.file}: no failure in this record (not a pull to failure)."
        su = quantity_text(self.ultimate_stress, "Pa")
        at = f"stretch {self.ultimate_stretch:.4g}"
        if self.kind == "censored":
            return (f"{self.file}: stopped at its largest stress, {su} at {at}, without failing: a force or "
                    f"extension limit. Its strength is at least {su} (censored).")
        what = "ruptured" if self.kind == "rupture" else "stopped at a drop from its peak"
        tail = f"; rupture at stretch {self.rupture_stretch:.4g}" if self.rupture_stretch is not None else ""
        return (f"{self.file}: {what}; ultimate stress {su} at {at}{tail}; the fit uses the {self.fit_end} samples "
                f"up to the ultimate stress, {self.cut} after it are left out.")


# --------------------------------------------------------------------------- analysis
def analyse(test: TensileTest) -> FailureTest:
    """The failure analysis of one record (see the module's docstring for each definition)."""
    x, y = np.asarray(test.stretch, float), np.asarray(test.stress, float)
    n = test.n
    if test.time is None or n < MIN_INTACT:
        return FailureTest(test.name, "none", n, n)
    sigma = float(events.noise_sd(y))
    k = events.rupture_index(x, y, sigma)
    if k is not None and k < MIN_INTACT:
        return FailureTest(test.name, "none", n, n, rupture_index=int(k), rupture_stretch=float(x[k]),
                           rupture_early=True)
    end = n if k is None else int(k)
    start = loading_start(x[:end])
    ult = start + int(np.argmax(y[start:end]))
    kind = _kind(x, y, start, ult, end, k, sigma)
    if kind == "none":
        return FailureTest(test.name, "none", n, n)
    fit_end = n if kind == "censored" else ult + 1
    force = None if test.force is None else float(test.force[ult])
    rupture = {} if k is None else {"rupture_index": int(k), "rupture_stretch": float(x[k]),
                                    "rupture_time": float(test.time[k])}
    moduli = loading_moduli(x[start:ult + 1], y[start:ult + 1])
    return FailureTest(test.name, kind, n, fit_end, ultimate_index=ult, ultimate_stress=float(y[ult]),
                       ultimate_stretch=float(x[ult]), ultimate_force=force, loading_start=start,
                       **rupture, **moduli)


def _kind(x, y, start: int, ult: int, end: int, k: int | None, sigma: float) -> str:
    if k is not None:
        return "rupture"
    top, last = float(y[ult]), float(y[end - 1])
    if top <= 0 or x[end - 1] - x[start] <= 0:
        return "none"
    tol = STRETCH_TOL * (float(np.ptp(x)) or 1.0)
    if last >= (1.0 - CENSOR_FRACTION) * top and x[end - 1] > x[start] + tol:
        return "censored"
    if top - last > drop_tolerance(top, sigma) and x[end - 1] > x[ult] + tol:
        return "drop"
    return "none"


def drop_tolerance(top: float, sigma: float) -> float:
    """The fall from the ultimate stress *top* [Pa] that a record with noise *sigma* cannot make by chance,
    and a class-1 load cell can resolve: the larger of DROP_SIGMAS σ and CENSOR_FRACTION of *top*."""
    return max(DROP_SIGMAS * sigma, CENSOR_FRACTION * abs(top))


def loading_start(x: np.ndarray) -> int:
    """First sample of the last run of rising stretch in *x* (decreases under STRETCH_TOL of the span ignored)."""
    if x.size < 2:
        return 0
    tol = STRETCH_TOL * (float(np.ptp(x)) or 1.0)
    i = x.size - 1
    low = float(x[i])
    while i > 0 and x[i - 1] <= low + tol:
        i -= 1
        low = min(low, float(x[i]))
    return i


def intact(test: TensileTest, failure: FailureTest) -> TensileTest:
    """*test* restricted to its intact samples ``[0, fit_end)`` (the test itself when nothing is cut)."""
    if failure.fit_end >= test.n:
        return test
    sl = slice(0, failure.fit_end)

    def sub(a):
        return None if a is None else np.asarray(a)[sl]

    md = dict(test.metadata)
    md["failure_cut"] = {"kind": failure.kind, "fit_end": failure.fit_end, "samples": test.n}
    return TensileTest(source=test.source, mode=test.mode, stretch=sub(test.stretch), stress=sub(test.stress),
                       time=sub(test.time), displacement=sub(test.displacement), force=sub(test.force), metadata=md)


# --------------------------------------------------------------------------- moduli
def loading_moduli(x: np.ndarray, y: np.ndarray) -> dict[str, float | None]:
    """Linear and toe moduli of a loading curve up to its ultimate stress (stretch *x*, stress *y* [Pa])."""
    out: dict[str, float | None] = {"toe_end_stretch": None, "toe_modulus": None, "linear_modulus": None,
                                    "linear_from": None, "linear_to": None, "linear_r2": None}
    if x.size > MAX_SAMPLES:
        idx = np.linspace(0, x.size - 1, MAX_SAMPLES).round().astype(int)
        x, y = x[idx], y[idx]
    order = np.argsort(x, kind="stable")
    x, y = x[order], y[order]
    if x.size < 2 * MIN_SAMPLES or float(x[-1] - x[0]) <= 0:
        return out
    lin = steepest_line(x, y)
    if lin is None:
        return out
    slope, lo, hi, r2 = lin
    out.update(linear_modulus=slope, linear_from=lo, linear_to=hi, linear_r2=r2)
    upto = x <= hi
    toe = hinge_fit(x[upto], y[upto])
    if toe is not None and toe[1] < slope:
        out.update(toe_end_stretch=toe[0], toe_modulus=toe[1])
    return out


def steepest_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float] | None:
    """(slope, from, to, R²) of the steepest least-squares line over windows of LINEAR_WINDOW of the span of
    sorted *x*, stepped by 1 % of it; None when no window holds MIN_SAMPLES samples."""
    span = float(x[-1] - x[0])
    w = LINEAR_WINDOW * span
    c = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(x), x, y, x * x, x * y, y * y)]
    best = None
    for a in x[0] + 0.01 * span * np.arange(int(round((1.0 - LINEAR_WINDOW) / 0.01)) + 1):
        i, j = int(np.searchsorted(x, a, "left")), int(np.searchsorted(x, a + w, "right"))
        if j - i < MIN_SAMPLES:
            continue
        m, sx, sy, sxx, sxy, syy = (float(s[j] - s[i]) for s in c)
        vxx, vxy, vyy = sxx - sx * sx / m, sxy - sx * sy / m, syy - sy * sy / m
        if vxx <= 0:
            continue
        slope = vxy / vxx
        if best is None or slope > best[0]:
            r2 = vxy * vxy / (vxx * vyy) if vyy > 0 else 1.0
            best = (slope, float(x[i]), float(x[j - 1]), r2)
    return best


def hinge_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float] | None:
    """(breakpoint, first slope, second slope) of the continuous two-segment least-squares line through
    sorted *x*, *y*, the breakpoint on a grid of TOE_GRID stretches inside the central 90 % of the span."""
    if x.size < 2 * MIN_SAMPLES or float(x[-1] - x[0]) <= 0:
        return None
    span = float(x[-1] - x[0])
    best = None
    for h in x[0] + span * np.linspace(0.05, 0.95, TOE_GRID):
        if np.count_nonzero(x < h) < MIN_SAMPLES // 2 or np.count_nonzero(x >= h) < MIN_SAMPLES // 2:
            continue
        A = np.column_stack([np.ones_like(x), x - h, np.maximum(x - h, 0.0)])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        sse = float(np.sum((A @ coef - y) ** 2))
        if best is None or sse < best[0]:
            best = (sse, float(h), float(coef[1]), float(coef[1] + coef[2]))
    return None if best is None else best[1:]


# --------------------------------------------------------------------------- groups
METRICS = (("ultimate_stress", "Pa"), ("ultimate_stretch", "1"), ("rupture_stretch", "1"),
           ("toe_end_stretch", "1"), ("toe_modulus", "Pa"), ("linear_modulus", "Pa"))


#: metrics a test that stopped before failing (censored) measures as well as one that failed
UNCENSORED = ("toe_end_stretch", "toe_modulus", "linear_modulus")


def group_summary(failures: Sequence[FailureTest]) -> dict[str, Any]:
    """Mean, SD and count of each metric: strengths over the tests that failed, moduli over every failure test.

    A censored test's ultimate stress (and stretch) is only a lower bound: averaging
    it with the failed tests' would bias the strength low, so it is counted and its
    largest stress reported (``censored_at``), never averaged. Its toe and linear
    moduli, read before it stopped, are measurements like any other and are averaged.
    """
    failed = [f for f in failures if f.failed]
    tested = [f for f in failures if f.kind != "none"]
    stats: dict[str, Any] = {}
    for key, unit in METRICS:
        vals = [float(getattr(f, key)) for f in (tested if key in UNCENSORED else failed)
                if getattr(f, key) is not None and math.isfinite(float(getattr(f, key)))]
        stats[key] = {"mean": float(np.mean(vals)) if vals else None,
                      "sd": float(np.std(vals, ddof=1)) if len(vals) > 1 else None, "n": len(vals), "unit": unit}
    cens = [f for f in failures if f.censored]
    return {"tests": len(failures), "failed": len(failed), "censored": len(cens),
            "censored_at": [f.ultimate_stress for f in cens], "stats": stats}
