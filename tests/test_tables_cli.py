"""``esmm tables``: rewrite an asset's stiffness tables atomically."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from esmm.pipeline.asset import read_asset, validate_asset, write_asset
from esmm.pipeline.compensation.virtual_tensile import cylinder_specimen
from esmm.pipeline.network.tables import build_tables


@pytest.fixture(scope="module")
def network():
    return cylinder_specimen(radius=4e-3, length=16e-3, size=2e-3).network


@pytest.fixture()
def asset(tmp_path, network, liver):
    path = tmp_path / "spec.h5"
    write_asset(path, network, material=liver, tables=build_tables(liver, n=256), fixed_region="test")
    return path


def _digest(path, name):
    with h5py.File(path, "r") as f:
        return f[name].attrs["sha256"]


def test_rewrite_law_keeps_everything_else(run_cli, asset):
    springs = _digest(asset, "/springs/volume_weight")
    code, out, err = run_cli("tables", asset, "--law", "energy")
    assert code == 0, err
    assert "tables rewritten" in out and "energy" in out
    assert validate_asset(asset) == []
    a = read_asset(asset)
    assert a.tables.default_law == "energy" and a.tables.n == 256
    assert _digest(asset, "/springs/volume_weight") == springs
    assert a.fixed_region == "test"
    assert a.tables.metadata["written_by"]["command"][:2] == ["esmm", "tables"]
    assert not list(asset.parent.glob(".spec.h5.tmp-*"))


def test_per_spring_and_json(run_cli, asset, network):
    code, out, err = run_cli("tables", asset, "--per-spring", "--points", "64", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["grid"]["n"] == 64 and summary["per_spring"]
    assert summary["mu_e_MPa"]["1.0"] == pytest.approx(0.0149231, rel=1e-4)
    assert validate_asset(asset) == []
    with h5py.File(asset, "r") as f:
        k = f["/tables/k_per_spring"]
        assert k.shape == (network.n_springs, 64) and k.attrs["units"] == "N/m"
        t = read_asset(asset).tables
        a = read_asset(asset).network
        np.testing.assert_allclose(k[:, 10], (a.volume_weight[:, None] * a.cos2) @ t.values[:, 10], rtol=1e-6)


def test_other_material_replaces_material_group(run_cli, asset, liver, tmp_path):
    text = liver.to_toml().replace("A1 = 3.9106", "A1 = 7.8212")
    assert "A1 = 7.8212" in text
    mfile = tmp_path / "stiffer.toml"
    mfile.write_text(text)
    code, out, err = run_cli("tables", asset, "--material", mfile)
    assert code == 0, err
    a = read_asset(asset)
    assert a.material.params["A1"] == pytest.approx(2 * liver.params["A1"])
    np.testing.assert_allclose(a.tables.values[0], a.material.mu_e(a.tables.lam), rtol=1e-12)
    assert np.all(a.tables.values[0, -5:] > build_tables(liver).mu_e(a.tables.lam[-5:])[0])


def test_errors_leave_the_asset_untouched(run_cli, asset, tmp_path):
    before = asset.read_bytes()
    code, _, err = run_cli("tables", asset, "--points", "many")
    assert code == 2 and "--points" in err
    code, _, err = run_cli("tables", asset, "--stretch-range", "0.5", "1.2")
    assert code == 2 and "--stretch-range: grid [0.5, 1.2] leaves" in err and "lam_min" not in err
    code, _, err = run_cli("tables", asset, "--stretch-range", "1.3", "0.9")     # the ends swapped
    assert code == 2 and "--stretch-range: need 0 < LO < 1 < HI" in err and "lam_min" not in err
    code, _, err = run_cli("tables", asset, "--specimen-elements", "100")   # without --compensate: unused
    assert code == 2 and "--specimen-elements" in err and "--compensate" in err
    code, _, err = run_cli("tables", asset, "--material", "no_such_material")
    assert code == 2 and "no_such_material" in err
    code, _, err = run_cli("tables", tmp_path / "missing.h5")
    assert code == 2 and "no such file" in err
    assert asset.read_bytes() == before


def test_asset_without_material_needs_one(run_cli, tmp_path, network):
    path = tmp_path / "bare.h5"
    write_asset(path, network)
    code, _, err = run_cli("tables", path)
    assert code == 2 and "--material" in err
    code, _, err = run_cli("tables", path, "--material", "porcine_liver_paper")
    assert code == 0, err
    assert read_asset(path).tables is not None


@pytest.mark.slow
def test_compensate_then_switch_law_keeps_it(run_cli, asset):
    code, out, err = run_cli("tables", asset, "--compensate", "--calibration-range", "0.95", "1.2",
                              "--specimen-elements", "2")
    assert code == 0, err
    assert "compensated" in out
    t = read_asset(asset).tables
    assert 5.0 < t.volume_factor < 8.0 and t.is_corrected("secant")
    rec = t.metadata["compensation"]["laws"]["secant"]
    assert rec["errors_after"]["max_abs_rel_error"] < 0.05
    assert rec["stretch_range"] == [pytest.approx(0.95), pytest.approx(1.2)]
    code, out, err = run_cli("tables", asset, "--law", "energy")
    assert code == 0, err
    t2 = read_asset(asset).tables
    assert t2.volume_factor == t.volume_factor and t2.is_corrected("secant") and "(kept)" in out
    np.testing.assert_array_equal(t2.values, t.values)
    # a new material drops it, with a warning
    code, out, err = run_cli("tables", asset, "--points", "300")
    assert code == 0 and "dropped" in err
    assert read_asset(asset).tables.volume_factor == 1.0


def test_mu_e_is_labelled_at_the_grid_end_and_calibration_range_needs_a_use(run_cli, asset):
    """Adversarial sweep: a grid ending at 1.05 printed a value "at 1.1" (the end's, clamped);
    --calibration-range without --compensate was silently ignored."""
    code, out, err = run_cli("tables", asset, "--stretch-range", "0.8", "1.05")
    assert code == 0, err
    assert "at 1.1" not in out and "(the grid's end)" in out
    code, out, err = run_cli("tables", asset, "--stretch-range", "0.8", "1.05", "--json")
    assert code == 0 and "1.1" not in json.loads(out)["mu_e_MPa"]
    before = asset.read_bytes()
    code, out, err = run_cli("tables", asset, "--calibration-range", "0.9", "1.2")
    errors = [ln for ln in err.splitlines() if ln.startswith("esmm: error:")]
    assert code == 2 and len(errors) == 1 and errors[0].startswith("esmm: error: --calibration-range: only used")
    assert asset.read_bytes() == before
