"""A calibration as a lab runs it: failure found and cut, the fit on the intact part, and its verdict.

:func:`calibrate` is the one call behind ``esmm calibrate`` (one fit) and each group of
``esmm calibrate --by`` (a batch): it analyses every record for failure
(:func:`esmm.pipeline.calibrate.failure.analyse`), fits the intact parts
(:func:`esmm.pipeline.calibrate.fit.fit_material`) and judges the fit
(:func:`esmm.pipeline.calibrate.verdict.judge`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from ..htmlreport import quantity_text
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from . import failure as F
from .fit import FitResult, fit_material
from .verdict import Verdict, judge


@dataclass
class Calibration:
    """A fit with what the lab needs around it.

    Attributes
    ----------
    result : FitResult
        The fit (of the intact parts).
    tests : list of TensileTest
        The records as read.
    fitted : list of TensileTest
        What was fitted: each record up to its ultimate stress when it failed, else whole.
    failures : list of FailureTest
        Each record's failure analysis (ultimate stress, stretch at failure, moduli, censoring).
    verdict : Verdict
        Good, poor or unusable, with the reasons.
    """

    result: FitResult
    tests: list[TensileTest]
    fitted: list[TensileTest]
    failures: list[F.FailureTest]
    verdict: Verdict

    @property
    def failure_summary(self) -> dict[str, Any]:
        """Mean ± SD of the failure metrics over the tests that failed; censored tests counted apart."""
        return F.group_summary(self.failures)

    @property
    def failure_tests(self) -> list[F.FailureTest]:
        """The records that are failure tests (failed or censored)."""
        return [f for f in self.failures if f.kind != "none"]


def calibrate(tests: Sequence[TensileTest], *, cut_failure: bool = True, reporter: Reporter | None = None,
              **fit_kwargs: Any) -> Calibration:
    """Analyse failure, fit the intact parts, judge the fit.

    Parameters
    ----------
    tests : sequence of TensileTest
    cut_failure : bool
        Fit each failed record only up to its ultimate stress (default). False fits every
        sample, failure included; the verdict then says the fit is unusable.
    reporter : Reporter, optional
        Receives a line per record cut and the verdict's reasons as warnings.
    **fit_kwargs
        Options of :func:`~esmm.pipeline.calibrate.fit.fit_material` (``model``, ``loss``,
        ``n_starts``, ``seed``, ``weights``, ``fixed``, ``free``, ...).
    """
    rep = ensure(reporter)
    tests = list(tests)
    failures = [F.analyse(t) for t in tests]
    fitted = [F.intact(t, f) if cut_failure else t for t, f in zip(tests, failures)]
    for f in failures:
        if f.kind != "none":
            rep.step(f.sentence() if cut_failure or not f.failed else f"{f.file}: {f.kind}; fitted whole")
    result = fit_material(fitted, reporter=reporter, **fit_kwargs)
    verdict = judge(result, fitted, failures)
    return Calibration(result, tests, fitted, failures, verdict)


def assess(result: FitResult, tests: Sequence[TensileTest]) -> Calibration:
    """The :class:`Calibration` of a fit made elsewhere, on *tests* as they were fitted (nothing cut)."""
    tests = list(tests)
    failures = [F.analyse(t) for t in tests]
    return Calibration(result, tests, tests, failures, judge(result, tests, failures))


def verdict_lines(cal: Calibration) -> list[str]:
    """The verdict for a console: the headline, then each reason and what to do."""
    v = cal.verdict
    lines = [f"verdict: {v.headline}"]
    lines += [f"  - {r.text}" for r in v.reasons]
    lines += [f"  what to do: {a}" for a in v.advice()]
    return lines


def failure_lines(cal: Calibration) -> list[str]:
    """The failure tests for a console: per test the strength and moduli with units; the group's mean ± SD."""
    lines = []
    for f in cal.failure_tests:
        parts = [f"{f.file}: {f.kind}", f"ultimate stress {'≥ ' if f.censored else ''}"
                 f"{quantity_text(f.ultimate_stress, 'Pa')} at stretch {f.ultimate_stretch:.4g}"]
        if f.rupture_stretch is not None:
            parts.append(f"rupture at stretch {f.rupture_stretch:.4g}")
        if f.linear_modulus is not None:
            parts.append(f"linear modulus {quantity_text(f.linear_modulus, 'Pa')}")
        if f.toe_modulus is not None:
            parts.append(f"toe modulus {quantity_text(f.toe_modulus, 'Pa')} up to stretch {f.toe_end_stretch:.4g}")
        lines.append("  " + "; ".join(parts))
    s = cal.failure_summary
    if s["failed"] > 1:
        st = s["stats"]["ultimate_stress"]
        sd = "" if st["sd"] is None else f" ± {quantity_text(st['sd'], 'Pa')}"
        lines.append(f"  {s['failed']} failed: ultimate stress {quantity_text(st['mean'], 'Pa')}{sd} (mean ± SD)")
    if s["censored"]:
        lines.append(f"  {s['censored']} stopped before failing (censored): not averaged")
    return (["failure tests:"] + lines) if lines else []
