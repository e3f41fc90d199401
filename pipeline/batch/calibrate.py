"""``esmm calibrate --by specimen|folder FILES...`` as a cached, parallel batch.

The files are read once to form the groups (:mod:`.groups`). Each group becomes one
:class:`~esmm.pipeline.batch.jobs.Job` whose worker reads its files again, analyses
failure, fits the intact parts and judges the fit
(:func:`esmm.pipeline.calibrate.calibration.calibrate`), and writes
``<out>/<group>/params.toml, fit.png, report.md, report.html, fit.json``
(:func:`esmm.pipeline.calibrate.report.write_outputs`). A file that cannot be
read is one failed row; the other groups still run; when no file can be read,
nothing is created. After the batch, ``<out>/summary.csv`` tabulates every
group's verdict, parameters (with whether the data determine each), errors and
failure tests, cached groups included (from their manifests), with statistics
across the usable groups (:mod:`.tables`), and ``<out>/report.html`` shows them.

The key of a group covers the bytes of its files and of their TOML sidecars,
the reader overrides and the fit options.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..atomicio import write_text
from ..calibrate.calibration import calibrate
from ..calibrate.report import write_outputs
from ..checks import choice
from ..errors import EsmmError
from ..progress import Reporter, ensure
from ..tensile import read
from .groups import (
    GROUP_BY,
    PARAMS_TABLE,
    RESERVED_NAMES,
    failed_jobs,
    group_names,
    refuse_if_nothing,
    safe_name,
    sidecars,
    sort_files,
)
from .jobs import BatchSummary, Job, JobOutput
from .runner import run_jobs
from .tables import batch_html, params_table

KIND = "calibrate"

__all__ = ["GROUP_BY", "KIND", "PARAMS_TABLE", "RESERVED_NAMES", "batch_document", "calibrate_batch",
           "calibrate_jobs", "fit_group", "group_names", "params_table", "safe_name", "sidecars"]


def read_group(files: Sequence[str], read_kwargs: Mapping[str, Any]) -> list:
    """The group's records, read again in the worker."""
    return [read(p, **dict(read_kwargs)) for p in files]


def named(exc: EsmmError, files: Sequence[str]) -> EsmmError:
    """*exc* with the group's files named where its message does not name them."""
    msg = str(exc)
    shown = [Path(p).name for p in files]
    if any(n in msg for n in shown):
        return exc
    listed = ", ".join(shown[:3]) + (f" and {len(shown) - 3} more" if len(shown) > 3 else "")
    return type(exc)(f"{listed}: {msg}")


def fit_group(files: Sequence[str], out_dir: str, name: str, read_kwargs: Mapping[str, Any],
              fit_kwargs: Mapping[str, Any]) -> JobOutput:
    """Worker function: read *files*, fit their intact parts jointly, judge, write ``<out_dir>/<name>/``.

    Returns
    -------
    JobOutput
        The output files and a summary: ``estimates`` (key, value, 95 % interval, kind,
        at_bound, identifiable), ``rmse``/``nrmse``/``r2``, ``verdict`` (level, text,
        reasons), ``failure`` (per test, and the group's mean ± SD), ``files``, ``warnings``.
    """
    tests = read_group(files, read_kwargs)
    try:
        cal = calibrate(tests, **dict(fit_kwargs))
    except EsmmError as exc:  # name the files where the fit's own message does not
        raise named(exc, files) from None
    result = cal.result
    written = write_outputs(Path(out_dir) / name, result, tests, calibration=cal, name=name)
    summary = {
        "model": result.model,
        "estimates": [{"key": e.key, "value": e.value, "lower": e.lower, "upper": e.upper, "kind": e.kind,
                       "at_bound": e.at_bound, "identifiable": e.identifiable} for e in result.estimates],
        "fixed": dict(result.fixed),
        "rmse": result.rmse, "nrmse": result.nrmse, "r2": result.r2,
        "noise_ratio": max((v.get("ratio", 0.0) for v in cal.verdict.noise.values()), default=None),
        "verdict": {"level": cal.verdict.level, "text": cal.verdict.short(),
                    "reasons": [r.code for r in cal.verdict.reasons]},
        "failure": {"tests": [f.to_dict() for f in cal.failures if f.kind != "none"],
                    "summary": cal.failure_summary},
        "files": [str(t.source) for t in tests],
        "specimens": sorted({t.specimen for t in tests}),
        "tissue": sorted({str(t.metadata.get("tissue")) for t in tests if t.metadata.get("tissue")}),
        "warnings": list(result.warnings),
    }
    return JobOutput(outputs=[p for k, p in written.items() if k != "json_extra"], summary=summary)


def plain_options(read_kwargs, options) -> tuple[dict, dict]:
    """The reader and fit options as plain data (a reporter left out, sequences as lists)."""
    read_kwargs = {k: v for k, v in dict(read_kwargs or {}).items() if k != "reporter"}
    options = {k: v for k, v in dict(options or {}).items() if k != "reporter"}
    if "free" in options and options["free"] is not None:
        options["free"] = list(options["free"])
    return read_kwargs, options


