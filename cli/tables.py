"""``esmm tables``: rebuild an asset's stiffness tables (material, force law, compensation)."""

from __future__ import annotations

import argparse

from esmm.pipeline.compensation.policy import (
    DEFAULT_RADIUS_ELEMENTS,
    DEFAULT_RANGE,
    RADIUS_ELEMENTS_RANGE,
)
from esmm.pipeline.errors import ConfigError

EPILOG = """\
examples:
  esmm tables liver.h5                               (rebuild from the asset's own material)
  esmm tables liver.h5 --material my_fit/params.toml (tables and /material from another fit)
  esmm tables liver.h5 --law energy                  (make the energy-consistent law the default)
  esmm tables liver.h5 --compensate                  (calibrate on a virtual tensile test, ~10-60 s)
  esmm tables liver.h5 --per-spring                  (also store k_ij(lambda) per spring, large)

The file is rewritten atomically (a new file, validated, then renamed over the old one).
A compensation already in the asset is kept when the material and the grid do not change.
Exit codes: 0 written; 2 bad asset, material or option; 3 the virtual tensile test failed.
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tables",
        help="rebuild an asset's stiffness tables (material, force law, compensation)",
        description="Rebuild the /tables group of an asset: mu_e(lambda) and the uniaxial stress "
        "of the material on a stretch grid, the default spring force law, optionally the "
        "per-spring stiffness table and the volumetric compensation found by a virtual "
        "tensile test on a cylinder meshed like the asset (docs/guide/tables.md).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("asset", metavar="ASSET.h5", help="asset written by 'esmm prepare'")
    p.add_argument("--material", metavar="FILE_OR_NAME",
                   help="material preset name or TOML file (default: the asset's material); "
                        "also replaces the asset's /material")
    p.add_argument("--law", choices=("secant", "energy"),
                   help="default spring force law (default: keep the asset's, else secant)")
    p.add_argument("--points", metavar="N", help="number of grid points (default: keep, else 1024)")
    p.add_argument("--stretch-range", nargs=2, metavar=("LO", "HI"),
                   help="grid ends (default: just inside the material's admissible range)")
    p.add_argument("--per-spring", action="store_true",
                   help="also write the per-spring table k_ij(lambda) (springs x points, float32)")
    p.add_argument("--compensate", action="store_true",
                   help="calibrate the volumetric compensation for the default law on a virtual "
                        "tensile test (scalar factor + stretch correction)")
    p.add_argument("--calibration-range", nargs=2, metavar=("LO", "HI"), default=None,
                   help=f"compression and tension ends of the calibration (default {DEFAULT_RANGE[0]:g} "
                        f"{DEFAULT_RANGE[1]:g}, clipped to the grid)")
    p.add_argument("--specimen-elements", dest="radius_elements", metavar="R", default=None,
                   help=f"radius of the calibration cylinder in element sizes (default "
                        f"{DEFAULT_RADIUS_ELEMENTS:g}, {RADIUS_ELEMENTS_RANGE[0]:g} to "
                        f"{RADIUS_ELEMENTS_RANGE[1]:g}; the element size is the asset's median spring "
                        "length; larger = slower, closer to the bulk)")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    p.set_defaults(func=run)


def _check_options(args, asset) -> None:
    """Refuse, in the command's terms, what :func:`~esmm.pipeline.retable.rebuild_tables` would refuse."""
    from esmm.pipeline.retable import unused_options

    if args.material is None and asset.material is None:
        raise ConfigError(f"{args.asset}: the asset stores no material; give one with --material")
    unused = unused_options(asset, material_given=args.material is not None, compensate=args.compensate,
                            calibration_range=args.calibration_range, radius_elements=args.radius_elements)
    if "radius_elements" in unused:
        raise ConfigError("radius_elements: only used by the virtual tensile test; add --compensate or remove it",
                          parameter="radius_elements")
    if "calibration_range" in unused:
        raise ConfigError("calibration_range: only used by the virtual tensile test (and to re-size the asset's "
                          "volume term for a new --material); add --compensate or remove it",
                          parameter="calibration_range")


