"""Run small dense linear algebra single-threaded.

The discovery solves many small least-squares problems (a few thousand rows,
a dozen columns). For these, OpenBLAS threads cost more than they save, and on
a machine whose cores are busy they cost a great deal: waking a second thread
takes far longer than the work itself. The implicit stepper's conjugate
gradients and sparse triangular solves are as small (docs/design/simulator.md,
"The implicit stepper (the default)").
:func:`single_threaded_blas` sets the thread count of every OpenBLAS
loaded in the process to 1 for the duration of a ``with`` block and restores
it after, using ``threadpoolctl`` when it is installed and the libraries'
own ``*_set_num_threads`` entry points otherwise. It does nothing where neither
is available. :func:`usable_cores` says how many processes a parallel step may
start (the discovery's nested folds, a validation's cases).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import multiprocessing
import os
from collections.abc import Iterator

_NAMES = (
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
    ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
    ("openblas_get_num_threads", "openblas_set_num_threads"),
)
_HANDLES: list[tuple] | None = None


def _handles() -> list[tuple]:
    global _HANDLES
    if _HANDLES is not None:
        return _HANDLES
    out = []
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line}
    except OSError:
        paths = set()
    for p in sorted(paths):
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for get, set_ in _NAMES:
            if hasattr(lib, get) and hasattr(lib, set_):
                g, s = getattr(lib, get), getattr(lib, set_)
                g.restype = ctypes.c_int
                s.argtypes = [ctypes.c_int]
                out.append((g, s))
                break
    _HANDLES = out
    return out


@functools.cache
def _controller():
    """threadpoolctl's controller of the libraries loaded so far (made once, then cheap per block), or None."""
    try:
        from threadpoolctl import ThreadpoolController  # type: ignore[import-not-found]
    except ImportError:
        return None
    import scipy.sparse.linalg  # noqa: F401 - scipy's OpenBLAS (SuperLU's) loaded before the controller looks

    return ThreadpoolController()


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Context manager: OpenBLAS uses one thread inside the block."""
    controller = _controller()
    if controller is not None:
        with controller.limit(limits=1, user_api="blas"):
            yield
        return
    saved = []
    try:
        for g, s in _handles():
            try:
                n = int(g())
                s(1)
                saved.append((s, n))
            except Exception:  # noqa: BLE001 - never fail a fit over a thread setting
                continue
        yield
    finally:
        for s, n in saved:
            with contextlib.suppress(Exception):
                s(max(n, 1))


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform says, else the machine's); 1 in
    a daemonic process (a process pool's or a Dask worker), which may not start processes of its own."""
    if multiprocessing.current_process().daemon:
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
