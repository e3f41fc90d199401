"""``report.html`` of ``esmm validate``: one self-contained page, the verdict in plain words first.

The network against the finite-element continuum, per load case: the errors (each with
its unit), the plots the validation drew (embedded), each case's boundary conditions in
words, and the settings. The verdict uses the asset's threshold
(:data:`esmm.pipeline.asset.trust.VALIDATION_POOR`): a case whose displacement or force
error exceeds it makes the network "poor", a case without an equilibrium too.
"""

from __future__ import annotations

from pathlib import Path

from .. import __version__
from ..asset.trust import VALIDATION_POOR
from ..htmlreport import DIMENSIONLESS, Column, Document


def _pct(v) -> str:
    return "?" if v is None else f"{100 * v:.3g} %"


def validation_document(report) -> Document:
    """The report of a :class:`~.validate.ValidationReport` as a :class:`~esmm.pipeline.htmlreport.Document`."""
    figs = report.figures()
    cases = figs["cases"]
    doc = Document(f"Validation: {Path(report.label).name if report.label else 'network'}",
                   producer=f"esmm {__version__} validate",
                   subtitle=f"{report.info.get('material', '?')}; volume term {report.volume_term}; "
                            f"{report.info.get('law', '?')} law; continuum {report.info.get('element', '?')}")
    failed = report.info.get("failed") or {}
    worst_u = max((c["l2_error"] for c in cases), default=None)
    worst_f = max((c["force_error"] for c in cases), default=None)
    reasons = [f"{c['case']}: {_pct(max(c['l2_error'], c['force_error']))} from the continuum (above "
               f"{_pct(VALIDATION_POOR)})" for c in cases if max(c["l2_error"], c["force_error"]) > VALIDATION_POOR]
    reasons += [f"{name}: no equilibrium found ({why})" for name, why in failed.items()]
    level = "poor" if reasons else "good"
    if not cases:
        level, headline = "unusable", "No case was solved: nothing is known about the network's accuracy."
    else:
        headline = (f"The network is within {_pct(worst_u)} of the finite-element continuum in displacement (L2) and "
                    f"{_pct(worst_f)} in force ({', '.join(c['case'] for c in cases)}).")
    advice = []
    if level == "poor" and cases:
        advice.append("the network is not compensated: esmm tables ASSET --compensate"
                      if report.info.get("volume_factor", 1.0) == 1.0 else
                      "a finer network: esmm prepare --split (or --config fine)")
    doc.verdict(level, headline, reasons=reasons, advice=advice)
    _table(doc, cases)
    _plots(doc, report)
    doc.section("The load cases")
    doc.items([f"{c['case']}: {c['boundary_conditions']}" for c in cases])
    doc.section("Settings", collapsed=True)
    info = report.info
    doc.facts([("material", str(info.get("material", "?")), None), ("force law", str(info.get("law", "?")), None),
               ("volume term", report.volume_term, None), ("continuum element", str(info.get("element", "?")), None),
               ("continuum's bulk modulus", info.get("bulk_modulus_Pa"), "Pa"),
               ("network compensation factor", info.get("volume_factor"), DIMENSIONLESS),
               ("nodes", str(info.get("nodes", "?")), None), ("tetrahedra", str(info.get("tets", "?")), None),
               ("time taken", info.get("seconds"), "s")])
    return doc


def _table(doc: Document, cases: list[dict]) -> None:
    doc.section("Errors per case")
    rows = [[c["case"], c["l2_error"], c["max_error"], c["force_error"], c["volume_change_continuum"],
             c["volume_change_network"], c["inverted_network"], c.get("continuum", {}).get("element", "")]
            for c in cases]
    doc.table([Column("case"), Column("displacement error (L2)", "%", digits=3),
               Column("largest displacement error", "%", digits=3), Column("force error", "%", digits=3),
               Column("volume change, continuum", "%", digits=3), Column("volume change, network", "%", digits=3),
               Column("inverted tetrahedra, network", DIMENSIONLESS), Column("continuum element")], rows,
              caption="Displacement errors over the continuum's largest displacement; the force error over the "
                      "continuum's reaction (gravity: over the organ's weight)")


def _plots(doc: Document, report) -> None:
    pngs = [(name[: -len("_png")], Path(path)) for name, path in report.files.items()
            if name.endswith("_png") and Path(path).is_file()]
    if not pngs:
        return
    doc.section("The continuum and the network, deformed")
    for case, path in pngs:
        doc.figure(path.read_bytes(), alt=f"{case}: the continuum's and the network's deformed shapes side by "
                   "side on one colour scale, and the error between them", caption=case)


def write_validation_html(report, out: str | Path) -> Path:
    """Write ``report.html`` into the folder *out* (atomically)."""
    return validation_document(report).write(Path(out) / "report.html")
