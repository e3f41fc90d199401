"""What runs in a worker for one job: checks, the job function, the manifest.

:func:`execute` never raises for a failure of the job itself: it returns an
outcome dict (``status`` ``"done"`` or ``"failed"`` with a one-line reason).
Only an interruption (KeyboardInterrupt, raised on SIGINT/SIGTERM) passes
through, after the job's atomic writers have removed their temporary files.
"""

from __future__ import annotations

import json
import os
import socket
import time
import traceback
from pathlib import Path
from typing import Any

from ..atomicio import jsonable
from ..errors import EsmmError
from .cache import write_manifest
from .jobs import JobOutput, code_version, sha256_file

#: Longest reason kept for an unexpected exception (the traceback goes to the log).
_MAX_REASON = 400


def one_line(text: str, limit: int = _MAX_REASON) -> str:
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 1] + "…"


def worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _normalise(result: Any) -> tuple[list[str], dict[str, Any]]:
    if result is None:
        return [], {}
    if isinstance(result, JobOutput):
        outputs, summary = result.outputs, result.summary
    elif isinstance(result, dict):
        outputs, summary = result.get("outputs", []), result.get("summary", {})
    else:
        raise TypeError(f"a job function must return a JobOutput or a dict, not {type(result).__name__}")
    summary = jsonable(summary or {}, strict=False)
    json.dumps(summary, allow_nan=True)  # a TypeError for what JSON cannot hold
    return [os.fspath(p) for p in outputs], summary


def execute(task: dict[str, Any]) -> dict[str, Any]:
    """Run one job (in a worker process) and record it in the cache when it succeeds.

    Parameters
    ----------
    task : dict
        Built by :func:`esmm.pipeline.batch.runner.run_jobs`: ``name``, ``kind``,
        ``key``, ``fn``, ``args``, ``kwargs``, ``out_dir``, ``key_inputs``,
        ``digests``, ``config``, ``code_version``.

    Returns
    -------
    dict
        ``name``, ``status`` ("done" or "failed"), ``reason``, ``exit_code``,
        ``seconds``, ``outputs`` (relative), ``summary``, ``worker``, and
        ``detail`` (a traceback, for the log only).
    """
    t0 = time.perf_counter()
    out = {"name": task["name"], "status": "failed", "reason": "", "exit_code": 1, "seconds": 0.0,
           "outputs": [], "summary": {}, "worker": worker_id(), "detail": ""}
    try:
        mine = code_version()
        if task.get("code_version") and task["code_version"] != mine:
            out.update(reason=f"the esmm code on this worker ({mine}) differs from the code that planned the "
                              f"batch ({task['code_version']}); install the same esmm everywhere and do not "
                              f"change it while a batch runs", exit_code=2)
            return out
        out_dir = Path(task["out_dir"])
        if not out_dir.is_dir():
            out.update(reason=f"the output folder {out_dir} is not visible on worker {socket.gethostname()}; "
                              f"put it on a file system every worker shares", exit_code=2)
            return out
        for path, (_name, digest) in zip(task["key_inputs"], task["digests"]):
            if sha256_file(path) != digest:
                out.update(reason=f"{path}: the file changed while the batch ran; run the batch again",
                           exit_code=2)
                return out
        fn = task["fn"]
        result = fn(*task.get("args", ()), **task.get("kwargs", {}))
        outputs, summary = _normalise(result)
        seconds = time.perf_counter() - t0
        rel = write_manifest(out_dir, task["key"], name=task["name"], kind=task["kind"],
                             inputs=task["digests"], config=task["config"], outputs=outputs,
                             summary=summary, seconds=seconds)
        out.update(status="done", exit_code=0, outputs=rel, summary=summary)
    except EsmmError as exc:
        out.update(reason=one_line(str(exc)), exit_code=exc.exit_code)
    except SystemExit as exc:  # meshio and others call sys.exit on some inputs
        out.update(reason=f"internal error: a library called sys.exit({exc.code!r}) (a bug; the traceback is in the "
                          f"batch log)", exit_code=1, detail=traceback.format_exc())
    except MemoryError:
        out.update(reason="out of memory; give the workers more memory or use a coarser target", exit_code=1)
    except Exception as exc:  # noqa: BLE001 - one job's bug must not end the batch
        out.update(reason=one_line(f"internal error: {type(exc).__name__}: {exc} (a bug; the traceback is in the "
                                   f"batch log)"), exit_code=1, detail=traceback.format_exc())
    out["seconds"] = time.perf_counter() - t0
    return out


def execute_blob(blob: bytes) -> dict[str, Any]:
    """:func:`execute` on a cloudpickled task (what a Dask worker runs).

    The runner pickles the task itself, with cloudpickle, so that job
    functions pickled *by value* (closures, functions of a script or a test
    module) arrive intact, and so that a task a worker cannot load fails as
    that job, with the reason, instead of taking the worker down.
    """
    import cloudpickle

    try:
        task = cloudpickle.loads(blob)
    except Exception as exc:  # noqa: BLE001
        return {"name": "?", "status": "failed", "exit_code": 1, "seconds": 0.0, "outputs": [], "summary": {},
                "worker": worker_id(), "detail": traceback.format_exc(),
                "reason": one_line(f"this worker cannot load the job ({type(exc).__name__}: {exc}); install the "
                                   f"same esmm and Python packages on every worker")}
    return execute(task)
