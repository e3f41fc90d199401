"""Packaging: every subpackage is listed, the top-level names cli and pipeline are not importable,
the console script answers --version and --help, and ``import esmm`` gives the public API with
``esmm.cli``, ``esmm.pipeline`` and ``esmm.configs`` beside it, in an editable and in a regular install."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MAPPING = {"api": "esmm", "cli": "esmm.cli", "pipeline": "esmm.pipeline", "configs": "esmm.configs"}


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


#: What an install must give, run in a fresh interpreter: where each package comes from, and the API.
PROBE = """
import json, sys
import esmm, esmm.cli.main, esmm.configs, esmm.pipeline
from esmm.pipeline import config
names = {n: callable(getattr(esmm, n)) for n in ("calibrate", "prepare", "load_asset", "simulate")}
print(json.dumps({"esmm": esmm.__file__, "cli": esmm.cli.main.__file__, "pipeline": esmm.pipeline.__file__,
                  "configs": esmm.configs.__file__, "names": names, "version": esmm.__version__,
                  "materials": config.bundled_names("materials"), "api": esmm.load_asset.__module__}))
"""


def _probe(cwd: Path, env: dict | None = None) -> dict:
    import json

    p = subprocess.run([sys.executable, "-c", PROBE], cwd=cwd, env=env, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout)


def _check(found: dict, root: Path) -> None:
    from esmm.pipeline import __version__

    assert Path(found["esmm"]).parent == root / ("api" if root == REPO else "esmm")
    for name, folder in (("cli", "cli"), ("pipeline", "pipeline"), ("configs", "configs")):
        where = Path(found[name] if name != "cli" else Path(found[name]).parent)
        assert where.is_relative_to(root / folder if root == REPO else root / "esmm" / folder), (name, where)
    assert found["names"] == {"calibrate": True, "prepare": True, "load_asset": True, "simulate": True}
    assert found["api"] == "esmm.pipeline.api" and found["version"] == __version__
    assert "porcine_liver_paper" in found["materials"]


def test_the_editable_install_gives_the_api_and_the_packages(tmp_path):
    """``make install`` (editable): ``esmm`` is api/__init__.py, its packages the repository's folders."""
    _check(_probe(tmp_path), REPO)


@pytest.mark.slow
def test_a_regular_install_gives_the_api_and_the_packages(tmp_path):
    """``pip install .`` (here into a folder, without the dependencies, which this venv has): the same
    names from the installed copy, every subpackage in it."""
    target = tmp_path / "site"
    p = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
                        str(REPO)], capture_output=True, text=True, cwd=tmp_path)
    if p.returncode and re.search(r"No matching distribution|Could not find a version|Failed to establish|"
                                  r"Temporary failure in name resolution|Network is unreachable", p.stderr):
        pytest.skip(f"pip cannot fetch the build requirements (setuptools>=69) here: {p.stderr.strip()[-200:]}")
    assert p.returncode == 0, p.stderr[-2000:]
    installed = {".".join(d.relative_to(target).parts) for d in target.joinpath("esmm").rglob("*")
                 if (d / "__init__.py").is_file()} | {"esmm"}
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert installed == set(cfg["tool"]["setuptools"]["packages"])
    assert not (target / "esmm" / "api").exists() and (target / "esmm" / "__init__.py").is_file()
    _check(_probe(tmp_path, env={**os.environ, "PYTHONPATH": str(target)}), target)
