"""``NAME.report.html``: an asset's report, one self-contained page, how far to trust it first.

Built from the asset file alone (:func:`~.read.read_asset`), so that it can be written
again whenever the asset changes (``esmm prepare`` writes it, ``esmm validate`` renews
it after recording its figures): the verdict in plain words (:func:`~.trust.judge`),
the errors the asset knows (the fit's, the compensation's, the validation's per case),
the asset's figures, the mesh quality against its floors, the material's curve over
the tables' grid, the cleaning, the warnings and the provenance. Every number has its
unit.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import __version__
from ..htmlreport import DIMENSIONLESS, Column, Document, Quantity
from ..network.tables import grid_note
from .read import Asset, read_asset
from .trust import CASE_ORDER, judge


def report_path(asset_path: str | os.PathLike) -> Path:
    """``liver.h5`` -> ``liver.report.html`` (beside it)."""
    p = Path(asset_path)
    return p.with_name(p.stem + ".report.html")


def write_asset_report(asset_path: str | os.PathLike) -> Path:
    """Read the asset and write its report beside it (atomically); returns the report's path."""
    import matplotlib.pyplot as plt

    doc = asset_document(read_asset(asset_path, verify=False))
    plt.close("all")
    return doc.write(report_path(asset_path))


def asset_document(asset: Asset) -> Document:
    """The report of *asset* as a :class:`~esmm.pipeline.htmlreport.Document`."""
    acc = asset.accuracy
    doc = Document(f"Asset: {asset.path.name}", producer=f"esmm {__version__} prepare",
                   subtitle=f"{acc.material or 'no material'}; made {asset.provenance.utc_time or '?'} from "
                            f"{Path(asset.provenance.input_path).name or '(no file)'}")
    level, reasons, advice = judge(acc, quality_passes=asset.quality_passes)
    doc.verdict(level, "How far to trust this asset: " + acc.headline() + ".", reasons=reasons, advice=advice)
    _trust(doc, asset)
    _figures(doc, asset)
    _quality(doc, asset)
    _material(doc, asset)
    _cleaning(doc, asset)
    warnings = asset.provenance.extra.get("warnings") or []
    if warnings:
        doc.section("Warnings of the preparation")
        doc.items([str(w) for w in warnings])
    doc.section("Provenance", collapsed=True)
    prov = asset.provenance
    doc.facts([("input", prov.input_path or "(none)", None), ("input SHA-256", prov.input_sha256 or "-", None),
               ("esmm", prov.packages.get("esmm", "?"), None), ("command", " ".join(prov.command_line), None)])
    doc.preformatted(prov.config_toml or "(no configuration recorded)")
    return doc


def _trust(doc: Document, asset: Asset) -> None:
    acc = asset.accuracy
    doc.section("How far to trust it")
    doc.items([acc.fit_words(), acc.compensation_words(), acc.validation_words()])
    cases = (acc.validation or {}).get("cases", {})
    if cases:
        rows = []
        for name in sorted(cases, key=lambda k: (CASE_ORDER.index(k) if k in CASE_ORDER else 99, k)):
            c = cases[name]
            rows.append([name, c.get("l2_error"), c.get("max_error"), c.get("force_error"),
                         c.get("volume_change_network"), c.get("inverted_network"),
                         c.get("failed") or f"{c.get('element')}, volume term {c.get('volume_term')}, {c.get('law')} "
                         f"law, scene {c.get('scene')}", str(c.get("utc_time", ""))[:19]])
        doc.table([Column("case"), Column("displacement error (L2)", "%", digits=3),
                   Column("largest displacement error", "%", digits=3), Column("force error", "%", digits=3),
                   Column("volume change of the network", "%", digits=3),
                   Column("inverted tetrahedra", DIMENSIONLESS), Column("how (or why it failed)"),
                   Column("when (UTC)")], rows,
                  caption="The network against a finite-element continuum of this organ (esmm validate); errors "
                          "over the continuum's largest displacement and its reaction force")


