"""The public Python API: ``import esmm`` gives calibrate, prepare, load_asset and simulate, keyword-only,
silent, returning result objects; the example of the README (and of docs/guide/python.md) runs."""

from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BRAIN = REPO / "data" / "tensile" / "budday2017_brain"
PAGES = (REPO / "README.md", REPO / "docs" / "guide" / "python.md")


def python_blocks() -> list[tuple[str, str]]:
    """(page, code) of every distinct ``python`` block of the README and the Python guide."""
    out: dict[str, str] = {}
    for page in PAGES:
        for code in re.findall(r"^```python\n(.*?)^```", page.read_text(encoding="utf-8"), flags=re.S | re.M):
            out.setdefault(code, page.name)        # the same example on two pages runs once
    return [(page, code) for code, page in out.items()]


def test_the_four_names_are_there_keyword_only():
    import esmm

    for name in ("calibrate", "prepare", "load_asset", "simulate"):
        fn = getattr(esmm, name)
        assert fn.__doc__ and fn.__module__ == "esmm.pipeline.api", name
        params = list(inspect.signature(fn).parameters.values())
        assert params[0].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
        assert all(p.kind in (p.KEYWORD_ONLY, p.VAR_KEYWORD) for p in params[1:]), name
    assert set(esmm.__all__) >= {"calibrate", "prepare", "load_asset", "simulate"}
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        esmm.nonsense  # noqa: B018


def test_the_command_line_does_not_load_the_api(tmp_path):
    """``import esmm.cli.main`` (every ``esmm`` command) pays nothing for the API's names."""
    code = "import sys, esmm.cli.main; sys.exit(int('esmm.pipeline.api' in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], cwd=tmp_path).returncode == 0


def test_calibrate_returns_the_fit_and_prints_nothing(tmp_path, capsys):
    import esmm

    fit = esmm.calibrate([BRAIN / "cortex_tension_compression.csv", BRAIN / "cortex_simple_shear.csv"],
                         out=tmp_path / "fit", n_starts=2)
    assert capsys.readouterr() == ("", "")
    assert fit.params_toml == tmp_path / "fit" / "params.toml" and fit.params_toml.is_file()
    assert 0 < fit.nrmse < 0.5 and 0 < fit.r2 <= 1 and fit.rmse_pa > 0
    assert fit.material.model == "esedf" and len(fit.tests) == 2
    assert fit.verdict.level in ("good", "poor", "unusable") and (tmp_path / "fit" / "report.html").is_file()
    assert fit.summary().startswith("esedf fitted to 2 file(s): RMSE ")
    assert fit.summary().endswith(f"verdict {fit.verdict.level}")
    assert esmm.calibrate(BRAIN / "cortex_simple_shear.csv", n_starts=1).outputs == {}   # no out: no files


def test_load_asset_gives_the_asset_and_its_accuracy():
    import esmm
    from esmm.pipeline.errors import AssetError

    a = esmm.load_asset(REPO / "tests" / "data" / "assets" / "box_v1.h5")
    assert a.network.n_nodes == 64 and a.accuracy.lines()[0].startswith("how far to trust this asset:")
    with pytest.raises(AssetError, match="no such file"):
        esmm.load_asset(REPO / "no-such-asset.h5")


@pytest.mark.slow
@pytest.mark.parametrize("page, code", python_blocks(), ids=lambda v: v if v.endswith(".md") else "")
def test_the_python_example_runs(page, code, tmp_path):
    """The example as a user runs it: a fresh interpreter, in a folder beside the bundled data."""
    (tmp_path / "data").symlink_to(REPO / "data")
    env = {**os.environ, "MPLBACKEND": "Agg"}
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=3600)
    assert p.returncode == 0, f"{page}: the example failed:\n{p.stderr[-3000:]}"
    # the speed in words, whatever the machine's load: "N times faster/slower than" or "as fast as real time"
    assert "how far to trust this asset:" in p.stdout and "x real time: " in p.stdout


def test_there_is_an_example():
    assert python_blocks(), "no python example in README.md or docs/guide/python.md"
