"""``esmm calibrate --by specimen|folder FILES...`` as a cached, parallel batch.

The files are read once here to form the groups (by specimen id: metadata
``specimen``, else the file stem; or by folder). Each group becomes one
:class:`~esmm.pipeline.batch.jobs.Job` whose worker reads its files again,
fits (:func:`esmm.pipeline.calibrate.fit.fit_material`) and writes
``<out>/<group>/params.toml, fit.png, report.md, fit.json``
(:func:`esmm.pipeline.calibrate.report.write_outputs`). A file that cannot be
read is one failed row; the other groups still run. After the batch,
``<out>/summary.csv`` tabulates every group's parameters and errors, cached
groups included (from their manifests).

The key of a group covers the bytes of its files and of their TOML sidecars,
the reader overrides and the fit options.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import statistics
import unicodedata
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..atomicio import write_text
from ..calibrate.fit import fit_material
from ..calibrate.report import write_outputs
from ..checks import choice
from ..errors import ConfigError, EsmmError, InputError
from ..progress import Reporter, ensure
from ..tensile import NotATestError, read
from ..tensile.files import record_files
from .cache import CACHE_DIR
from .jobs import BatchSummary, Job, JobOutput, sha256_file
from .runner import SUMMARY_NAME, run_jobs

GROUP_BY = ("specimen", "folder")
KIND = "calibrate"
#: Name of the parameters table in the batch folder.
PARAMS_TABLE = "summary.csv"

#: Names in the batch folder that no group folder may take (compared case-insensitively).
RESERVED_NAMES = (PARAMS_TABLE, SUMMARY_NAME, CACHE_DIR)

#: Longest group folder name, in UTF-8 bytes (file systems allow 255).
_MAX_NAME_BYTES = 120

def safe_name(text: str) -> str:
    """A file-system-safe folder name for a group (letters of any script, digits, ``-_.``).

    At most 120 UTF-8 bytes; ``"group"`` when nothing is left.
    """
    s = re.sub(r"[^\w.\-]+", "_", unicodedata.normalize("NFC", str(text))).strip("._")
    while len(s.encode("utf-8")) > _MAX_NAME_BYTES:
        s = s[:-1]
    return s.rstrip("._") or "group"


def group_names(keys: Sequence[str], by: str) -> dict[str, str]:
    """Group key -> unique, file-system-safe folder name.

    Specimen ids are sanitised (:func:`safe_name`); folders are named by their
    last component, or, where two share it (``lab1/left``, ``lab2/left``), by
    as many trailing components as it takes to tell them apart
    (``lab1_left``, ``lab2_left``). Any remaining clash gets ``-2``, ``-3``...
    """
    out: dict[str, str] = {}
    if by == "folder":
        by_base: dict[str, list[str]] = {}
        for k in keys:
            by_base.setdefault(safe_name(Path(k).name), []).append(k)
        for base, ks in by_base.items():
            names = [base]
            depth, deepest = 1, max(len(Path(k).parts) for k in ks)
            while len(ks) > 1 and depth < deepest:
                depth += 1
                names = [safe_name("_".join(Path(k).parts[-depth:])) for k in ks]
                if len(set(names)) == len(names):
                    break
            out.update(zip(ks, names if len(names) == len(ks) else [base] * len(ks)))
    else:
        out = {k: safe_name(k) for k in keys}
    # Any clash left (also with the batch's own files, and names that differ only in case, which
    # are one folder on macOS and Windows): suffixes, in input order.
    taken: set[str] = {n.casefold() for n in RESERVED_NAMES}
    for k in keys:
        name, n = out[k], 2
        while name.casefold() in taken:
            name, n = f"{out[k]}-{n}", n + 1
        out[k] = name
        taken.add(name.casefold())
    return out


def sidecars(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """The TOML sidecars (``x.toml`` beside ``x.csv``) that exist for *paths*."""
    out = []
    for p in paths:
        side = Path(p).with_suffix(".toml")
        if side != Path(p) and side.is_file():
            out.append(side)
    return out


def fit_group(files: Sequence[str], out_dir: str, name: str, read_kwargs: Mapping[str, Any],
              fit_kwargs: Mapping[str, Any]) -> JobOutput:
    """Worker function: read *files*, fit them jointly, write ``<out_dir>/<name>/``.

    Returns
    -------
    JobOutput
        The four output files and a summary: ``estimates`` (key, value, 95 %
        interval, kind), ``rmse``/``nrmse``/``r2``, ``files``, ``warnings``.
    """
    tests = [read(p, **dict(read_kwargs)) for p in files]
    try:
        result = fit_material(tests, **dict(fit_kwargs))
    except EsmmError as exc:  # name the files where the fit's own message does not
        msg = str(exc)
        shown = [Path(p).name for p in files]
        if not any(n in msg for n in shown):
            listed = ", ".join(shown[:3]) + (f" and {len(shown) - 3} more" if len(shown) > 3 else "")
            raise type(exc)(f"{listed}: {msg}") from None
        raise
    written = write_outputs(Path(out_dir) / name, result, tests, name=name)
    summary = {
        "model": result.model,
        "estimates": [{"key": e.key, "value": e.value, "lower": e.lower, "upper": e.upper, "kind": e.kind,
                       "at_bound": e.at_bound} for e in result.estimates],
        "fixed": dict(result.fixed),
        "rmse": result.rmse, "nrmse": result.nrmse, "r2": result.r2,
        "files": [str(t.source) for t in tests],
        "specimens": sorted({t.specimen for t in tests}),
        "warnings": list(result.warnings),
    }
    return JobOutput(outputs=[p for k, p in written.items() if k != "json_extra"], summary=summary)


def calibrate_jobs(files: Sequence[str | os.PathLike], *, by: str = "specimen",
                   out_dir: str | os.PathLike, read_kwargs: Mapping[str, Any] | None = None,
                   fit_kwargs: Mapping[str, Any] | None = None,
                   reporter: Reporter | None = None) -> list[Job]:
    """Group *files* and make one job per group (plus a failed job per unreadable file).

    Parameters
    ----------
    files : sequence of path
        Tensile files.
    by : {"specimen", "folder"}
    out_dir : path
        The batch folder (``<out_dir>/<group>/`` per group).
    read_kwargs : mapping, optional
        Keyword arguments of :func:`esmm.pipeline.tensile.read` (``overrides``,
        ``encoding``).
    fit_kwargs : mapping, optional
        Keyword arguments of :func:`esmm.pipeline.calibrate.fit.fit_material`
        (plain data: model, loss, n_starts, seed, weights, fixed, free, ...).

    Raises
    ------
    ConfigError
        *by* is unknown, or the reader options are invalid (they would fail
        every file alike).
    """
    choice(by, GROUP_BY, "by")
    rep = ensure(reporter)
    read_kwargs = {k: v for k, v in dict(read_kwargs or {}).items() if k != "reporter"}
    fit_kwargs = {k: v for k, v in dict(fit_kwargs or {}).items() if k != "reporter"}
    if "free" in fit_kwargs and fit_kwargs["free"] is not None:
        fit_kwargs["free"] = list(fit_kwargs["free"])
    groups, failed, skipped, n_files = _sort_files(files, by, read_kwargs, rep)
    if not groups and not failed:
        why = f" ({skipped[0]})" if skipped else ""
        raise InputError(f"none of the {n_files} file(s) is a test record{why}; give the tests' CSV files")
    names = group_names(list(groups), by)
    jobs = _failed_jobs(failed, {n.casefold() for n in names.values()})
    for key, paths in groups.items():
        name = names[key]
        config = {"by": by, "group": key, "read": read_kwargs, "fit": fit_kwargs}
        jobs.append(Job(name=name, kind=KIND, fn=fit_group,
                        args=(paths, str(Path(out_dir).resolve()), name, read_kwargs, fit_kwargs),
                        key_inputs=[*paths, *map(str, sidecars(paths))], config=config))
    return jobs


def _sort_files(files, by: str, read_kwargs: dict, rep: Reporter):
    """Read every record once: (groups: key -> paths, failed: (as given, path, error), skipped: messages,
    the number of distinct files). What a wildcard picks up beside the records is skipped with a
    warning (:func:`esmm.pipeline.tensile.files.record_files`, and measurement tables)."""
    groups: dict[str, list[str]] = {}
    digests: dict[str, dict[str, str]] = {}  # group -> sha256 -> first file with those bytes
    failed: list[tuple[str, str, EsmmError]] = []
    records, skipped, n_files = record_files(files)
    for msg in skipped:
        rep.warn(msg)
    for f, p in records:
        try:
            t = read(p, **read_kwargs)
        except ConfigError:            # the reader's options: every file would fail alike
            raise
        except NotATestError as exc:   # a measurements table picked up by a wildcard (as without --by)
            skipped.append(f"{exc} - skipped")
            rep.warn(skipped[-1])
            continue
        except EsmmError as exc:
            failed.append((f, p, exc))
            rep.warn(f"skipped: {exc}")
            continue
        key = t.specimen if by == "specimen" else str(Path(p).parent)
        try:  # the same bytes with the same sidecar (or none): one test given twice
            digest = ":".join(sha256_file(x) for x in [p, *sidecars([p])])
        except EsmmError as exc:  # gone or unreadable since it was read
            failed.append((f, p, exc))
            continue
        first = digests.setdefault(key, {}).setdefault(digest, p)
        if first != p:  # kept (the user may mean it) but said: it doubles that test's weight in the fit
            rep.warn(f"{f}: the same bytes as {first} in one group (a copy?); both are fitted, which doubles "
                     f"that test's weight - remove one if it is a copy")
        groups.setdefault(key, []).append(p)
    return groups, failed, skipped, n_files


def _failed_jobs(failed, taken: set[str]) -> list[Job]:
    """A failed job per unreadable file, named by the path given; never by a group's name (*taken*,
    case-folded), since it writes nothing."""
    jobs = []
    for shown, p, exc in failed:
        name, n = shown, 2
        while name.casefold() in taken:
            name, n = (p if n == 2 else f"{p}-{n - 1}"), n + 1
        taken.add(name.casefold())
        jobs.append(Job.failed(name, KIND, str(exc), exit_code=exc.exit_code,
                               summary={"unreadable": True, "files": [p]}))
    return jobs


def params_table(summary: BatchSummary) -> str:
    """CSV: one row per group (status, parameters [SI], errors, reason) plus mean and std rows.

    ``status`` is ``ok`` (fitted now or earlier: ``cached`` says which), ``failed``,
    ``unreadable`` (a file that could not be read; its row is named by the path)
    or ``interrupted``.
    """
    keys: list[str] = []
    for o in summary.outcomes:
        for e in o.summary.get("estimates", []) if o.status in ("done", "cached") else []:
            if e["key"] not in keys:
                keys.append(e["key"])
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["group", "status", "files", *[f"{k} [SI]" for k in keys], "rmse [Pa]", "nrmse", "r2", "seconds",
                "cached", "reason"])
    cols: dict[str, list[float]] = {k: [] for k in [*keys, "rmse", "nrmse", "r2"]}
    for o in summary.outcomes:
        s = o.summary
        status = {"done": "ok", "cached": "ok"}.get(o.status, o.status)
        if o.status == "failed" and s.get("unreadable"):
            status = "unreadable"
        cached = "yes" if o.status == "cached" else ""
        if o.status in ("done", "cached") and "estimates" in s:
            vals = {e["key"]: float(e["value"]) for e in s["estimates"]}
            for k in keys:
                cols[k].append(vals.get(k, math.nan))
            for k in ("rmse", "nrmse", "r2"):
                cols[k].append(float(s.get(k, math.nan)))
            w.writerow([o.name, status, len(s.get("files", [])), *[f"{vals.get(k, math.nan):.8g}" for k in keys],
                        f"{float(s.get('rmse', math.nan)):.6g}", f"{float(s.get('nrmse', math.nan)):.6g}",
                        f"{float(s.get('r2', math.nan)):.6g}", f"{o.seconds:.2f}", cached, ""])
        else:
            w.writerow([o.name, status, len(s.get("files", [])) or "", *[""] * len(keys), "", "", "",
                        f"{o.seconds:.2f}", "", o.reason])
    n_ok = len(cols["rmse"])
    if n_ok:
        def mean(v):
            f = [x for x in v if math.isfinite(x)]
            return statistics.fmean(f) if f else math.nan

        def std(v):
            f = [x for x in v if math.isfinite(x)]
            return statistics.stdev(f) if len(f) > 1 else math.nan

        for label, fn in (("mean", mean), ("std", std)):
            w.writerow([label, f"{n_ok} group(s)", "", *[f"{fn(cols[k]):.8g}" for k in keys],
                        *[f"{fn(cols[k]):.6g}" for k in ("rmse", "nrmse", "r2")], "", "", ""])
    return buf.getvalue()


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
        Batch folder: ``<group>/`` outputs, ``summary.csv`` (parameters),
        ``batch-summary.csv`` (status), ``esmm-batch-<time>.log``, ``.esmm-cache/``.
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
    write_text(summary.out_dir / PARAMS_TABLE, params_table(summary))
    return summary
