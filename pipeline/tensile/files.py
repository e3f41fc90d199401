"""Which of the files a user gave are tensile records: the one rule for a wildcard's catch.

``esmm calibrate DIR/*`` (one fit, or a batch with ``--by``) hands over whatever the
shell matched, and ``esmm calibrate DIR`` means the files in DIR (:func:`expand_folders`).
Beside the records that is often a sidecar (``x.toml``, read with ``x.csv``), another
TOML file, or an editor's backup or lock file. They are sorted out here, before any file
is read; a measurement table that names no test quantity is found by the reader
(:class:`~.reader.NotATestError`) and skipped by the caller the same way.

A file that lacks metadata (its encoding, gauge length, cross-section) is read on with
a stand-in for each missing key until nothing more is missing, so that one message
lists every key every file needs (:func:`read_test`,
:class:`~.metadata.MissingMetadataError`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError, EsmmError, InputError
from ..progress import ensure
from .data import TensileTest
from .metadata import NEEDED, Missing, MissingMetadataError, sidecar_path
from .reader import NotATestError, _suggest_encoding, read

#: Files a wildcard picks up beside the data that are copies or locks of editors and tools:
#: ``x.csv~``, ``#x.csv#``, ``.#x.csv``, ``.~lock.x.csv#`` (LibreOffice), ``.x.csv.swp`` (vim),
#: ``x.csv.bak``, ``x.csv.orig``, ``x.csv.old``.
_BACKUP = re.compile(r"(^\.#|^\.~lock\.|[~#]$|\.(bak|orig|old|swp|swo|swn|swx)$)", re.IGNORECASE)


def backup_file(path: str | os.PathLike) -> bool:
    """Whether *path* is named like an editor backup, swap or lock file (not test data)."""
    return _BACKUP.search(Path(path).name) is not None


def expand_folders(paths: Sequence[str | os.PathLike]) -> list[str]:
    """*paths* with each folder replaced by the files directly in it (sorted; hidden files left out).

    Raises
    ------
    InputError
        A folder holds no file (its sub-folders are named: give them, or their files).
    """
    out: list[str] = []
    for p in paths:
        if not Path(p).is_dir():
            out.append(str(p))
            continue
        entries = sorted(Path(p).iterdir())
        files = [str(e) for e in entries if e.is_file() and not e.name.startswith(".")]
        if not files:
            subs = [e.name for e in entries if e.is_dir() and not e.name.startswith(".")]
            hint = (f" (it has the folder{'s' if len(subs) > 1 else ''} {', '.join(subs[:5])}"
                    f"{' ...' if len(subs) > 5 else ''}: give those)") if subs else ""
            raise InputError(f"{p}: a folder with no test files{hint}; give the tests' CSV files or their folder")
        out += files
    return out


def record_files(paths: Sequence[str | os.PathLike]) -> tuple[list[tuple[str, str]], list[str], int]:
    """Sort the files given (a folder: its files) into records to read and the rest.

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
    paths = expand_folders(paths)
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


def read_test(path: str | os.PathLike, *, overrides: dict[str, Any] | None = None, reporter=None) -> TensileTest:
    """Read one record; metadata it misses are all listed in one :class:`MissingMetadataError`.

    On a missing key (encoding, gauge length, cross-section) the file is read again with a
    stand-in for it (the encoding the bytes suggest, a unit gauge length or area) to find
    what else is missing; the stand-ins never reach a result: the error is raised.
    """
    over = dict(overrides or {})
    missing: list[Missing] = []
    while True:
        try:
            test = read(path, overrides=over, reporter=reporter if not missing else None)
        except EsmmError as exc:
            found = _missing(path, exc)
            if found is None or found.key in over or not missing and found.key not in NEEDED:
                if missing:
                    break
                raise
            missing.append(found)
            over[found.key] = _STAND_IN.get(found.key) or _encoding_guess(path) or "latin-1"
            continue
        if not missing:
            return test
        break
    raise MissingMetadataError([(str(path), sidecar_path(Path(path)).name, missing)])


#: stand-ins for missing geometry while looking for what else is missing (never used in a result)
_STAND_IN = {"gauge_length": "1 m", "area": "1 m2"}


def _missing(path, exc: EsmmError) -> Missing | None:
    """The key a reader's error says is missing, or None (another problem)."""
    key = getattr(exc, "parameter", None)
    if not isinstance(exc, InputError) or key not in NEEDED:
        return None
    if key == "encoding":
        guess = _encoding_guess(path)
        return Missing("encoding", "not UTF-8 text" + (f"; its bytes read as {guess}" if guess else ""),
                       f'"{guess}"' if guess else '"..."')
    if "missing geometry" not in str(exc):
        return None
    return Missing(key, NEEDED[key][1], NEEDED[key][0])


def _encoding_guess(path) -> str | None:
    """The encoding the reader's hint suggests for the file's bytes (gbk, shift_jis, cp1252), or None."""
    try:
        hint = _suggest_encoding(Path(path).read_bytes())
    except OSError:
        return None
    m = re.search(r'encoding = "([\w\-]+)"', hint)
    if m:
        return m.group(1)
    return "shift_jis" if "Shift-JIS" in hint else "cp1252" if "cp1252" in hint else None


def read_tests(paths: Sequence[str | os.PathLike], *, overrides: dict[str, Any] | None = None,
               reporter=None) -> list[TensileTest]:
    """Read the tensile records among *paths* (a folder: its files), in order.

    Of several files, what a wildcard picks up beside the records (sidecars of
    files given too, other TOML files, editor backups, measurement tables) is
    skipped with a warning (:func:`record_files`, :class:`~.reader.NotATestError`).
    A single such file, or any other problem, is an error. Metadata missing in any
    file are listed all at once, for every file (:class:`MissingMetadataError`).

    Raises
    ------
    ConfigError
        None of the files is a test record.
    NotATestError
        The single file given is not a test record.
    MissingMetadataError
        Files lack metadata they need (every key of every file).
    """
    rep = ensure(reporter)
    folder = any(Path(p).is_dir() for p in paths)
    if len(paths) > 1 or folder:
        records, skipped, _ = record_files(paths)
        for msg in skipped:
            rep.warn(msg)
        paths = [given for given, _ in records]
    tests, missing = [], []
    for p in paths:
        try:
            tests.append(read_test(p, overrides=overrides, reporter=rep))
        except MissingMetadataError as exc:
            missing += exc.missing
        except NotATestError as exc:
            if len(paths) == 1:
                raise
            rep.warn(f"{exc} - skipped")
    if missing:
        raise MissingMetadataError(missing)
    if not tests:
        raise ConfigError("none of the files is a test record; give the tests' CSV files")
    return tests
