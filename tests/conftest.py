"""Shared fixtures. Tests import only esmm.* (pytest runs with --import-mode=importlib)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BUNDLED = REPO / "data"
SHARED = REPO.parent / "shared" / "data"


def pytest_configure(config):
    # Calibrated compensations are cached (pipeline/compensation/policy.py); tests use a fresh cache
    # of their own, never the user's ~/.cache/esmm.
    os.environ["ESMM_CACHE_DIR"] = tempfile.mkdtemp(prefix="esmm-test-cache-")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def bundled_data() -> Path:
    """The real data shipped in the repository (data/, see data/README.md)."""
    return BUNDLED


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repository; tests using it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data is not beside this checkout")
    return SHARED


@pytest.fixture(scope="session")
def liver():
    """The bundled porcine-liver material of the ESMM paper (configs/materials)."""
    from esmm.pipeline.materials.material import load_material

    return load_material("porcine_liver_paper")


@pytest.fixture(scope="session")
def tables(liver):
    """The stiffness tables of :func:`liver` on the default grid (no compensation)."""
    from esmm.pipeline.network.tables import build_tables

    return build_tables(liver)


@pytest.fixture()
def run_cli(capsys):
    """Run ``esmm`` in-process: returns (exit code, stdout, stderr)."""
    from esmm.cli.main import main

    def _run(*argv: str):
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err

    return _run
