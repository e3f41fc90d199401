"""``esmm validate``: the spring network against an independent finite-element reference."""

from __future__ import annotations

import argparse

EPILOG = """\
cases: tension, compression (frictionless grips on the end faces along z), shear (bottom
face clamped, top face moved sideways), gravity (the organ on its bed: the scene's anchor
and floor), lift (the bed, and the grasped patch moved by the scene's lift). Default: the
organ cases for an ASSET, the specimen cases for --specimen. docs/guide/validate.md states every
boundary condition and the figures.

outputs (in --out DIR, default ASSET-validate/ or specimen-validate/):
  validation.md, validation.json   the table and every figure per case
  CASE.png                         the continuum and the network side by side, and the error
  CASE.xdmf + CASE.h5              both displacement fields and their difference (ParaView)

examples:
  esmm validate liver.h5
  esmm validate --specimen --size 2.5 --json spec.json
  esmm validate liver.h5 --cases gravity --volume-term off --out runs/val
"""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "validate", help="compare the network with a finite-element continuum, case by case",
        description="Solve the asset's mesh with its material as a nearly incompressible hyperelastic "
                    "continuum (felupe) and the spring network under the same load cases, and report the "
                    "displacement, force and volume errors of the network.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("asset", metavar="ASSET.h5", nargs="?", default=None, help="asset written by 'esmm prepare'")
    p.add_argument("--specimen", action="store_true",
                   help="validate on the built-in specimen (a meshed cube) instead of an asset")
    p.add_argument("--side", metavar="MM", type=float, default=None, help="specimen cube edge in mm (20)")
    p.add_argument("--size", metavar="MM", type=float, default=None, help="specimen element size in mm (2.5)")
    p.add_argument("--split", action="store_true", default=None,
                   help="split the specimen's tets in eight, as 'esmm prepare --split' does (springs of half --size)")
    p.add_argument("--material", metavar="FILE_OR_NAME", default=None,
                   help="specimen material: preset name or TOML file (default porcine_liver_paper)")
    p.add_argument("--cases", metavar="CASE", nargs="+", default=None,
                   help="tension, compression, shear, gravity, lift")
    p.add_argument("--volume-term", dest="volume_term", choices=("auto", "on", "off"), default="auto",
                   help="the network with its volume term (on), without it (off), or with it if the asset "
                        "has one (auto, default)")
    p.add_argument("--law", choices=("secant", "energy"), default=None, help="network force law (the tables')")
    p.add_argument("--element", choices=("auto", "p2", "mini"), default="auto",
                   help="continuum element: quadratic tets (p2, the reference) or MINI (first order); "
                        "auto: p2 up to a size (docs/design/validation.md), MINI above it and for a case p2 "
                        "cannot solve")
    p.add_argument("--scene", metavar="C", default=None, help="scene of the organ cases (default 'default')")
    p.add_argument("--jobs", metavar="N", type=int, default=None,
                   help="cases solved at once, one process each (default: the usable cores)")
    p.add_argument("--json", metavar="OUT.json", default=None, help="also write the figures there ('-': stdout)")
    p.add_argument("--out", metavar="DIR", default=None, help="output folder")
    p.set_defaults(func=run)
    return p


def _check_kind_options(args) -> None:
    """Refuse options of the other kind of run: they would be ignored without a word."""
    from esmm.pipeline.errors import ConfigError

    if not args.specimen:
        given = [f for f, v in (("--side", args.side), ("--size", args.size), ("--material", args.material),
                                ("--split", args.split)) if v is not None]
        if given:
            raise ConfigError(f"{', '.join(given)}: describe the built-in specimen (--specimen), not used with "
                              f"an ASSET (its mesh and material are in the asset); drop them or validate "
                              f"--specimen instead")
    elif args.scene is not None:
        raise ConfigError("--scene: sets the organ cases' scene, not used with --specimen; drop it or give an "
                          "ASSET.h5")


def run(args, ui) -> int:
    import math
    from pathlib import Path

    from esmm.cli.outputs import check_out_dir, check_out_file
    from esmm.pipeline.atomicio import json_text, write_json
    from esmm.pipeline.errors import ConfigError, SimulationError
    from esmm.pipeline.fidelity.validate import (
        LoadOptions,
        default_out_dir,
        validate_asset,
        validate_specimen,
    )
    from esmm.pipeline.materials.material import load_material

    if (args.asset is None) == (not args.specimen):
        raise ConfigError("give an ASSET.h5 or --specimen (one of them)")
    _check_kind_options(args)
    for flag, mm in (("--side", args.side), ("--size", args.size)):
        if mm is not None and not (math.isfinite(mm) and mm > 0):
            raise ConfigError(f"{flag}: expected a positive length in mm, got {mm:g}")
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs: expected a positive number of processes, got {args.jobs}")
    if args.json not in (None, "-"):
        check_out_file(args.json, "--json", "validation.json")
    opts = {"cases": args.cases, "volume_term": args.volume_term, "law": args.law, "element": args.element,
            "loads": LoadOptions(scene=args.scene), "jobs": args.jobs, "reporter": ui}
    out = Path(args.out) if args.out else default_out_dir(args.asset)
    check_out_dir(out, "--out")
    if args.specimen:
        cube = {name: mm * 1e-3 for name, mm in (("side", args.side), ("size", args.size)) if mm is not None}
        rep = validate_specimen(None if args.material is None else load_material(args.material),
                                split=bool(args.split), out_dir=out, **cube, **opts)
    else:
        rep = validate_asset(args.asset, out_dir=out, **opts)
    say = ui.step if args.json == "-" else ui.info    # with --json -, stdout is the JSON alone
    say(f"validated {rep.label} (volume term {rep.volume_term}, continuum element {rep.info['element']}, "
        f"{rep.info['seconds']:.3g} s)")
    say(rep.table())
    if args.json == "-":
        ui.info(json_text(rep.figures()).rstrip("\n"))
    elif args.json:
        write_json(args.json, rep.figures())
    say(f"outputs: {out}")
    failed = rep.info.get("failed", {})
    if failed:  # the other cases are reported and written; the run is not a complete validation
        ui.error(f"{len(failed)} case(s) without an equilibrium ({', '.join(failed)}): see the table above; "
                 f"the table gives each solver's reason; another continuum element (--element) or a lighter "
                 f"scene (--scene) may converge")
        return SimulationError.exit_code
    return 0
