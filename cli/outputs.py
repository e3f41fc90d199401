"""Output paths checked before any work: a run must not fail at its end on a path it could not write."""

from __future__ import annotations

from pathlib import Path

from esmm.pipeline.atomicio import unwritable_folder
from esmm.pipeline.errors import ConfigError


def check_out_dir(path, flag: str) -> None:
    """Refuse, before any work, an output folder that cannot be one (a file, under a file, not writable)."""
    problem = unwritable_folder(path)
    if problem:
        raise ConfigError(f"{flag}: {problem}")


def check_out_file(path, flag: str, example: str) -> None:
    """Refuse, before any work, an output file name that is a folder or lies in one that cannot be written."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{flag}: {p} is a folder; give a file name in it, e.g. {p / example}")
    if p.parent.exists() and not p.parent.is_dir():
        raise ConfigError(f"{flag}: {p} cannot be written, {p.parent} is a file; give a path in a folder")
    check_out_dir(p.parent, flag)
