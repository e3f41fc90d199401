"""report.html of a calibration: one self-contained page, the verdict in plain words first.

Built with :mod:`esmm.pipeline.htmlreport`: the verdict and what to do, the data and the
model (one figure per loading mode, residual = model − data, stress against time beside
stress against stretch), the parameters in readable units with whether the data
determine them, the errors per file against what the file resolves, the failure tests,
and how each file was read.
"""

from __future__ import annotations

from pathlib import Path

from .. import __version__
from ..htmlreport import DIMENSIONLESS, Column, Document, Quantity
from .calibration import Calibration
from .failure import FailureTest
from .inputs import columns_text, how_read
from .markdown import group_sentences
from .plots import MODE_TITLES, failure_figure, mode_figure, modes


def calibrate_html(cal: Calibration, *, title: str | None = None) -> Document:
    """The HTML report of *cal* as a :class:`~esmm.pipeline.htmlreport.Document`."""
    r, v = cal.result, cal.verdict
    doc = Document(title or f"Calibration: {r.model} on {', '.join(sorted({t.specimen for t in cal.tests}))}",
                   producer=f"esmm {__version__} calibrate",
                   subtitle=f"{len(cal.tests)} file(s): " + ", ".join(t.name for t in cal.tests[:6])
                   + (" ..." if len(cal.tests) > 6 else ""))
    doc.verdict(v.level, v.headline, reasons=[x.text for x in v.reasons], advice=v.advice())
    _figures(doc, cal)
    _parameters(doc, cal)
    _errors(doc, cal)
    _failures(doc, cal)
    if r.warnings:
        doc.section("Warnings of the fit")
        doc.items(r.warnings)
    rng = r.drucker.get("range") if r.drucker else None
    if rng:
        doc.section("Stability")
        stable = r.drucker.get("stable", True)
        doc.text(f"Drucker stability over stretch λ from {rng[0]:.3g} to {rng[1]:.3g} (dimensionless): "
                 + ("stable." if stable else f"NOT stable: {r.drucker.get('detail', '')}."))
    _inputs(doc, cal)
    return doc


def write_html(path: str | Path, cal: Calibration) -> Path:
    """Write report.html (atomically)."""
    import matplotlib.pyplot as plt

    doc = calibrate_html(cal)
    plt.close("all")
    return doc.write(path)


def _figures(doc: Document, cal: Calibration) -> None:
    import matplotlib.pyplot as plt

    doc.section("Data and model")
    doc.text("One row per loading mode. Dots: the data; lines: the fitted model; grey: samples left out of the "
             "fit (after a failure's ultimate stress, marked ▼; a dashed line marks a rupture). The residual is "
             "model − data everywhere.")
    for m in modes(cal):
        fig = mode_figure(cal, m)
        doc.figure(fig, alt=f"{MODE_TITLES[m]}: nominal stress against stretch and against time, data and model, "
                   "and the residual model − data", caption=MODE_TITLES[m])
        plt.close(fig)


def _parameters(doc: Document, cal: Calibration) -> None:
    r = cal.result
    doc.section("Parameters")
    rows = []
    for e in r.estimates:
        rows.append([e.key, Quantity(e.value, e.unit, digits=5, note="(at bound)" if e.at_bound else ""),
                     Quantity(e.lower, e.unit), Quantity(e.upper, e.unit), "yes" if e.identifiable else "no"])
    for k, val, unit in r.held():
        rows.append([k, Quantity(val, unit, note="(fixed)"), None, None, "–"])
    doc.table([Column("parameter"), Column("value"), Column("95 % interval, lower"), Column("95 % interval, upper"),
               Column("determined by the data")], rows,
              caption="95 % intervals from the Jacobian, widened for serially correlated residuals; a parameter "
                      "the data do not determine is a value, not a measurement.")


def _errors(doc: Document, cal: Calibration) -> None:
    r, v = cal.result, cal.verdict
    doc.section("Errors per file")
    doc.facts([("RMSE (all files)", r.rmse, "Pa"), ("NRMSE (RMSE / range of the measured stress)", r.nrmse, "%"),
               ("R²", r.r2, DIMENSIONLESS)])
    rows = []
    for fe, t in zip(r.files, cal.fitted):
        nz = v.noise.get(t.name, {})
        rows.append([t.name, fe.mode, fe.n, Quantity(fe.rmse, "Pa"), fe.nrmse, fe.r2,
                     Quantity(nz.get("resolution_Pa"), "Pa", digits=3), nz.get("ratio"), v.files.get(t.name, "–")])
    doc.table([Column("file"), Column("mode"), Column("samples fitted", unit="1", digits=9), Column("RMSE"),
               Column("NRMSE", unit="%", digits=3), Column("R²", unit=DIMENSIONLESS),
               Column("resolution r"), Column("RMSE / r", unit=DIMENSIONLESS, digits=3), Column("verdict")],
              rows, caption="r: what the record resolves, the larger of its own measurement noise (estimated from "
                            "the record alone) and 0.5 % of its RMS stress (a class 0.5 testing machine's "
                            "accuracy); RMSE/r near 1 means the misfit is what the measurement cannot resolve.")


def _failures(doc: Document, cal: Calibration) -> None:
    import matplotlib.pyplot as plt

    tests = cal.failure_tests
    if not tests:
        return
    doc.section("Failure tests")
    doc.items([f.sentence() for f in tests] + group_sentences(cal))
    doc.table([Column("file"), Column("result"), Column("ultimate stress"), Column("stretch at ultimate", unit="1"),
               Column("stretch at rupture", unit="1"), Column("toe end stretch", unit="1"), Column("toe modulus"),
               Column("linear modulus"), Column("linear region from", unit="1"), Column("to", unit="1")],
              [_failure_row(f) for f in tests],
              caption="Moduli: dP/dλ, nominal stress per unit stretch (= per unit engineering strain).")
    doc.text("Definitions. Ultimate stress: the largest nominal stress of the last loading before the rupture; "
             "stretch at failure: the stretch there. Linear modulus: the slope of the steepest least-squares line "
             "over windows of 20 % of the last loading's stretch span up to the ultimate stress. Toe: a continuous "
             "two-segment line fitted up to the top of that window; its breakpoint is the toe end, its first slope "
             "the toe modulus (none when the curve does not stiffen). Censored: stopped at its largest stress "
             "without failing, so the ultimate stress is a lower bound and is not averaged.")
    fig = failure_figure(cal)
    if fig is not None:
        doc.figure(fig, alt="the last loading of each failure test with its ultimate stress, linear region, "
                   "toe end and rupture", caption="How the strengths and moduli were read")
        plt.close(fig)


def _failure_row(f: FailureTest) -> list:
    return [f.file, f.kind + (" (a lower bound)" if f.censored else ""), Quantity(f.ultimate_stress, "Pa"),
            f.ultimate_stretch, f.rupture_stretch, f.toe_end_stretch,
            None if f.toe_modulus is None else Quantity(f.toe_modulus, "Pa"),
            None if f.linear_modulus is None else Quantity(f.linear_modulus, "Pa"), f.linear_from, f.linear_to]


def _inputs(doc: Document, cal: Calibration) -> None:
    doc.section("How each file was read", collapsed=True)
    doc.table([Column("file"), Column("stretch from"), Column("stress from"), Column("columns used")],
              [[t.name, how_read(t)["stretch_from"] or "–", how_read(t)["stress_from"] or "–",
                columns_text(t) or "–"] for t in cal.tests])
    doc.items([w for t in cal.tests for w in how_read(t)["warnings"]])
