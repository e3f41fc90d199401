"""Calibration: published Treloar parameters, recovery of known parameters, anisotropy,
identifiability warnings, batch with a bad file, and the CLI outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.calibrate.fit import fit_material, predict
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.loading import nominal_stress
from esmm.pipeline.tensile import TensileTest, read


def _synthetic(model, params, mode, x, *, noise=0.0, seed=0, name="syn.csv", **meta):
    rng = np.random.default_rng(seed)
    p = nominal_stress(get_model(model), params, mode, x)
    p = p + noise * np.max(np.abs(p)) * rng.standard_normal(p.shape)
    return TensileTest(source=Path(name), mode=mode, stretch=np.asarray(x, float), stress=p,
                       time=np.arange(len(x), dtype=float), metadata=dict(meta))


def _ab_param(result, *names):
    for n in names:
        if n in result.params:
            return result.params[n]
    raise KeyError(names)


def test_treloar_arruda_boyce_reproduces_published_parameters(bundled_data):
    """Arruda & Boyce (1993): C_R ~ 0.27 MPa, N ~ 26 for Treloar's uniaxial data."""
    test = read(bundled_data / "tensile" / "treloar1944" / "uniaxial.csv")
    res = fit_material([test], model="arruda-boyce")
    c_r = _ab_param(res, "mu", "C_R")
    assert c_r == pytest.approx(0.27e6, rel=0.05)
    assert res.params["N"] == pytest.approx(26.0, rel=0.10)
    assert res.r2 > 0.99
    # the interval brackets the estimate
    for e in res.estimates:
        assert e.lower <= e.value <= e.upper


def test_recovers_known_parameters_from_noisy_multimode_data():
    model = get_model("arruda-boyce")
    truth = {p.name: p.default for p in model.parameters}
    truth.update({"mu": 0.4e6, "N": 8.0} if "mu" in truth else {})
    lam = np.linspace(1.0, 3.0, 60)
    tests = [
        _synthetic("arruda-boyce", truth, "uniaxial", lam, noise=0.01, seed=1, name="u.csv"),
        _synthetic("arruda-boyce", truth, "equibiaxial", np.linspace(1, 2.0, 40), noise=0.01, seed=2, name="e.csv"),
    ]
    res = fit_material(tests, model="arruda-boyce", n_starts=4)
    for name in ("mu", "N"):
        est = next(e for e in res.estimates if e.name == name)
        assert est.value == pytest.approx(truth[name], rel=0.05)
        assert est.lower < truth[name] < est.upper
    assert res.nrmse < 0.02


def test_anisotropic_fit_gives_direction_specific_parameters():
    model = get_model("esedf")
    directional = [p.name for p in model.parameters if p.directional]
    assert directional, "the ESEDF must declare which parameters are per fibre direction"
    base = {p.name: p.default for p in model.parameters}
    lam = np.linspace(1.0, 1.25, 50)
    stiff = dict(base)
    for name in directional:
        stiff[name] = base[name] * 3.0
    tests = [
        _synthetic("esedf", base, "uniaxial", lam, noise=0.005, seed=3, name="x.csv", orientation="x"),
        _synthetic("esedf", stiff, "uniaxial", lam, noise=0.005, seed=4, name="y.csv", orientation="y"),
    ]
    res = fit_material(tests, model="esedf", n_starts=4)
    assert res.directions is not None and set(res.directions) == {"x", "y", "z"}
    # y is stiffer than x at the largest stretch
    m = get_model("esedf")
    px = nominal_stress(m, res.directions["x"], "uniaxial", np.array([1.25]))[0]
    py = nominal_stress(m, res.directions["y"], "uniaxial", np.array([1.25]))[0]
    assert py > 1.5 * px
    assert any("no data for fibre direction(s) z" in w for w in res.warnings)
    assert res.nrmse < 0.03


