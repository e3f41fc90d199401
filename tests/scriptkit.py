"""The repository's scripts (``scripts/*.py``, not a package) loaded as modules for their tests.

Importable because pytest's ``pythonpath`` includes ``tests/``.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def load_script(name: str):
    """``scripts/<name>.py`` as a module (run from the top, as ``python scripts/<name>.py`` would import it)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
