"""How far an asset can be trusted, and the failures of the simulation engineer's runs mended:
an organ of implausible size for its name is warned about, any calibrate fit prepares, the
XDMF files open in meshio."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from esmm.cli.main import main
from esmm.pipeline.mesh.organsize import check_organ_size, generic_band_ml, organ_of, reference_ml
from esmm.pipeline.mesh.readers import read_surface, write_stl
from esmm.pipeline.mesh.surface import Surface
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.progress import ListReporter
from esmm.pipeline.simulate.history import History, HistoryWriter

DATA = Path(__file__).resolve().parent.parent / "data" / "meshes"
LIVER = DATA / "ts_liver_3mm_closed.stl"


@pytest.fixture(scope="module")
def liver_in_cm(tmp_path_factory) -> Path:
    """The bundled liver written in centimetres (19.5 across, 1.04 in cm^3 read as mL)."""
    s = read_surface(LIVER)
    out = tmp_path_factory.mktemp("cm") / "liver.stl"
    return write_stl(Surface(s.points * 0.1, s.faces, "liver in cm"), out, unit="mm")


# -- an organ's size against its name -----------------------------------------------------------

def test_a_liver_in_cm_read_as_mm_gets_a_warning_naming_the_unit(liver_in_cm):
    rep = ListReporter()
    s = read_surface(liver_in_cm, reporter=rep)
    assert s.extent() * 1e3 == pytest.approx(19.5, abs=0.1)
    (w,) = rep.warnings
    assert w.startswith("unit: a liver of 1.04 mL (19.5 mm across, read in mm) is implausibly small")
    assert "read it with unit cm (the organ is then 1 042 mL)" in w and "ICRP Publication 89" in w
    rep = ListReporter()
    read_surface(liver_in_cm, unit="cm", reporter=rep)     # the right unit: no warning
    assert rep.warnings == []
    rep = ListReporter()
    read_surface(LIVER, reporter=rep)                      # the liver in mm, 1 042 mL: no warning
    assert rep.warnings == []


def test_organs_of_the_shared_data_are_plausible(shared_data):
    for name, organ in (("openhelp_Kidney_left.stl", "kidney"), ("openhelp_Spleen.stl", "spleen"),
                        ("sofa_liver.stl", "liver"), ("ts_liver_partial_1mm.stl", "")):
        rep = ListReporter()
        read_surface(shared_data / "meshes" / name, reporter=rep)
        assert organ_of(name) == organ and rep.warnings == [], name


def test_organ_names_and_the_bands():
    assert organ_of("openhelp_Kidney_left.stl") == "kidney" and organ_of("Brain_T1.nii.gz") == "brain"
    assert organ_of("liver_segment_4.stl") == "" and organ_of("box.stl") == ""   # a part; no organ
    lo, hi = reference_ml("liver")
    assert lo == pytest.approx(1400 / 1.05) and hi == pytest.approx(1800 / 1.05)
    assert generic_band_ml() == pytest.approx((17 / 1.05 / 10, 1800 / 1.05 * 10))
    # at the edge of the band: a tenth of the smaller adult reference passes, below it does not
    assert check_organ_size(lo / 10 * 1e-6 * 1.001, 0.05, name="liver.stl", unit="mm").plausible
    assert not check_organ_size(lo / 10 * 1e-6 * 0.999, 0.05, name="liver.stl", unit="mm").plausible
    # a big liver (hepatomegaly, 4 L) is fine; 30 L is not
    assert check_organ_size(4e-3, 0.3, name="liver.stl", unit="mm").plausible
    big = check_organ_size(30e-3, 0.39, name="liver.stl", unit="mm")
    assert "implausibly large" in big.message and big.message.startswith("unit:")


def test_an_unknown_organ_gets_the_generic_band():
    thin = check_organ_size(10e-3 * 10e-3 * 0.1e-3, 0.01, name="plate.stl", unit="mm")   # 0.01 mL
    assert thin.organ == "" and "implausibly small: organs are" in thin.message
    assert check_organ_size(20e-3**3, 0.02, name="cube.stl", unit="mm").plausible          # 8 mL


@pytest.mark.slow
def test_prepare_warns_with_the_option_on_the_command_line(liver_in_cm, tmp_path, capsys):
    rc = main(["prepare", str(liver_in_cm), "--config", "coarse", "--no-compensate", "-o",
               str(tmp_path / "liver.h5")])
    out, err = capsys.readouterr()
    assert rc == 0
    assert "warning: --unit: a liver of 1.04 mL" in " ".join(err.split())
    # prepare says how far to trust the asset, and writes its report beside it
    assert "trust how far to trust this asset: the network is not compensated" in " ".join(out.split())
    assert (tmp_path / "liver.report.html").is_file() and f"{tmp_path / 'liver.report.html'}" in out


# -- the simulation history in meshio -----------------------------------------------------------

def test_the_history_reads_with_meshios_time_series_reader(tmp_path):
    """``meshio.xdmf.TimeSeriesReader`` reads the history (it failed: the frames' displacement was a
    hyperslab, which meshio cannot read, in XDMF 2, which it does not read as a series)."""
    meshio = pytest.importorskip("meshio")
    net = network_from_tets(box_tets(2, 2, 2, (0.02, 0.02, 0.02)))
    rng = np.random.default_rng(3)
    frames = [rng.normal(scale=1e-3, size=(net.n_nodes, 3)) for _ in range(4)]
    p = tmp_path / "history.h5"
    with HistoryWriter(p, points=net.points, cells=net.tets, surface=net.surface_faces, fixed=[0]) as w:
        for k, d in enumerate(frames):
            w.add_frame(k / 30, d)
    with meshio.xdmf.TimeSeriesReader(tmp_path / "history.xdmf") as r:
        points, cells = r.read_points_cells()
        assert r.num_steps == 4 and cells[0].type == "tetra"
        np.testing.assert_array_equal(cells[0].data, net.tets)
        np.testing.assert_allclose(points, net.points + frames[0], atol=1e-9)   # the first frame's positions
        with History(p) as h:
            for k in range(4):
                t, point_data, _ = r.read_data(k)
                assert t == pytest.approx(k / 30)
                np.testing.assert_array_equal(point_data["displacement"], h.displacement(k).astype(np.float32))
    root = ET.parse(tmp_path / "history.xdmf").getroot()        # valid XDMF 3: one temporal collection
    assert root.attrib["Version"] == "3.0"
    (domain,) = list(root)
    (series,) = list(domain)
    assert series.attrib["CollectionType"] == "Temporal" and len(list(series)) == 4
    assert all(i.attrib["Format"] == "HDF" for i in root.iter("DataItem"))


# -- any calibrate fit prepares -------------------------------------------------------------------

#: A params.toml as ``esmm calibrate --by specimen`` writes it for the Budday et al. (2017) basal ganglia
#: data (budday2017_brain): the chain count at its bound puts the locking stretch at about 7 900.
BRAIN_PARAMS = """# model esedf; RMSE 37.8 Pa; NRMSE 4.1%; R2 0.95
[material]
model = "esedf"
name = "budday2017-basal_ganglia"
stress_unit = "MPa"