def _figures(doc: Document, asset: Asset) -> None:
    net = asset.network
    lo, hi = net.points.min(0), net.points.max(0)
    doc.section("The asset")
    facts = [("structure", net.structure, None), ("nodes", str(net.n_nodes), None),
             ("springs", str(net.n_springs), None), ("tetrahedra", str(net.n_tets), None),
             ("volume", net.total_volume() * 1e6, "mL"), ("mass", net.total_mass() * 1e3, "g"),
             ("density", net.density, "kg/m3"), ("extent x", float(hi[0] - lo[0]), "m"),
             ("extent y", float(hi[1] - lo[1]), "m"), ("extent z", float(hi[2] - lo[2]), "m"),
             ("fixed nodes", f"{net.fixed.size}: {asset.fixed_region or 'region not recorded'}", None),
             ("shortest spring", float(net.rest_length.min()), "m"), ("longest spring", float(net.rest_length.max()), "m")]
    t = asset.tables
    if t is not None:
        facts += [("tables' stretch range", f"{t.lam_min:.4g} to {t.lam_max:.4g} (dimensionless), {t.n} points",
                   None), ("force law", t.default_law, None), ("compensation factor", t.volume_factor, DIMENSIONLESS)]
    if net.volume_term is not None:
        facts.append(("volume term's bulk modulus", net.volume_term.bulk_modulus, "Pa"))
    doc.facts(facts)


def _quality(doc: Document, asset: Asset) -> None:
    q = asset.quality
    if not q:
        return
    doc.section("Mesh quality")
    verdict = {True: "passes the floors", False: "is below the floors (written with --force)",
               None: "was not judged against the floors"}[asset.quality_passes]
    doc.text(f"The tetrahedral mesh {verdict}.")
    pct = q.get("percentiles", {})
    rows = [[name, Quantity(pct.get(key, {}).get("p0"), unit), Quantity(pct.get(key, {}).get("p1"), unit),
             Quantity(pct.get(key, {}).get("p50"), unit)]
            for name, key, unit in (("smallest dihedral angle", "min_dihedral_deg", "deg"),
                                    ("SICN (1: regular)", "sicn", DIMENSIONLESS),
                                    ("gamma (1: regular)", "gamma", DIMENSIONLESS),
                                    ("radius ratio (1: regular)", "radius_ratio", DIMENSIONLESS))]
    doc.table([Column("measure"), Column("worst"), Column("worst 1 %"), Column("median")], rows,
              caption="Per tetrahedron; the floors: docs/guide/prepare.md, 'Quality floors'")
    hist = pct.get("min_dihedral_deg_hist")
    if hist:
        doc.figure(_histogram(hist), alt="histogram of the tetrahedra's smallest dihedral angle in degrees, with "
                   "the floor of 10 degrees marked", caption="Smallest dihedral angle per tetrahedron")


def _histogram(hist):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts, edges = np.asarray(hist[0], float), np.asarray(hist[1], float)
    fig, ax = plt.subplots(figsize=(6, 3), constrained_layout=True)
    ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="#4c72b0")
    ax.axvline(10.0, color="#c62828", ls="--", label="floor 10°")
    ax.set_xlabel("smallest dihedral angle [°]")
    ax.set_ylabel("tetrahedra [count]")
    ax.legend()
    return fig


def _material(doc: Document, asset: Asset) -> None:
    t = asset.tables
    if t is None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    doc.section("The material over the tables' grid")
    fig, ax = plt.subplots(figsize=(6, 3.4), constrained_layout=True)
    ax.plot(t.lam, t.material_stress[0] / 1e3, color="#222", label="material, nominal uniaxial stress")
    rng = (asset.accuracy.compensation or {}).get("stretch_range")
    if rng:
        ax.axvspan(rng[0], rng[1], color="#4c72b0", alpha=0.15, label="compensation's calibration range")
    ax.set_xlabel("stretch λ [–]")
    ax.set_ylabel("nominal stress [kPa]")
    ax.legend()
    doc.figure(fig, alt="the material's nominal uniaxial stress in kPa against stretch over the tables' grid, "
               "with the compensation's calibration range shaded", caption=f"{asset.accuracy.material}: the curve "
               "the springs follow (the secant law's modulus is tabulated from it)")
    doc.text(f"Why the grid ends where it does: {grid_note(t) or 'not recorded'}.")


def _cleaning(doc: Document, asset: Asset) -> None:
    c = asset.cleaning
    if not c:
        return
    doc.section("Cleaning of the surface", collapsed=True)
    rows = [[s.get("name", "?"), s.get("faces_before"), s.get("faces_after"), s.get("volume_before"),
             s.get("volume_after")] for s in c.get("steps", []) if isinstance(s, dict)]
    doc.table([Column("step"), Column("faces before", DIMENSIONLESS), Column("faces after", DIMENSIONLESS),
               Column("volume before", "mL", scale=1e-6), Column("volume after", "mL", scale=1e-6)], rows,
              caption=f"Relative volume change over the cleaning: {100 * c.get('relative_volume_change', 0):.3g} %")
