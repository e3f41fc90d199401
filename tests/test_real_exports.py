"""Real exports that used to stop the run: built here as the files came, read and fitted.

* A compression ramp-hold on porcine muscle, Cauchy ("true") stress in kPa, tagged
  ``orientation: x``: one tested fibre direction made an anisotropic fit whose material
  had no value for the directional parameters (``parameter 'A1' ... is missing``).
* An Instron pull-to-failure export re-saved by a spreadsheet that wrote the time's
  decimals without their leading zeros (``40.9, 40.10, 40.11`` for 40.09, 40.10,
  40.11 s): the numbers go backwards though the record is whole.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.calibrate.fit import fit_material, predict
from esmm.pipeline.calibrate.problem import ParameterLayout
from esmm.pipeline.calibrate.report import how_read, params_toml
from esmm.pipeline.errors import InputError
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.material import load_material
from esmm.pipeline.tensile import read

KPA = 1e3


def _muscle_ramp_hold(folder: Path, *, sidecar: bool = False) -> tuple[Path, dict[str, np.ndarray]]:
    """Unconfined compression to stretch 0.75 at 1 %/s, a 60 s hold, 40 % relaxation (τ 15 s); Cauchy stress in kPa.

    Nominal stress of a neo-Hookean solid, P = μ(λ - λ⁻²), relaxed by one Prony term (the
    exact recursion for a piecewise-linear history), written as σ = λP in kPa.
    """
    dt = 0.1
    t = np.round(np.arange(0.0, 85.0 + 1e-9, dt), 6)
    lam = np.where(t <= 25.0, 1.0 - 0.01 * t, 0.75)
    p_el = 3.0e3 * (lam - lam**-2)
    g, tau = 0.4, 15.0
    p, h = p_el.copy(), 0.0
    for k in range(1, t.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau)
        h = a * h + (1.0 - a) * tau / (t[k] - t[k - 1]) * (p_el[k] - p_el[k - 1])
        p[k] = (1.0 - g) * p_el[k] + g * h
    sigma_kpa = np.round(p * lam / KPA, 6)
    path = folder / "muscle_compression_x.csv"
    head = "# specimen: porcine-muscle-3\n# tissue: porcine skeletal muscle\n"
    head += "" if sidecar else "# orientation: x\n"
    rows = "\n".join(f"{a:.1f},{b:.5f},{c:.6f}" for a, b, c in zip(t, lam, sigma_kpa))
    path.write_text(head + "Time (s),Stretch,True Stress (kPa)\n" + rows + "\n", encoding="utf-8")
    if sidecar:
        path.with_suffix(".toml").write_text('orientation = "x"\n', encoding="utf-8")
    return path, {"time": t, "lam": np.round(lam, 5), "sigma": sigma_kpa * KPA}


@pytest.mark.parametrize("sidecar", [False, True])
def test_cauchy_compression_with_one_orientation_reads_and_fits(tmp_path, sidecar):
    path, truth = _muscle_ramp_hold(tmp_path, sidecar=sidecar)
    test = read(path)
    assert test.orientation == "x" and test.mode == "uniaxial"
    np.testing.assert_array_equal(test.stretch, truth["lam"])
    # P = sigma / lambda under incompressibility, and the reading says so
    np.testing.assert_allclose(test.stress, truth["sigma"] / truth["lam"], rtol=1e-12)
    assert "true stress / stretch" in how_read(test)["stress_from"]
    res = fit_material([test], model="esedf", n_starts=2)
    assert res.directions is not None and set(res.directions) == {"x", "y", "z"}
    # the material as a whole is complete: its directional parameters are those of the tested direction
    for name in ("A1", "A2"):
        assert res.params[name] == res.directions["x"][name] == res.directions["y"][name]
    (tmp_path / "params.toml").write_text(params_toml(res, [test]), encoding="utf-8")
    mat = load_material(tmp_path / "params.toml")
    assert set(mat.params) == set(get_model("esedf").parameter_names)
    assert np.all(np.isfinite(predict(res, test)))
    assert any("no data for fibre direction(s) y, z" in w for w in res.warnings)


def test_the_material_of_an_anisotropic_fit_holds_the_mean_of_its_directions():
    model = get_model("esedf")
    layout = ParameterLayout(model, fixed={}, directions=["x", "y"])
    z = layout.from_params({**model.defaults(), "A1": 2e6, "A2": 4e8})
    z[[i for i, s in enumerate(layout.slots) if s.key == "A1[y]"]] = math.log(6e6)
    per_dir = layout.to_params(z)
    assert per_dir["x"]["A1"] == pytest.approx(2e6) and per_dir["y"]["A1"] == pytest.approx(6e6)
    assert per_dir[None]["A1"] == pytest.approx(4e6)  # the mean of the fitted directions
    assert per_dir[None]["A2"] == pytest.approx(4e8)
    assert set(per_dir[None]) == set(model.parameter_names)
    iso = ParameterLayout(model, fixed={}, directions=None)
    assert set(iso.to_params(iso.from_params(model.defaults()))) == {None}


def _spreadsheet_time(src: Path, out: Path) -> np.ndarray:
    """*src* re-saved with its time's hundredths written as an integer (0.09 -> "0.9", 0.10 -> "0.10").

    Returns the times as meant (the two-decimal numbers such an export stands for).
    """
    lines = src.read_text(encoding="utf-8").splitlines()
    header = next(i for i, ln in enumerate(lines) if ln.startswith("Extension,"))
    t_col = next(csv.reader([lines[header]])).index("Time")
    rows, meant = [], []
    for ln in lines[header + 2:]:
        cells = next(csv.reader([ln]))
        hundredths = round(float(cells[t_col]) * 100)
        cells[t_col] = f"{hundredths // 100}.{hundredths % 100}"
        meant.append(float(f"{hundredths // 100}.{hundredths % 100:02d}"))
        rows.append(",".join(cells))
    out.write_text("\n".join(lines[:header + 2] + rows) + "\n", encoding="utf-8")
    return np.array(meant)


def test_time_written_without_its_decimals_leading_zeros_is_repaired(tmp_path, bundled_data):
    src = bundled_data / "tensile" / "tendon_instron" / "failure_incubated_1.csv"
    path = tmp_path / "failure_spreadsheet.csv"
    meant = _spreadsheet_time(src, path)
    text = path.read_text(encoding="utf-8")
    assert ",0.9," in text and ",0.10," in text  # the pattern of the issue: 0.9 stands for 0.09
    test = read(path)
    orig = read(src)
    np.testing.assert_array_equal(test.time, meant - meant[0])
    np.testing.assert_array_equal(test.stretch, orig.stretch)
    np.testing.assert_array_equal(test.stress, orig.stress)
    notes = [w for w in test.metadata["warnings"] if "time repaired" in w]
    assert len(notes) == 1 and "0.1 on line" in notes[0] and "read as 0.01" in notes[0]
    assert np.all(np.diff(test.time) > 0)


def test_time_that_really_goes_backwards_is_still_refused(tmp_path, bundled_data):
    src = bundled_data / "tensile" / "tendon_instron" / "failure_incubated_1.csv"
    path = tmp_path / "joined.csv"
    _spreadsheet_time(src, path)
    lines = path.read_text(encoding="utf-8").splitlines()
    header = next(i for i, ln in enumerate(lines) if ln.startswith("Extension,"))
    data = lines[header + 2:]
    # two records joined: the second starts its clock again
    path.write_text("\n".join(lines[:header + 2] + data[:600] + data[:600]) + "\n", encoding="utf-8")
    with pytest.raises(InputError, match="time goes backwards") as exc:
        read(path)
    assert "\n" not in str(exc.value) and "split joined records" in str(exc.value)
    # the same with the decimals written in full: refused, nothing repaired
    plain = tmp_path / "joined_plain.csv"
    src_lines = src.read_text(encoding="utf-8").splitlines()
    src_data = src_lines[header + 2:]
    plain.write_text("\n".join(src_lines[:header + 2] + src_data[:600] + src_data[:600]) + "\n", encoding="utf-8")
    with pytest.raises(InputError, match="time goes backwards"):
        read(plain)


def test_a_time_column_with_a_step_back_and_short_decimals_is_not_repaired(tmp_path):
    """Short decimals alone do not license the repair: read as meant the time must run forward."""
    rows = ["Time (s),Stretch,Stress (kPa)"]
    times = ["0.0", "0.5", "0.10", "0.15", "0.12", "0.25"]  # 0.12 after 0.15: backwards in any reading
    rows += [f"{t},{1 + 0.01 * k:.2f},{0.5 * k:.1f}" for k, t in enumerate(times)]
    path = tmp_path / "back.csv"
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    with pytest.raises(InputError, match="time goes backwards"):
        read(path)


def test_calibrate_cli_reads_the_muscle_file_and_says_what_it_converted(tmp_path, run_cli):
    path, _ = _muscle_ramp_hold(tmp_path)
    code, out, err = run_cli("calibrate", path, "--out", tmp_path / "o", "--starts", "2")
    assert code == 0, err
    report = (tmp_path / "o" / "report.md").read_text(encoding="utf-8")
    assert "true stress column (nominal stress = true stress / stretch, incompressible)" in report
    assert "[material.directions.x]" in (tmp_path / "o" / "params.toml").read_text(encoding="utf-8")


@pytest.mark.slow
def test_discover_cli_reads_the_muscle_file_and_finds_its_relaxation(tmp_path, run_cli):
    path, _ = _muscle_ramp_hold(tmp_path)
    code, out, err = run_cli("calibrate", path, "--discover", "--out", tmp_path / "o")
    assert code == 0, err
    mat = load_material(tmp_path / "o" / "params.toml")
    assert mat.params["A1"] > 0 and mat.directions and "x" in mat.directions
    kept = json.loads((tmp_path / "o" / "discover.json").read_text(encoding="utf-8"))["effects"]
    assert "viscoelastic" in kept  # the hold's relaxation (40 %, τ 15 s in the file)
