"""Batch calibration: fit each group of files on its own, in parallel, and tabulate.

Groups are formed by specimen id (``--by specimen``: metadata ``specimen``,
else the file stem) or by folder (``--by folder``). A file that cannot be read,
or a group whose fit fails, is reported with its one-line reason and skipped;
the other groups still complete.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..atomicio import write_text
from ..errors import ConfigError, EsmmError
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest

GROUP_BY = ("specimen", "folder")


@dataclass
class GroupOutcome:
    group: str
    files: list[str]
    ok: bool
    reason: str = ""
    result: Any = None  # FitResult when ok
    out_dir: str | None = None


@dataclass
class BatchResult:
    groups: list[GroupOutcome]
    unreadable: list[tuple[str, str]] = field(default_factory=list)  # (path, reason)
    summary_csv: str | None = None

    @property
    def n_failed(self) -> int:
        return sum(not g.ok for g in self.groups) + len(self.unreadable)


def group_tests(tests: Sequence[TensileTest], by: str) -> dict[str, list[TensileTest]]:
    """Group tests by ``specimen`` id or by ``folder``, keeping input order."""
    if by not in GROUP_BY:
        raise ConfigError(f"--by: choose one of {', '.join(GROUP_BY)}, got {by!r}")
    groups: dict[str, list[TensileTest]] = {}
    for t in tests:
        key = t.specimen if by == "specimen" else str(t.source.resolve().parent)
        groups.setdefault(key, []).append(t)
    return groups


def _fit_one(key: str, tests: list[TensileTest], fit_kwargs: dict[str, Any],
             out_dir: str | None) -> GroupOutcome:
    from .fit import fit_material
    from .report import write_outputs

    files = [str(t.source) for t in tests]
    try:
        result = fit_material(tests, **fit_kwargs)
        path = None
        if out_dir is not None:
            path = str(Path(out_dir) / _safe(key))
            write_outputs(path, result, tests, name=key)
        return GroupOutcome(key, files, True, result=result, out_dir=path)
    except EsmmError as exc:
        return GroupOutcome(key, files, False, reason=str(exc))
    except Exception as exc:  # noqa: BLE001 - one group must not end the batch
        return GroupOutcome(key, files, False, reason=f"internal error: {type(exc).__name__}: {exc}")


def _safe(name: str) -> str:
    keep = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in Path(name).name or name)
    return keep or "group"


def run_batch(
    paths: Sequence[str | os.PathLike],
    *,
    by: str = "specimen",
    read: Callable[[str | os.PathLike], TensileTest] | None = None,
    fit_kwargs: Mapping[str, Any] | None = None,
    out_dir: str | os.PathLike | None = None,
    jobs: int | None = None,
    reporter: Reporter | None = None,
) -> BatchResult:
    """Read *paths*, group them, fit every group (in parallel) and tabulate.

    Parameters
    ----------
    paths : sequence of path
        Tensile files.
    by : {"specimen", "folder"}
        How files are grouped.
    read : callable, optional
        ``read(path) -> TensileTest`` (default :func:`esmm.pipeline.tensile.read`).
    fit_kwargs : mapping, optional
        Keyword arguments of :func:`~esmm.pipeline.calibrate.fit.fit_material`.
    out_dir : path, optional
        Where each group's outputs go (``out_dir/<group>/``) and ``summary.csv``.
    jobs : int, optional
        Worker processes (default: the number of cores); 1 runs in this process.
    """
    from ..tensile import read as default_read

    rep = ensure(reporter)
    read = read or default_read
    tests: list[TensileTest] = []
    unreadable: list[tuple[str, str]] = []
    for p in paths:
        try:
            tests.append(read(p))
        except EsmmError as exc:
            unreadable.append((str(p), str(exc)))
            rep.warn(f"skipped: {exc}")
    groups = group_tests(tests, by)
    kwargs = dict(fit_kwargs or {})
    kwargs.pop("reporter", None)
    jobs = max(1, int(jobs or os.cpu_count() or 1))
    outcomes: list[GroupOutcome] = []
    out = None if out_dir is None else str(out_dir)
    with rep.task(f"calibrating {len(groups)} group(s) on {min(jobs, max(len(groups), 1))} worker(s)",
                  total=len(groups)) as advance:
        if jobs == 1 or len(groups) <= 1:
            for key, ts in groups.items():
                outcomes.append(_fit_one(key, ts, kwargs, out))
                advance(1)
        else:
            with ProcessPoolExecutor(max_workers=min(jobs, len(groups))) as pool:
                futs = {pool.submit(_fit_one, key, ts, kwargs, out): key for key, ts in groups.items()}
                for fut in as_completed(futs):
                    outcomes.append(fut.result())
                    advance(1)
    order = {k: i for i, k in enumerate(groups)}
    outcomes.sort(key=lambda g: order[g.group])
    for g in outcomes:
        if not g.ok:
            rep.warn(f"group {g.group} failed: {g.reason}")
    result = BatchResult(outcomes, unreadable)
    result.summary_csv = summary_table(result)
    if out is not None:
        write_text(Path(out) / "summary.csv", result.summary_csv)
    return result


def summary_table(batch: BatchResult) -> str:
    """CSV: one row per group (parameters, errors, status) plus mean and spread rows."""
    keys: list[str] = []
    for g in batch.groups:
        if g.ok:
            for e in g.result.estimates:
                if e.key not in keys:
                    keys.append(e.key)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["group", "status", "files", *[f"{k} [SI]" for k in keys], "rmse [Pa]", "nrmse", "r2", "reason"])
    cols: dict[str, list[float]] = {k: [] for k in [*keys, "rmse", "nrmse", "r2"]}
    for g in batch.groups:
        if g.ok:
            vals = {e.key: e.value for e in g.result.estimates}
            row = [vals.get(k, math.nan) for k in keys]
            for k in keys:
                cols[k].append(vals.get(k, math.nan))
            for k in ("rmse", "nrmse", "r2"):
                cols[k].append(getattr(g.result, k))
            w.writerow([g.group, "ok", len(g.files), *[f"{v:.8g}" for v in row],
                        f"{g.result.rmse:.6g}", f"{g.result.nrmse:.6g}", f"{g.result.r2:.6g}", ""])
        else:
            w.writerow([g.group, "failed", len(g.files), *[""] * len(keys), "", "", "", g.reason])
    for path, reason in batch.unreadable:
        w.writerow([Path(path).name, "unreadable", 1, *[""] * len(keys), "", "", "", reason])
    n_ok = sum(g.ok for g in batch.groups)
    if n_ok:
        for label, fn in (("mean", np.nanmean), ("std", lambda a: np.nanstd(a, ddof=1) if len(a) > 1 else math.nan)):
            w.writerow([label, f"{n_ok} group(s)", "",
                         *[f"{fn(np.array(cols[k])):.8g}" for k in keys],
                         *[f"{fn(np.array(cols[k])):.6g}" for k in ("rmse", "nrmse", "r2")], ""])
    return buf.getvalue()
