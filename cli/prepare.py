"""``esmm prepare``: turn an organ surface into a spring-network asset (.h5 + .xdmf)."""

from __future__ import annotations

import argparse
from pathlib import Path

from esmm.pipeline.errors import ConfigError, QualityError

EPILOG = """\
examples:
  esmm prepare liver.stl                          (-> liver.h5 + liver.xdmf here, preset "paper")
  esmm prepare liver.stl -o assets/liver.h5 --size 6
  esmm prepare liver.stl --config coarse --structure skeleton
  esmm prepare seg.nii.gz --label 5 --nodes 2000 --material my_fit/params.toml
  esmm prepare p01/liver.stl p02/liver.stl --out assets/ --config coarse   (a batch: assets/p01/liver.h5, ...)

Presets (--config): coarse (~1 500 tets), paper (~5 000 tets, default), fine (~30 000 tets),
or a TOML file (docs/reference/configuration.md). Options given here override the config.
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
    b.add_argument("--jobs", type=int, default=None, metavar="N", dest="workers", help="local worker processes (default: all cores)")
    b.add_argument("--scheduler", metavar="ADDR", default=None,
                   help="'local' (default), 'serial', or a Dask scheduler address, e.g. tcp://10.0.0.5:8786")
    b.add_argument("--redo", action="store_true",
                   help="recompute organs whose assets are already in --out (cached); --force is the quality override")
    p.add_argument("--config", metavar="C", help="prepare preset (coarse, paper, fine) or TOML file; default paper")
    p.add_argument("--size", metavar="MM", help="target tet size in mm (instead of the preset's target)")
    p.add_argument("--nodes", metavar="N", help="target number of mesh nodes")
    p.add_argument("--elements", metavar="N", help="target number of tetrahedra")
    p.add_argument("--structure", metavar="S", help="tetra (default) or skeleton")
    p.add_argument("--unit", metavar="U", help="length unit of the input file: mm (default), cm or m; "
                   "given, it wins over a NIfTI mask's header unit (used by default)")
    p.add_argument("--label", metavar="N", help="label to extract from a mask input")
    p.add_argument("--keep-all", action="store_true", help="keep every body (default: the largest)")
    p.add_argument("--body", metavar="N", help="keep body N (0 = largest, by volume)")
    p.add_argument("--material", metavar="FILE_OR_NAME",
                   help="material preset name or TOML file (default porcine_liver_paper)")
    p.add_argument("--density", metavar="KG_M3", help="tissue density in kg/m3 (default 1060)")
    p.add_argument("--no-compensate", dest="compensate", action="store_false", default=None,
                   help="skip the volumetric compensation (one virtual tensile test of the mesh, "
                        "a few tens of seconds); the raw network is then ~6x too soft")
    p.add_argument("--no-volume", dest="volume", action="store_false", default=None,
                   help="give the network no volume term (it then loses volume under load: Poisson ratio ~1/4); "
                        "by default the tet network keeps the organ's volume")
    p.add_argument("--split", action="store_true", default=None,
                   help="split every tet of the mesh in eight: the network on the quadratic tets' nodes, "
                        "within a few %% of the continuum where the unsplit one is 5-17 %% stiff, at ~6x the "
                        "nodes and ~12x the simulation cost (docs/design/model.md)")
    p.add_argument("--force", action="store_true", help="write the asset even if the mesh is below the quality floors")
    p.set_defaults(func=run)


def _summary_lines(result) -> list[str]:
    """What ``esmm prepare`` prints about a :class:`~esmm.pipeline.prepare.PrepareResult`."""
    net = result.network
    lines = [
        f"structure   {net.structure} ({result.mesher})",
        f"nodes       {net.n_nodes}",
        f"springs     {net.n_springs}",
    ]
    if net.tets is not None:
        lines.append(f"tets        {net.n_tets}")
    lines += [
        f"volume      {net.total_volume() * 1e6:.2f} mL, mass {net.total_mass() * 1e3:.1f} g",
        f"rest length {net.rest_length.min() * 1e3:.2f} .. {net.rest_length.max() * 1e3:.2f} mm "
        f"(mean {net.rest_length.mean() * 1e3:.2f})",
        f"fixed       {net.fixed.size} nodes",
    ]
    if result.quality is not None:
        verdict = "passes the floors" if result.quality_passed else "BELOW the floors (--force)"
        lines.append(f"quality     min dihedral {result.quality.min_dihedral_deg:.1f} deg, {verdict}")
    t = result.tables
    lines.append(f"tables      {t.n} points, stretch {t.lam_min:.3g}..{t.lam_max:.3g}")
    lines.append("time        " + ", ".join(f"{k} {v:.1f} s" for k, v in result.timings.items())
                 + f" (total {sum(result.timings.values()):.1f} s)")
    lines.append(f"wrote       {result.asset}")
    lines.append(f"            {result.xdmf} (open in ParaView or meshio; .springs.xdmf, .surface.xdmf beside it)")
    if result.report is not None:
        lines.append(f"            {result.report} (how far to trust it, in a browser)")
    return lines


def _options(args) -> dict:
    """The keyword options of :func:`~esmm.pipeline.prepare.prepare` from the command line.

    Text becomes numbers here (``--size`` is in mm); the library checks the values
    and names the option it refuses.
    """
    from esmm.pipeline.checks import number_text

    def whole(text, name):
        return None if text is None else number_text(text, name, integer=True)

    size_mm = None if args.size is None else number_text(args.size, "size", lo=0.0, lo_open=True)
    return dict(
        config=args.config, size=None if size_mm is None else size_mm * 1e-3,
        nodes=whole(args.nodes, "nodes"), elements=whole(args.elements, "elements"),
        structure=args.structure, unit=args.unit, label=whole(args.label, "label"),
        keep_all=args.keep_all, body=whole(args.body, "body"), material=args.material,
        density=None if args.density is None else number_text(args.density, "density"),
        force=args.force, compensate=args.compensate, volume=args.volume, split=args.split,
    )


class _FlagReporter:
    """The UI as prepare's reporter, a warning's leading library parameter name (``unit:``) shown as the
    option that sets it (``--unit:``), as errors are (:func:`esmm.cli.main.flag_message`)."""

    FLAGS = {"unit": "--unit", "label": "--label", "density": "--density", "material": "--material"}

    def __init__(self, ui) -> None:
        self._ui = ui

    def __getattr__(self, name):
        return getattr(self._ui, name)

    def warn(self, message: str) -> None:
        head, sep, rest = message.partition(":")
        self._ui.warn(self.FLAGS[head] + sep + rest if sep and head in self.FLAGS else message)


def run(args, ui) -> int:
    from esmm.pipeline.prepare import prepare

    options = _options(args)
    argv = ["esmm", *getattr(args, "_argv", [])]
    if len(args.inputs) > 1 or args.out is not None:
        if args.output:
            raise ConfigError("-o names one asset; for several inputs give --out DIR")
        if args.out is None:
            raise ConfigError(f"{len(args.inputs)} inputs: give --out DIR for their assets")
        from esmm.cli.calibrate import report_batch_problems
        from esmm.cli.outputs import check_out_dir
        from esmm.pipeline.batch.prepare import prepare_batch

        if not args.out.strip():
            raise ConfigError("--out: empty folder name; give the folder for the assets")
        if args.out.lower().endswith(".h5") and not Path(args.out).is_dir():
            raise ConfigError(f"--out {args.out}: --out names the folder for a batch's assets, not an asset file; "
                              f"to write one asset give -o {args.out}")
        check_out_dir(args.out, "--out")

        summary = prepare_batch(args.inputs, out_dir=args.out, options=options, argv=argv,
                                scheduler=args.scheduler, workers=args.workers, force=args.redo, reporter=ui)
        ui.info(summary.table())
        ui.info(f"assets in {summary.out_dir}; batch-summary.csv and "
                f"{summary.log_path.name if summary.log_path else 'the batch log'} there too")
        report_batch_problems(summary, ui)
        return summary.exit_code
    if args.redo or args.scheduler or args.workers:
        raise ConfigError("--redo, --scheduler and --jobs apply to a batch: give --out DIR")
    try:
        result = prepare(args.inputs[0], output=args.output, reporter=_FlagReporter(ui), argv=argv, **options)
    except QualityError as exc:
        raise QualityError(f"{exc} (--force)") from None
    for line in _summary_lines(result):
        ui.info(line)
    from esmm.pipeline.asset import read_asset

    ui.info("trust       how far to trust this asset: " + read_asset(result.asset, verify=False).accuracy.headline())
    return 0
