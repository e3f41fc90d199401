"""``esmm info``: summarise and validate asset files."""

from __future__ import annotations

import argparse
import json
import textwrap
from pathlib import Path

from esmm.pipeline.errors import AssetError

EPILOG = """\
examples:
  esmm info liver.h5
  esmm info liver.h5 --json > liver-info.json

Exit codes: 0 every file is a valid asset; 2 a file is missing, truncated, tampered with,
of another schema or inconsistent (one line per problem on stderr).
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "info",
        help="summarise and validate asset files",
        description="Print what an asset holds (nodes, springs, tets, volume, quality, material, "
        "tables, volume term, provenance), how far to trust it (the fit's, the compensation's and, once "
        "'esmm validate' ran on it, the validation's errors) and check it: schema, checksums, shapes, NaNs, index ranges, "
        "positive tet volumes and masses, direction cosines, the volume term's rest volumes, the XDMF sidecar.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("assets", nargs="+", metavar="ASSET.h5", help="asset file(s) written by 'esmm prepare'")
    p.add_argument("--json", action="store_true", help="print one JSON object per file instead of text")
    p.set_defaults(func=run)


def _summary(path: Path):
    from esmm.pipeline.asset import read_asset

    try:
        return read_asset(path, verify=False).summary()
    except AssetError:
        return None


def _text(s: dict) -> list[str]:
    lines = [f"{s['path']}",
             f"  structure    {s['structure']} (asset schema {s['schema_version']})",
             f"  nodes        {s['nodes']} ({s['fixed_nodes']} fixed: {s['fixed_region'] or 'unspecified'})",
             f"  springs      {s['springs']}, rest length {s['rest_length_mm'].get('min', 0):.2f} .. "
             f"{s['rest_length_mm'].get('max', 0):.2f} mm (mean {s['rest_length_mm'].get('mean', 0):.2f})"]
    if s["tets"]:
        split = f" ({s['split_from']} tets split in eight)" if s.get("split_from") else ""
        lines.append(f"  tets         {s['tets']}{split}")
    lo, hi = s["bounds_mm"]
    lines += [f"  volume       {s['volume_mL']:.2f} mL, mass {s['mass_g']:.1f} g "
              f"(density {s['density_kg_m3']:g} kg/m3)",
              "  extent       " + " x ".join(f"{b - a:.1f}" for a, b in zip(lo, hi)) + " mm",
              f"  material     {s['material'] or '(none)'}"]
    effects = s.get("effects")
    if effects:
        names = effects.get("names", []) if isinstance(effects, dict) else list(effects)
        lines.append("  effects      " + (", ".join(names) or "(none)"))
    v = s.get("volume_term")
    lines.append("  volume term  " + ("(none: the network is compressible)" if not v else
                                      f"{v['formulation']} elements, bulk modulus {v['bulk_modulus_pa'] / 1e3:.4g} kPa"
                                      + ("" if v.get("poisson_ratio") is None else
                                         f" (Poisson ratio {v['poisson_ratio']:g} at the material's stiffest "
                                         "tangent)")))
    t = s.get("tables")
    lines.append("  tables       " + ("(none)" if not t else
                                      f"{t['n']} points, stretch {t['lam_min']:.3g}..{t['lam_max']:.3g}, "
                                      f"law {t['default_law']}, volume factor {t['volume_factor']:g}"))
    q = s.get("quality")
    if q is not None:
        verdict = {True: "passes the floors", False: "below the floors (written with --force)",
                   None: "not judged against the floors"}[s.get("quality_passes")]
        md = q.get("min_dihedral_deg")
        lines.append(f"  quality      min dihedral {md:.1f} deg, {verdict}" if isinstance(md, (int, float))
                     else f"  quality      {verdict}")
    lines += _trust_lines(s.get("accuracy"))
    lines.append(f"  made         {s['created_utc']} by esmm {s['esmm_version']} from {s['input'] or '(no file)'}")
    if s["input_sha256"]:
        lines.append(f"  input sha256 {s['input_sha256']}")
    return lines


def _trust_lines(accuracy: dict | None) -> list[str]:
    """How far to trust the asset, in words, wrapped under the "trust" label."""
    if not accuracy:
        return []
    out = []
    for k, text in enumerate(accuracy["lines"]):
        out += textwrap.wrap(text, width=100, initial_indent="  trust        " if k == 0 else " " * 15,
                             subsequent_indent=" " * (15 if k == 0 else 17))
    return out


def run(args, ui) -> int:
    from esmm.pipeline.asset import validate_asset
    from esmm.pipeline.atomicio import jsonable

    worst = 0
    for name in args.assets:
        path = Path(name)
        problems = validate_asset(path)
        summary = _summary(path)
        if args.json:
            text = json.dumps(jsonable({"path": path, "valid": not problems, "problems": problems,
                                        "summary": summary}), allow_nan=False)
            ui.out.print(text, markup=False, highlight=False, soft_wrap=True)
        else:
            if summary is not None:
                for line in _text(summary):
                    ui.info(line)
            if not problems:
                ui.info("  valid        yes (schema, checksums, shapes, indices, volumes, masses, cos2)")
        for pr in problems:
            ui.error(pr if pr.startswith(str(path)) else f"{path}: {pr}")
        if problems:
            worst = AssetError.exit_code
    return worst
