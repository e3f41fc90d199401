"""``esmm prepare``: turn an organ surface into a spring-network asset (.h5 + .xdmf)."""

from __future__ import annotations

import argparse
import math

from esmm.pipeline.errors import ConfigError

EPILOG = """\
examples:
  esmm prepare liver.stl                          (-> liver.h5 + liver.xdmf here, preset "paper")
  esmm prepare liver.stl -o assets/liver.h5 --size 6
  esmm prepare liver.stl --config coarse --structure skeleton
  esmm prepare seg.nii.gz --label 5 --nodes 2000 --material my_fit/params.toml
  esmm prepare p01/liver.stl p02/liver.stl --out assets/ --config coarse   (a batch: assets/p01/liver.h5, ...)

Presets (--config): coarse (~1 500 tets), paper (~5 000 tets, default), fine (~30 000 tets),
or a TOML file (docs/prepare-config.md). Options given here override the config.
Exit codes: 0 written, 2 bad input/options, 3 meshing failed, 4 mesh below the quality
floors (--force writes it anyway); a batch: 5 if any organ failed, 130 interrupted.
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "prepare",
        help="turn an organ surface into a spring-network asset",
        description="Read an organ surface (STL, OBJ, PLY, VTK, legacy .msh or a NIfTI label mask), "
        "clean it, mesh it, build the spring network, the stiffness tables and the fixed region, "
        "and write one HDF5 asset with an XDMF sidecar for ParaView.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="organ surface or label mask; several make a batch (with --out)")
    p.add_argument("-o", "--output", metavar="ASSET.h5",
                   help="asset file (default: <input stem>.h5 in the current folder)")
    b = p.add_argument_group("batch (several inputs, or --out)")
    b.add_argument("--out", metavar="DIR",
                   help="folder for the assets (<stem>.h5 each), the batch log, the summary and the cache")
    b.add_argument("--jobs", type=int, default=None, metavar="N", help="local worker processes (default: all cores)")
    b.add_argument("--scheduler", metavar="ADDR", default=None,
                   help="'local' (default), 'serial', or a Dask scheduler address, e.g. tcp://10.0.0.5:8786")
    b.add_argument("--redo", action="store_true",
                   help="recompute organs whose assets are already in --out (cached); --force is the quality override")
    p.add_argument("--config", metavar="C", help="prepare preset (coarse, paper, fine) or TOML file; default paper")
    p.add_argument("--size", metavar="MM", help="target tet size in mm (instead of the preset's target)")
    p.add_argument("--nodes", metavar="N", help="target number of mesh nodes")
    p.add_argument("--elements", metavar="N", help="target number of tetrahedra")
    p.add_argument("--structure", metavar="S", help="tetra (default) or skeleton")
    p.add_argument("--unit", metavar="U", help="length unit of the input file: mm (default), cm or m")
    p.add_argument("--label", metavar="N", help="label to extract from a mask input")
    p.add_argument("--keep-all", action="store_true", help="keep every body (default: the largest)")
    p.add_argument("--body", metavar="N", help="keep body N (0 = largest, by volume)")
    p.add_argument("--material", metavar="FILE_OR_NAME",
                   help="material preset name or TOML file (default porcine_liver_paper)")
    p.add_argument("--density", metavar="KG_M3", help="tissue density in kg/m3 (default 1060)")
    p.add_argument("--no-compensate", dest="compensate", action="store_false", default=None,
                   help="skip the volumetric compensation (one virtual tensile test of the mesh, "
                        "a few tens of seconds); the raw network is then ~6x too soft")
    p.add_argument("--force", action="store_true", help="write the asset even if the mesh is below the quality floors")
    p.set_defaults(func=run)


def _number(text, option: str, *, integer: bool = False, positive: bool = True):
    if text is None:
        return None
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        kind = "a whole number" if integer else "a number"
        raise ConfigError(f"{option}: expected {kind}, got {text!r}") from None
    if not math.isfinite(value) or (positive and value <= 0) or value < 0:
        sign = "positive" if positive else "non-negative"
        raise ConfigError(f"{option}: expected a {sign} {'whole ' if integer else ''}number, got {text!r}")
    return value


def run(args, ui) -> int:
    from esmm.pipeline.prepare import prepare

    given = [o for o, v in (("--size", args.size), ("--nodes", args.nodes), ("--elements", args.elements))
             if v is not None]
    if len(given) > 1:
        raise ConfigError(f"give one of {', '.join(given)}, not several")
    if args.keep_all and args.body is not None:
        raise ConfigError("give either --keep-all or --body, not both")
    if args.structure is not None and args.structure not in ("tetra", "skeleton"):
        raise ConfigError(f"--structure: {args.structure!r} is not tetra or skeleton")
    size_mm = _number(args.size, "--size (mm)")
    options = dict(
        config=args.config, size=None if size_mm is None else size_mm * 1e-3,
        nodes=_number(args.nodes, "--nodes", integer=True),
        elements=_number(args.elements, "--elements", integer=True),
        structure=args.structure, unit=args.unit,
        label=_number(args.label, "--label", integer=True, positive=False),
        keep_all=args.keep_all, body=_number(args.body, "--body", integer=True, positive=False),
        material=args.material, density=_number(args.density, "--density (kg/m3)"),
        force=args.force, compensate=args.compensate,
    )
    argv = ["esmm", *getattr(args, "_argv", [])]
    if len(args.inputs) > 1 or args.out:
        if args.output:
            raise ConfigError("-o names one asset; for several inputs give --out DIR")
        if not args.out:
            raise ConfigError(f"{len(args.inputs)} inputs: give --out DIR for their assets")
        from esmm.pipeline.batch.prepare import prepare_batch

        summary = prepare_batch(args.inputs, out_dir=args.out, options=options, argv=argv,
                                scheduler=args.scheduler, workers=args.jobs, force=args.redo, reporter=ui)
        ui.info(summary.table())
        ui.info(f"assets in {summary.out_dir}; batch-summary.csv and "
                f"{summary.log_path.name if summary.log_path else 'the batch log'} there too")
        return summary.exit_code
    if args.redo or args.scheduler or args.jobs:
        raise ConfigError("--redo, --scheduler and --jobs apply to a batch: give --out DIR")
    result = prepare(args.inputs[0], output=args.output, reporter=ui, argv=argv, **options)
    for line in result.summary_lines():
        ui.info(line)
    return 0
