"""report.html of prepare (the asset's ``NAME.report.html``), validate and simulate: the verdict in plain
words first, every number with its unit, and a page that opens in a headless browser without an error."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest
from htmlkit import browser_or_skip, check_page

HERE = Path(__file__).resolve().parent

FIT = {"schema": "esmm.asset-fit/1", "source": "brain/params.toml", "model": "esedf", "rmse_pa": 102.5,
       "nrmse": 0.0606, "r2": 0.909, "files": ["cortex_simple_shear.csv"], "read_from": "fit.json",
       "verdict": "poor", "reasons": ["mu is not identifiable from these data"]}


def _reference_inputs():
    spec = importlib.util.spec_from_file_location("make_reference", HERE / "data" / "assets" / "make_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.inputs()


def _verdict_first(html: str) -> str:
    """The verdict box's level, checked to come before every section of the page."""
    m = re.search(r'<section class="verdict (\w+)"', html)
    assert m is not None, "no verdict"
    assert m.start() < html.index("<h2>"), "the verdict is not first"
    return m.group(1)


def _opens_cleanly(path: Path) -> str:
    page = check_page(path, browser=browser_or_skip())
    assert page.problems == [], page.problems
    assert page.images and all(i["width"] > 0 for i in page.images)
    return page.text


@pytest.fixture()
def box(tmp_path):
    from esmm.pipeline.asset import write_asset

    net, material, tables, prov = _reference_inputs()
    return write_asset(tmp_path / "box.h5", net, material=material, tables=tables, provenance=prov, fit=FIT)


def test_the_asset_report_says_how_far_to_trust_it_first(box):
    from esmm.pipeline.asset.report import report_path, write_asset_report

    path = write_asset_report(box)
    assert path == report_path(box) == box.with_name("box.report.html")
    html = path.read_text()
    # uncompensated: its forces are several times too small, and the fit's verdict is poor
    assert _verdict_first(html) == "unusable"
    assert "the network is not compensated: its forces are several times too small" in html
    assert "calibrate&#x27;s verdict on the material&#x27;s fit is poor" in html
    assert "<td class=\"num\">8.48 g</td>" in html and "<td class=\"num\">8 mL</td>" in html   # with units
    text = _opens_cleanly(path)
    assert text.index("How far to trust this asset") < text.index("The asset\n")


def test_validate_writes_its_report_and_renews_the_assets(box, tmp_path):
    from esmm.pipeline.asset.report import report_path, write_asset_report
    from esmm.pipeline.fidelity.validate import validate_asset

    write_asset_report(box)
    before = report_path(box).read_text()
    rep = validate_asset(box, cases=["tension"], out_dir=tmp_path / "val")
    html = (tmp_path / "val" / "report.html").read_text()
    assert rep.files["html"] == str(tmp_path / "val" / "report.html")
    level = _verdict_first(html)
    l2 = rep.results[0].l2_error
    assert f"The network is within {100 * l2:.3g} % of the finite-element continuum in displacement (L2)" in html
    assert level == ("poor" if max(l2, rep.results[0].force_error) > 0.10 else "good")
    assert "esmm tables ASSET --compensate" in html          # the box is not compensated: that is the advice
    assert "displacement error (L2) [%]" in html
    _opens_cleanly(tmp_path / "val" / "report.html")
    after = report_path(box).read_text()                      # the asset's report now has the case
    assert after != before and "tension: " in after and "not yet compared" not in after


@pytest.mark.slow
def test_simulate_writes_its_report(run_cli, tmp_path):
    import numpy as np
    from esmm.pipeline.asset import write_asset
    from esmm.pipeline.mesh.synthetic import box_tets
    from esmm.pipeline.network.springs import network_from_tets

    net = network_from_tets(box_tets(6, 3, 2, (0.06, 0.03, 0.015)))
    net = net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))
    _, material, tables, _ = _reference_inputs()
    asset = write_asset(tmp_path / "slab.h5", net, material=material, tables=tables)
    code, out, err = run_cli("simulate", asset, "--duration", "100 ms", "--threads", "1", "--out", tmp_path / "run")
    assert code == 0, err
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    html = (tmp_path / "run" / "report.html").read_text()
    level = _verdict_first(html)
    words = "slower" if s["real_time_factor"] < 1 else "faster"
    assert f"times {words} than real time" in html and "largest force on the grasper" in html
    assert level in ("good", "poor") and (level == "poor") == (s["real_time_factor"] < 1 or bool(
        s["outside_table"]["frames"]) or abs(s["volume"]["final"]["volume_ratio"] - 1) > 0.01)
    assert f"report: {tmp_path / 'run' / 'report.html'}" in " ".join(out.split())
    text = _opens_cleanly(tmp_path / "run" / "report.html")
    assert "Force of the tissue on the grasper" in text
