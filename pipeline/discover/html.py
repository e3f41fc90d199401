"""report.html of a discovery: one self-contained page beside discover.md, what was found said first.

Built with :mod:`esmm.pipeline.htmlreport` from the discovery's JSON document
(:func:`~esmm.pipeline.discover.report.result_to_dict`, schema ``esmm.discover/1``) and
its fitted models: the verdict (is what is left noise?), the plain-language summary,
one figure per loading mode (data, the base model dashed, the final model solid; the
residual model − data against stretch and against time, so a relaxation hold reads
as a curve in time), the errors before and after, the candidates, the final
parameters with their units and whether the data determine them, and the noise.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..htmlreport import DIMENSIONLESS, Column, Document, Quantity, readable_unit
from .report import result_to_dict
from .search import DiscoverResult

MODE_TITLES = {"uniaxial": "uniaxial", "equibiaxial": "equibiaxial", "pure_shear": "pure shear",
               "simple_shear": "simple shear"}
DRAWN = 3000


def verdict_of(doc: dict[str, Any]) -> tuple[str, str, list[str], list[str]]:
    """(level, headline, reasons, advice) of a discovery from its JSON document.

    Good: what is left after the kept effects is the records' noise. Poor: something
    systematic is left (the outcome says what), or a kept effect's parameters are not
    determined by the data. A discovery is not a fit to be used or not: it never says
    unusable; the fit's own verdict is in plain ``esmm calibrate``.
    """
    b, f = doc["base"], doc["final"]
    kept = doc.get("effects", [])
    change = (f"Error {_pct(b.get('nrmse'))} → {_pct(f.get('nrmse'))} of the stress range, held out "
              f"{_pct(b.get('heldout_nrmse'))} → {_pct(f.get('heldout_nrmse'))}.")
    unident = [k for k, p in f.get("parameters", {}).items() if p.get("not_identifiable")]
    reasons, advice = [], []
    if doc.get("outcome"):
        reasons.append("left unexplained: " + doc["outcome"])
        advice.append("look at the residual against time; a test that isolates the effect (a hold, cycles, two "
                      "rates) may tell it apart")
    if unident:
        reasons.append("the data do not determine " + ", ".join(unident) + ": their values are not measurements")
        advice.append("do not report or average those values")
    found = ("found: " + ", ".join(kept).replace("_", " ")) if kept else "nothing to add"
    level = "poor" if reasons else "good"
    undetermined = f"the data do not determine {', '.join(unident)}"
    if doc.get("outcome"):
        poor = f"{found}, but not everything is explained" + (f"; {undetermined}" if unident else "")
    else:       # the residual is the noise: what is poor is the parameters alone
        poor = f"{found}; what is left is the records' noise, but {undetermined}"
    head = {"good": f"Good: {found}; what is left is the records' noise. {change}",
            "poor": f"Poor: {poor}. {change}"}[level]
    return level, head, reasons, advice


def _pct(v) -> str:
    return "–" if v is None or not math.isfinite(float(v)) else f"{100 * float(v):.3g} %"


def discover_html(res: DiscoverResult, doc: dict[str, Any] | None = None) -> Document:
    """The HTML report of a discovery as a :class:`~esmm.pipeline.htmlreport.Document`."""
    doc = doc or result_to_dict(res)
    files = [Path(f).name for f in doc["files"]]
    page = Document(f"What the {res.model} model is missing", producer=f"esmm {__version__} calibrate --discover",
                    subtitle=f"{len(files)} file(s): " + ", ".join(files[:6]) + (" ..." if len(files) > 6 else ""))
    level, head, reasons, advice = verdict_of(doc)
    page.verdict(level, head, reasons=reasons, advice=advice)
    page.section("In plain words")
    page.text(doc.get("summary", ""))
    _figures(page, res)
    _errors(page, doc)
    _candidates(page, doc)
    _parameters(page, doc)
    _noise(page, doc)
    if doc.get("warnings"):
        page.section("Warnings")
        page.items(doc["warnings"])
    return page


def write_discover_html(path: str | Path, res: DiscoverResult, doc: dict[str, Any] | None = None) -> Path:
    """Write report.html of a discovery (atomically)."""
    import matplotlib.pyplot as plt

    page = discover_html(res, doc)
    plt.close("all")
    return page.write(path)


def _predictions(res: DiscoverResult, which: str) -> list[np.ndarray]:
    f = res.base if which == "base" else res.final
    prob = f.problem
    coefs = prob.offsets(f.z)
    return [np.asarray(prob.full_prediction(k, f.z, coefs[k]), float) for k in range(len(res.records))]


def _figures(page: Document, res: DiscoverResult) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base, final = _predictions(res, "base"), _predictions(res, "final")
    page.section("Data, base model and final model")
    page.text("One row per loading mode. Dots: the data; dashed: the base model alone; solid: the final model "
              "with what was kept. The residual is model − data everywhere; stress against time shows holds "
              "(relaxation) and cycles as they happened.")
    for mode in [m for m in MODE_TITLES if any(r.test.mode == m for r in res.records)]:
        fig, axes = plt.subplots(1, 4, figsize=(17, 4.2), constrained_layout=True)
        _draw_mode(axes, res, mode, base, final)
        page.figure(fig, alt=f"{MODE_TITLES[mode]}: stress against stretch and time with the base and final "
                    "models, and the residual model − data", caption=MODE_TITLES[mode])
        plt.close(fig)


def _draw_mode(axes, res: DiscoverResult, mode: str, base, final) -> None:
    idx = [k for k, r in enumerate(res.records) if r.test.mode == mode]
    unit, fac = readable_unit([float(np.max(np.abs(res.records[k].y))) for k in idx], "Pa")
    xl = "shear strain γ [–]" if mode == "simple_shear" else "stretch λ [–]"
    has_time = False
    for n, k in enumerate(idx):
        r, c = res.records[k], f"C{n % 10}"
        sl = np.arange(r.test.n) if r.test.n <= DRAWN else np.linspace(0, r.test.n - 1, DRAWN).round().astype(int)
        axes[0].plot(r.x[sl], r.y[sl] / fac, ".", ms=2, color=c, alpha=0.4, label=r.name if len(idx) <= 10 else None)
        axes[0].plot(r.x[sl], base[k][sl] / fac, "--", lw=0.9, color=c)
        axes[0].plot(r.x[sl], final[k][sl] / fac, "-", lw=1.2, color=c)
        axes[1].plot(r.x[sl], (base[k][sl] - r.y[sl]) / fac, ".", ms=1.2, color="0.6")
        axes[1].plot(r.x[sl], (final[k][sl] - r.y[sl]) / fac, ".", ms=1.5, color=c)
        if r.t is not None:
            has_time = True
            axes[2].plot(r.t[sl], r.y[sl] / fac, ".", ms=1.5, color=c, alpha=0.4)
            axes[2].plot(r.t[sl], final[k][sl] / fac, "-", lw=1.0, color=c)
            axes[3].plot(r.t[sl], (base[k][sl] - r.y[sl]) / fac, "-", lw=0.6, color="0.6")
            axes[3].plot(r.t[sl], (final[k][sl] - r.y[sl]) / fac, "-", lw=0.8, color=c)
    t = MODE_TITLES[mode]
    axes[0].set(xlabel=xl, ylabel=f"nominal stress [{unit}]", title=f"{t}: data, base (dashed), final (solid)")
    axes[1].set(xlabel=xl, ylabel=f"model − data [{unit}]", title=f"{t}: residual (grey: base)")
    for ax in (axes[1], axes[3]):
        ax.axhline(0, color="k", lw=0.6)
    if has_time:
        axes[2].set(xlabel="time [s]", ylabel=f"nominal stress [{unit}]", title=f"{t}: stress vs time (final)")
        axes[3].set(xlabel="time [s]", ylabel=f"model − data [{unit}]", title=f"{t}: residual vs time")
    else:
        for ax in axes[2:]:
            ax.set_axis_off()
    if len(idx) <= 10:
        axes[0].legend(fontsize=7, loc="best")


def _errors(page: Document, doc: dict[str, Any]) -> None:
    b, f = doc["base"], doc["final"]
    page.section("Error before and after")
    rows = [[label, Quantity(m.get("rmse"), "Pa"), m.get("nrmse"), Quantity(m.get("max_abs"), "Pa"),
             m.get("heldout_nrmse")] for label, m in ((f"base ({b['model']})", b),
                                                       ("final (+" + (", ".join(doc["effects"]) or "nothing") + ")", f))]
    page.table([Column("model"), Column("RMSE"), Column("NRMSE", unit="%", digits=3), Column("max abs error"),
                Column("held-out NRMSE", unit="%", digits=3)], rows,
               caption=f"NRMSE = RMSE / range of the measured stress; held out: {doc['heldout']['scheme']}.")


def _candidates(page: Document, doc: dict[str, Any]) -> None:
    page.section("What was tried")
    rows = [[c["name"].replace("_", " "), c.get("kind", ""), "yes" if c.get("kept") else "no",
             c.get("heldout_nrmse"), c.get("reason", "")] for c in doc.get("candidates", [])]
    page.table([Column("candidate"), Column("kind"), Column("kept"), Column("held-out NRMSE", unit="%", digits=3),
                Column("why")], rows)


def _parameters(page: Document, doc: dict[str, Any]) -> None:
    page.section("Final parameters")
    rows = []
    for key, p in doc["final"].get("parameters", {}).items():
        unit = p.get("unit") or DIMENSIONLESS
        ci = p.get("ci95") or [None, None]
        rows.append([key, Quantity(p.get("value"), unit, digits=5), Quantity(ci[0], unit), Quantity(ci[1], unit),
                     "no" if p.get("not_identifiable") else "yes"])
    page.table([Column("parameter"), Column("value"), Column("95 % interval, lower"), Column("95 % interval, upper"),
                Column("determined by the data")], rows)


def _noise(page: Document, doc: dict[str, Any]) -> None:
    page.section("Measurement noise, from each record alone", collapsed=True)
    rows = [[name, Quantity(n.get("sd_Pa"), "Pa", digits=3), n.get("sd_of_range")]
            for name, n in doc.get("noise", {}).items()]
    page.table([Column("file"), Column("noise σ"), Column("of the stress range", unit="%", digits=3)], rows)
