"""esmm evaluate: predict new files with a saved fit (discover, calibrate or a material file),
refitting nothing by default; per-test artefacts re-estimated on each new file only when asked."""

from __future__ import annotations

import json

import numpy as np
import pytest
from esmm.pipeline.discover import discover_and_save
from esmm.pipeline.discover import synthetic as syn
from esmm.pipeline.discover.evaluate import evaluate, load_fit
from esmm.pipeline.discover.population import family
from esmm.pipeline.errors import ConfigError, InputError
from esmm.pipeline.tensile import read

BASE = {"mu": 20e3, "N": 4.0}
FAST = dict(model="arruda-boyce", n_starts=2, max_points=200)
NOISE = 0.003  # the generator's force noise, fraction of the largest force


@pytest.fixture(scope="module")
def visco_fit(tmp_path_factory):
    """A discovery on two rates; a third rate and a relaxation kept back for evaluation."""
    root = tmp_path_factory.mktemp("visco")
    truth = syn.Truth("arruda-boyce", BASE, viscoelastic={"g": [0.4, 0.2], "tau": [1.0, 20.0]})
    train = [read(p) for p in syn.write_set(root / "train", [syn.load_unload(0.01, 1.5), syn.load_unload(0.1, 1.5)],
                                            truth, seed=1)]
    new = syn.write_set(root / "new", [syn.load_unload(0.03, 1.4), syn.ramp_hold(0.2, 1.4, 40.0)], truth, seed=7)
    res = discover_and_save(train, out_dir=root / "fit", **FAST)
    return root, res, new


def test_new_rate_predicted_to_noise_level_without_refitting(visco_fit):
    root, res, new = visco_fit
    assert "viscoelastic" in res.kept
    me = res.material_effects  # Prony terms sorted by tau, intervals bracket their own term
    for j, (g, tau) in enumerate(zip(me.viscoelastic.g, me.viscoelastic.tau)):
        lo, hi = me.intervals[f"viscoelastic.tau[{j}]"]
        assert lo <= tau <= hi
        lo, hi = me.intervals[f"viscoelastic.g[{j}]"]
        assert lo <= g <= hi
    ev = evaluate(root / "fit", [read(p) for p in new])
    assert ev.fit.kind == "discover" and ev.fit.effects == ["viscoelastic"]
    # the rate-independent base model cannot predict another rate or a hold; the final model can
    assert ev.after.nrmse < 0.25 * ev.before.nrmse
    for f in ev.after.per_file:
        assert f["nrmse"] < 4 * NOISE, f
    # the material was not refitted: evaluating the training files reproduces the discovery's errors
    ev_train = evaluate(root / "fit", [r.test for r in res.records])
    assert ev_train.after.rmse == pytest.approx(res.final.errors.rmse, rel=1e-6)
    assert ev_train.before.rmse == pytest.approx(res.base.errors.rmse, rel=1e-6)


def test_slack_is_re_estimated_on_each_new_file_only_when_asked(tmp_path):
    truth = syn.Truth("arruda-boyce", BASE)
    train = [read(p) for p in syn.write_set(tmp_path / "train", [syn.load_unload(0.05, 1.5, name="a"),
                                                                   syn.load_unload(0.05, 1.4, name="b")],
                                            truth, seed=3, vary={"slack": [1.5e-3, 0.8e-3]})]
    res = discover_and_save(train, out_dir=tmp_path / "fit", **FAST)
    assert "slack" in res.kept
    [p] = syn.write_set(tmp_path / "new", [syn.cycles(0.05, [1.3, 1.5], name="c")], truth, seed=11,
                        vary={"slack": [2.2e-3]})
    plain = evaluate(tmp_path / "fit", [read(p)])  # the default: nothing refitted, no artefact applied
    assert not plain.artefacts_refitted and plain.artefacts == {}
    assert plain.after.nrmse > 4 * NOISE  # the material alone does not know the new file's slack
    ev = evaluate(tmp_path / "fit", [read(p)], refit_artefacts=True)
    assert ev.artefacts_refitted
    assert ev.artefacts["slack"]["c.csv"]["length_m"] == pytest.approx(2.2e-3, rel=0.05)
    assert ev.after.nrmse < 4 * NOISE < ev.before.nrmse


def test_plain_calibrate_output_and_material_file_are_accepted(tmp_path, visco_fit):
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.calibrate.report import write_outputs

    root, res, new = visco_fit
    tests = [read(p) for p in new]
    # a calibrate --out folder (fit.json): no effects, before == after
    fr = fit_material([r.test for r in res.records], model="arruda-boyce", n_starts=2)
    write_outputs(tmp_path / "cal", fr, [r.test for r in res.records])
    ev = evaluate(tmp_path / "cal", tests)
    assert ev.fit.kind == "calibrate" and ev.fit.effects == []
    assert ev.after.rmse == pytest.approx(ev.before.rmse)
    # the discovery's params.toml alone carries the effects: same prediction as discover.json
    ev_toml = evaluate(root / "fit" / "params.toml", tests)
    ev_json = evaluate(root / "fit", tests)
    assert ev_toml.fit.kind == "material"
    assert ev_toml.after.rmse == pytest.approx(ev_json.after.rmse, rel=1e-4)


