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


def check_run_folder(path, flag: str, *, kind: str, overwrite: bool):
    """Refuse, before any work, an output folder that holds an earlier run, unless *overwrite*.

    A batch into the folder of an earlier batch of the same kind reuses it (its cache:
    what is done is not redone), so it passes. Returns the earlier run (to clear once the
    inputs are read, with *overwrite*), or None.
    """
    from esmm.pipeline.batch.runfolder import DESCRIPTIONS, previous_run

    prev = previous_run(path)
    if prev is None or (kind.endswith("-batch") and prev.kind == kind and not overwrite):
        return None
    if not overwrite:
        raise ConfigError(
            f"{flag}: {path} holds the outputs of {prev.describe()}; give another folder, or add --overwrite to "
            f"remove that run's files and write this {DESCRIPTIONS.get(kind, kind)} there")
    return prev
