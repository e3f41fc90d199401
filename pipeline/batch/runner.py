"""Run a batch of jobs: cached ones skipped, the rest on a local pool or a Dask cluster.

:func:`run_jobs` is the one entry point. It locks the output folder, removes
temporary files a killed run left behind, computes every job's key
(:func:`~esmm.pipeline.batch.jobs.cache_key`), skips jobs whose complete result
is already there (unless ``force``), runs the others, and writes a log
(``<out>/esmm-batch-<UTC time>.log``: every job's outcome and timing) and a CSV
table (``<out>/batch-summary.csv``). One job failing, raising, or killing its
worker never stops the others. Ctrl-C (or SIGTERM) stops the batch: queued jobs
are not started, running local jobs are stopped (their temporary files
removed), and the summary of what finished is still written.

Schedulers
----------
``None`` / ``"local"``
    A pool of local worker processes (:class:`~esmm.pipeline.batch.local.LocalPool`),
    ``workers`` of them (default: the CPUs available).
``"serial"``
    In this process, one job after the other (debugging; no crash isolation).
``"tcp://HOST:PORT"`` (or ``tls://``, ``ucx://``), or a ``distributed.Client``
    An existing Dask cluster: every job is one ``client.submit(..., pure=False)``.
    The workers must have the same esmm installed and see the input and output
    folders at the same paths (a shared file system).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import re
import signal
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..atomicio import write_text
from ..errors import ConfigError, EsmmError
from ..progress import Reporter, ensure
from . import cache as _cache
from .jobs import (
    SUMMARY_CSV,
    BatchSummary,
    Job,
    JobOutcome,
    _canonical,
    cache_key,
    code_version,
    input_digests,
)
from .local import LocalPool, available_cpus
from .worker import execute, execute_blob, one_line

#: Name of the CSV table of the last batch in the output folder.
SUMMARY_NAME = SUMMARY_CSV

_DASK_ADDRESS = re.compile(r"^(tcp|tls|ucx|ws|wss|inproc)://\S+$")
_counter = itertools.count()


def parse_scheduler(scheduler: Any) -> tuple[str, Any]:
    """``(kind, target)`` with kind ``"local"``, ``"serial"`` or ``"dask"``.

    Raises
    ------
    ConfigError
        Not ``local``, ``serial``, a Dask address or a ``distributed.Client``.
    """
    if scheduler is None:
        return "local", None
    if isinstance(scheduler, str):
        s = scheduler.strip()
        if s.lower() in ("local", "processes", ""):
            return "local", None
        if s.lower() in ("serial", "inline", "none"):
            return "serial", None
        if _DASK_ADDRESS.match(s):
            return "dask", s
        if re.match(r"^[A-Za-z0-9_.\-]+:\d+$", s):  # host:port
            return "dask", f"tcp://{s}"
        raise ConfigError(f"scheduler: {scheduler!r} is not 'local', 'serial' or a Dask scheduler address "
                          f"such as tcp://10.0.0.5:8786", parameter="scheduler")
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - dask is a dependency
        Client = ()  # type: ignore[assignment]
    if Client and isinstance(scheduler, Client):
        return "dask", scheduler
    raise ConfigError(f"scheduler: expected an address or a dask Client, got {type(scheduler).__name__}",
                      parameter="scheduler")


def _check_workers(workers: int | None) -> int | None:
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers: expected a whole number >= 1, got {workers!r}", parameter="workers")
    return workers


# ----------------------------------------------------------------------------- logging
def _open_log(out: Path) -> tuple[logging.Logger, logging.Handler, Path]:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    path = out / f"esmm-batch-{stamp}.log"
    n = 2
    while path.exists():
        path = out / f"esmm-batch-{stamp}-{n}.log"
        n += 1
    handler = logging.FileHandler(path, encoding="utf-8", delay=False)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(message)s"))
    logger = logging.getLogger(f"esmm.batch.run{next(_counter)}")
    logger.setLevel(logging.DEBUG)
    logger.addHandler(handler)
    return logger, handler, path


# ----------------------------------------------------------------------------- SIGTERM -> Ctrl-C
@contextlib.contextmanager
def _sigterm_as_interrupt():
    """While the batch runs, SIGTERM (a cluster's time limit, ``kill``) stops it like Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt("SIGTERM")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


# ----------------------------------------------------------------------------- backends
Task = dict[str, Any]
OnEvent = Callable[[Task, dict[str, Any]], None]


def _interrupted(task: Task, why: str) -> dict[str, Any]:
    return {"name": task["name"], "status": "interrupted", "reason": why, "exit_code": 130, "seconds": 0.0,
            "outputs": [], "summary": {}, "worker": "", "detail": ""}


def _failed(task: Task, reason: str, exit_code: int = 1, detail: str = "") -> dict[str, Any]:
    return {"name": task["name"], "status": "failed", "reason": one_line(reason), "exit_code": exit_code,
            "seconds": 0.0, "outputs": [], "summary": {}, "worker": "", "detail": detail}


def _run_serial(tasks: list[Task], on_event: OnEvent) -> None:
    for i, t in enumerate(tasks):
        try:
            res = execute(t)
        except KeyboardInterrupt:
            on_event(t, _interrupted(t, "stopped by Ctrl-C"))
            for rest in tasks[i + 1:]:
                on_event(rest, _interrupted(rest, "not started: the batch was interrupted"))
            raise
        on_event(t, res)


def _run_local(tasks: list[Task], workers: int, on_event: OnEvent, timeout: float | None = None,
               stderr_dir: Path | None = None) -> None:
    by_id = dict(enumerate(tasks))
    pool = LocalPool(min(workers, len(tasks)), stderr_dir=stderr_dir)
    reported: set[int] = set()
    try:
        for i, t in by_id.items():
            pool.submit(i, execute, t)
        for tid, kind, value in pool.events(timeout=timeout):
            reported.add(tid)
            t = by_id[tid]
            if kind == "result":
                on_event(t, value)
            elif kind == "died":
                reason, tail = value
                on_event(t, _failed(t, reason, 1, f"worker output (last lines):\n{tail}" if tail else ""))
            elif kind == "interrupted":
                on_event(t, _interrupted(t, "stopped"))
            else:
                last = value.strip().splitlines()[-1] if value.strip() else "unknown error"
                on_event(t, _failed(t, f"internal error in the worker: {last}", 1, value))
        pool.close()
    except KeyboardInterrupt:
        running = set(pool.busy)
        for tid, kind, value in pool.interrupt():
            if tid in reported:
                continue
            reported.add(tid)
            t = by_id[tid]
            if kind == "result":
                on_event(t, value)
            elif kind == "died":
                on_event(t, _failed(t, value[0], 1))
        for tid, t in by_id.items():
            if tid not in reported:
                why = "stopped by Ctrl-C" if tid in running else "not started: the batch was interrupted"
                on_event(t, _interrupted(t, why))
        raise
    except BaseException:
        pool.close(kill=True)
        raise


def _dask_client(target: Any, timeout: float = 15.0):
    """A connected ``distributed.Client`` and whether we own it."""
    if not isinstance(target, str):
        return target, False
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - dask is a dependency
        raise ConfigError("scheduler: dask.distributed is not installed; pip install 'dask[distributed]'",
                          parameter="scheduler") from None
    try:
        return Client(target, timeout=f"{float(timeout)}s", set_as_default=False), True
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"scheduler: cannot connect to a Dask scheduler at {target} ({one_line(str(exc), 160)}); "
                          f"check the address and that 'dask scheduler' is running there", parameter="scheduler") from None


