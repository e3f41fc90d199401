"""Jobs, their content-addressed keys, and what a batch produced.

A :class:`Job` is one unit of batch work (one calibration group, one organ to
prepare): a picklable function with its arguments, the files whose *bytes*
decide its result (``key_inputs``) and the options that do (``config``).
:func:`cache_key` hashes those with the code version, so that a job whose
inputs, options and code are unchanged is recognised as done
(:mod:`esmm.pipeline.batch.cache`) and not recomputed.

:class:`BatchSummary` is what :func:`~esmm.pipeline.batch.runner.run_jobs`
returns: one :class:`JobOutcome` per job (done, cached, failed, interrupted),
a text/CSV table, and the exit code of the batch.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from .. import __version__, distributions
from ..errors import ConfigError, InputError

#: Version of the key recipe; bump when :func:`cache_key` changes meaning.
KEY_SCHEMA = "esmm-batch-key/1"

#: Job statuses, in the order of the summary table.
STATUSES = ("done", "cached", "failed", "interrupted")

#: Exit codes of a batch (see esmm.cli.main): any failure -> 5, Ctrl-C -> 130.
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 5, 130

_CHUNK = 1 << 20

#: The status table of a batch, in its output folder (written by the runner).
SUMMARY_CSV = "batch-summary.csv"


def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of a file's bytes.

    Raises
    ------
    InputError
        The file is missing, a folder or unreadable.
    """
    p = Path(path)
    h = hashlib.sha256()
    try:
        with open(p, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder, not a file") from None
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot be read ({exc.strerror or exc}); check the path and permissions") from None
    return h.hexdigest()


def _canonical(obj: Any, where: str) -> Any:
    """*obj* as plain JSON types with a fixed order (sets sorted, paths as text)."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        if math.isnan(obj):
            return "NaN"
        if math.isinf(obj):
            return "Infinity" if obj > 0 else "-Infinity"
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise ConfigError(f"{where}: option keys must be text, got {k!r}")
            out[k] = _canonical(v, f"{where}.{k}")
        return dict(sorted(out.items()))
    if isinstance(obj, (list, tuple)):
        return [_canonical(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, (set, frozenset)):
        items = [_canonical(v, where) for v in obj]
        return sorted(items, key=lambda v: json.dumps(v, sort_keys=True))
    # numpy scalars and arrays without importing numpy here
    if hasattr(obj, "tolist") and callable(obj.tolist):
        return _canonical(obj.tolist(), where)
    raise ConfigError(f"{where}: {type(obj).__name__} values cannot be part of a batch job's options; "
                      f"give numbers, text, lists or tables")


def canonical_json(config: Mapping[str, Any]) -> str:
    """The canonical JSON text of *config* (sorted keys, no spaces): the same options give the same text."""
    return json.dumps(_canonical(config, "config"), sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def _package_root() -> Path:
    return Path(__file__).resolve().parent.parent


#: Environment variable that pins the code version (see :func:`code_version`).
CODE_VERSION_ENV = "ESMM_CODE_VERSION"


def source_digest(roots: Sequence[str | os.PathLike]) -> str:
    """SHA-256 over the ``.py`` and ``.toml`` files under *roots* (names and bytes, sorted)."""
    h = hashlib.sha256()
    for root in map(Path, roots):
        for p in sorted(root.rglob("*")):
            if p.suffix in (".py", ".toml") and p.is_file() and "__pycache__" not in p.parts:
                h.update(str(p.relative_to(root).as_posix()).encode())
                h.update(b"\0")
                h.update(p.read_bytes())
                h.update(b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """The version of the code that makes results: ``<esmm version>+<digest>``.

    The digest covers the source of :mod:`esmm.pipeline` and the bundled
    presets (:mod:`esmm.configs`), and the versions of esmm's dependencies
    (pyproject's ``dependencies`` as installed, the list recorded in every
    asset), so that an edited checkout or an upgraded dependency never
    reuses results made by other code. The environment variable
    ``ESMM_CODE_VERSION`` replaces the digest (``<esmm version>+<value>``):
    for a deliberate reuse of results across code changes, at your own risk.
    """
    pinned = os.environ.get(CODE_VERSION_ENV, "").strip()
    if pinned:
        return f"{__version__}+{pinned}"
    roots: list[Path] = [_package_root()]
    try:
        from importlib import resources

        roots.append(Path(str(resources.files("esmm.configs"))))
    except (ModuleNotFoundError, TypeError):  # pragma: no cover - configs always installed
        pass
    h = hashlib.sha256(source_digest(roots).encode())
    for dist in distributions()[1:]:  # esmm itself is the source digest above
        try:
            v = metadata.version(dist)
        except metadata.PackageNotFoundError:
            v = "-"
        h.update(f"{dist}={v}\n".encode())
    return f"{__version__}+{h.hexdigest()[:16]}"


@dataclass
class Job:
    """One unit of batch work.

    Parameters
    ----------
    name : str
        Unique within the batch; names the job's output (e.g. the group or the
        asset stem) in the summary and the log. Part of the cache key.
    kind : str
        What the job does (``"calibrate"``, ``"prepare"``, ...). Part of the key.
    fn : callable
        ``fn(*args, **kwargs) -> JobOutput | dict`` run in a worker; it must be
        picklable (module-level function; closures work through cloudpickle)
        and write its outputs atomically (:mod:`esmm.pipeline.atomicio`).
        It returns the paths it wrote (``{"outputs": [...], "summary": {...}}``).
    args, kwargs
        Arguments of *fn*.
    key_inputs : sequence of path
        Files whose bytes decide the result (data files, sidecars, config
        files). Their SHA-256 and base names enter the key.
    config : mapping
        Every option that changes the result (plain JSON types). Enters the key
        as canonical JSON.
    error : str, optional
        The job is known to fail before running (e.g. an unreadable input):
        it is reported as failed with this one-line reason and not run.
    """

    name: str
    kind: str
    fn: Callable[..., Any] | None = None
    args: tuple = ()
    kwargs: dict[str, Any] = field(default_factory=dict)
    key_inputs: Sequence[str | os.PathLike] = ()
    config: Mapping[str, Any] = field(default_factory=dict)
    error: str | None = None
    error_exit_code: int = 2
    error_summary: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def failed(cls, name: str, kind: str, reason: str, *, exit_code: int = 2,
               summary: dict[str, Any] | None = None) -> Job:
        """A job that failed before it could run (reported, never executed; *summary* goes to its outcome)."""
        return cls(name=name, kind=kind, error=" ".join(str(reason).split()), error_exit_code=exit_code,
                   error_summary=dict(summary or {}))


@dataclass
class JobOutput:
    """What a job function returns: the files it wrote and a small JSON-able summary."""

    outputs: list[str | os.PathLike] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)


def input_digests(paths: Sequence[str | os.PathLike]) -> list[tuple[str, str]]:
    """``[(base name, sha256), ...]`` of *paths*, in order."""
    return [(Path(p).name, sha256_file(p)) for p in paths]


def cache_key(job: Job, *, digests: Sequence[tuple[str, str]] | None = None) -> str:
    """The content-addressed key of *job* (64 hex digits).

    SHA-256 over: the key recipe version, ``job.kind``, ``job.name``, the code
    version (:func:`code_version`), the base name and SHA-256 of every file in
    ``job.key_inputs`` (in order), and the canonical JSON of ``job.config``.
    Folders are not part of the key: moving the data keeps the results valid,
    renaming a file (which appears in the reports) does not.

    Parameters
    ----------
    job : Job
    digests : list of (name, sha256), optional
        Precomputed :func:`input_digests` of ``job.key_inputs``.

    Raises
    ------
    InputError
        A key input cannot be read.
    ConfigError
        ``job.config`` holds a value that is not plain data.
    """
    if digests is None:
        digests = input_digests(job.key_inputs)
    h = hashlib.sha256()
    for part in (KEY_SCHEMA, job.kind, job.name, code_version()):
        h.update(part.encode())
        h.update(b"\0")
    for name, digest in digests:
        h.update(f"{name}\0{digest}\0".encode())
    h.update(b"\1")
    h.update(canonical_json(job.config).encode())
    return h.hexdigest()


@dataclass
class JobOutcome:
    """How one job ended.

    Attributes
    ----------
    name, kind : str
    status : {"done", "cached", "failed", "interrupted"}
        ``cached``: skipped, a complete result for the same key was found.
        ``interrupted``: not run, or stopped, because the batch was interrupted.
    reason : str
        One line, for failed (and interrupted) jobs.
    seconds : float
        Wall time in the worker (0 for cached).
    key : str
        The cache key ("" when it could not be computed).
    outputs : list of str
        Files of the result, relative to the batch folder where possible.
    summary : dict
        The job's own figures (e.g. fitted parameters), also for cached jobs.
    worker : str
        ``host:pid`` that ran it.
    exit_code : int
        The exit code the failure would have on its own (2 input, 3 fit, ...).
    """

    name: str
    kind: str
    status: str
    reason: str = ""
    seconds: float = 0.0
    key: str = ""
    outputs: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    worker: str = ""
    exit_code: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("name", "kind", "status", "reason", "seconds", "key",
                                               "outputs", "summary", "worker", "exit_code")}


@dataclass
class BatchSummary:
    """The outcome of a batch: one :class:`JobOutcome` per job, in job order.

    Attributes
    ----------
    outcomes : list of JobOutcome
    out_dir : Path
    scheduler : str
        ``"local (N processes)"``, ``"serial"`` or the Dask scheduler address.
    seconds : float
        Wall time of the whole batch.
    interrupted : bool
        Ctrl-C (or SIGTERM) stopped the batch.
    log_path, table_path : Path or None
        The batch log and the CSV summary written in *out_dir*.
    """

    outcomes: list[JobOutcome]
    out_dir: Path
    scheduler: str = ""
    seconds: float = 0.0
    interrupted: bool = False
    log_path: Path | None = None
    table_path: Path | None = None

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def n_done(self) -> int:
        return self.count("done")

    @property
    def n_cached(self) -> int:
        return self.count("cached")

    @property
    def n_failed(self) -> int:
        return self.count("failed")

    @property
    def n_interrupted(self) -> int:
        return self.count("interrupted")

    @property
    def ok(self) -> bool:
        """Every job is done or cached."""
        return all(o.status in ("done", "cached") for o in self.outcomes)

    @property
    def exit_code(self) -> int:
        """130 when interrupted, 5 when any job failed, else 0."""
        if self.interrupted:
            return EXIT_INTERRUPTED
        return EXIT_FAILED if self.n_failed else EXIT_OK

    def by_name(self) -> dict[str, JobOutcome]:
        return {o.name: o for o in self.outcomes}

    def counts_line(self) -> str:
        """``"12 jobs: 7 done, 4 skipped (cached), 1 failed in 83.2 s"``."""
        parts = [f"{self.n_done} done", f"{self.n_cached} skipped (cached)", f"{self.n_failed} failed"]
        if self.n_interrupted:
            parts.append(f"{self.n_interrupted} interrupted")
        return f"{len(self.outcomes)} job(s): {', '.join(parts)} in {self.seconds:.1f} s"

    def problem_line(self) -> str:
        """One line on what went wrong ("" when every job is done or cached): the failed jobs, or the
        interruption and what to do."""
        failed = [o.name for o in self.outcomes if o.status == "failed"]
        names = ", ".join(failed[:5]) + (f" and {len(failed) - 5} more" if len(failed) > 5 else "")
        if self.interrupted:
            stopped = sum(o.status == "interrupted" for o in self.outcomes)
            kept = self.n_done + self.n_cached
            return (f"interrupted: {stopped} of {len(self.outcomes)} job(s) not finished, {kept} complete and "
                    f"kept{f', {len(failed)} failed' if failed else ''}; run the same command again to do "
                    f"only what is missing")
        if failed:
            return (f"{len(failed)} of {len(self.outcomes)} job(s) failed: {names}; the others are complete "
                    f"(the reasons are in {SUMMARY_CSV} and the batch log)")
        return ""

    def table(self, fmt: str = "text") -> str:
        """The summary table: one row per job (name, status, seconds, reason).

        Parameters
        ----------
        fmt : {"text", "csv"}
            Aligned text for a terminal, or CSV (with key, outputs and worker).
        """
        if fmt == "csv":
            buf = io.StringIO()
            w = csv.writer(buf, lineterminator="\n")
            w.writerow(["name", "kind", "status", "seconds", "reason", "exit_code", "key", "worker", "outputs"])
            for o in self.outcomes:
                w.writerow([o.name, o.kind, _status_label(o.status), f"{o.seconds:.3f}", o.reason,
                            o.exit_code, o.key, o.worker, ";".join(o.outputs)])
            return buf.getvalue()
        if fmt != "text":
            raise ConfigError(f"fmt: {fmt!r} is not 'text' or 'csv'")
        rows = [("name", "status", "time", "reason")]
        for o in self.outcomes:
            t = f"{o.seconds:.1f} s" if o.status == "done" or (o.status == "failed" and o.seconds) else ""
            rows.append((o.name, _status_label(o.status), t, o.reason))
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        lines = []
        for r in rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r[:3], widths)) + ("  " + r[3] if r[3] else ""))
        lines.append(self.counts_line())
        return "\n".join(line.rstrip() for line in lines)

    def to_dict(self) -> dict[str, Any]:
        return {"schema": "esmm.batch/1", "scheduler": self.scheduler, "seconds": self.seconds,
                "interrupted": self.interrupted, "exit_code": self.exit_code,
                "counts": {s: self.count(s) for s in STATUSES},
                "log": None if self.log_path is None else str(self.log_path),
                "jobs": [o.to_dict() for o in self.outcomes]}


def _status_label(status: str) -> str:
    return "skipped (cached)" if status == "cached" else status
