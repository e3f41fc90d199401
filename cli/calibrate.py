"""``esmm calibrate``: fit the ESEDF (or another model) to tensile files."""

from __future__ import annotations

import argparse
from pathlib import Path
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

  esmm calibrate lab/specimens/ --out fit/                           (a folder: its test files)
  esmm calibrate --discover --by specimen data/*.csv --out disc/     (one discovery per specimen)

Outputs in --out: params.toml (a material config, readable back with --material),
fit.png (one row per loading mode: data vs model, residual model - data against
stretch and time), report.html (the verdict first), report.md, fit.json.
A folder that holds an earlier run is refused unless --overwrite (which removes that
run's files first); a batch into its own earlier folder reuses what is done.
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
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="tensile-test files (CSV-like text), or folders (their test files)")
    p.add_argument("--model", default=None, help="material model: esedf (default) or arruda-boyce")
    p.add_argument("--config", metavar="C", help="calibrate config (TOML with a [calibrate] table; "
                   "docs/reference/configuration.md); the options below override it")
    p.add_argument("--out", metavar="DIR", help="folder for params.toml, fit.png, report.md, fit.json")
    p.add_argument("--json", metavar="PATH", help="also write the JSON result here")
    p.add_argument("--overwrite", action="store_true",
                   help="write into an --out that holds an earlier run, removing that run's files first "
                        "(by default such a folder is refused)")
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
    p.add_argument("--no-nested", dest="nested", action="store_false",
                   help="with --discover: skip the nested held-out errors (the whole selection run again inside "
                        "each fold; most of a discovery's time). What is kept does not change; the report then "
                        "gives the held-out errors of the chosen model only, which are optimistic")
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


def run_kind(args) -> str:
    """The kind of run (what its --out folder will hold)."""
    return ("discover" if args.discover else "calibrate") + ("-batch" if args.by else "")


def check_outputs(args) -> None:
    """Refuse, before reading and fitting, an --out or --json path that could not be written at the end,
    and an --out that holds an earlier run (unless --overwrite); nothing is created here."""
    from esmm.cli.outputs import check_out_dir, check_out_file, check_run_folder

    args.previous_run = None
    if args.out:
        check_out_dir(args.out, "--out")
        args.previous_run = check_run_folder(args.out, "--out", kind=run_kind(args), overwrite=args.overwrite)
    if args.json:
        check_out_file(args.json, "--json", "fit.json")


def run(args, ui) -> int:
    if not args.nested and not args.discover:
        raise ConfigError("--no-nested: the nested held-out errors belong to a discovery; add --discover, or drop "
                          "--no-nested")
    check_outputs(args)
    overrides = metadata_overrides(args)
    fit_kwargs = _config(args).fit_kwargs()
    if args.discover and args.by:
        return run_discover_batch(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)
    if args.discover:
        return run_discover(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)
    if args.by:
        return run_batch(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)
    return run_fit(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)


def clear_previous(args, ui) -> None:
    """Remove the earlier run's files from --out (only with --overwrite; checked before any work)."""
    from esmm.pipeline.batch.runfolder import clear_run

    if args.out and args.previous_run is not None:
        removed = clear_run(args.out, args.previous_run)
        ui.detail(f"--overwrite: removed {len(removed)} file(s) of the earlier run in {args.out}")


def record(args, outputs) -> None:
    """Record in --out what this run wrote (the next run into the folder reads it)."""
    from esmm.pipeline.batch.runfolder import record_run

    if args.out:
        record_run(args.out, kind=run_kind(args), outputs=list(outputs))


def run_fit(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """One joint fit of every file (failures cut at their ultimate stress): print the parameters, the
    failure tests and the verdict; write --out and --json."""
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.calibrate.calibration import calibrate, failure_lines, verdict_lines
    from esmm.pipeline.calibrate.report import result_to_dict, write_outputs
    from esmm.pipeline.tensile.files import read_tests

    tests = read_tests(args.files, overrides=overrides, reporter=ui)
    cal = calibrate(tests, **fit_kwargs, reporter=ui)
    for line in result_lines(cal) + failure_lines(cal) + verdict_lines(cal):
        ui.info(line)
    if args.out:
        clear_previous(args, ui)
        written = write_outputs(args.out, cal.result, tests, calibration=cal, json_path=args.json)
        record(args, [p for k, p in written.items() if k != "json_extra"])
        ui.info("outputs: " + ", ".join(str(p) for k, p in written.items() if k != "json_extra"))
    elif args.json:
        write_json(args.json, result_to_dict(cal.result, tests, calibration=cal))
    if args.json:
        ui.info(f"json: {args.json}")
    return 0


def result_lines(cal) -> list[str]:
    """The fit for a console: each parameter in its readable unit with its interval, then the errors."""
    from esmm.pipeline.htmlreport import interval_text, quantity_text

    r = cal.result
    lines = [f"model {r.model}: {len(cal.tests)} file(s), {sum(t.n for t in cal.fitted)} samples fitted"]
    for e in r.estimates:
        flag = "" if e.identifiable else "   (not determined by the data)"
        lines.append(f"  {e.key:>10} = {quantity_text(e.value, e.unit, digits=6):<24} 95% CI "
                     f"{interval_text(e.lower, e.upper, e.unit, like=e.value)}{flag}")
    lines.append(f"  RMSE {quantity_text(r.rmse, 'Pa')}   NRMSE {r.nrmse:.2%}   R² {r.r2:.4f}")
    return lines


def run_batch(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """``--by``: one fit per group of files, in parallel, cached (docs/guide/batch.md)."""
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.batch.calibrate import batch_document, calibrate_jobs, write_tables
    from esmm.pipeline.batch.runner import run_jobs

    if not args.out:
        raise ConfigError("--by: give --out DIR; each group's outputs, the cache and the batch log go there")
    # calibrate_batch's three steps, with the earlier run cleared once the inputs are read
    jobs = calibrate_jobs(args.files, by=args.by, out_dir=args.out, read_kwargs={"overrides": overrides},
                          fit_kwargs=fit_kwargs, reporter=ui)
    clear_previous(args, ui)
    summary = run_jobs(jobs, out_dir=args.out, scheduler=args.scheduler, workers=args.workers, force=args.redo,
                       reporter=ui, title="calibrating")
    write_tables(summary, by=args.by)
    return finish_batch(args, ui, summary, batch_document(summary, by=args.by), write_json)


def finish_batch(args, ui, summary, document, write_json) -> int:
    """Print the table and each group's verdict, record the run, write --json; the batch's exit code."""
    ui.info(summary.table())
    for o in summary.outcomes:
        v = o.summary.get("verdict")
        if v and o.status in ("done", "cached"):
            ui.info(f"  {o.name}: {v.get('text', v.get('level', ''))}")
    if args.json:
        write_json(args.json, document)
    record(args, [summary.out_dir / p for o in summary.outcomes for p in o.outputs]
           + [summary.out_dir / n for n in ("summary.csv", "batch-summary.csv", "report.html", "effects.csv",
                                             "effect-parameters.csv") if (summary.out_dir / n).exists()])
    ui.info(f"outputs in {summary.out_dir}: one folder per group, summary.csv, report.html, "
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


def discover_options(fit_kwargs: dict[str, Any], ui, *, nested: bool = True) -> dict[str, Any]:
    """The discovery's options from the calibrate options (the linear loss only: a robust one is ignored)."""
    kw = dict(fit_kwargs, nested=nested)
    loss = kw.pop("loss", "linear")
    if loss not in (None, "linear"):
        ui.warn(f"--discover compares models by likelihood and held-out error with the linear loss; "
                f"--loss {loss} is ignored")
    return kw


def run_discover(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """``--discover``: find what the model misses, report before and after (docs/guide/discover.md).

    Reads the files, runs :func:`esmm.pipeline.discover.discover` with the calibrate options
    (model, starts, seed, weights, --fix, --free), clears an earlier run from ``--out``
    (with --overwrite), writes the outputs (:func:`esmm.pipeline.discover.write_outputs`)
    and report.html, and prints the before/after summary.
    """
    from esmm.pipeline.discover import discover, result_to_dict, summary_lines, write_outputs
    from esmm.pipeline.discover.html import verdict_of, write_discover_html
    from esmm.pipeline.tensile.files import read_tests

    tests = read_tests(args.files, overrides=overrides, reporter=ui)
    res = discover(tests, reporter=ui, **discover_options(fit_kwargs, ui, nested=args.nested))
    if args.out:
        clear_previous(args, ui)
    written = write_outputs(args.out, res, json_path=args.json)
    doc = result_to_dict(res)
    for line in summary_lines(res):
        ui.info(line)
    ui.info("verdict: " + verdict_of(doc)[1])
    if args.out:
        html = write_discover_html(Path(args.out) / "report.html", res, doc)
        outs = [html] + [p for k, p in written.items() if k not in ("json_extra", "corrected")]
        corrected = written.get("corrected")
        record(args, outs + (sorted(Path(corrected).iterdir()) if corrected else []))
        ui.info(f"outputs in {args.out}: report.html, params.toml (with the kept effects), params_base.toml, "
                "discover.json, discover.md, residuals_before.png, residuals_after.png"
                + (", corrected/" if any(n in ("slack", "sensor_offset") for n in res.kept) else ""))
    if args.json:
        ui.info(f"json: {args.json}")
    return 0


def run_discover_batch(args, ui, *, fit_kwargs: dict[str, Any], overrides: dict[str, Any]) -> int:
    """``--discover --by``: one discovery per group, on the local pool or a Dask cluster, and what the groups
    share (docs/guide/batch.md, "Discovery in batch")."""
    from esmm.pipeline.atomicio import write_json
    from esmm.pipeline.batch import discover as bd
    from esmm.pipeline.batch.runner import run_jobs

    if not args.out:
        raise ConfigError("--by: give --out DIR; each group's outputs, the cache and the batch log go there")
    jobs = bd.discover_jobs(args.files, by=args.by, out_dir=args.out, read_kwargs={"overrides": overrides},
                            options=discover_options(fit_kwargs, ui, nested=args.nested), reporter=ui)
    clear_previous(args, ui)
    summary = run_jobs(jobs, out_dir=args.out, scheduler=args.scheduler, workers=args.workers, force=args.redo,
                       reporter=ui, title="discovering")
    bd.write_tables(summary, by=args.by)
    for r in bd.effect_counts(summary):
        if r["found"]:
            ui.info(f"  {r['effect']}: found in {r['found']} of {r['testable']} group(s) where it can be found"
                    + (f" ({r['tissue']})" if r["tissue"] != bd.NO_TISSUE else ""))
    doc = {"schema": "esmm.discover-batch/1", "by": args.by, "exit_code": summary.exit_code,
           "groups": [o.to_dict() for o in summary.outcomes], "effects": bd.effect_counts(summary),
           "parameters": bd.effect_parameters(summary)}
    return finish_batch(args, ui, summary, doc, write_json)
