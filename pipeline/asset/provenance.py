"""Provenance of an asset: what went in, with which settings and software, when, where."""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import platform
import socket
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from .. import distributions


@dataclass
class Provenance:
    """Where an asset came from.

    Attributes
    ----------
    input_path : str
        The input file as given (absolute).
    input_sha256 : str
        SHA-256 of the input file's bytes (empty when there is no input file).
    config_toml : str
        The full, resolved prepare configuration as TOML text.
    command_line : list of str
        ``argv`` of the command that made the asset (empty for library calls).
    utc_time : str
        ISO 8601 UTC time of writing.
    host : str
        Host name.
    packages : dict
        Distribution name -> version (``"absent"`` when not installed).
    python : str
        Python version and implementation.
    platform : str
        ``platform.platform()``.
    extra : dict
        Other facts (timings, mesher path, ...), JSON-serialisable.
    """

    input_path: str = ""
    input_sha256: str = ""
    config_toml: str = ""
    command_line: list[str] = field(default_factory=list)
    utc_time: str = ""
    host: str = ""
    packages: dict[str, str] = field(default_factory=dict)
    python: str = ""
    platform: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def sha256_file(path: str | os.PathLike, *, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            block = fh.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def package_versions(names=None) -> dict[str, str]:
    """Installed versions of *names* (default :func:`distributions`; ``"absent"`` for those not installed)."""
    out = {}
    for name in distributions() if names is None else names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def utc_now() -> str:
    """The current UTC time, ISO 8601 to the second, with a ``Z``."""
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def collect_provenance(input_path: str | os.PathLike | None = None, *, config_toml: str = "",
                       argv: list[str] | None = None, extra: dict | None = None) -> Provenance:
    """Fill a :class:`Provenance` for the current process (hashes the input file)."""
    path = Path(input_path).resolve() if input_path else None
    return Provenance(
        input_path=str(path) if path else "",
        input_sha256=sha256_file(path) if path and path.is_file() else "",
        config_toml=config_toml,
        command_line=[str(a) for a in (argv or [])],
        utc_time=utc_now(),
        host=socket.gethostname(),
        packages=package_versions(),
        python=f"{platform.python_implementation()} {sys.version.split()[0]}",
        platform=platform.platform(),
        extra=dict(extra or {}),
    )
