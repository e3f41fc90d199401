"""The volume term through the pipeline: prepare writes it by default, info shows it, simulate uses it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from esmm.pipeline.asset import read_asset, validate_asset
from esmm.pipeline.network.volume import DEFAULT_POISSON, bulk_modulus, bulk_ratio, nodal_volumes


@pytest.fixture(scope="module")
def assets(tmp_path_factory, bundled_data):
    """The bundled liver, coarse preset, without the (slow) compensation: with and without the term."""
    from esmm.pipeline.prepare import prepare

    out = tmp_path_factory.mktemp("vol")
    stl = bundled_data / "meshes" / "ts_liver_3mm_closed.stl"
    on = prepare(stl, output=out / "on.h5", config="coarse", compensate=False)
    off = prepare(stl, output=out / "off.h5", config="coarse", compensate=False, volume=False)
    return on, off


def test_prepare_writes_the_volume_term_by_default(assets, tables):
    on, off = assets
    assert validate_asset(on.asset) == [] and validate_asset(off.asset) == []
    a = read_asset(on.asset)
    spec = a.network.volume_term
    assert spec is not None and spec.formulation == "nodal" and spec.poisson_ratio == DEFAULT_POISSON
    # kappa from the material: the rule on the asset's own tables, independent of the mesh
    expect = bulk_modulus(tables, poisson=DEFAULT_POISSON, calibration_range=(0.9, 1.3))
    assert spec.bulk_modulus == pytest.approx(expect.bulk_modulus, rel=1e-6)
    assert spec.bulk_modulus == pytest.approx(bulk_ratio(DEFAULT_POISSON) * spec.shear_modulus, rel=1e-12)
    import h5py

    with h5py.File(on.asset, "r") as f:
        np.testing.assert_allclose(f["/volume/rest_volume"][()], nodal_volumes(a.network.points, a.network.tets),
                                   rtol=1e-14)
    assert read_asset(off.asset).network.volume_term is None
    assert any("no volume term" in w for w in off.warnings)


def test_info_shows_the_volume_term(run_cli, assets):
    on, off = assets
    rc, out, _ = run_cli("info", on.asset)
    assert rc == 0 and "volume term  nodal elements, bulk modulus" in out
    rc, out, _ = run_cli("info", off.asset, "--json")
    assert rc == 0 and json.loads(out)["summary"]["volume_term"] is None


def test_scene_switch_and_run_records(assets, tmp_path):
    """A short run with the term on and off: the volume records of the summary.

    The asset is uncompensated; the run uses its tables with the scalar factor
    a compensation with the term finds (c = 5.1, docs/design/model.md, "The volume term (nearly incompressible network)"), so that
    the springs have about the tissue's small-strain modulus.
    """
    from esmm.pipeline.simulate.run import simulate_network
    from esmm.pipeline.simulate.scene import load_scene

    on, _ = assets
    a = read_asset(on.asset)
    tables = a.tables.with_compensation(5.1)
    scene = load_scene("default").with_overrides(duration=1 / 30)     # one frame
    runs = {}
    for switch in ("asset", "none"):
        res = simulate_network(a.network, tables, scene.with_overrides(volume=switch), tmp_path / switch)
        runs[switch] = res.summary
    v = runs["asset"].volume
    assert v["term"]["formulation"] == "nodal" and v["scene"] == "asset"
    assert runs["none"].volume["term"] is None
    for s in runs.values():
        assert s.equilibrium["shape"]["sag_max_m"] > 0 and s.volume["final"]["volume_ratio"] is not None
    assert runs["asset"].equilibrium["shape"]["inverted_tets"] == 0
    # the organ keeps its volume with the term, within the 1 % goal, and loses more without it
    dv_on = abs(runs["asset"].equilibrium["shape"]["volume_ratio"] - 1)
    dv_off = abs(runs["none"].equilibrium["shape"]["volume_ratio"] - 1)
    assert dv_on < 0.01 and dv_on < 0.2 * dv_off