def _dask_reason(exc: BaseException | None) -> tuple[str, int]:
    if exc is None:
        return ("worker died (the job was lost with its worker three times and not rerun; "
                "see the Dask worker logs)"), 1
    name = type(exc).__name__
    if name == "KilledWorker":
        return ("worker died (the job's worker process ended every time it ran it; "
                "out of memory or a crash, see the Dask worker logs)"), 1
    if name in ("CancelledError", "FutureCancelledError"):
        return "cancelled on the Dask cluster (a worker or the scheduler was restarted?)", 1
    return f"internal error on the Dask worker: {name}: {one_line(str(exc), 300)}", 1


def _run_dask(tasks: list[Task], target: Any, on_event: OnEvent, logger: logging.Logger,
              timeout: float = 15.0) -> str:
    import cloudpickle
    from distributed import as_completed

    client, owned = _dask_client(target, timeout)
    address = getattr(client.scheduler, "address", str(target))
    logger.info("dask scheduler %s: %d worker(s)", address, len(client.scheduler_info().get("workers", {})))
    futures = {}
    reported: set[int] = set()
    try:
        for i, t in enumerate(tasks):
            # One key prefix for the whole batch: Dask sees one task group (one dashboard bar), and a
            # big batch is queued on the scheduler instead of being piled onto the first workers.
            key = f"esmm-batch-{uuid.uuid4().hex}"
            futures[client.submit(execute_blob, cloudpickle.dumps(t), pure=False, key=key, retries=0)] = i
            logger.debug("job %s: submitted as %s", t["name"], key)
        regather: dict[int, int] = {}
        ac = as_completed(list(futures), with_results=False, loop=client.loop)
        for fut in ac:
            i = futures[fut]
            t = tasks[i]
            if fut.status == "finished":
                try:
                    res = fut.result()
                except Exception as exc:  # noqa: BLE001 - the worker holding the result died
                    if fut.status != "error" and regather.get(i, 0) < 3:
                        # Dask reschedules a lost result; wait for it again.
                        regather[i] = regather.get(i, 0) + 1
                        logger.info("job %s: result lost with its worker, waiting for the rerun", t["name"])
                        ac.add(fut)
                        continue
                    reported.add(i)
                    reason, code = _dask_reason(exc)
                    on_event(t, _failed(t, reason, code))
                    continue
                reported.add(i)
                # Let go of the result: a worker that dies later holding it must not make Dask run
                # the job again (a rerun after the report rewrote its outputs behind its cache record).
                fut.release()
                on_event(t, res)
            elif fut.status not in ("error", "cancelled") and regather.get(i, 0) < 3:
                # "lost" (or back to "pending"): its worker died and Dask reruns it; wait again.
                regather[i] = regather.get(i, 0) + 1
                logger.info("job %s: lost with its worker (%s), waiting for the rerun", t["name"], fut.status)
                ac.add(fut)
            else:
                reported.add(i)
                try:
                    exc = fut.exception()
                except BaseException as e:  # noqa: BLE001 - cancelled futures raise here
                    exc = e
                reason, code = _dask_reason(exc)
                on_event(t, _failed(t, reason, code))
    except KeyboardInterrupt:
        pending = [f for f, i in futures.items() if i not in reported]
        with contextlib.suppress(Exception):
            client.cancel(pending, force=True)
        for f in pending:
            i = futures[f]
            on_event(tasks[i], _interrupted(tasks[i], "cancelled by Ctrl-C (a job already running on a "
                                                      "worker may still complete)"))
        raise
    finally:
        if owned:
            with contextlib.suppress(Exception):
                client.close(timeout=10)
    return address


