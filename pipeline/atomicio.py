"""Write outputs so that nothing is ever left half-written.

Every output goes to a temporary file in the target's folder and is renamed
over the target only once it is complete (``os.replace`` is atomic on POSIX).
An exception, Ctrl-C or a kill leaves at most a ``.<name>.tmp-*`` file, which
:func:`atomic_path` removes on the way out where it can.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to *target*; rename it to *target* on success.

    Parameters
    ----------
    target
        The final file name.
    suffix
        Suffix of the temporary file (default: the target's), for writers that
        look at the extension.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.name}.tmp-", suffix=suffix if suffix is not None else target.suffix,
        dir=target.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            # mkstemp creates 0600; give the output the permissions of a normal new file
            os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def unwritable_folder(path: str | os.PathLike) -> str | None:
    """Why the folder *path* could not be created or written, as the end of a message (None: it can):
    it is a file, lies under a file, or its nearest existing folder is not writable."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        return f"{p} is a file, not a folder; give a folder (it is created if missing)"
    anc = p.absolute()
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        return f"{p} cannot be created, {anc} is a file; give a folder"
    if not os.access(anc, os.W_OK | os.X_OK):
        return f"cannot write in {anc}; give a writable folder"
    return None


def unwritable_file(path: str | os.PathLike, example: str) -> str | None:
    """Why the file *path* could not be written, as the end of a message (None: it can): it is a folder
    (*example*: a file name to suggest in it), or its folder could not be made or written."""
    p = Path(path)
    if p.is_dir():
        return f"{p} is a folder; give a file name in it, e.g. {p / example}"
    if p.parent.exists() and not p.parent.is_dir():
        return f"{p} cannot be written, {p.parent} is a file; give a path in a folder"
    return unwritable_folder(p.parent)


@contextlib.contextmanager
def output_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Create the folder *path* (and its missing parents) for a run's outputs; if the run fails, remove
    the folders this call created that are still empty, so that a refused input leaves nothing behind."""
    path = Path(path)
    created = []
    p = path.absolute()
    while not p.exists():
        created.append(p)
        p = p.parent
    path.mkdir(parents=True, exist_ok=True)
    try:
        yield path
    except BaseException:
        for d in created:                  # deepest first
            with contextlib.suppress(OSError):
                d.rmdir()                  # only if empty
        raise


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text(target: str | os.PathLike, text: str, *, encoding: str = "utf-8") -> Path:
    """Write *text* to *target* atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(target)


def write_bytes(target: str | os.PathLike, data: bytes) -> Path:
    """Write *data* to *target* atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


def jsonable(obj: Any, *, strict: bool = True) -> Any:
    """*obj* as plain JSON types: numpy scalars and arrays become numbers and lists, paths text.

    With *strict*, NaN and infinities become ``None`` (JSON has no spelling for them);
    otherwise they stay floats (for values kept in Python, e.g. a batch job's summary).
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v, strict=strict) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, strict=strict) for v in obj]
    if hasattr(obj, "tolist") and callable(obj.tolist):  # numpy arrays and scalars
        return jsonable(obj.tolist(), strict=strict)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if strict and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def json_text(document: Any) -> str:
    """*document* as indented strict JSON text (see :func:`jsonable`), ending in a newline."""
    return json.dumps(jsonable(document), indent=2, allow_nan=False) + "\n"


def write_json(target: str | os.PathLike, document: Any) -> Path:
    """Write *document* as strict JSON to *target* atomically and return the target path."""
    return write_text(target, json_text(document))