def _summary(args, material, tables, carried: bool, comp) -> dict:
    from esmm.pipeline.network.tables import LAWS

    # mu_e at 1 and at 1.1, or at the grid's end when the grid stops short of 1.1 (the table
    # holds nothing beyond it: a value "at 1.1" would be the end's, mislabelled).
    lam2 = 1.1 if tables.lam_max >= 1.1 else tables.lam_max
    mu = tables.mu_e([1.0, lam2, 1.3 if tables.lam_max >= 1.3 else tables.lam_max])[2]
    summary = {
        "asset": str(args.asset), "material": getattr(material, "name", ""),
        "grid": {"lam_min": tables.lam_min, "lam_max": tables.lam_max, "n": tables.n, "dlam": tables.dlam},
        "default_law": tables.default_law, "volume_factor": tables.volume_factor,
        "corrected_laws": [lw for lw in LAWS if tables.is_corrected(lw)],
        "compensation_kept": carried, "per_spring": bool(args.per_spring),
        "mu_e_MPa": {"1.0": mu[0] / 1e6, ("1.1" if lam2 == 1.1 else f"{lam2:.6g}"): mu[1] / 1e6},
    }
    if comp is not None:
        rec = comp.record
        summary["compensation"] = {
            "law": rec["law"], "volume_factor": rec["volume_factor"], "iterations": rec["iterations"],
            "converged": rec["converged"], "specimen": rec["specimen"],
            "max_error_before": rec["errors_before"]["max_abs_rel_error"],
            "max_error_scalar_only": rec["errors_scalar"]["max_abs_rel_error"],
            "max_error_after": rec["errors_after"]["max_abs_rel_error"],
            "stretch_range": rec["stretch_range"],
            "reused_from": None if comp.reused is None else str(comp.reused),
        }
    return summary


def _text(summary: dict, tables, n_springs: int) -> list[str]:
    mu = summary["mu_e_MPa"]
    at2 = next(k for k in mu if k != "1.0")
    end = "" if at2 == "1.1" else " (the grid's end)"
    comp_text = ("none" if tables.volume_factor == 1.0 and not summary["corrected_laws"] else
                 f"c = {tables.volume_factor:.4g}, stretch correction for "
                 f"{', '.join(summary['corrected_laws']) or 'no law'}"
                 + (" (kept)" if summary["compensation_kept"] else ""))
    lines = [f"{summary['asset']}: tables rewritten",
             f"  material     {summary['material']}",
             f"  grid         stretch {tables.lam_min:.4g} .. {tables.lam_max:.4g}, {tables.n} points",
             f"  mu_e         {mu['1.0']:.5g} MPa at 1 (small-strain E), {mu[at2]:.5g} MPa at {at2}{end}",
             f"  law          {tables.default_law} (default)",
             f"  compensation {comp_text}"]
    c = summary.get("compensation")
    if c is not None:
        lines.append(f"  virtual test {c['specimen']['nodes']} nodes, stretch {c['stretch_range'][0]:.3g} .. "
                     f"{c['stretch_range'][1]:.3g}: max |stress error| {100 * c['max_error_before']:.1f} % "
                     f"uncompensated, {100 * c['max_error_scalar_only']:.1f} % with c only, "
                     f"{100 * c['max_error_after']:.2f} % compensated"
                     + ("" if c["converged"] else " (NOT converged)")
                     + (f" (calibration reused from {c['reused_from']})" if c["reused_from"] else ""))
    if summary["per_spring"]:
        lines.append(f"  per-spring   /tables/k_per_spring ({n_springs} x {tables.n})")
    return lines


def run(args, ui) -> int:
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.atomicio import json_text
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.retable import rebuild_tables

    asset = read_asset(args.asset)
    material = None if args.material is None else load_material(args.material)
    _check_options(args, asset)
    result = rebuild_tables(asset, material=material, law=args.law, points=args.points,
                            stretch_range=args.stretch_range, per_spring=args.per_spring, compensate=args.compensate,
                            calibration_range=args.calibration_range, radius_elements=args.radius_elements,
                            argv=["esmm", *getattr(args, "_argv", [])], reporter=ui)
    summary = _summary(args, result.material, result.tables, result.compensation_kept, result.compensation)
    if args.json:
        ui.info(json_text(summary).rstrip("\n"))
        return 0
    for line in _text(summary, result.tables, asset.network.n_springs):
        ui.info(line)
    return 0
