"""A local pool of worker processes that knows which job killed a worker.

:class:`concurrent.futures.ProcessPoolExecutor` marks *every* pending job
failed ("BrokenProcessPool") when one worker dies, and cannot say which job
was to blame. A batch that must survive a segfaulting mesher or the OOM killer
needs better, so this pool gives each worker its own socket and runs one job at
a time on it: when a worker's process ends without a reply, the job it held is
reported as ``died`` with the signal or exit code (and the end of the worker's
stderr), a new worker replaces it and the other jobs carry on.

Workers are fresh interpreters (``python -P -c ...``, not ``multiprocessing``):
nothing of the caller's ``__main__`` is re-run in them, which makes the pool
safe from scripts without a ``__main__`` guard, notebooks and the CLI alike,
and gmsh, VTK and numba (not fork-safe) start clean. A worker

* ignores SIGINT: the parent decides what a Ctrl-C stops;
* turns SIGTERM into KeyboardInterrupt, so atomic writers remove their
  temporary files and gmsh children are killed;
* ends itself when the parent dies, even by SIGKILL (it watches a pipe whose
  other end only the parent holds);
* dumps a Python traceback on a fatal signal (faulthandler) into its stderr.

Payloads travel with cloudpickle, so jobs may be closures.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import interrupts

#: Environment variables that limit a library's threads; set for each worker
#: (unless the user set them) so that N workers do not each start N threads.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS")

_ID = struct.Struct("<q")
#: What :meth:`LocalPool._receive` returns for a worker's start notice (a bare task id).
_STARTED = ("started",)
_TAIL_BYTES = 4000


def available_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def thread_env(workers: int) -> dict[str, str]:
    """Thread-limit variables for *workers* processes sharing this machine."""
    n = str(max(1, available_cpus() // max(1, workers)))
    return {k: n for k in THREAD_VARIABLES}


def describe_exit(exitcode: int | None) -> str:
    """``"worker died (killed by SIGKILL: out of memory, or killed by someone)"`` and the like."""
    if exitcode is None:
        return "worker died (no exit status)"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        hint = {"SIGKILL": ": out of memory, or killed by someone",
                "SIGSEGV": ": a crash in compiled code", "SIGABRT": ": a crash in compiled code",
                "SIGBUS": ": a crash in compiled code"}.get(name, "")
        return f"worker died (killed by {name}{hint})"
    return f"worker died (exit code {exitcode} without a result)"


# ----------------------------------------------------------------------------- child side
def _on_sigterm(signum, frame):  # pragma: no cover - runs in the child
    raise KeyboardInterrupt("terminated")


def _watch_parent(fd: int) -> None:  # pragma: no cover - runs in the child
    """End this worker when the read end *fd* reaches EOF (the parent, its only writer, died)."""

    def run():
        with contextlib.suppress(OSError):
            while os.read(fd, 1):
                pass
        with contextlib.suppress(OSError):
            os.kill(os.getpid(), signal.SIGTERM)  # like a Ctrl-C: temporary files removed
        time.sleep(20)
        os._exit(70)

    threading.Thread(target=run, name="esmm-parent-watch", daemon=True).start()


def _child_main(sock_fd: int, death_fd: int) -> None:  # pragma: no cover - runs in the child
    """Entry point of a worker process: receive jobs on *sock_fd*, reply, until EOF."""
    import faulthandler
    from multiprocessing.connection import Connection

    faulthandler.enable()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    interrupts.install((signal.SIGTERM,))  # not in the middle of an import of a compiled library
    _watch_parent(death_fd)
    conn = Connection(sock_fd)
    import cloudpickle

    while True:
        try:
            data = conn.recv_bytes()
        except (EOFError, OSError, KeyboardInterrupt):
            return
        if not data:
            return
        (tid,) = _ID.unpack_from(data)
        try:
            fn, args = cloudpickle.loads(data[_ID.size:])
            conn.send_bytes(_ID.pack(tid))  # started: the job's own time begins now
            reply = ("result", fn(*args))
        except KeyboardInterrupt:
            with contextlib.suppress(Exception):
                conn.send_bytes(_ID.pack(tid) + cloudpickle.dumps(("interrupted", "")))
            return
        except BaseException:  # noqa: BLE001 - includes SystemExit from a library
            reply = ("error", traceback.format_exc())
        try:
            payload = cloudpickle.dumps(reply)
        except Exception:  # noqa: BLE001
            payload = cloudpickle.dumps(("error", "the job's result cannot be pickled:\n" + traceback.format_exc()))
        try:
            conn.send_bytes(_ID.pack(tid) + payload)
        except (OSError, KeyboardInterrupt):
            return


# ----------------------------------------------------------------------------- parent side
@dataclass
class _Worker:
    proc: subprocess.Popen
    conn: Any
    death_w: int
    stderr_path: Path | None
    task: int | None = None
    started: float = 0.0

    def stderr_tail(self) -> str:
        if self.stderr_path is None:
            return ""
        try:
            with open(self.stderr_path, "rb") as fh:
                fh.seek(0, os.SEEK_END)
                n = fh.tell()
                fh.seek(max(0, n - _TAIL_BYTES))
                return fh.read().decode("utf-8", "replace").strip()
        except OSError:
            return ""


class LocalPool:
    """Run callables in worker processes, one at a time per worker.

    Parameters
    ----------
    workers : int
        Number of worker processes (started lazily, at most one per queued job).
    env : dict, optional
        Extra environment of the workers (default :func:`thread_env`; variables
        the user has set win).
    stderr_dir : path, optional
        Where each worker's stdout/stderr go (``worker-<pid>.txt``; removed when
        the worker ends normally). Default: a private temporary folder.
    kill_grace : float
        Seconds a timed-out task gets between SIGTERM and SIGKILL.

    Events from :meth:`events` are ``(task_id, kind, value)`` with kind
    ``"result"`` (value: the callable's return value), ``"error"`` (value: a
    traceback text; the callable raised), ``"died"`` (value: ``(reason,
    stderr tail)``; the worker ended without replying) or ``"interrupted"``.
    """

    def __init__(self, workers: int, *, env: dict[str, str] | None = None,
                 stderr_dir: str | os.PathLike | None = None, kill_grace: float = 5.0):
        if isinstance(workers, bool) or int(workers) < 1:
            raise ValueError("workers must be >= 1")
        self.n = int(workers)
        self._env = dict(os.environ)
        for k, v in (thread_env(self.n) if env is None else env).items():
            self._env.setdefault(k, v)
        self._own_dir = stderr_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="esmm-pool-")) if stderr_dir is None else Path(stderr_dir)
        self._dir.mkdir(parents=True, exist_ok=True)
        self._workers: list[_Worker] = []
        self._queue: deque[tuple[int, bytes]] = deque()
        self._closed = False
        self.kill_grace = float(kill_grace)

    # -- submission
    def submit(self, task_id: int, fn: Callable[..., Any], *args: Any) -> None:
        import cloudpickle

        self._queue.append((int(task_id), _ID.pack(int(task_id)) + cloudpickle.dumps((fn, args))))

    @property
    def busy(self) -> list[int]:
        """Ids of the tasks running now."""
        return [w.task for w in self._workers if w.task is not None]

    @property
    def pending(self) -> list[int]:
        """Ids of the tasks not started yet."""
        return [tid for tid, _ in self._queue]

    def _start_worker(self) -> _Worker:
        from multiprocessing.connection import Connection

        parent_sock, child_sock = socket.socketpair()
        death_r, death_w = os.pipe()
        os.set_inheritable(child_sock.fileno(), True)
        os.set_inheritable(death_r, True)
        err_path = self._dir / f"worker-{time.monotonic_ns()}.txt"
        code = ("from esmm.pipeline.batch.local import _child_main; "
                f"_child_main({child_sock.fileno()}, {death_r})")
        with open(err_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-P", "-c", code], stdin=subprocess.DEVNULL, stdout=err,
                                    stderr=subprocess.STDOUT, env=self._env,
                                    pass_fds=(child_sock.fileno(), death_r), close_fds=True,
                                    start_new_session=True)
        child_sock.close()
        os.close(death_r)
        conn = Connection(parent_sock.detach())
        w = _Worker(proc, conn, death_w, err_path)
        self._workers.append(w)
        return w

    def _fill(self) -> None:
        idle = [w for w in self._workers if w.task is None]
        while self._queue:
            if not idle:
                if len(self._workers) >= self.n:
                    return
                idle.append(self._start_worker())
            w = idle.pop()
            tid, data = self._queue.popleft()
            try:
                w.conn.send_bytes(data)
            except OSError:  # the idle worker is gone: retire it, requeue the task
                self._queue.appendleft((tid, data))
                self._retire(w)
                continue
            w.task, w.started = tid, time.monotonic()

    def _retire(self, w: _Worker, *, keep_log: bool = False) -> None:
        with contextlib.suppress(Exception):
            w.conn.close()
        with contextlib.suppress(OSError):
            os.close(w.death_w)
        with contextlib.suppress(Exception):
            w.proc.wait(timeout=5)
        if w.stderr_path is not None and not keep_log:
            with contextlib.suppress(OSError):
                w.stderr_path.unlink()
        if w in self._workers:
            self._workers.remove(w)

    def _receive(self, w: _Worker) -> tuple[int, str, Any] | None:
        """The worker's reply; ``_STARTED`` for its start notice; None if it died."""
        import cloudpickle

        try:
            data = w.conn.recv_bytes()
        except (EOFError, OSError):
            return None
        (tid,) = _ID.unpack_from(data)
        if len(data) == _ID.size:  # the job has been loaded and starts running
            w.started = time.monotonic()
            return _STARTED
        try:
            kind, value = cloudpickle.loads(data[_ID.size:])
        except Exception:  # noqa: BLE001
            kind, value = "error", "the job's result could not be unpickled:\n" + traceback.format_exc()
        w.task = None
        return tid, kind, value

    def _death(self, w: _Worker) -> tuple[int, str, Any]:
        tid = w.task
        with contextlib.suppress(Exception):
            w.proc.wait(timeout=10)
        reason = describe_exit(w.proc.returncode)
        tail = w.stderr_tail()
        self._retire(w)
        return tid, "died", (reason, tail)

    def events(self, *, timeout: float | None = None) -> Iterator[tuple[int, str, Any]]:
        """Run every submitted task; yield each one's event as it ends.

        Parameters
        ----------
        timeout : float, optional
            Wall-time limit of one task [s], counted from the moment its
            worker has loaded it (a fresh worker's start-up is not the job's
            time; it is bounded by the same limit): a task running longer has
            its worker killed (SIGKILL) and ends as ``"died"`` with the reason
            ``"timed out after ... s (the worker was killed)"``.
        """
        from multiprocessing.connection import wait

        while True:
            self._fill()
            running = [w for w in self._workers if w.task is not None]
            if not running:
                return
            wait_for = None
            if timeout is not None:
                wait_for = max(0.0, min(w.started for w in running) + timeout - time.monotonic())
            ready = set(wait([w.conn for w in running], timeout=wait_for))
            for w in running:
                if w.conn in ready:
                    ev = self._receive(w)
                    if ev is not _STARTED:
                        yield ev if ev is not None else self._death(w)
                elif timeout is not None and time.monotonic() - w.started >= timeout:
                    yield self._kill_overdue(w, timeout)

    def _kill_overdue(self, w: _Worker, timeout: float) -> tuple[int, str, Any]:
        tid = w.task
        # SIGTERM first: the job stops like on Ctrl-C (temporary files removed, gmsh children killed).
        with contextlib.suppress(OSError):
            w.proc.send_signal(signal.SIGTERM)
        try:
            w.proc.wait(timeout=self.kill_grace)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                os.killpg(w.proc.pid, signal.SIGKILL)  # the worker and what it started in its group
            with contextlib.suppress(Exception):
                w.proc.wait(timeout=10)
        tail = w.stderr_tail()
        self._retire(w)
        return tid, "died", (f"timed out after {timeout:g} s (the worker was killed)", tail)

    def interrupt(self, *, grace: float = 15.0) -> list[tuple[int, str, Any]]:
        """Stop now: drop queued tasks, SIGTERM the running ones, wait *grace* s, then SIGKILL.

        Returns the events of tasks that still ended during the grace period
        (some may have finished their work). Tasks that were queued or stopped
        are not in the list: the caller knows them as interrupted.
        """
        from multiprocessing.connection import wait

        self._queue.clear()
        events: list[tuple[int, str, Any]] = []
        busy = [w for w in self._workers if w.task is not None]
        for w in busy:
            with contextlib.suppress(OSError):
                w.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        try:
            while busy and time.monotonic() < deadline:
                ready = set(wait([w.conn for w in busy], timeout=max(0.0, deadline - time.monotonic())))
                for w in list(busy):
                    if w.conn in ready:
                        ev = self._receive(w)
                        if ev is _STARTED:
                            continue
                        if ev is not None and ev[1] != "interrupted":
                            events.append(ev)
                        busy.remove(w)
        except KeyboardInterrupt:  # a second Ctrl-C: do not wait any longer
            pass
        self.close(kill=True)
        return events

    def close(self, *, kill: bool = False) -> None:
        """End every worker (politely: end of input; with *kill*: SIGTERM, then SIGKILL)."""
        if self._closed:
            return
        self._closed = True
        for w in self._workers:
            with contextlib.suppress(Exception):
                if kill:
                    if w.proc.poll() is None:
                        w.proc.send_signal(signal.SIGTERM)
                else:
                    w.conn.send_bytes(b"")
        deadline = time.monotonic() + (5.0 if kill else 15.0)
        for w in list(self._workers):
            try:
                w.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(Exception):
                    w.proc.kill()
                    w.proc.wait(timeout=5)
            self._retire(w)
        self._queue.clear()
        if self._own_dir:
            with contextlib.suppress(OSError):
                for p in self._dir.iterdir():
                    p.unlink()
                self._dir.rmdir()

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(kill=exc_type is not None)

    def __del__(self):  # pragma: no cover - safety net
        with contextlib.suppress(Exception):
            if not self._closed:
                self.close(kill=True)


class Sandbox:
    """One worker process that runs callables one at a time and survives their crashes.

    For work that may take its process down (a segfault in a compiled reader
    on a damaged file, a hang): ``call`` returns ``("result", value)``,
    ``("error", traceback text)`` or ``("died", (reason, stderr tail))``; after
    a death the next call starts a fresh worker.

    Examples
    --------
    >>> with Sandbox() as sb:                                  # doctest: +SKIP
    ...     kind, value = sb.call(validate_asset, "liver.h5", timeout=60)
    """

    def __init__(self, *, env: dict[str, str] | None = None, kill_grace: float = 2.0):
        self._pool = LocalPool(1, env=env, kill_grace=kill_grace)
        self._n = 0

    def call(self, fn: Callable[..., Any], *args: Any, timeout: float | None = None) -> tuple[str, Any]:
        self._n += 1
        self._pool.submit(self._n, fn, *args)
        for _tid, kind, value in self._pool.events(timeout=timeout):
            return kind, value
        return "died", ("no result", "")  # pragma: no cover - events always yields one

    def close(self) -> None:
        self._pool.close()

    def __enter__(self) -> Sandbox:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
