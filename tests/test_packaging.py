"""Packaging: every subpackage is listed, the top-level names cli and pipeline are not importable,
and the console script answers --version and --help."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MAPPING = {"cli": "esmm.cli", "pipeline": "esmm.pipeline", "configs": "esmm.configs"}


def _tree_packages() -> set[str]:
    found = set()
    for top, name in MAPPING.items():
        for init in (REPO / top).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / top)
            parts = [] if str(rel) == "." else list(rel.parts)
            if "__pycache__" in parts:
                continue
            found.add(".".join([name, *parts]))
    return found


def test_every_subpackage_is_listed_in_pyproject():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    listed = set(cfg["tool"]["setuptools"]["packages"])
    assert _tree_packages() == listed


def test_no_tests_init_and_importlib_mode():
    assert not (REPO / "tests" / "__init__.py").exists()
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert "--import-mode=importlib" in cfg["tool"]["pytest"]["ini_options"]["addopts"]


@pytest.mark.parametrize("name", ["cli", "pipeline"])
def test_bare_package_names_are_not_importable(name, tmp_path):
    # from a neutral folder, as a user would run it
    code = f"import importlib.util,sys; sys.exit(0 if importlib.util.find_spec({name!r}) is None else 1)"
    assert subprocess.run([sys.executable, "-c", code], cwd=tmp_path).returncode == 0
    assert importlib.util.find_spec(f"esmm.{name}") is not None


def test_version_and_help(run_cli):
    from esmm.pipeline import __version__

    code, out, _ = run_cli("--version")
    assert code == 0 and __version__ in out
    code, out, _ = run_cli("--help")
    assert code == 0
    for cmd in ("calibrate", "prepare", "simulate", "info"):
        assert cmd in out


def test_bundled_configs_are_found():
    from esmm.pipeline import config

    assert "porcine_liver_paper" in config.bundled_names("materials")
