"""The cases of a validation solved at once, one per core: they share nothing but their inputs.

Each case's two solutions (the continuum's Newton iterations and the
network's) are independent of every other case's, and one core solves one
case at a time (the factorizations run on one thread,
:mod:`.linear`), so :func:`map_cases` gives each case a process of its own
where the process may use more than one core. The workers are forked: they
inherit the network, tables and material without copying them, and each sends
back its result and what it would have reported (its steps and warnings,
replayed in the cases' order, so that the output reads as a serial run's, with
a line as each case ends; the progress bars inside a case are not shown). The answers are a serial run's,
number for number: each worker solves its case with the same code on the same
inputs.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time
from collections.abc import Callable, Iterator, Sequence

from ..blas import single_threaded_blas, usable_cores

__all__ = ["map_cases"]


class _Recorder:
    """A reporter that keeps the steps and warnings of a case in their order, for the parent to replay."""

    def __init__(self) -> None:
        self.log: list[tuple[str, str]] = []

    def step(self, message: str) -> None:
        self.log.append(("step", message))

    def warn(self, message: str) -> None:
        self.log.append(("warn", message))

    @contextlib.contextmanager
    def task(self, description: str, total: float | None = None) -> Iterator[Callable[[float], None]]:
        yield lambda amount=1.0: None


#: the function and items of the cases being solved in forked workers (set by :func:`map_cases` before forking)
_SHARED: tuple | None = None


def _die_with_parent(parent: int) -> None:
    """Linux: the worker is sent SIGTERM when the process that forked it ends (a parent that is killed cannot
    shut its pool down, and its workers would otherwise solve their cases on for nobody)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))     # PR_SET_PDEATHSIG
    except (OSError, AttributeError, TypeError):
        return
    if os.getppid() != parent:          # the parent ended before the request
        os._exit(1)


def _worker(i: int):
    fn, items = _SHARED
    rec = _Recorder()
    with single_threaded_blas():
        out = fn(items[i], rec)
    return out, rec.log


def map_cases(fn: Callable, items: Sequence, *, jobs: int | None = None, reporter,
              names: Sequence[str] | None = None) -> list:
    """``[fn(item, reporter) for item in items]``, in up to *jobs* forked processes (default: the usable cores).

    Serial where one process is asked for or usable, there is one item, or the
    platform cannot fork. In workers, *fn* reports to a recorder whose steps and
    warnings are replayed on *reporter* afterwards, case by case, and its
    result must pickle. An exception raised by *fn* is raised here. Each case
    that ends is reported as a step at once (by its name in *names*), so that a
    log shows progress where no progress bar is drawn.
    """
    global _SHARED
    n = len(items)
    workers = min(n, usable_cores() if jobs is None else max(1, int(jobs)))
    if workers <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return [fn(item, reporter) for item in items]
    from concurrent.futures import ProcessPoolExecutor, as_completed

    _SHARED = (fn, items)
    names = [f"case {i + 1}" for i in range(n)] if names is None else list(names)
    reporter.step(f"solving {n} cases in {workers} processes: {', '.join(names)}")
    t0 = time.perf_counter()
    try:
        with reporter.task(f"{n} cases in {workers} processes", total=n) as advance, \
                ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                                    initializer=_die_with_parent, initargs=(os.getpid(),)) as pool:
            futures = {pool.submit(_worker, i): i for i in range(n)}
            got: list = [None] * n
            for done, fut in enumerate(as_completed(futures), 1):
                i = futures[fut]
                got[i] = fut.result()
                reporter.step(f"{names[i]}: solved ({done} of {n}, {time.perf_counter() - t0:.0f} s)")
                advance(1)
    finally:
        _SHARED = None
    results = []
    for out, log in got:
        for kind, message in log:
            (reporter.warn if kind == "warn" else reporter.step)(message)
        results.append(out)
    return results
