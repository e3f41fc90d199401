"""``esmm calibrate``: fit the ESEDF (or another model) to tensile files."""

from __future__ import annotations

import argparse
from typing import Any

from esmm.cli.tensile_options import add_metadata_options, metadata_overrides
from esmm.pipeline.errors import ConfigError

EPILOG = """\
examples:
  esmm calibrate uniaxial.csv --model arruda-boyce --json out.json
  esmm calibrate test_x.csv test_y.csv test_z.csv --out fit/        (orientation-tagged: anisotropic)
  esmm calibrate --by specimen data/*.csv --out batch/               (one fit per specimen, in parallel)
  esmm calibrate --by specimen data/*.csv --out batch/ --scheduler tcp://10.0.0.5:8786   (on a Dask cluster)
  esmm calibrate raw.csv --gauge-length "30 mm" --area "22 mm2" --out fit/

Outputs in --out: params.toml (a material config, readable back with --material),
fit.png (data vs model, residuals vs stretch and vs time), report.md, fit.json.
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the tissue model to tensile-test files",
        description="Fit one material to all files given, jointly across files and loading modes "
        "(or, with --by, one material per group of files).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="tensile-test files (CSV-like text)")
    p.add_argument("--model", default=None, help="material model: esedf (default) or arruda-boyce")
    p.add_argument("--config", metavar="C", help="calibrate config (TOML with a [calibrate] table; "
                   "docs/reference/configuration.md); the options below override it")
    p.add_argument("--out", metavar="DIR", help="folder for params.toml, fit.png, report.md, fit.json")
    p.add_argument("--json", metavar="PATH", help="also write the JSON result here")
    p.add_argument("--loss", default=None, help="robust loss: linear (default), soft_l1, huber, cauchy, arctan")
    p.add_argument("--starts", dest="n_starts", type=int, default=None, metavar="N",
                   help="number of starting points (default 8)")
    p.add_argument("--seed", type=int, default=None, help="seed of the starting points (default 0)")
    p.add_argument("--weight", dest="weights", action="append", default=[], metavar="FILE=W",
                   help="weight of one file (by name or stem); repeatable")
    p.add_argument("--fix", dest="fixed", action="append", default=[], metavar="NAME=VALUE",
                   help="hold a parameter (value with unit for stress-like ones, e.g. mu=\"3e-6 MPa\")")
    p.add_argument("--free", action="append", default=[], metavar="NAME",
                   help="fit a parameter the model holds by default (e.g. the ESEDF's f); repeatable")
    p.add_argument("--discover", action="store_true",
                   help="also find what the model misses (rate dependence, Mullins softening, damage, slack, "
                        "load-cell offset), add what the data support and report the error before and after "
                        "(docs/guide/discover.md)")
    p.add_argument("--by", choices=["specimen", "folder"], help="batch: fit each group of files on its own")
    p.add_argument("--jobs", type=int, default=None, metavar="N", dest="workers",
                   help="batch: local worker processes (default: all cores)")
    p.add_argument("--scheduler", metavar="ADDR", default=None,
                   help="batch: 'local' (default: a pool of --jobs processes), 'serial', or the address of a "
                        "running Dask scheduler, e.g. tcp://10.0.0.5:8786")
    p.add_argument("--force", "--redo", dest="redo", action="store_true",
                   help="batch: recompute groups whose results are already in --out (by default a group whose "
                        "files, options and esmm version are unchanged is skipped)")
    add_metadata_options(p)
    p.set_defaults(func=run)


def _pairs(items, option: str) -> dict[str, str]:
    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"{option}: expected NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _config(args):
    """The calibrate options: the --config file's [calibrate] table, then the flags (the flags win)."""
    from esmm.pipeline.calibrate.config import load_calibrate_config

    return load_calibrate_config(args.config, model=args.model, loss=args.loss, n_starts=args.n_starts,
                                 seed=args.seed, weights=_pairs(args.weights, "--weight"),
                                 fixed=_pairs(args.fixed, "--fix"), free=args.free)


def check_outputs(args) -> None:
    """Refuse, before reading and fitting, an --out or --json path that could not be written at the end."""
    from esmm.cli.outputs import check_out_dir, check_out_file

    if args.out:
        check_out_dir(args.out, "--out")
    if args.json:
        check_out_file(args.json, "--json", "fit.json")