def calibrate_jobs(files: Sequence[str | os.PathLike], *, by: str = "specimen",
                   out_dir: str | os.PathLike, read_kwargs: Mapping[str, Any] | None = None,
                   fit_kwargs: Mapping[str, Any] | None = None,
                   reporter: Reporter | None = None) -> list[Job]:
    """Group *files* and make one job per group (plus a failed job per unreadable file).

    Parameters
    ----------
    files : sequence of path
        Tensile files, or folders (their files).
    by : {"specimen", "folder"}
    out_dir : path
        The batch folder (``<out_dir>/<group>/`` per group).
    read_kwargs : mapping, optional
        Keyword arguments of :func:`esmm.pipeline.tensile.read` (``overrides``,
        ``encoding``).
    fit_kwargs : mapping, optional
        Keyword arguments of :func:`esmm.pipeline.calibrate.calibration.calibrate`
        (plain data: model, loss, n_starts, seed, weights, fixed, free, cut_failure, ...).

    Raises
    ------
    ConfigError
        *by* is unknown, or the reader options are invalid (they would fail
        every file alike).
    InputError
        No file can be read (nothing would run: nothing is created).
    """
    choice(by, GROUP_BY, "by")
    rep = ensure(reporter)
    read_kwargs, fit_kwargs = plain_options(read_kwargs, fit_kwargs)
    groups, failed, skipped, n_files = sort_files(files, by, read_kwargs, rep)
    refuse_if_nothing(groups, failed, skipped, n_files)
    names = group_names(list(groups), by)
    jobs = failed_jobs(failed, {n.casefold() for n in names.values()}, KIND)
    for key, paths in groups.items():
        name = names[key]
        config = {"by": by, "group": key, "read": read_kwargs, "fit": fit_kwargs}
        jobs.append(Job(name=name, kind=KIND, fn=fit_group,
                        args=(paths, str(Path(out_dir).resolve()), name, read_kwargs, fit_kwargs),
                        key_inputs=[*paths, *map(str, sidecars(paths))], config=config))
    return jobs


def batch_document(summary: BatchSummary, *, by: str) -> dict[str, Any]:
    """The ``--json`` document of a calibration batch (schema ``esmm.calibrate-batch/2``).

    Each group carries its status, reason, outputs and, when it succeeded
    (now or before: cached), the contents of its ``fit.json``.
    """
    groups = []
    for o in summary.outcomes:
        result = None
        fit_json = next((p for p in o.outputs if p.endswith("fit.json")), None)
        if fit_json is not None and o.status in ("done", "cached"):
            p = Path(fit_json) if Path(fit_json).is_absolute() else summary.out_dir / fit_json
            try:
                result = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                result = None
        groups.append({"group": o.name, "status": o.status, "ok": o.status in ("done", "cached"),
                       "reason": o.reason, "files": o.summary.get("files", []), "outputs": o.outputs,
                       "seconds": o.seconds, "result": result})
    return {"schema": "esmm.calibrate-batch/2", "by": by, "exit_code": summary.exit_code,
            "counts": {"done": summary.n_done, "cached": summary.n_cached, "failed": summary.n_failed,
                       "interrupted": summary.n_interrupted},
            "groups": groups}


def calibrate_batch(files: Sequence[str | os.PathLike], *, out_dir: str | os.PathLike, by: str = "specimen",
                    read_kwargs: Mapping[str, Any] | None = None, fit_kwargs: Mapping[str, Any] | None = None,
                    scheduler: Any = None, workers: int | None = None, force: bool = False,
                    reporter: Reporter | None = None) -> BatchSummary:
    """Fit every group of *files* on its own, in parallel, with caching; tabulate.

    Parameters
    ----------
    files, by, read_kwargs, fit_kwargs
        See :func:`calibrate_jobs`.
    out_dir : path
        Batch folder: ``<group>/`` outputs, ``summary.csv`` (verdicts, parameters, failure
        tests, statistics), ``report.html``, ``batch-summary.csv`` (status),
        ``esmm-batch-<time>.log``, ``.esmm-cache/``.
    scheduler, workers, force, reporter
        See :func:`esmm.pipeline.batch.runner.run_jobs`.

    Returns
    -------
    BatchSummary
        ``exit_code`` 0, 5 (a file or group failed) or 130 (interrupted).
    """
    jobs = calibrate_jobs(files, by=by, out_dir=out_dir, read_kwargs=read_kwargs, fit_kwargs=fit_kwargs,
                          reporter=reporter)
    summary = run_jobs(jobs, out_dir=out_dir, scheduler=scheduler, workers=workers, force=force,
                       reporter=reporter, title="calibrating")
    write_tables(summary, by=by)
    return summary


def write_tables(summary: BatchSummary, *, by: str) -> None:
    """summary.csv and report.html of a batch of fits (:mod:`.tables`)."""
    write_text(summary.out_dir / PARAMS_TABLE, params_table(summary))
    batch_html(summary, by=by).write(summary.out_dir / "report.html")