def test_mixing_tagged_and_untagged_files_is_refused():
    model = get_model("arruda-boyce")
    p = {q.name: q.default for q in model.parameters}
    lam = np.linspace(1, 2, 20)
    tests = [_synthetic("arruda-boyce", p, "uniaxial", lam, name="a.csv", orientation="x"),
             _synthetic("arruda-boyce", p, "uniaxial", lam, name="b.csv")]
    with pytest.raises(ConfigError, match="tag every file"):
        fit_material(tests, model="arruda-boyce")


def test_unidentifiable_parameters_are_flagged():
    """The full ESEDF on a small-strain record cannot pin every parameter."""
    model = get_model("esedf")
    p = {q.name: q.default for q in model.parameters}
    test = _synthetic("esedf", p, "uniaxial", np.linspace(1.0, 1.05, 30), noise=0.01, seed=5)
    res = fit_material([test], model="esedf", n_starts=3)
    assert any("not identifiable" in w or "correlated" in w for w in res.warnings)


def test_predict_matches_fit_errors(bundled_data):
    test = read(bundled_data / "tensile" / "treloar1944" / "uniaxial.csv")
    res = fit_material([test], model="arruda-boyce", n_starts=2)
    pred = predict(res, test)
    rmse = float(np.sqrt(np.mean((pred - test.stress) ** 2)))
    assert rmse == pytest.approx(res.rmse, rel=1e-9)


def test_cli_treloar_json_and_outputs(run_cli, bundled_data, tmp_path):
    src = bundled_data / "tensile" / "treloar1944" / "uniaxial.csv"
    out_json = tmp_path / "out.json"
    code, out, err = run_cli("calibrate", src, "--model", "arruda-boyce", "--json", out_json,
                             "--out", tmp_path / "fit")
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert doc["schema"] == "esmm.calibrate/1"
    assert doc["model"] == "arruda-boyce"
    assert set(doc["errors"]) >= {"rmse", "nrmse", "r2", "per_file"}
    assert doc["files"] == [str(src)]
    cr = doc["parameters"].get("mu", doc["parameters"].get("C_R"))
    assert cr["value"] == pytest.approx(0.27e6, rel=0.05)
    assert cr["ci95"][0] < cr["value"] < cr["ci95"][1]
    for name in ("params.toml", "fit.png", "report.md", "fit.json"):
        assert (tmp_path / "fit" / name).stat().st_size > 0
    # params.toml reads back as a material config
    from esmm.pipeline.materials.material import load_material

    mat = load_material(tmp_path / "fit" / "params.toml")
    assert mat.model == "arruda-boyce"
    assert mat.params["N"] == pytest.approx(doc["parameters"]["N"]["value"], rel=1e-6)
    assert not list(tmp_path.rglob("*.tmp-*"))


def test_cli_bad_file_one_line_error(run_cli, tmp_path):
    bad = tmp_path / "empty.csv"
    bad.write_text("")
    code, out, err = run_cli("calibrate", bad, "--out", tmp_path / "fit")
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("esmm: error:") and "empty.csv" in err
    assert "Traceback" not in err
    assert not (tmp_path / "fit").exists()


def test_cli_unknown_model(run_cli, bundled_data):
    code, _, err = run_cli("calibrate", bundled_data / "tensile" / "treloar1944" / "uniaxial.csv",
                           "--model", "ogden9")
    assert code == 2 and "unknown model" in err