def run(args, ui) -> int:
    check_outputs(args)
    overrides = metadata_overrides(args)
    fit_kwargs = _config(args).fit_kwargs()
    if args.discover:
        return run_discover(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)
    if args.by:
        return run_batch(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)
    return run_fit(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)


def run_fit(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """One joint fit of every file: print the parameters, write --out and --json."""
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.calibrate.report import display_stress_unit, result_to_dict, write_outputs
    from esmm.pipeline.tensile.files import read_tests

    tests = read_tests(args.files, overrides=overrides, reporter=ui)
    result = fit_material(tests, **fit_kwargs, reporter=ui)

    unit, fac = display_stress_unit([abs(e.value) for e in result.estimates if e.kind == "stress"] or [1.0])
    ui.info(f"model {result.model}: {len(tests)} file(s), {sum(t.n for t in tests)} samples")
    for e in result.estimates:
        f, u = (fac, unit) if e.kind == "stress" else (1.0, "")
        ui.info(f"  {e.key:>10} = {e.value / f:<12.6g} 95% CI [{e.lower / f:.4g}, {e.upper / f:.4g}] {u}")
    sunit, sfac = display_stress_unit([float(abs(t.stress).max()) for t in tests])
    ui.info(f"  RMSE {result.rmse / sfac:.4g} {sunit}   NRMSE {result.nrmse:.2%}   R² {result.r2:.4f}")
    if args.out:
        written = write_outputs(args.out, result, tests, json_path=args.json)
        ui.info("outputs: " + ", ".join(str(p) for k, p in written.items() if k != "json_extra"))
    elif args.json:
        write_json(args.json, result_to_dict(result, tests))
    if args.json:
        ui.info(f"json: {args.json}")
    return 0


def run_batch(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """``--by``: one fit per group of files, in parallel, cached (docs/guide/batch.md)."""
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.batch.calibrate import batch_document, calibrate_batch

    if not args.out:
        raise ConfigError("--by: give --out DIR; each group's outputs, the cache and the batch log go there")
    summary = calibrate_batch(args.files, out_dir=args.out, by=args.by, read_kwargs={"overrides": overrides},
                              fit_kwargs=fit_kwargs, scheduler=args.scheduler, workers=args.workers,
                              force=args.redo, reporter=ui)
    ui.info(summary.table())
    if args.json:
        write_json(args.json, batch_document(summary, by=args.by))
    ui.info(f"outputs in {summary.out_dir}: one folder per group, summary.csv (parameters), "
            f"batch-summary.csv, {summary.log_path.name if summary.log_path else 'the batch log'}")
    report_batch_problems(summary, ui)
    return summary.exit_code


def report_batch_problems(summary, ui) -> None:
    """A batch that did not complete ends with one error line (and, with -q, one per failed job)."""
    if summary.exit_code == 0:
        return
    if ui.verbosity < 0:  # the warnings and the table were not shown
        for o in summary.outcomes:
            if o.status == "failed":  # an unreadable file's reason starts with its path already
                ui.error(o.reason if o.summary.get("unreadable") else f"{o.name}: {o.reason}")
    ui.error(summary.problem_line())


def run_discover(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """``--discover``: find what the model misses, report before and after (docs/guide/discover.md).

    Reads the files, runs :func:`esmm.pipeline.discover.discover_and_save` with the calibrate
    options (model, starts, seed, weights, --fix, --free), writes the outputs to ``--out`` and
    ``--json``, and prints the before/after summary.
    """
    from esmm.pipeline.discover import discover_and_save, summary_lines
    from esmm.pipeline.tensile.files import read_tests

    if args.by:
        raise ConfigError("--discover analyses one group of files at a time and cannot be combined with --by; "
                          "run it once per specimen")
    kw = dict(fit_kwargs)
    loss = kw.pop("loss", "linear")
    if loss not in (None, "linear"):
        ui.warn(f"--discover compares models by likelihood and held-out error with the linear loss; "
                f"--loss {loss} is ignored")
    tests = read_tests(args.files, overrides=overrides, reporter=ui)
    res = discover_and_save(tests, out_dir=args.out, json_path=args.json, reporter=ui, **kw)
    for line in summary_lines(res):
        ui.info(line)
    if args.out:
        ui.info(f"outputs in {args.out}: params.toml (with the kept effects), params_base.toml, discover.json, "
                "discover.md, residuals_before.png, residuals_after.png"
                + (", corrected/" if any(n in ("slack", "sensor_offset") for n in res.kept) else ""))
    if args.json:
        ui.info(f"json: {args.json}")
    return 0