[material.parameters]
mu = 1.6129306952624201e-15
N = 20727568.702826597
A1 = 0.49506550023784673
A2 = 15.834950390136049
f = 0.0019
"""


@pytest.mark.slow
def test_prepare_takes_a_brain_fit_whose_lock_is_far_away(tmp_path):
    """It stopped with "the tables' grid (stretch 0.5..512 ...) is too coarse"."""
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.prepare import prepare

    params = tmp_path / "params.toml"
    params.write_text(BRAIN_PARAMS)
    rep = ListReporter()
    res = prepare(LIVER, output=tmp_path / "brain.h5", config="coarse", material=str(params), compensate=False,
                  reporter=rep)
    assert res.tables.lam_min == 0.5 and 1.99 < res.tables.lam_max <= 2.0
    step = next(s for s in rep.steps if s.startswith("tables:"))
    assert "lam_max 2: the bound 2 (100 % strain)" in step and "locks only at 7886" in step
    a = read_asset(res.asset)
    assert a.tables.lam_max == res.tables.lam_max
    assert a.accuracy.fit["rmse_pa"] == 37.8 and a.accuracy.fit["source"].endswith("/params.toml")


# -- the asset states its accuracy ----------------------------------------------------------------

def _reference_inputs():
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_reference", Path(__file__).parent / "data" / "assets"
                                                  / "make_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.inputs()


FIT = {"schema": "esmm.asset-fit/1", "source": "brain/params.toml", "model": "esedf", "rmse_pa": 102.5,
       "nrmse": 0.0606, "r2": 0.909, "files": ["cortex_simple_shear.csv"], "read_from": "fit.json",
       "verdict": "poor", "reasons": ["mu is not identifiable from these data"]}


@pytest.fixture()
def box_asset(tmp_path):
    from esmm.pipeline.asset import write_asset

    net, material, tables, prov = _reference_inputs()
    return write_asset(tmp_path / "box.h5", net, material=material, tables=tables, provenance=prov, fit=FIT)


def test_the_fit_error_is_stored_and_said(box_asset, capsys):
    from esmm.pipeline.asset import read_asset, validate_asset

    assert validate_asset(box_asset) == []
    a = read_asset(box_asset)
    assert a.accuracy.fit == FIT and a.accuracy.validation is None and a.accuracy.compensation is None
    assert main(["info", str(box_asset)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "trust how far to trust this asset: the network is not compensated and not validated" in out
    assert ("fit: the material follows its tensile data on cortex_simple_shear.csv with a normalised RMS error "
            "of 6.06 % (RMSE 102.5 Pa, R² 0.909); calibrate's verdict: poor (mu is not identifiable") in out
    assert "continuum: not yet compared with a finite-element continuum of this organ" in out


def test_validate_records_its_figures_in_the_asset(box_asset, capsys):
    """``esmm validate ASSET`` writes its figures into the asset, each case's latest; ``esmm info`` says them."""
    from esmm.pipeline.asset import read_asset, update_asset_tables, validate_asset
    from esmm.pipeline.fidelity.validate import validate_asset as validate

    first = validate(box_asset, cases=["tension"])
    second = validate(box_asset, cases=["shear"])
    assert validate_asset(box_asset) == []
    cases = read_asset(box_asset).accuracy.validation["cases"]
    assert sorted(cases) == ["shear", "tension"]       # the second run kept the first's case
    assert cases["tension"]["l2_error"] == pytest.approx(first.results[0].l2_error, rel=1e-12)
    assert cases["shear"]["force_error"] == pytest.approx(second.results[0].force_error, rel=1e-12)
    assert cases["shear"]["volume_term"] == "off" and cases["shear"]["law"] == "secant"
    assert main(["info", str(box_asset)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    worst_u = max(first.results[0].l2_error, second.results[0].l2_error)
    assert f"the network is within {100 * worst_u:.3g} % of a finite-element continuum in displacement" in out
    assert f"tension: {100 * first.results[0].l2_error:.3g} % in displacement (L2)" in out
    # new tables make the figures stale: they are dropped
    update_asset_tables(box_asset, read_asset(box_asset).tables)
    a = read_asset(box_asset)
    assert a.accuracy.validation is None and a.accuracy.fit == FIT


def test_a_damaged_accuracy_record_is_reported(box_asset):
    import h5py
    from esmm.pipeline.asset import hdf5, read_asset, validate_asset
    from esmm.pipeline.errors import AssetError

    with h5py.File(box_asset, "r+") as f:
        del f["/accuracy/fit/record"]
        hdf5.put_text(f["/accuracy/fit"], "record", '{"schema": "esmm.asset-fit/1", "rmse_pa": "low"}')
        hdf5.seal(f)
    assert validate_asset(box_asset) == ["/accuracy/fit/record: rmse_pa is not a number ('low')"]
    with pytest.raises(AssetError, match="rmse_pa is not a number"):
        read_asset(box_asset)


def test_the_fit_record_of_a_calibrate_output(tmp_path):
    import json

    from esmm.pipeline.asset import fit_record
    from esmm.pipeline.materials.material import load_material

    params = tmp_path / "brain" / "params.toml"
    params.parent.mkdir()
    params.write_text("# files: a.csv, b.csv\n# verdict: poor: N at its bound; mu not identifiable\n" + BRAIN_PARAMS)
    rec = fit_record(params)                          # from the header lines
    assert rec["rmse_pa"] == 37.8 and rec["nrmse"] == pytest.approx(0.041) and rec["r2"] == 0.95
    assert rec["files"] == ["a.csv", "b.csv"] and rec["source"] == "brain/params.toml"
    assert rec["verdict"] == "poor" and rec["reasons"] == ["N at its bound", "mu not identifiable"]
    mat = load_material(params)
    doc = {"errors": {"rmse": 40.1, "nrmse": 0.05, "r2": 0.9}, "material": {"params": dict(mat.params)},
           "model": "esedf", "files": ["/x/a.csv"], "verdict": {"level": "unusable", "reasons": [{"text": "why"}]}}
    (params.parent / "fit.json").write_text(json.dumps(doc))
    rec = fit_record(params, loaded=mat)              # the same fit: calibrate's fit.json beside it
    assert (rec["rmse_pa"], rec["verdict"], rec["reasons"]) == (40.1, "unusable", ["why"])
    doc["material"]["params"]["N"] = 3.0               # another fit's fit.json: the header again
    (params.parent / "fit.json").write_text(json.dumps(doc))
    assert fit_record(params, loaded=mat)["rmse_pa"] == 37.8
    assert fit_record("porcine_liver_paper") is None


# -- the simulation's messages ---------------------------------------------------------------------

def test_real_time_in_words():
    from esmm.pipeline.simulate.summary import real_time_words

    assert real_time_words(0.269) == "0.27x real time: 3.7 times slower than real time"
    assert real_time_words(5.75) == "5.75x real time: 5.8 times faster than real time"
    assert real_time_words(1.03) == "1.03x real time: 1.03 times faster than real time"
    assert real_time_words(1.001) == "1x real time: as fast as real time"


@pytest.mark.slow
def test_simulate_says_the_scene_replaced_the_fixed_nodes_and_the_speed_in_words(run_cli, tmp_path):
    """The default scene holds its own band (the lowest 5 % along gravity), not the asset's fixed nodes:
    the run says so, with both counts; the real-time factor says slower or faster."""
    import json

    from esmm.pipeline.asset import write_asset

    net = network_from_tets(box_tets(6, 3, 2, (0.06, 0.03, 0.015)))
    net = net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))     # the asset's: the face x = 0
    _, material, tables, _ = _reference_inputs()
    asset = write_asset(tmp_path / "slab.h5", net, material=material, tables=tables)
    code, out, err = run_cli("simulate", asset, "--duration", "100 ms", "--threads", "1", "--out", tmp_path / "run")
    assert code == 0, err
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["fixed"]["source"] == "scene" and s["fixed"]["asset_nodes"] == net.fixed.size
    assert s["fixed_nodes"] != net.fixed.size
    text = " ".join(out.split())
    assert (f"fixed: {s['fixed_nodes']} fixed nodes from the scene's [fixed] region (band at the min end of "
            "the normal") in text and f"in place of the asset's {net.fixed.size}" in text
    factor = s["real_time_factor"]
    assert f"{'slower' if factor < 1 else 'faster'} than real time" in text
