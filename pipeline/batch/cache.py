"""The result cache of a batch folder: manifests, the folder lock, temp-file sweeping.

Layout (inside the batch's output folder ``<out>``)::

    <out>/.esmm-cache/<key>.json   one manifest per completed job
    <out>/.esmm-cache/lock         held (flock) by the batch writing to <out>
    <out>/.esmm-cache/workers/     the local workers' stdout/stderr while they run

A job's outputs live where the user expects them (``<out>/<group>/params.toml``,
``<out>/liver.h5``); each is written atomically by the job. The manifest is
written atomically *after* every output is complete and records the SHA-256
and size of each output: it is the only "done" marker. A job killed at any
moment therefore leaves no manifest (it is redone) and at most a
``.<name>.tmp-*`` file, which the next batch sweeps. A job counts as cached
only if its manifest exists for the same key *and* every output still has the
recorded size and digest (an edited or deleted output is remade).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..atomicio import write_text
from ..errors import ConfigError
from .jobs import code_version, sha256_file

CACHE_DIR = ".esmm-cache"
MANIFEST_SCHEMA = "esmm.batch-manifest/1"


def cache_dir(out_dir: str | os.PathLike) -> Path:
    return Path(out_dir) / CACHE_DIR


def manifest_path(out_dir: str | os.PathLike, key: str) -> Path:
    return cache_dir(out_dir) / f"{key}.json"


def relative_output(path: str | os.PathLike, out_dir: str | os.PathLike) -> str:
    """*path* relative to *out_dir* when inside it (POSIX separators), else absolute."""
    p = Path(path).resolve()
    base = Path(out_dir).resolve()
    try:
        return p.relative_to(base).as_posix()
    except ValueError:
        return str(p)


def _absolute(rel: str, out_dir: str | os.PathLike) -> Path:
    p = Path(rel)
    return p if p.is_absolute() else Path(out_dir) / p


def write_manifest(out_dir: str | os.PathLike, key: str, *, name: str, kind: str,
                   inputs: Sequence[tuple[str, str]], config: Any, outputs: Sequence[str | os.PathLike],
                   summary: dict[str, Any], seconds: float) -> list[str]:
    """Record a completed job (atomically; call only once every output is complete).

    Returns
    -------
    list of str
        The outputs relative to *out_dir*.

    Raises
    ------
    FileNotFoundError
        An output the job reported does not exist (a bug in the job function).
    """
    rows, rel = [], []
    for p in outputs:
        r = relative_output(p, out_dir)
        ap = _absolute(r, out_dir)
        if not ap.is_file():
            raise FileNotFoundError(f"the job reported output {ap} but it does not exist")
        rows.append({"path": r, "size": ap.stat().st_size, "sha256": sha256_file(ap)})
        rel.append(r)
    doc = {
        "schema": MANIFEST_SCHEMA, "key": key, "name": name, "kind": kind,
        "code_version": code_version(), "inputs": [list(x) for x in inputs], "config": config,
        "outputs": rows, "summary": summary, "seconds": seconds,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    cache_dir(out_dir).mkdir(parents=True, exist_ok=True)
    write_text(manifest_path(out_dir, key), json.dumps(doc, indent=1, allow_nan=True) + "\n")
    return rel


def lookup(out_dir: str | os.PathLike, key: str) -> tuple[dict[str, Any] | None, str]:
    """The manifest of *key* if its result is complete and intact, else ``(None, why)``.

    ``why`` is ``""`` when there simply is no manifest, otherwise one line
    saying why the recorded result cannot be reused (for the log).
    """
    mp = manifest_path(out_dir, key)
    try:
        text = mp.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None, ""
    except OSError as exc:
        return None, f"manifest {mp.name} unreadable ({exc.strerror or exc})"
    try:
        doc = json.loads(text)
    except ValueError:
        return None, f"manifest {mp.name} is not valid JSON"
    if not isinstance(doc, dict) or doc.get("schema") != MANIFEST_SCHEMA or doc.get("key") != key:
        return None, f"manifest {mp.name} is of another schema or key"
    outputs = doc.get("outputs")
    if not isinstance(outputs, list):
        return None, f"manifest {mp.name} has no output list"
    for row in outputs:
        try:
            ap = _absolute(row["path"], out_dir)
            if not ap.is_file():
                return None, f"output {row['path']} is missing"
            if ap.stat().st_size != row["size"]:
                return None, f"output {row['path']} changed size"
            if sha256_file(ap) != row["sha256"]:
                return None, f"output {row['path']} changed content"
        except (KeyError, TypeError):
            return None, f"manifest {mp.name} has a malformed output row"
        except Exception as exc:  # noqa: BLE001 - unreadable output: recompute it
            return None, f"output {row.get('path')} unreadable ({exc})"
    return doc, ""


def is_temp_name(name: str) -> bool:
    """True for the temporary names of :func:`esmm.pipeline.atomicio.atomic_path` (``.x.h5.tmp-abc.h5``)."""
    return name.startswith(".") and ".tmp-" in name


def sweep_temp(folder: str | os.PathLike) -> list[Path]:
    """Delete the atomic writers' leftover temporary files under *folder* (recursively).

    Call it only while no other writer uses *folder* (the batch holds
    :class:`FolderLock`). Returns the files removed.
    """
    removed: list[Path] = []
    root = Path(folder)
    if not root.is_dir():
        return removed
    for dirpath, _dirnames, filenames in os.walk(root):
        for fn in filenames:
            if is_temp_name(fn):
                p = Path(dirpath) / fn
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed


def workers_dir(out_dir: str | os.PathLike) -> Path:
    """Where local workers' stdout/stderr go while they run (``.esmm-cache/workers``)."""
    return cache_dir(out_dir) / "workers"


def sweep_workers(out_dir: str | os.PathLike) -> list[Path]:
    """Remove the output files of workers of a batch that was killed (call under the lock)."""
    removed = []
    d = workers_dir(out_dir)
    if d.is_dir():
        for p in d.iterdir():
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


class FolderLock:
    """An exclusive lock on a batch folder (``<out>/.esmm-cache/lock``, flock).

    The kernel drops the lock when the holder dies, even on SIGKILL, so a
    stale lock never blocks the next run.
    """

    def __init__(self, out_dir: str | os.PathLike):
        self.path = cache_dir(out_dir) / "lock"
        self._fh = None
        #: True when the file system cannot lock (some NFS setups): the batch runs unlocked.
        self.unsupported = False

    def acquire(self) -> None:
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.path, "a+")  # noqa: SIM115 - held until release()
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                fh.close()
                self.unsupported = True
                return
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            fh.close()
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise ConfigError(f"{self.path.parent.parent}: another esmm batch ({holder}) is writing to "
                                  f"this folder; wait for it to finish or choose another output folder") from None
            raise ConfigError(f"{self.path}: cannot lock the batch folder ({exc.strerror or exc}); "
                              f"check that the folder is writable") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        self._fh = fh

    def release(self) -> None:
        if self._fh is not None:
            with contextlib.suppress(OSError):
                self._fh.seek(0)
                self._fh.truncate()
            self._fh.close()  # closing drops the flock
            self._fh = None

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


@contextlib.contextmanager
def locked(out_dir: str | os.PathLike) -> Iterator[FolderLock]:
    with FolderLock(out_dir) as lock:
        yield lock
