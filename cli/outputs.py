"""Output paths checked before any work: a run must not fail at its end on a path it could not write."""

from __future__ import annotations

import os
from pathlib import Path

from esmm.pipeline.errors import ConfigError


def check_out_dir(path, flag: str) -> None:
    """Refuse, before any work, an output folder that cannot be one (a file, under a file, not writable)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{flag}: {p} is a file, not a folder; give a folder (it is created if missing)")
    anc = p.absolute()
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise ConfigError(f"{flag}: {p} cannot be created, {anc} is a file; give a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag}: cannot write in {anc}; give a writable folder")


def check_out_file(path, flag: str, example: str) -> None:
    """Refuse, before any work, an output file name that is a folder or lies in one that cannot be written."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{flag}: {p} is a folder; give a file name in it, e.g. {p / example}")
    if p.parent.exists() and not p.parent.is_dir():
        raise ConfigError(f"{flag}: {p} cannot be written, {p.parent} is a file; give a path in a folder")
    check_out_dir(p.parent, flag)
