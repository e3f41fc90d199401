"""``esmm evaluate``: predict new tensile files with a saved fit, without refitting the material."""

from __future__ import annotations

import argparse

from esmm.cli.tensile_options import add_metadata_options, metadata_overrides

EPILOG = """\
examples:
  esmm evaluate fit/ new_test.csv                          (fit/ from 'esmm calibrate ... --out fit/')
  esmm evaluate fit/ lu_0d01_*.csv --json eval.json         (after 'esmm calibrate --discover')
  esmm evaluate fit/params.toml raw.csv --gauge-length "30 mm" --area "22 mm2"

Reports, per file and over all files, the error of the base model alone (before) and of the
final model with the effects the discovery kept (after): RMSE, NRMSE (RMSE / range of the
measured stress) and the largest error. Nothing is refitted: the material as saved, and no
measurement artefact applied (a new file's slack, load-cell offset, specimen scale and slips are
its own). --refit-artefacts re-estimates the artefacts the discovery kept on each file, the
material held, and says so in the output.
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="predict new tensile files with a saved fit and report the errors",
        description="Predict tensile-test files with the material saved by 'esmm calibrate' "
        "(or 'esmm calibrate --discover'), without refitting it, and report the errors.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("fit", metavar="FIT_DIR", help="output folder of 'esmm calibrate' (or its discover.json, "
                   "fit.json or params.toml)")
    p.add_argument("files", nargs="+", metavar="FILE", help="tensile-test files to predict")
    p.add_argument("--json", metavar="PATH", help="write the result as JSON (schema esmm.evaluate/1)")
    p.add_argument("--refit-artefacts", action="store_true",
                   help="re-estimate the kept measurement artefacts (slack, load-cell offset and drift, specimen "
                   "scale, grip slips) on each file, the material held (default: none applied)")
    add_metadata_options(p, specimen=False)
    p.set_defaults(func=run)


def run(args, ui) -> int:
    from esmm.cli.outputs import check_out_file
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.discover.evaluate import evaluate, load_fit, summary_lines
    from esmm.pipeline.tensile import read

    if args.json:
        check_out_file(args.json, "--json", "eval.json")
    saved = load_fit(args.fit)
    overrides = metadata_overrides(args)
    tests = [read(p, overrides=overrides, reporter=ui) for p in args.files]
    ev = evaluate(saved, tests, refit_artefacts=args.refit_artefacts, reporter=ui)
    for line in summary_lines(ev):
        ui.info(line)
    if args.json:
        write_json(args.json, ev.to_dict())
        ui.info(f"json: {args.json}")
    return 0
