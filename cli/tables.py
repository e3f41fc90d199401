"""``esmm tables``: rebuild an asset's stiffness tables (material, force law, compensation)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from datetime import UTC, datetime

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
        "tensile test on a cylinder meshed like the asset (docs/model.md).",
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


def _material(args, asset):
    from esmm.pipeline.materials.material import load_material

    if args.material is not None:
        return load_material(args.material)
    if asset.material is not None:
        return asset.material
    raise ConfigError(f"{args.asset}: the asset stores no material; give one with --material")


def _grid(args, old) -> dict:
    """The grid options of build_tables: the command line's, else the asset's (same material)."""
    from esmm.pipeline.checks import number_text

    n = None if args.points is None else number_text(args.points, "points", lo=3, hi=1_000_000, integer=True)
    n = n or (old.n if old is not None else None)
    lo = hi = None
    if args.stretch_range is not None:
        lo, hi = (number_text(v, "stretch_range") for v in args.stretch_range)
        if not 0 < lo < 1 < hi:
            raise ConfigError(f"stretch_range: need 0 < LO < 1 < HI, got {lo:g} {hi:g}", parameter="stretch_range")
    elif old is not None and args.material is None:
        lo, hi = old.lam_min, old.lam_max
    return {"lam_min": lo, "lam_max": hi, **({} if n is None else {"n": n})}


def _carry(tables, old, args, ui):
    """*tables* with the asset's compensation when the material and grid are unchanged: (tables, kept)."""
    from esmm.pipeline.network.tables import LAWS

    if old is None or (old.volume_factor == 1.0 and not any(old.is_corrected(lw) for lw in LAWS)):
        return tables, False
    same = (old.material_toml == tables.material_toml and old.n == tables.n
            and math.isclose(old.lam_min, tables.lam_min, rel_tol=1e-12)
            and math.isclose(old.lam_max, tables.lam_max, rel_tol=1e-12))
    if same:
        return tables.with_compensation(
            old.volume_factor, correction={lw: old.correction[i] for i, lw in enumerate(LAWS)},
            record=old.metadata.get("compensation")), True
    if not args.compensate:
        ui.warn("the asset's compensation was dropped (the material or the grid changed); "
                "run again with --compensate")
    return tables, False


def _calibration_range(args):
    from esmm.pipeline.checks import number_text

    if args.calibration_range is None:
        return None
    return tuple(number_text(v, "calibration_range") for v in args.calibration_range)


def _volume(tables, asset, args, ui):
    """The asset's volume term for these tables: (spec or None, replaced?).

    Kept as it is for the same material; re-sized (same Poisson ratio) when
    ``--material`` gives another one, since its bulk modulus follows the material.
    """
    from esmm.pipeline.compensation.calibration import calibration_stretches
    from esmm.pipeline.network.volume import DEFAULT_POISSON, bulk_modulus

    old = asset.network.volume_term
    if old is None or args.material is None:
        return old, False
    nu = DEFAULT_POISSON if old.poisson_ratio is None else old.poisson_ratio
    spec = bulk_modulus(tables, poisson=nu, calibration_range=calibration_stretches(tables, _calibration_range(args)),
                        formulation=old.formulation)
    ui.step(f"volume term re-sized for the new material: bulk modulus {old.bulk_modulus / 1e3:.4g} -> "
            f"{spec.bulk_modulus / 1e3:.4g} kPa (Poisson ratio {nu:g})")
    return spec, True


def _compensate(tables, asset, material, volume, args, ui):
    """The compensation of ``esmm prepare`` (same policy and cache), with the command line's overrides."""
    from esmm.pipeline.checks import number_text
    from esmm.pipeline.compensation.calibration import compensate

    r_el = None if args.radius_elements is None else number_text(args.radius_elements, "radius_elements")
    return compensate(tables, asset.network, material=material, calibration_range=_calibration_range(args),
                      radius_elements=r_el, volume=volume, reporter=ui)


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
    from esmm.pipeline.asset import read_asset, update_asset_tables
    from esmm.pipeline.atomicio import json_text
    from esmm.pipeline.network.tables import build_tables

    asset = read_asset(args.asset)
    material = _material(args, asset)
    law = args.law or (asset.tables.default_law if asset.tables is not None else "secant")
    if args.radius_elements is not None and not args.compensate:
        raise ConfigError("radius_elements: only used by the virtual tensile test; add --compensate or remove it",
                          parameter="radius_elements")
    if (args.calibration_range is not None and not args.compensate
            and not (args.material is not None and asset.network.volume_term is not None)):
        raise ConfigError("calibration_range: only used by the virtual tensile test (and to re-size the asset's "
                          "volume term for a new --material); add --compensate or remove it",
                          parameter="calibration_range")
    grid = _grid(args, asset.tables)
    try:
        tables = build_tables(material, law=law, **grid)
    except ConfigError as exc:   # the library names its grid "lam_min/lam_max"; here it is --stretch-range
        prefix = "lam_min/lam_max:"
        if args.stretch_range is None or not str(exc).startswith(prefix):
            raise
        raise ConfigError("stretch_range:" + str(exc)[len(prefix):], parameter="stretch_range") from None
    tables, carried = _carry(tables, asset.tables, args, ui)
    volume, resized = _volume(tables, asset, args, ui)
    comp = None
    if args.compensate:
        comp = _compensate(tables, asset, material, volume, args, ui)
        tables, carried = comp.tables, False
        if comp.reused is not None and not comp.record.get("converged", True):
            # calibrated earlier (its warning then is not repeated by the library): say it again
            ui.warn(f"the reused compensation did not converge (max |stress error| "
                    f"{100 * comp.record['errors_after']['max_abs_rel_error']:.2f} %); try a narrower "
                    f"--calibration-range")
    meta = dict(tables.metadata)
    meta["written_by"] = {"command": ["esmm", *getattr(args, "_argv", [])],
                          "utc": datetime.now(UTC).isoformat(timespec="seconds")}
    tables = dataclasses.replace(tables, metadata=meta)
    update_asset_tables(args.asset, tables, material=material if args.material is not None else None,
                        per_spring=args.per_spring, volume=volume if resized else None, reporter=ui)
    summary = _summary(args, material, tables, carried, comp)
    if args.json:
        ui.info(json_text(summary).rstrip("\n"))
        return 0
    for line in _text(summary, tables, asset.network.n_springs):
        ui.info(line)
    return 0
