"""Ctrl-C (and a worker's SIGTERM) never lands in the middle of an import.

A KeyboardInterrupt raised while a compiled extension is being initialised
leaves it half-made, and VTK then crashes the process (SIGSEGV, as when
``esmm prepare`` is interrupted during its first ``import vtk``) instead of
stopping cleanly with exit code 130. The library imports such modules lazily,
so the moment is real.

:func:`install` wraps ``builtins.__import__`` with a depth counter and the
signal handlers with a check: a signal that arrives while an import runs is
held, and its handler runs as soon as the outermost import returns. Only the
process's owner calls it (the CLI's ``main`` and the batch worker's entry
point); importing this module changes nothing.
"""

from __future__ import annotations

import builtins
import signal
import threading
from collections.abc import Callable

_state: dict = {"depth": 0, "pending": None, "installed": False}
_original_import = builtins.__import__


def _guarded_import(*args, **kwargs):
    if threading.current_thread() is not threading.main_thread():  # signals go to the main thread
        return _original_import(*args, **kwargs)
    _state["depth"] += 1
    try:
        return _original_import(*args, **kwargs)
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0 and _state["pending"] is not None:
            handler, signum, frame = _state["pending"]
            _state["pending"] = None
            handler(signum, frame)


def deferring(handler: Callable) -> Callable:
    """*handler*, held back while an import runs (run when the outermost import returns)."""

    def held(signum, frame):
        if _state["depth"] > 0:
            if _state["pending"] is None:
                _state["pending"] = (handler, signum, frame)
            return
        handler(signum, frame)

    held.__wrapped__ = handler
    return held


def install(signals: tuple[int, ...] = (signal.SIGINT,)) -> None:
    """Hold *signals* whose handler is a Python function while an import runs (main thread only).

    Ignored or default-action signals are left alone. Safe to call twice.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    if not _state["installed"]:
        builtins.__import__ = _guarded_import
        _state["installed"] = True
    for sig in signals:
        current = signal.getsignal(sig)
        if callable(current) and not hasattr(current, "__wrapped__"):
            signal.signal(sig, deferring(current))
