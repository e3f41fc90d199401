"""Which of the files a user gave are tensile records: the one rule for a wildcard's catch.

``esmm calibrate DIR/*`` (one fit, or a batch with ``--by``) hands over whatever the
shell matched. Beside the records that is often a sidecar (``x.toml``, read with
``x.csv``), another TOML file, or an editor's backup or lock file. They are sorted out
here, before any file is read; a measurement table that names no test quantity is found
by the reader (:class:`~.reader.NotATestError`) and skipped by the caller the same way.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..progress import ensure
from .data import TensileTest
from .reader import NotATestError, read

#: Files a wildcard picks up beside the data that are copies or locks of editors and tools:
#: ``x.csv~``, ``#x.csv#``, ``.#x.csv``, ``.~lock.x.csv#`` (LibreOffice), ``.x.csv.swp`` (vim),
#: ``x.csv.bak``, ``x.csv.orig``, ``x.csv.old``.
_BACKUP = re.compile(r"(^\.#|^\.~lock\.|[~#]$|\.(bak|orig|old|swp|swo|swn|swx)$)", re.IGNORECASE)


def backup_file(path: str | os.PathLike) -> bool:
    """Whether *path* is named like an editor backup, swap or lock file (not test data)."""
    return _BACKUP.search(Path(path).name) is not None


def record_files(paths: Sequence[str | os.PathLike]) -> tuple[list[tuple[str, str]], list[str], int]:
    """Sort the files given into records to read and the rest.

    Returns
    -------
    records : list of (as given, resolved path)
        In the order given, each file once.
    skipped : list of str
        One message per file set aside (editor backups and locks, TOML files that are not the
        sidecar of a file given too), naming it and why.
    n_files : int
        Distinct files given (sidecars of given files included: they are read with them).
    """
    resolved = [str(Path(f).resolve()) for f in paths]
    side_of_given = {str(Path(r).with_suffix(".toml")) for r in resolved if Path(r).suffix.lower() != ".toml"}
    records, skipped, seen = [], [], set()
    for f, p in zip(paths, resolved):
        if p in seen:
            continue
        seen.add(p)
        toml = Path(p).suffix.lower() == ".toml" and Path(p).is_file()
        if toml and p in side_of_given:
            continue                      # the sidecar of a file given too: read with it
        if backup_file(p):
            skipped.append(f"{f}: named like an editor backup or lock file, not test data - skipped")
        elif toml:
            skipped.append(f"{f}: a TOML file without a data file of the same stem among the files, not test "
                           f"data - skipped")
        else:
            records.append((str(f), p))
    return records, skipped, len(seen)


def read_tests(paths: Sequence[str | os.PathLike], *, overrides: dict[str, Any] | None = None,
               reporter=None) -> list[TensileTest]:
    """Read the tensile records among *paths*, in order.

    Of several files, what a wildcard picks up beside the records (sidecars of
    files given too, other TOML files, editor backups, measurement tables) is
    skipped with a warning (:func:`record_files`, :class:`~.reader.NotATestError`).
    A single such file, or any other problem, is an error.

    Raises
    ------
    ConfigError
        None of the files is a test record.
    NotATestError
        The single file given is not a test record.
    """
    rep = ensure(reporter)
    if len(paths) > 1:
        records, skipped, _ = record_files(paths)
        for msg in skipped:
            rep.warn(msg)
        paths = [given for given, _ in records]
    tests = []
    for p in paths:
        try:
            tests.append(read(p, overrides=overrides, reporter=rep))
        except NotATestError as exc:
            if len(paths) == 1:
                raise
            rep.warn(f"{exc} - skipped")
    if not tests:
        raise ConfigError("none of the files is a test record; give the tests' CSV files")
    return tests
