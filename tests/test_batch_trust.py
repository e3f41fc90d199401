"""Batch statistics that mean something (usable fits, determined parameters), and discovery in batch."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import pytest
from esmm.pipeline.batch.discover import effect_counts, effect_parameters
from esmm.pipeline.batch.jobs import BatchSummary, JobOutcome
from esmm.pipeline.batch.tables import params_table


def _fit(name, level, mu, mu_det, n_val, n_det, ultimate=None, censored=0):
    stats = {k: {"mean": None, "sd": None, "n": 0} for k in ("ultimate_stress", "ultimate_stretch", "rupture_stretch",
                                                               "toe_end_stretch", "toe_modulus", "linear_modulus")}
    if ultimate is not None:
        stats["ultimate_stress"] = {"mean": ultimate, "sd": None, "n": 1}
    return JobOutcome(name, "calibrate", "done", summary={
        "estimates": [{"key": "mu", "value": mu, "kind": "stress", "identifiable": mu_det},
                      {"key": "N", "value": n_val, "kind": "dimensionless", "identifiable": n_det}],
        "rmse": 1.0, "nrmse": 0.01, "r2": 0.99, "noise_ratio": 1.0,
        "verdict": {"level": level, "text": f"{level}: because"},
        "failure": {"summary": {"failed": int(ultimate is not None), "censored": censored,
                                "censored_at": [5e6] if censored else [], "stats": stats}},
        "files": [f"{name}.csv"]})


def _rows(text: str) -> dict[str, dict[str, str]]:
    return {r["group"]: r for r in csv.DictReader(io.StringIO(text))}


def test_batch_statistics_skip_unusable_fits_and_undetermined_values(tmp_path):
    """The issue's mean row averaged parameters from 1e-7 to 6e10, some undetermined, of fits that were not
    usable. Now: usable fits only, determined values only, n per column, the unusable group listed."""
    s = BatchSummary(outcomes=[
        _fit("a", "good", 100e3, True, 10.0, True, ultimate=4e6),
        _fit("b", "poor", 300e3, True, 1e8, False, ultimate=6e6),      # N undetermined: not averaged
        _fit("c", "unusable", 6e10, True, 2.0, True, ultimate=9e9),    # unusable: nothing averaged
        _fit("d", "poor", 1e-7, False, 12.0, True, censored=1),        # mu undetermined; censored strength
        JobOutcome("e.csv", "calibrate", "failed", reason="e.csv: bad", summary={"unreadable": True}),
    ], out_dir=tmp_path)
    rows = _rows(params_table(s))
    assert rows["c"]["verdict"] == "unusable" and rows["c"]["reason"] == "unusable: because"
    assert rows["e.csv"]["status"] == "unreadable" and rows["e.csv"]["reason"] == "e.csv: bad"
    assert rows["b"]["N determined"] == "no" and rows["a"]["mu determined"] == "yes"
    assert float(rows["mean"]["mu [Pa]"]) == pytest.approx(200e3)             # a and b
    assert float(rows["sd"]["mu [Pa]"]) == pytest.approx(141421.356, rel=1e-6)
    assert rows["n"]["mu [Pa]"] == "2"
    assert float(rows["mean"]["N [1]"]) == pytest.approx(11.0) and rows["n"]["N [1]"] == "2"   # a and d
    assert float(rows["mean"]["ultimate stress [Pa]"]) == pytest.approx(5e6)  # a and b; d was censored
    assert rows["d"]["censored at [Pa]"] == "5000000"
    assert "c (unusable: because)" in rows["mean"]["status"]


def _disc(name, tissue, kept, params, testable=("viscoelastic", "mullins")):
    cands = {n: {"kind": "material", "kept": n in kept, "testable": n in testable}
             for n in ("viscoelastic", "mullins", "damage")}
    return JobOutcome(name, "discover", "done", summary={"effects": list(kept), "candidates": cands,
                                                          "parameters": params, "tissue": [tissue] if tissue else [],
                                                          "verdict": {"level": "good", "text": ""}})


def test_effects_are_counted_over_the_groups_that_could_show_them(tmp_path):
    tau = {"value": 2.0, "unit": "s", "not_identifiable": False}
    s = BatchSummary(outcomes=[
        _disc("s1", "tendon", ["viscoelastic"], {"viscoelastic.tau[0]": tau}),
        _disc("s2", "tendon", ["viscoelastic"], {"viscoelastic.tau[0]": {**tau, "value": 4.0}}),
        _disc("s3", "tendon", ["viscoelastic"], {"viscoelastic.tau[0]": {**tau, "value": 1e6,
                                                                         "not_identifiable": True}}),
        _disc("s4", "tendon", [], {"viscoelastic.tau[0]": {**tau, "value": 99.0}}, testable=("mullins",)),
        _disc("s5", "liver", ["mullins"], {}),
    ], out_dir=tmp_path)
    counts = {(r["tissue"], r["effect"]): r for r in effect_counts(s)}
    ve = counts[("tendon", "viscoelastic")]
    assert (ve["found"], ve["testable"], ve["groups"]) == (3, 3, 4)  # s4 could not show it: not counted against
    assert ve["fraction"] == 1.0 and ve["found_in"] == ["s1", "s2", "s3"]
    assert counts[("tendon", "damage")]["fraction"] is None          # never testable: no fraction
    assert counts[("liver", "mullins")]["found"] == 1
    (p,) = [r for r in effect_parameters(s) if r["tissue"] == "tendon"]
    assert (p["n"], p["undetermined"]) == (2, 1)                     # s3 undetermined, s4 did not keep it
    assert (p["median"], p["q1"], p["q3"]) == (3.0, 2.5, 3.5)


@pytest.mark.slow
def test_discovery_in_batch_one_per_group_and_the_summary_across(run_cli, bundled_data, tmp_path):
    """`esmm calibrate --discover --by specimen` (refused before): one discovery per specimen in its folder,
    and what the specimens of one tissue share."""
    src = bundled_data / "tensile" / "tendon_instron" / "relax_incubated_3_truncated.csv"
    data = tmp_path / "data"
    data.mkdir()
    for spec in ("r1", "r2"):
        shutil.copy(src, data / f"{spec}.csv")
        (data / f"{spec}.toml").write_text(f'specimen = "{spec}"\ntissue = "tendon"\n')
    out = tmp_path / "out"
    code, stdout, err = run_cli("calibrate", "--discover", "--by", "specimen", *sorted(data.glob("*.csv")),
                                "--out", out, "--scheduler", "serial", "--starts", "2")
    assert code == 0, err
    for spec in ("r1", "r2"):
        names = {p.name for p in (out / spec).iterdir()}
        assert {"discover.json", "discover.md", "params.toml", "report.html"} <= names
    groups = _rows((out / "summary.csv").read_text())
    assert groups["r1"]["effects found"] == groups["r2"]["effects found"]       # the same bytes, the same answer
    assert "viscoelastic" in groups["r1"]["effects found"]
    effects = {r["effect"]: r for r in csv.DictReader(io.StringIO((out / "effects.csv").read_text()))}
    ve = effects["viscoelastic"]
    assert (ve["tissue"], ve["found"], ve["fraction found [1]"]) == ("tendon", "2", "1")
    params = list(csv.DictReader(io.StringIO((out / "effect-parameters.csv").read_text())))
    tau = next(r for r in params if r["parameter"].startswith("viscoelastic.tau"))
    assert tau["unit"] == "s" and tau["q1 (25 %)"] == tau["q3 (75 %)"] == tau["median"]
    assert "viscoelastic: found in 2 of 2" in stdout
    assert Path(out / "report.html").is_file()


@pytest.mark.slow
def test_discovery_in_batch_on_a_dask_cluster(bundled_data, tmp_path):
    """The same jobs on a Dask cluster: each group's discovery in its folder, the tables across groups."""
    pytest.importorskip("distributed")
    import distributed
    from esmm.pipeline.batch.discover import discover_batch

    src = bundled_data / "tensile" / "tendon_instron" / "relax_incubated_3_truncated.csv"
    data = tmp_path / "r1.csv"
    shutil.copy(src, data)
    out = tmp_path / "out"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=50) as cluster:
        s = discover_batch([data], out_dir=out, options={"n_starts": 2}, scheduler=cluster.scheduler_address)
    assert s.exit_code == 0 and s.scheduler.startswith("dask ")
    (o,) = s.outcomes
    assert o.status == "done" and "viscoelastic" in o.summary["effects"]
    assert (out / "r1" / "discover.json").is_file() and (out / "r1" / "report.html").is_file()
    assert "viscoelastic" in (out / "effects.csv").read_text()
