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
    p.add_argument("--config", metavar="C", help="calibrate config (TOML with a [calibrate] table)")
    p.add_argument("--out", metavar="DIR", help="folder for params.toml, fit.png, report.md, fit.json")
    p.add_argument("--json", metavar="PATH", help="also write the JSON result here")
    p.add_argument("--loss", default=None, help="robust loss: linear (default), soft_l1, huber, cauchy, arctan")
    p.add_argument("--starts", type=int, default=None, metavar="N", help="number of starting points (default 8)")
    p.add_argument("--seed", type=int, default=None, help="seed of the starting points (default 0)")
    p.add_argument("--weight", action="append", default=[], metavar="FILE=W",
                   help="weight of one file (by name or stem); repeatable")
    p.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                   help="hold a parameter (value with unit for stress-like ones, e.g. mu=\"3e-6 MPa\")")
    p.add_argument("--free", action="append", default=[], metavar="NAME",
                   help="fit a parameter the model holds by default (e.g. the ESEDF's f); repeatable")
    p.add_argument("--discover", action="store_true",
                   help="also find what the model misses (rate dependence, Mullins softening, damage, slack, "
                        "load-cell offset), add what the data support and report the error before and after "
                        "(docs/discover.md)")
    p.add_argument("--by", choices=["specimen", "folder"], help="batch: fit each group of files on its own")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
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


def _fit_options(args) -> dict[str, Any]:
    """Merge the --config file and the command line (the command line wins)."""
    from esmm.pipeline import config as cfg
    from esmm.pipeline.units import parse_quantity

    opts: dict[str, Any] = {"model": "esedf", "loss": "linear", "n_starts": 8, "seed": 0,
                            "weights": {}, "fixed": {}}
    if args.config:
        data, src = cfg.load_toml(args.config), args.config
        c = data.get("calibrate", data)
        unknown = set(c) - {"model", "loss", "starts", "seed", "weights", "fix", "stress_unit"}
        if unknown:
            raise ConfigError(f"{src}: unknown key(s) {', '.join(sorted(unknown))} in [calibrate]")
        for key, dest in (("model", "model"), ("loss", "loss"), ("starts", "n_starts"), ("seed", "seed")):
            if key in c:
                opts[dest] = c[key]
        opts["weights"].update({str(k): float(v) for k, v in c.get("weights", {}).items()})
        for k, v in c.get("fix", {}).items():
            opts["fixed"][k] = v
    if args.model:
        opts["model"] = args.model
    if args.loss:
        opts["loss"] = args.loss
    if args.starts is not None:
        opts["n_starts"] = args.starts
    if args.seed is not None:
        opts["seed"] = args.seed
    for k, v in _pairs(args.weight, "--weight").items():
        try:
            opts["weights"][k] = float(v)
        except ValueError:
            raise ConfigError(f"--weight {k}: {v!r} is not a number") from None
    opts["fixed"].update(_pairs(args.fix, "--fix"))
    # Fixed values: stress-like ones need a unit.
    from esmm.pipeline.materials import MODEL_NAMES, get_model

    if opts["model"] not in MODEL_NAMES:
        raise ConfigError(f"--model: unknown model {opts['model']!r}; choose one of {', '.join(MODEL_NAMES)}")
    kinds = {p.name: p.kind for p in get_model(opts["model"]).parameters}
    fixed = {}
    for k, v in opts["fixed"].items():
        if k not in kinds:
            raise ConfigError(f"--fix: {opts['model']} has no parameter {k!r}; it has {', '.join(kinds)}")
        if kinds[k] == "stress":
            fixed[k] = parse_quantity(str(v), "stress", where=f"--fix {k}")
        else:
            try:
                fixed[k] = float(v)
            except ValueError:
                raise ConfigError(f"--fix {k}: {v!r} is not a number") from None
    opts["fixed"] = fixed
    return opts


def run(args, ui) -> int:
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.calibrate.report import (
        display_stress_unit,
        result_to_dict,
        write_json,
        write_outputs,
    )
    from esmm.pipeline.tensile import read

    overrides = metadata_overrides(args)
    opts = _fit_options(args)
    fit_kwargs = dict(model=opts["model"], loss=opts["loss"], n_starts=int(opts["n_starts"]),
                      seed=int(opts["seed"]), weights=opts["weights"] or None, fixed=opts["fixed"] or None,
                      free=tuple(args.free))
    if args.discover:  # --discover: esmm.cli.evaluate.run_discover (docs/discover.md)
        from esmm.cli.evaluate import run_discover

        return run_discover(args, ui, fit_kwargs=fit_kwargs, overrides=overrides)

    if args.by:
        from esmm.pipeline.batch.calibrate import batch_document, calibrate_batch

        if not args.out:
            raise ConfigError("--by: give --out DIR; each group's outputs, the cache and the batch log go there")
        summary = calibrate_batch(args.files, out_dir=args.out, by=args.by, read_kwargs={"overrides": overrides},
                                  fit_kwargs=fit_kwargs, scheduler=args.scheduler, workers=args.jobs,
                                  force=args.redo, reporter=ui)
        ui.info(summary.table())
        if args.json:
            write_json(args.json, batch_document(summary, by=args.by))
        ui.info(f"outputs in {summary.out_dir}: one folder per group, summary.csv (parameters), "
                f"batch-summary.csv, {summary.log_path.name if summary.log_path else 'the batch log'}")
        return summary.exit_code

    tests = [read(p, overrides=overrides, reporter=ui) for p in args.files]
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
