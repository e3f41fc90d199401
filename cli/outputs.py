"""Output paths checked before any work: a run must not fail at its end on a path it could not write."""

from __future__ import annotations

from esmm.pipeline.atomicio import unwritable_file, unwritable_folder
from esmm.pipeline.errors import ConfigError


def check_out_dir(path, flag: str) -> None:
    """Refuse, before any work, an output folder that cannot be one (a file, under a file, not writable)."""
    problem = unwritable_folder(path)
    if problem:
        raise ConfigError(f"{flag}: {problem}")


def check_out_file(path, flag: str, example: str) -> None:
    """Refuse, before any work, an output file name that is a folder or lies in one that cannot be written."""
    problem = unwritable_file(path, example)
    if problem:
        raise ConfigError(f"{flag}: {problem}")
