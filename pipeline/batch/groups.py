"""Groups of tensile files for a batch: which files, how they are grouped, the groups' folder names.

The files are read once here to form the groups (by specimen id: metadata ``specimen``,
else the file stem; or by folder); a file that cannot be read becomes a failed job of
its own (:func:`failed_jobs`) and the other groups still run. A folder given means its
files (:func:`esmm.pipeline.tensile.files.expand_folders`). Shared by the batches of
fits (:mod:`.calibrate`) and of discoveries (:mod:`.discover`).
"""

from __future__ import annotations

import os
import re
import unicodedata
from collections.abc import Sequence
from pathlib import Path

from ..errors import ConfigError, EsmmError, InputError
from ..progress import Reporter
from ..tensile import NotATestError
from ..tensile.files import read_test, record_files
from ..tensile.metadata import MissingMetadataError
from .cache import CACHE_DIR
from .jobs import Job, sha256_file
from .runner import SUMMARY_NAME

GROUP_BY = ("specimen", "folder")
#: Name of the per-group table in the batch folder.
PARAMS_TABLE = "summary.csv"
#: Names in the batch folder that no group folder may take (compared case-insensitively).
RESERVED_NAMES = (PARAMS_TABLE, SUMMARY_NAME, CACHE_DIR, "report.html", "effects.csv", "effect-parameters.csv")

#: Longest group folder name, in UTF-8 bytes (file systems allow 255).
_MAX_NAME_BYTES = 120

def safe_name(text: str) -> str:
    """A file-system-safe folder name for a group (letters of any script, digits, ``-_.``).

    At most 120 UTF-8 bytes; ``"group"`` when nothing is left.
    """
    s = re.sub(r"[^\w.\-]+", "_", unicodedata.normalize("NFC", str(text))).strip("._")
    while len(s.encode("utf-8")) > _MAX_NAME_BYTES:
        s = s[:-1]
    return s.rstrip("._") or "group"


def group_names(keys: Sequence[str], by: str) -> dict[str, str]:
    """Group key -> unique, file-system-safe folder name.

    Specimen ids are sanitised (:func:`safe_name`); folders are named by their
    last component, or, where two share it (``lab1/left``, ``lab2/left``), by
    as many trailing components as it takes to tell them apart
    (``lab1_left``, ``lab2_left``). Any remaining clash gets ``-2``, ``-3``...
    """
    out: dict[str, str] = {}
    if by == "folder":
        by_base: dict[str, list[str]] = {}
        for k in keys:
            by_base.setdefault(safe_name(Path(k).name), []).append(k)
        for base, ks in by_base.items():
            names = [base]
            depth, deepest = 1, max(len(Path(k).parts) for k in ks)
            while len(ks) > 1 and depth < deepest:
                depth += 1
                names = [safe_name("_".join(Path(k).parts[-depth:])) for k in ks]
                if len(set(names)) == len(names):
                    break
            out.update(zip(ks, names if len(names) == len(ks) else [base] * len(ks)))
    else:
        out = {k: safe_name(k) for k in keys}
    # Any clash left (also with the batch's own files, and names that differ only in case, which
    # are one folder on macOS and Windows): suffixes, in input order.
    taken: set[str] = {n.casefold() for n in RESERVED_NAMES}
    for k in keys:
        name, n = out[k], 2
        while name.casefold() in taken:
            name, n = f"{out[k]}-{n}", n + 1
        out[k] = name
        taken.add(name.casefold())
    return out


def sidecars(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """The TOML sidecars (``x.toml`` beside ``x.csv``) that exist for *paths*."""
    out = []
    for p in paths:
        side = Path(p).with_suffix(".toml")
        if side != Path(p) and side.is_file():
            out.append(side)
    return out


def reader_overrides(read_kwargs: dict) -> dict:
    """The reader's metadata overrides of *read_kwargs* (its ``encoding`` argument among them)."""
    over = dict(read_kwargs.get("overrides") or {})
    if read_kwargs.get("encoding") is not None:
        over["encoding"] = read_kwargs["encoding"]
    return over


def sort_files(files, by: str, read_kwargs: dict, rep: Reporter):
    """Read every record once: (groups: key -> paths, failed: (as given, path, error), skipped: messages,
    the number of distinct files). What a wildcard picks up beside the records is skipped with a
    warning (:func:`esmm.pipeline.tensile.files.record_files`, and measurement tables)."""
    groups: dict[str, list[str]] = {}
    digests: dict[str, dict[str, str]] = {}  # group -> sha256 -> first file with those bytes
    failed: list[tuple[str, str, EsmmError]] = []
    records, skipped, n_files = record_files(files)
    for msg in skipped:
        rep.warn(msg)
    for f, p in records:
        try:
            t = read_test(p, overrides=reader_overrides(read_kwargs))
        except ConfigError:            # the reader's options: every file would fail alike
            raise
        except NotATestError as exc:   # a measurements table picked up by a wildcard (as without --by)
            skipped.append(f"{exc} - skipped")
            rep.warn(skipped[-1])
            continue
        except EsmmError as exc:
            failed.append((f, p, exc))
            rep.warn(f"skipped: {exc}")
            continue
        key = t.specimen if by == "specimen" else str(Path(p).parent)
        try:  # the same bytes with the same sidecar (or none): one test given twice
            digest = ":".join(sha256_file(x) for x in [p, *sidecars([p])])
        except EsmmError as exc:  # gone or unreadable since it was read
            failed.append((f, p, exc))
            continue
        first = digests.setdefault(key, {}).setdefault(digest, p)
        if first != p:  # kept (the user may mean it) but said: it doubles that test's weight in the fit
            rep.warn(f"{f}: the same bytes as {first} in one group (a copy?); both are fitted, which doubles "
                     f"that test's weight - remove one if it is a copy")
        groups.setdefault(key, []).append(p)
    return groups, failed, skipped, n_files


def failed_jobs(failed, taken: set[str], kind: str) -> list[Job]:
    """A failed job per unreadable file, named by the path given; never by a group's name (*taken*,
    case-folded), since it writes nothing."""
    jobs = []
    for shown, p, exc in failed:
        name, n = shown, 2
        while name.casefold() in taken:
            name, n = (p if n == 2 else f"{p}-{n - 1}"), n + 1
        taken.add(name.casefold())
        jobs.append(Job.failed(name, kind, str(exc), exit_code=exc.exit_code,
                               summary={"unreadable": True, "files": [p]}))
    return jobs




def refuse_if_nothing(groups, failed, skipped: list[str], n_files: int) -> None:
    """Raise before anything is created when no file can make a job: every file failed or was skipped.

    Raises
    ------
    MissingMetadataError
        Every failed file lacks metadata (all of them listed, with every key).
    InputError
        Otherwise: the first file's reason, and how many more failed.
    """
    if groups:
        return
    if failed:
        if all(isinstance(e, MissingMetadataError) for _, _, e in failed):
            raise MissingMetadataError([m for _, _, e in failed for m in e.missing])
        first = failed[0][2]
        more = f" (and {len(failed) - 1} more file(s) that cannot be read)" if len(failed) > 1 else ""
        raise type(first)(f"{first}{more}")
    why = f" ({skipped[0]})" if skipped else ""
    raise InputError(f"none of the {n_files} file(s) is a test record{why}; give the tests' CSV files")
