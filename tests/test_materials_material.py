"""Material files: loading, validation messages, TOML round trip, directions."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest
from esmm.pipeline.config import load_toml
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.materials.material import Material, load_material

LIVER_SI = {"mu": 2.973, "N": 1.1074, "A1": 3.9106e6, "A2": 451.9193e6, "f": 0.0019}


def _write(tmp_path, body: str, name: str = "m.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(body), encoding="utf-8")
    return p


GOOD = """
    [material]
    model = "esedf"
    stress_unit = "kPa"
    [material.parameters]
    mu = 0.002973
    N = 1.1074
    A1 = "3.9106 MPa"
    A2 = 451919.3
    f = 0.0019
"""


def test_bundled_preset_in_si():
    mat = load_material("porcine_liver_paper")
    assert mat.model == "esedf" and mat.name == "porcine liver (ESMM paper)"
    for k, v in LIVER_SI.items():
        assert mat.params[k] == pytest.approx(v, rel=1e-15)
    assert mat.directions is None and mat.is_isotropic
    assert mat.metadata["reported"]["E"] == 0.67712
    assert mat.stress_unit == "MPa"


def test_units_strings_and_file_name(tmp_path):
    mat = load_material(_write(tmp_path, GOOD, "liver_kpa.toml"))
    for k, v in LIVER_SI.items():
        assert mat.params[k] == pytest.approx(v, rel=1e-14)
    assert mat.name == "liver_kpa" and mat.source.endswith("liver_kpa.toml")


def test_round_trip_with_directions(tmp_path):
    mat = Material(
        model="esedf", params=LIVER_SI,
        directions={"x": {"A1": 4.2e6}, "z": {"A1": 3.0e6, "A2": 4e8}},
        name='liver "fit" 2', source="fit of 3 tests", stress_unit="kPa",
        metadata={"reported": {"E": 0.5, "note": "x"}, "fit_rms": np.float64(0.031)},
    )
    text = mat.to_toml()
    assert "# [kPa]" in text and "[material.directions.z]" in text
    path = mat.save(tmp_path / "out" / "fit.toml")
    back = load_material(path)
    assert back.model == mat.model and back.name == mat.name and back.source == mat.source
    for k, v in mat.params.items():
        assert back.params[k] == pytest.approx(v, rel=1e-15)
    assert back.directions.keys() == {"x", "z"}
    assert back.directions["z"]["A2"] == pytest.approx(4e8, rel=1e-15)
    assert back.metadata == {"reported": {"E": 0.5, "note": "x"}, "fit_rms": 0.031}
    assert back.stress_unit == "kPa"
    # per-direction parameters and stiffness
    assert back.params_for("x")["A1"] == pytest.approx(4.2e6) and back.params_for("y") == back.params
    assert back.mu_e(1.2, "x") > back.mu_e(1.2, "y") > back.mu_e(1.2, "z")
    assert not back.is_isotropic
    # the bundled preset survives a round trip too
    liver = load_material("porcine_liver_paper")
    again = load_material(liver.save(tmp_path / "liver.toml"))
    assert np.allclose(again.mu_e(np.array([0.9, 1.0, 1.3])), liver.mu_e(np.array([0.9, 1.0, 1.3])),
                       rtol=1e-14)


BAD = [
    ("no_material", "[parameters]\nmu = 1\n", "no \\[material\\] table"),
    ("no_model", "[material]\nname = 'x'\n", "model is missing"),
    ("unknown_model", "[material]\nmodel = 'ogden'\n[material.parameters]\n", "unknown material model 'ogden'"),
    ("missing", GOOD.replace("    f = 0.0019\n", ""), "parameter 'f' of model 'esedf' is missing"),
    ("unknown", GOOD + "    k9 = 3\n", "unknown parameter 'k9'"),
    ("paper_b", GOOD + "    b = 5.2022\n", "'b' is not a parameter.*\\[material.reported\\]"),
    ("bounds", GOOD.replace("N = 1.1074", "N = 0.95"), "\\[material.parameters\\].*'N' = 0.95 is outside"),
    ("bare", GOOD.replace('    stress_unit = "kPa"\n', ""), "mu: 0.002973 is a bare number.*stress_unit"),
    ("bad_unit", GOOD.replace('"kPa"', '"psi"'), "stress_unit.*unknown stress unit 'psi'"),
    ("string_unit", GOOD.replace('"3.9106 MPa"', '"3.9106 mm"'), "A1.*unknown stress unit 'mm'"),
    ("not_number", GOOD.replace("f = 0.0019", "f = true"), "f: expected a number"),
    ("shared_dir", GOOD + "    [material.directions.x]\n    N = 2.0\n", "directions.x.*'N'.*shared"),
    ("bad_dir", GOOD + "    [material.directions.w]\n    A1 = 2.0\n", "unknown direction 'w'"),
    ("top_level", GOOD + "    [fit]\n    rms = 1\n", "unexpected top-level key or table 'fit'"),
]


@pytest.mark.parametrize("name,body,pattern", BAD, ids=[b[0] for b in BAD])
def test_validation_errors_are_one_line_with_file_and_key(tmp_path, name, body, pattern):
    p = _write(tmp_path, body, f"{name}.toml")
    with pytest.raises(ConfigError, match=pattern) as exc:
        load_material(p)
    msg = str(exc.value)
    assert "\n" not in msg and f"{name}.toml" in msg


def test_missing_file_and_unknown_preset(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_material(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="no materials preset named 'kidney'.*porcine_liver_paper"):
        load_material("kidney")


def test_material_constructor_validates():
    with pytest.raises(ConfigError, match="'N' = 1 is outside"):
        Material(model="arruda-boyce", params={"mu": 1e5, "N": 1.0})
    with pytest.raises(ConfigError, match="unknown direction 'q'"):
        Material(model="arruda-boyce", params={"mu": 1e5, "N": 5.0}, directions={"q": {"mu": 1.0}})
    with pytest.raises(ConfigError, match="'N'.*shared"):
        Material(model="arruda-boyce", params={"mu": 1e5, "N": 5.0}, directions={"x": {"N": 6.0}})
    # full per-direction sets (as a fitter produces them): equal shared values are dropped
    full = Material(model="arruda-boyce", params={"mu": 1e5, "N": 5.0},
                    directions={d: {"mu": 1e5 * (i + 1), "N": 5.0} for i, d in enumerate("xyz")})
    assert full.directions == {"x": {"mu": 1e5}, "y": {"mu": 2e5}, "z": {"mu": 3e5}}
    m = Material(model="Arruda_Boyce", params={"mu": 1e5, "N": 5.0}, directions={"y": {"mu": 2e5}})
    assert m.model == "arruda-boyce"
    assert m.youngs_modulus("y") == pytest.approx(2 * m.youngs_modulus(), rel=1e-14)
    with pytest.raises(ConfigError, match="unknown direction 'w'"):
        m.params_for("w")


def test_to_toml_is_valid_toml_with_unit_comments(tmp_path):
    text = load_material("porcine_liver_paper").to_toml()
    p = tmp_path / "x.toml"
    p.write_text(text)
    data = load_toml(p)
    assert data["material"]["parameters"]["A2"] == pytest.approx(451.9193, rel=1e-15)
    assert "mu = 2.973e-06  # [MPa]" in text