def test_errors_are_one_line_and_name_the_problem(tmp_path, visco_fit):
    root, res, new = visco_fit
    with pytest.raises(ConfigError, match="no discover.json, fit.json or params.toml"):
        load_fit(tmp_path)
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps({"schema": "something/1"}))
    with pytest.raises(ConfigError, match="unknown schema"):
        load_fit(bad)
    with pytest.raises(InputError, match="no tensile files"):
        evaluate(root / "fit", [])


def test_cli_evaluate(run_cli, tmp_path, visco_fit):
    root, res, new = visco_fit
    out = tmp_path / "ev.json"
    code, stdout, stderr = run_cli("evaluate", root / "fit", *new, "--json", out)
    assert code == 0, stderr
    assert "all files" in stdout and "NRMSE before" in stdout
    doc = json.loads(out.read_text())
    assert doc["schema"] == "esmm.evaluate/1" and doc["artefacts_refitted"] is False
    assert "nothing refitted" in stdout
    assert doc["effects"] == ["viscoelastic"]
    assert doc["after"]["nrmse"] < doc["before"]["nrmse"]
    assert {"rmse", "nrmse", "max_abs", "per_file"} <= set(doc["after"])
    code, stdout, stderr = run_cli("evaluate", tmp_path / "nowhere", *new)
    assert code == 2 and stderr.count("\n") == 1 and "esmm: error:" in stderr


@pytest.mark.slow
def test_vhb_fit_on_fast_rate_predicts_slow_rate(shared_data, tmp_path):
    folder = shared_data / "tensile" / "vhb4910_raw"
    train = [read(folder / n) for n in ("lu_0d05_2d0.csv", "lu_0d05_3d0.csv")]
    discover_and_save(train, out_dir=tmp_path / "fit", model="esedf", max_points=250)
    ev = evaluate(tmp_path / "fit", [read(folder / "lu_0d01_2d0.csv")])
    assert ev.after.nrmse < 0.5 * ev.before.nrmse
    assert np.isfinite(ev.after.max_abs)


def test_discovered_elastic_law_predicts_a_new_file_from_discover_json_and_params_toml(tmp_path):
    """A strain-energy term kept by a discovery travels: the saved model and its params.toml
    (model "arruda-boyce+<term>") predict another tension-compression test."""
    truth = syn.Truth("arruda-boyce+mooney", {**BASE, "c2": 15e3})
    train = [read(p) for p in syn.write_set(tmp_path / "train", [syn.tension_compression(0.05, 0.8, 1.35)],
                                            truth, seed=2)]
    new = [read(p) for p in syn.write_set(tmp_path / "new", [syn.tension_compression(0.05, 0.85, 1.3)],
                                          truth, seed=9)]
    res = discover_and_save(train, out_dir=tmp_path / "fit", **FAST)
    assert len(res.kept) == 1 and family(res.kept) == {"I2 term"}  # which I2 term a stretch range favours
    assert res.final_model == f"arruda-boyce+{res.kept[0]}"
    ev = evaluate(tmp_path / "fit", new)
    assert ev.after.nrmse < 3 * NOISE and ev.after.nrmse < 0.5 * ev.before.nrmse
    assert evaluate(tmp_path / "fit" / "params.toml", new).after.nrmse < 3 * NOISE


def test_cli_evaluate_shows_the_readers_warnings(run_cli, tmp_path):
    """A derived stress column that disagrees with force / area is warned about by evaluate, as by calibrate."""
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.calibrate.report import write_outputs

    lam = np.linspace(1.0, 1.5, 20)
    p = 20e3 * (lam - lam**-2)
    fitted = tmp_path / "fitted.csv"
    fitted.write_text("stretch,stress [Pa]\n" + "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(lam, p)))
    write_outputs(tmp_path / "cal", fit_material([read(fitted)], model="arruda-boyce", n_starts=2), [read(fitted)])
    new = tmp_path / "new.csv"   # the machine's 'Tensile stress' used a 10 % smaller area
    new.write_text("# gauge_length: 30 mm\n# area: 20 mm2\nTime (s),Extension (mm),Load (N),Tensile stress (kPa)\n"
                   + "".join(f"{i},{(a - 1) * 30:.17g},{b * 20e-6:.17g},{b / 0.9e3:.17g}\n" for i, (a, b) in enumerate(zip(lam, p))))
    code, stdout, stderr = run_cli("evaluate", tmp_path / "cal", new)
    assert code == 0, stderr
    assert "'Tensile stress': the stress computed from the raw channels" in stderr