# ----------------------------------------------------------------------------- run_jobs
@dataclass
class _Batch:
    """What the steps of one :func:`run_jobs` call share: the folder, the log, the outcomes so far."""

    out: Path
    logger: logging.Logger
    rep: Reporter
    summary: BatchSummary
    outcomes: dict[str, JobOutcome] = field(default_factory=dict)


def _check_jobs(jobs: Sequence[Job], job_timeout: float | None) -> list[str]:
    """The job names, after checking the time limit and that no two jobs share a name."""
    if job_timeout is not None and not (isinstance(job_timeout, (int, float)) and job_timeout > 0):
        raise ConfigError(f"job_timeout: expected a positive number of seconds, got {job_timeout!r}")
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"two batch jobs would write the same output {dup[0]!r}; rename one of the inputs")
    return names


def _make_out_dir(out_dir: str | os.PathLike) -> Path:
    """The batch folder, created if needed, as an absolute path."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    return out.resolve()


def _describe_scheduler(kind: str, target: Any, workers: int | None) -> tuple[int, str]:
    """``(worker processes, description for the log)``; 0 processes for Dask (the cluster decides)."""
    if kind == "local":
        n_workers = workers or available_cpus()
        return n_workers, f"local ({n_workers} process{'es' if n_workers > 1 else ''})"
    if kind == "serial":
        return 1, "serial (this process)"
    return 0, f"dask {target if isinstance(target, str) else 'client'}"


def _open_batch(out: Path, rep: Reporter, summary: BatchSummary,
                lock: _cache.FolderLock) -> tuple[_Batch, logging.Handler, list[Path]]:
    """Sweep what a killed run left (only under a working lock), open the log: the batch, its log handler, the sweep."""
    # Temporary files can be swept only while no one else writes here (the lock says so).
    swept = [] if lock.unsupported else _cache.sweep_temp(out) + _cache.sweep_workers(out)
    logger, handler, log_path = _open_log(out)
    if lock.unsupported:
        logger.warning("the file system cannot lock %s: make sure no other batch writes there; "
                       "leftover temporary files are not removed", out)
    summary.log_path = log_path
    return _Batch(out, logger, rep, summary), handler, swept


def _log_start(batch: _Batch, n_jobs: int, *, desc: str, force: bool, version: str, swept: list[Path]) -> None:
    """The log's first lines: the batch's settings and the temporary files swept."""
    batch.logger.info("batch start: %d job(s); scheduler %s; out %s; force %s; esmm %s; pid %d",
                      n_jobs, desc, batch.out, force, version, os.getpid())
    if swept:
        batch.logger.info("removed %d temporary file(s) left by an interrupted run: %s", len(swept),
                          ", ".join(str(p.relative_to(batch.out)) for p in swept[:20]))


def _plan_tasks(jobs: Sequence[Job], batch: _Batch, *, force: bool, version: str) -> list[Task]:
    """The tasks to run; jobs that failed before running and cached jobs go straight to the outcomes."""
    out, logger, outcomes = batch.out, batch.logger, batch.outcomes
    tasks: list[Task] = []
    for job in jobs:
        if job.error is not None or job.fn is None:
            reason = job.error or "the job has no function to run"
            outcomes[job.name] = JobOutcome(job.name, job.kind, "failed", reason=reason,
                                            exit_code=job.error_exit_code,
                                            summary=dict(job.error_summary))
            logger.warning("job %s: failed before running (exit %d): %s", job.name,
                           job.error_exit_code, reason)
            continue
        try:
            digests = input_digests(job.key_inputs)
            config = _canonical(job.config, "config")
            key = cache_key(job, digests=digests)
        except EsmmError as exc:
            outcomes[job.name] = JobOutcome(job.name, job.kind, "failed", reason=str(exc),
                                            exit_code=exc.exit_code)
            logger.warning("job %s: failed before running (exit %d): %s", job.name, exc.exit_code, exc)
            continue
        if not force:
            doc, why = _cache.lookup(out, key)
            if doc is not None:
                outcomes[job.name] = JobOutcome(
                    job.name, job.kind, "cached", key=key,
                    outputs=[r["path"] for r in doc["outputs"]], summary=doc.get("summary") or {},
                    worker=str(doc.get("worker", "")))
                logger.info("job %s: skipped, cached (key %s, made %s in %.2f s)", job.name, key[:12],
                            doc.get("finished_utc", "?"), float(doc.get("seconds") or 0.0))
                continue
            if why:
                logger.info("job %s: recomputing, the cached result is not usable: %s", job.name, why)
        tasks.append({"name": job.name, "kind": job.kind, "key": key, "fn": job.fn,
                      "args": tuple(job.args), "kwargs": dict(job.kwargs), "out_dir": str(out),
                      "key_inputs": [os.fspath(p) for p in job.key_inputs], "digests": digests,
                      "config": config, "code_version": version})
    return tasks


def _outcome_recorder(batch: _Batch, advance: Callable[[int], Any]) -> OnEvent:
    """The callback a scheduler calls with each finished task: record, log, report, advance."""
    logger, rep = batch.logger, batch.rep

    def on_event(task: Task, res: dict[str, Any]) -> None:
        o = JobOutcome(task["name"], task["kind"], res["status"], reason=res.get("reason", ""),
                       seconds=float(res.get("seconds") or 0.0), key=task["key"],
                       outputs=list(res.get("outputs") or []), summary=res.get("summary") or {},
                       worker=res.get("worker", ""), exit_code=int(res.get("exit_code", 0)))
        batch.outcomes[o.name] = o
        if o.status == "done":
            logger.info("job %s: done in %.2f s on %s (key %s); outputs: %s", o.name, o.seconds, o.worker,
                        o.key[:12], ", ".join(o.outputs) or "-")
            rep.step(f"done     {o.name} ({o.seconds:.1f} s)")
        elif o.status == "failed":
            logger.warning("job %s: failed after %.2f s on %s (exit %d): %s", o.name, o.seconds,
                           o.worker or "?", o.exit_code, o.reason)
            if res.get("detail"):
                logger.error("job %s: traceback:\n%s", o.name, res["detail"].rstrip())
            rep.warn(f"{o.name} failed: {o.reason}")
        else:
            logger.warning("job %s: %s: %s", o.name, o.status, o.reason)
        advance(1)

    return on_event


def _run_tasks(tasks: list[Task], batch: _Batch, *, kind: str, target: Any, n_workers: int, desc: str,
               title: str, job_timeout: float | None, connect_timeout: float, can_sweep: bool) -> None:
    """Run *tasks* on the scheduler; an interruption is recorded in the summary, not raised."""
    where = desc if kind != "local" else f"{min(n_workers, len(tasks))} local process(es)"
    # The interruption is caught outside the progress task, so that the task ends as
    # stopped (not "done") in the reporter.
    try:
        with _sigterm_as_interrupt(), batch.rep.task(f"{title}: {len(tasks)} job(s) on {where}",
                                                     total=len(tasks)) as advance:
            on_event = _outcome_recorder(batch, advance)
            if kind == "serial":
                _run_serial(tasks, on_event)
            elif kind == "local":
                _run_local(tasks, n_workers, on_event, job_timeout, _cache.workers_dir(batch.out))
            else:
                addr = _run_dask(tasks, target, on_event, batch.logger, connect_timeout)
                batch.summary.scheduler = f"dask {addr}"
    except KeyboardInterrupt:
        batch.summary.interrupted = True
        batch.logger.warning("batch interrupted (Ctrl-C or SIGTERM): queued jobs not started")
        if kind != "dask" and can_sweep:
            late = _cache.sweep_temp(batch.out)
            if late:
                batch.logger.info("removed %d temporary file(s) of stopped jobs", len(late))


def _write_summary(batch: _Batch, jobs: Sequence[Job], names: list[str], desc: str, t_start: float) -> None:
    """Fill the summary (jobs never started count as interrupted), write the table, log the end."""
    summary, logger = batch.summary, batch.logger
    by_name = {j.name: j for j in jobs}
    summary.outcomes = [batch.outcomes.get(n) or JobOutcome(n, by_name[n].kind, "interrupted",
                                                            reason="not started: the batch was interrupted",
                                                            exit_code=130)
                        for n in names]
    summary.scheduler = summary.scheduler or desc
    summary.seconds = time.perf_counter() - t_start
    try:
        summary.table_path = write_text(batch.out / SUMMARY_NAME, summary.table("csv"))
    except OSError as exc:  # pragma: no cover - disk full
        logger.error("cannot write %s: %s", SUMMARY_NAME, exc)
    logger.info("summary (%s):\n%s", "INTERRUPTED" if summary.interrupted else "complete",
                summary.table("text"))
    logger.info("batch end: exit code %d", summary.exit_code)


def run_jobs(jobs: Sequence[Job], *, out_dir: str | os.PathLike, scheduler: Any = None,
             workers: int | None = None, force: bool = False, reporter: Reporter | None = None,
             title: str = "batch", connect_timeout: float = 15.0,
             job_timeout: float | None = None) -> BatchSummary:
    """Run *jobs*, skipping those whose result is cached; never stop for one failure.

    Parameters
    ----------
    jobs : sequence of Job
        Names must be unique.
    out_dir : path
        The batch folder: outputs, ``.esmm-cache/``, the log and the table.
    scheduler : None, "local", "serial", "tcp://HOST:PORT" or distributed.Client
        Where jobs run (see the module docstring).
    workers : int, optional
        Local worker processes (default: the CPUs available; capped at the
        number of jobs to run). Ignored for Dask (the cluster decides).
    force : bool
        Recompute every job even when its result is cached.
    reporter : Reporter, optional
        Progress (one task advancing per job), a step per outcome and a
        warning per failure.
    title : str
        What the progress bar calls the batch (e.g. "calibrating").
    connect_timeout : float
        Seconds to wait for a Dask scheduler given by address.
    job_timeout : float, optional
        Wall-time limit of one job on the local pool [s]: a job still running
        then is stopped (SIGTERM, then SIGKILL) and fails with "timed out".
        Not applied by the serial and Dask schedulers.

    Returns
    -------
    BatchSummary
        ``exit_code`` is 0, 5 (some job failed) or 130 (interrupted). An
        interruption is *returned* (``interrupted=True``), not raised, after
        the log and table are written.

    Raises
    ------
    ConfigError
        Duplicate job names, a bad scheduler or worker count, an output folder
        that cannot be created or is locked by another batch, or a Dask
        scheduler that cannot be reached.
    """
    rep = ensure(reporter)
    kind, target = parse_scheduler(scheduler)
    workers = _check_workers(workers)
    names = _check_jobs(jobs, job_timeout)
    out = _make_out_dir(out_dir)
    t_start = time.perf_counter()
    summary = BatchSummary([], out)
    desc = ""

    with _cache.locked(out) as lock:
        batch, handler, swept = _open_batch(out, rep, summary, lock)
        logger = batch.logger
        try:
            version = code_version()
            n_workers, desc = _describe_scheduler(kind, target, workers)
            _log_start(batch, len(jobs), desc=desc, force=force, version=version, swept=swept)
            tasks = _plan_tasks(jobs, batch, force=force, version=version)
            n_cached = sum(o.status == "cached" for o in batch.outcomes.values())
            if n_cached:
                rep.step(f"{n_cached} job(s) already done (cached); {len(tasks)} to run")
            if tasks:
                _run_tasks(tasks, batch, kind=kind, target=target, n_workers=n_workers, desc=desc, title=title,
                           job_timeout=job_timeout, connect_timeout=connect_timeout,
                           can_sweep=not lock.unsupported)
        except KeyboardInterrupt:  # during planning
            summary.interrupted = True
            logger.warning("batch interrupted before any job ran")
        finally:
            _write_summary(batch, jobs, names, desc, t_start)
            logger.removeHandler(handler)
            handler.close()
    return summary