def test_batch_by_specimen_skips_bad_file(run_cli, bundled_data, tmp_path):
    brain = sorted((bundled_data / "tensile" / "budday2017_brain").glob("*tension_compression.csv"))[:3]
    bad = tmp_path / "broken.csv"
    bad.write_bytes(b"\x00\x01\x02binary")
    out = tmp_path / "batch"
    code, stdout, err = run_cli("calibrate", "--by", "specimen", *brain, bad, "--out", out,
                                "--model", "arruda-boyce", "--jobs", "2", "--starts", "3")
    assert code == 5  # something failed
    summary = (out / "summary.csv").read_text().splitlines()
    rows = [r.split(",")[:2] for r in summary[1:]]
    assert sum(r[1] == "ok" for r in rows) == 3
    assert any(r[1] == "unreadable" for r in rows)
    assert any(r[0] == "mean" for r in rows) and any(r[0] == "sd" for r in rows) and any(r[0] == "n" for r in rows)
    assert len([p for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")]) == 3


def test_calibrate_config_file_and_overrides(tmp_path):
    """The [calibrate] table is read and checked by the library; the caller's options win."""
    from esmm.pipeline.calibrate.config import load_calibrate_config

    cfg = tmp_path / "c.toml"
    cfg.write_text('[calibrate]\nmodel = "arruda-boyce"\nstarts = 3\nseed = 2\nstress_unit = "kPa"\n'
                   'weights = { a = 2.0 }\nfix = { mu = 270 }\n')
    c = load_calibrate_config(cfg)
    assert (c.model, c.n_starts, c.seed, c.weights, c.fixed) == ("arruda-boyce", 3, 2, {"a": 2.0}, {"mu": 270e3})
    c = load_calibrate_config(cfg, n_starts="5", weights={"b": "0.5"}, fixed={"N": "20", "mu": "0.3 MPa"},
                              free=["N"])
    assert c.fit_kwargs() == dict(model="arruda-boyce", loss="linear", n_starts=5, seed=2,
                                  weights={"a": 2.0, "b": 0.5}, fixed={"mu": 0.3e6, "N": 20.0}, free=("N",))
    assert load_calibrate_config().fit_kwargs()["weights"] is None
    cfg.write_text('[calibrate]\nstarts = "x"\n')
    with pytest.raises(ConfigError, match=r"c.toml: \[calibrate\] starts"):
        load_calibrate_config(cfg)
    with pytest.raises(ConfigError, match="^fixed: unknown parameter 'zz'") as info:
        load_calibrate_config(None, model="arruda-boyce", fixed={"zz": "1"})
    assert info.value.parameter == "fixed"
    with pytest.raises(ConfigError, match="^fixed: mu: '3' has no unit"):
        load_calibrate_config(None, model="arruda-boyce", fixed={"mu": "3"})


def test_cli_outputs_say_which_columns_were_used_and_the_true_stress_conversion(run_cli, tmp_path):
    """specs/tensile-data.md: true stress is converted to nominal (P = sigma / lambda) and the outputs say so,
    with the columns used and the reader's warnings."""
    lam = np.linspace(1.0, 1.6, 25)
    mu = 50e3
    sigma = mu * (lam**2 - 1 / lam)                    # neo-Hookean true stress in uniaxial tension [Pa]
    src = tmp_path / "true.csv"
    src.write_text("Time (s),Stretch,Cauchy stress (kPa)\n"
                   + "".join(f"{i},{a:.6f},{s / 1e3:.6f}\n" for i, (a, s) in enumerate(zip(lam, sigma))))
    code, out, err = run_cli("calibrate", src, "--model", "arruda-boyce", "--starts", "2", "--out", tmp_path / "fit")
    assert code == 0, err
    doc = json.loads((tmp_path / "fit" / "fit.json").read_text())
    (how,) = doc["inputs"]
    assert "true stress" in how["stress_from"] and "stretch" in how["stress_from"]
    assert {c["header"] for c in how["used_columns"].values()} >= {"Stretch", "Cauchy stress"}
    report = (tmp_path / "fit" / "report.md").read_text()
    assert "## How each file was read" in report and "nominal stress = true stress / stretch" in report
    # the conversion itself: the fit sees nominal stress, sigma / lambda
    np.testing.assert_allclose(read(src).stress, sigma / lam, rtol=1e-5)


def test_whole_numbers_written_in_exponent_form_are_whole():
    """`--points 1e6` was refused as "expected a whole number" while the range in the same message read
    [3, 1e+06]: a whole number in exponent form is read as one; fractions still are not."""
    from esmm.pipeline.checks import number_text
    from esmm.pipeline.errors import ConfigError

    assert number_text("1e6", "points", lo=3, integer=True) == 1_000_000
    assert number_text(" 2.0E3 ", "points", integer=True) == 2000
    for bad in ("1.5", "1e-3", "inf", "nan", "x"):
        with pytest.raises(ConfigError, match="points: expected a whole number"):
            number_text(bad, "points", integer=True)
