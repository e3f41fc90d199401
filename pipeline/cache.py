"""Where esmm keeps results it can compute again, and how it names them.

Root: ``$ESMM_CACHE_DIR``, else ``$XDG_CACHE_HOME/esmm``, else
``~/.cache/esmm``; one folder per kind of result (``compensation``: the
calibrations of :mod:`~esmm.pipeline.compensation.policy`;
``settle``: the equilibria under gravity a simulation starts from,
:mod:`~esmm.pipeline.simulate.relax`). An entry is named by the SHA-256 of
everything its result depends on, the code that computes it included
(:func:`digest`), so an entry is never stale; a missing or unreadable entry is
a miss, and a cache that cannot be written only costs time. Deleting the
folder is always safe.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def root() -> Path:
    """The cache's root folder (module docstring); not created here."""
    base = os.environ.get("ESMM_CACHE_DIR")
    if not base:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        base = os.path.join(xdg, "esmm")
    return Path(base)


def folder(kind: str) -> Path:
    """The folder of one kind of cached result."""
    return root() / kind


def digest(*parts) -> str:
    """SHA-256 (hex) of *parts*: arrays (dtype, shape and bytes), tuples and lists (recursively, named
    tuples included), dicts (sorted keys), strings, bytes, numbers, booleans and None, each tagged with
    its type so that no two different structures give the same stream."""
    import numpy as np  # here, so that the module stays light to import (the CLI's help reads the cache's policy)

    h = hashlib.sha256()
    _feed(h, parts, np)
    return h.hexdigest()


def _feed(h, obj, np) -> None:
    if obj is None:
        h.update(b"N;")
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(f"A{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    elif isinstance(obj, (tuple, list)):
        h.update(f"T{len(obj)};".encode())
        for item in obj:
            _feed(h, item, np)
    elif isinstance(obj, dict):
        h.update(f"D{len(obj)};".encode())
        for key in sorted(obj):
            _feed(h, str(key), np)
            _feed(h, obj[key], np)
    elif isinstance(obj, bytes):
        h.update(f"B{len(obj)};".encode() + obj)
    elif isinstance(obj, str):
        data = obj.encode()
        h.update(f"S{len(data)};".encode() + data)
    elif isinstance(obj, (bool, np.bool_)):
        h.update(b"b1;" if obj else b"b0;")
    elif isinstance(obj, (int, np.integer)):
        h.update(f"i{int(obj)};".encode())
    elif isinstance(obj, (float, np.floating)):
        h.update(f"f{float(obj).hex()};".encode())
    else:
        raise TypeError(f"cannot digest a {type(obj).__name__}")
