"""Configuration files: TOML, bundled presets by name, and validation.

A config argument is either a path to a TOML file or the name of a bundled
preset (``configs/<section>/<name>.toml``, installed as ``esmm.configs``).
"""

from __future__ import annotations

import os
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from .errors import ConfigError


def bundled_names(section: str) -> list[str]:
    """Names of the bundled presets of a section (``materials``, ``prepare``, ``scenes``)."""
    root = resources.files("esmm.configs").joinpath(section)
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def bundled_path(section: str, name: str):
    """A traversable for a bundled preset, or raise ConfigError listing the choices."""
    root = resources.files("esmm.configs").joinpath(section)
    candidate = root.joinpath(f"{name}.toml")
    if not candidate.is_file():
        raise ConfigError(
            f"no {section} preset named {name!r}; choose one of {', '.join(bundled_names(section))} "
            f"or give a path to a .toml file"
        )
    return candidate


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML file into a dict, with one-line errors."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a folder, expected a .toml file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML ({exc}); fix the syntax at that line") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not a UTF-8 text file; TOML files must be UTF-8") from None


def load(section: str, name_or_path: str | os.PathLike) -> tuple[dict[str, Any], str]:
    """Load a config by bundled name or path; return ``(data, source description)``."""
    s = str(name_or_path)
    if s.endswith(".toml") or os.sep in s or Path(s).exists():
        return load_toml(s), str(Path(s).resolve())
    trav = bundled_path(section, s)
    with trav.open("rb") as fh:
        try:
            return tomllib.load(fh), f"bundled:{section}/{s}"
        except tomllib.TOMLDecodeError as exc:  # pragma: no cover - bundled files are tested
            raise ConfigError(f"bundled {section}/{s}.toml is invalid: {exc}") from None
