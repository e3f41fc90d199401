"""``esmm tables``: rebuild an asset's stiffness tables (material, force law, compensation)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from datetime import UTC, datetime

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
                   help="compression and tension ends of the calibration (default 0.9 1.3, "
                        "clipped to the grid)")
    p.add_argument("--specimen-elements", metavar="R", default=None,
                   help="radius of the calibration cylinder in element sizes (default 4; the "
                        "element size is the asset's median spring length; larger = slower, "
                        "closer to the bulk)")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    p.set_defaults(func=run)


def _float(text: str, option: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ConfigError(f"{option}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{option}: expected a finite number, got {text!r}")
    return v


def _points(text) -> int | None:
    if text is None:
        return None
    try:
        n = int(text)
    except ValueError:
        raise ConfigError(f"--points: expected a whole number, got {text!r}") from None
    if n < 3 or n > 1_000_000:
        raise ConfigError(f"--points: expected 3 to 1000000 grid points, got {n}")
    return n


def run(args, ui) -> int:
    from esmm.pipeline.asset import read_asset, update_asset_tables
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.network.tables import LAWS, build_tables

    asset = read_asset(args.asset)
    old = asset.tables
    if args.material is not None:
        material = load_material(args.material)
    elif asset.material is not None:
        material = asset.material
    else:
        raise ConfigError(f"{args.asset}: the asset stores no material; give one with --material")
    law = args.law or (old.default_law if old is not None else "secant")
    n = _points(args.points) or (old.n if old is not None else None)
    lo = hi = None
    if args.stretch_range is not None:
        lo, hi = (_float(v, "--stretch-range") for v in args.stretch_range)
    elif old is not None and args.material is None:
        lo, hi = old.lam_min, old.lam_max
    kw = {} if n is None else {"n": n}
    tables = build_tables(material, lam_min=lo, lam_max=hi, law=law, **kw)

    carried = False
    if old is not None and (old.volume_factor != 1.0 or any(old.is_corrected(lw) for lw in LAWS)):
        same = (old.material_toml == tables.material_toml and old.n == tables.n
                and math.isclose(old.lam_min, tables.lam_min, rel_tol=1e-12)
                and math.isclose(old.lam_max, tables.lam_max, rel_tol=1e-12))
        if same:
            tables = tables.with_compensation(
                old.volume_factor, correction={lw: old.correction[i] for i, lw in enumerate(LAWS)},
                record=old.metadata.get("compensation"))
            carried = True
        elif not args.compensate:
            ui.warn("the asset's compensation was dropped (the material or the grid changed); "
                    "run again with --compensate")

    calib = None
    if args.compensate:
        from esmm.pipeline.network.compensation import calibrate_compensation, specimen_for

        c_lo, c_hi = 0.9, 1.3
        if args.calibration_range is not None:
            c_lo, c_hi = (_float(v, "--calibration-range") for v in args.calibration_range)
            if not c_lo < 1.0 < c_hi:
                raise ConfigError(f"--calibration-range: need LO < 1 < HI, got {c_lo:g} {c_hi:g}")
        c_lo = max(c_lo, tables.lam_min + 2 * tables.dlam)
        c_hi = min(c_hi, tables.lam_max - 2 * tables.dlam)
        r_el = 4.0 if args.specimen_elements is None else _float(args.specimen_elements, "--specimen-elements")
        if not 1.5 <= r_el <= 20:
            raise ConfigError(f"--specimen-elements: expected 1.5 to 20 element sizes, got {r_el:g}")
        specimen = specimen_for(asset.network, radius_elements=r_el, reporter=ui)
        tables, calib = calibrate_compensation(tables, specimen, law=law, material=material,
                                               tension=c_hi, compression=c_lo, reporter=ui)
        carried = False

    meta = dict(tables.metadata)
    meta["written_by"] = {"command": ["esmm", *getattr(args, "_argv", [])],
                          "utc": datetime.now(UTC).isoformat(timespec="seconds")}
    tables = dataclasses.replace(tables, metadata=meta)
    update_asset_tables(args.asset, tables, material=material if args.material is not None else None,
                        per_spring=args.per_spring, reporter=ui)

    mu = tables.mu_e([1.0, 1.1, 1.3 if tables.lam_max >= 1.3 else tables.lam_max])[2]
    summary = {
        "asset": str(args.asset), "material": getattr(material, "name", ""),
        "grid": {"lam_min": tables.lam_min, "lam_max": tables.lam_max, "n": tables.n, "dlam": tables.dlam},
        "default_law": tables.default_law, "volume_factor": tables.volume_factor,
        "corrected_laws": [lw for lw in LAWS if tables.is_corrected(lw)],
        "compensation_kept": carried, "per_spring": bool(args.per_spring),
        "mu_e_MPa": {"1.0": mu[0] / 1e6, "1.1": mu[1] / 1e6},
    }
    if calib is not None:
        summary["compensation"] = {
            "law": calib.law, "volume_factor": calib.factor, "iterations": calib.iterations,
            "converged": calib.converged, "specimen": calib.specimen,
            "max_error_before": calib.before.max_abs_rel_error,
            "max_error_scalar_only": calib.scalar.max_abs_rel_error,
            "max_error_after": calib.after.max_abs_rel_error,
            "stretch_range": [float(calib.after.stretch.min()), float(calib.after.stretch.max())],
        }
    if args.json:
        ui.info(json.dumps(summary, indent=2))
        return 0
    ui.info(f"{args.asset}: tables rewritten")
    ui.info(f"  material     {summary['material']}")
    ui.info(f"  grid         stretch {tables.lam_min:.4g} .. {tables.lam_max:.4g}, {tables.n} points")
    ui.info(f"  mu_e         {mu[0] / 1e6:.5g} MPa at 1 (small-strain E), {mu[1] / 1e6:.5g} MPa at 1.1")
    ui.info(f"  law          {tables.default_law} (default)")
    comp = ("none" if tables.volume_factor == 1.0 and not summary["corrected_laws"] else
            f"c = {tables.volume_factor:.4g}, stretch correction for "
            f"{', '.join(summary['corrected_laws']) or 'no law'}" + (" (kept)" if carried else ""))
    ui.info(f"  compensation {comp}")
    if calib is not None:
        c = summary["compensation"]
        ui.info(f"  virtual test {c['specimen']['nodes']} nodes, stretch {c['stretch_range'][0]:.3g} .. "
                f"{c['stretch_range'][1]:.3g}: max |stress error| {100 * c['max_error_before']:.1f} % "
                f"uncompensated, {100 * c['max_error_scalar_only']:.1f} % with c only, "
                f"{100 * c['max_error_after']:.2f} % compensated")
    if args.per_spring:
        ui.info(f"  per-spring   /tables/k_per_spring ({asset.network.n_springs} x {tables.n})")
    return 0
