"""Reading tensile-test files: real data sets, every format variant of the contract, precedence."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.errors import InputError
from esmm.pipeline.progress import ListReporter
from esmm.pipeline.tensile import MODES, NotATestError, TensileTest, read
from esmm.pipeline.tensile.columns import quantity_of

FIXTURES = Path(__file__).resolve().parent / "data" / "tensile"
MU = 20e3


def truth(n=21, lam_max=1.4):
    """The analytic truth of tests/data/tensile/make_fixtures.py."""
    half = (n + 1) // 2
    up = np.linspace(1.0, lam_max, half)
    lam = np.concatenate([up, up[-2::-1]])[:n]
    return 0.1 * np.arange(n), lam, MU * (lam - lam**-2)


def write(folder: Path, name: str, text: str, *, encoding="utf-8", sidecar: str | None = None,
          bom: bytes = b"") -> Path:
    p = folder / name
    p.write_bytes(bom + text.encode(encoding))
    if sidecar is not None:
        p.with_suffix(".toml").write_text(sidecar, encoding="utf-8")
    return p


def file_numbers(path: Path, encoding: str, skip: int) -> np.ndarray:
    """The numbers of a comma-separated file, parsed independently of the reader."""
    with open(path, encoding=encoding, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    return np.array([[float(c) for c in r] for r in rows[skip:]])


# ---------------------------------------------------------------------------
# real data: ../shared/data/tensile and the bundled copies in data/tensile


def _tensile_dirs(shared_data, bundled_data):
    return [shared_data / "tensile", bundled_data / "tensile"]


def _is_measurements_table(path: Path) -> bool:
    """foam_cyclic/*-measurements.csv: the specimens' widths, thicknesses and gauge lengths, not a test."""
    return path.stem.endswith("-measurements")


def test_every_shared_and_bundled_file_reads(shared_data, bundled_data):
    for root in _tensile_dirs(shared_data, bundled_data):
        files = sorted(f for f in root.rglob("*.csv") if not _is_measurements_table(f))
        # 8 brain + 3 Treloar + 11 VHB + 6 tendon + 8 foam at the time of writing
        assert len(files) >= 36, root
        for f in files:
            t = read(f)
            assert isinstance(t, TensileTest) and t.mode in MODES
            assert t.n >= 13 and np.all(np.isfinite(t.stretch)) and np.all(np.isfinite(t.stress))
            assert t.metadata["n_rows"] == t.n


def test_a_table_of_specimen_measurements_is_refused_in_one_line(shared_data):
    tables = sorted((shared_data / "tensile").rglob("*-measurements.csv"))
    assert tables
    for f in tables:
        with pytest.raises(NotATestError, match=r"unknown column names 'W', .*'G'.*not a test record") as ei:
            read(f)
        assert "\n" not in str(ei.value) and isinstance(ei.value, InputError)


def test_cli_skips_a_table_that_is_not_a_test_among_several(run_cli, shared_data, tmp_path):
    folder = shared_data / "tensile" / "foam_cyclic"
    files = [folder / "new-heel-tension-3_1.csv", folder / "new-heel-tension-measurements.csv"]
    code, stdout, stderr = run_cli("calibrate", *files, "--model", "arruda-boyce", "--starts", "1")
    assert code == 0, stderr
    assert "not a test record" in stderr and "skipped" in stderr
    code, _, stderr = run_cli("calibrate", files[1])
    assert code == 2 and "not a test record" in stderr


def test_instron_bluehill_export_reads_as_written(shared_data):
    """Geometry from the file's own header lines, the raw channels chosen among eight columns,
    and the machine's derived stress and strain columns used as a cross-check."""
    f = shared_data / "tensile" / "tendon_instron" / "relax_incubated_1.csv"
    t = read(f)
    md = t.metadata
    d, length = 0.376e-3, 12.02e-3   # 'Specimen properties : Diameter,"0.37600",mm' and Length
    assert md["diameter"] == pytest.approx(d) and md["gauge_length"] == pytest.approx(length)
    assert md["area"] == pytest.approx(math.pi * d * d / 4) and md["area_from"] == "diameter"
    assert md["sources"]["diameter"] == "comment" and md["specimen"] is None  # its label is empty
    assert md["extra"]["Test : Duration"] == "180.00000 s"
    assert md["raw"] and md["stretch_from"] == "displacement / gauge_length" and md["stress_from"] == "force / area"
    assert md["used_columns"]["displacement"]["header"] == "Extension"
    assert md["used_columns"]["force"]["header"] == "Load"
    assert any("'Tensile extension' not used" in n for n in md["column_notes"])
    # The machine's own 'Tensile stress' (MPa) agrees with force / (pi d^2 / 4) to its 5 printed digits.
    assert md["cross_checks"]["stress"]["header"] == "Tensile stress"
    assert md["cross_checks"]["stress"]["max_difference"] < 1e-4
    assert md["cross_checks"]["stretch"]["max_difference"] < 1e-3
    assert not md["warnings"]
    ref = file_numbers(f, "utf-8", skip=8)  # 6 header lines, the header, the units row (blank lines skipped)
    np.testing.assert_allclose(t.stress, ref[:, 1] / (math.pi * d * d / 4), rtol=1e-12)
    np.testing.assert_allclose(t.stretch, 1 + ref[:, 0] * 1e-3 / length, rtol=1e-12)
    assert t.time[-1] == pytest.approx(ref[-1, 3] - ref[0, 3])


def test_a_derived_column_that_disagrees_with_the_raw_channels_is_warned_about(tmp_path):
    text = ("Specimen properties : Width,\"2\",mm\nSpecimen properties : Thickness,\"1\",mm\n"
            "Specimen properties : Length,\"10\",mm\n\nTime,Extension,Load,Tensile stress\n"
            "(s),(mm),(N),(MPa)\n" + "".join(f"{i},{0.1 * i},{0.2 * i},{0.1 * i * 1.05}\n" for i in range(20)))
    rep = ListReporter()
    t = read(write(tmp_path, "x.csv", text), reporter=rep)
    assert t.metadata["area_from"] == "width x thickness" and t.metadata["raw"]
    assert t.metadata["cross_checks"]["stress"]["max_difference"] == pytest.approx(0.05 / 1.05)
    assert any("differs from this column by up to 4.8 %" in w for w in rep.warnings)


def test_true_stress_is_converted_to_nominal_stress(tmp_path):
    lam = np.linspace(1.0, 1.5, 11)
    p_nominal = 1e3 * (lam - lam ** -2)
    rows = "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(lam, p_nominal * lam / 1e3))
    t = read(write(tmp_path, "x.csv", "stretch,true stress [kPa]\n" + rows))
    np.testing.assert_allclose(t.stress, p_nominal, rtol=1e-12)
    assert t.metadata["stress_from"].startswith("true stress column (nominal stress = true stress / stretch")


def test_treloar_uniaxial_values(shared_data):
    f = shared_data / "tensile" / "treloar1944" / "uniaxial.csv"
    t = read(f)
    ref = file_numbers(f, "utf-8", skip=1)
    assert t.mode == "uniaxial" and not t.metadata["raw"]
    # The digitised file holds 24 points (data/README.md says 25), stretch 1.02 .. 7.6.
    assert t.n == len(ref) == 24
    assert t.stretch[0] == 1.02 and t.stretch.max() == 7.6
    np.testing.assert_allclose(t.stress, ref[:, 1] * 1e6, rtol=1e-15)
    assert t.metadata["specimen"] == "treloar1944-8pct-sulphur-rubber"
    assert t.metadata["temperature"] == "20 C"
    assert t.metadata["sources"]["mode"] == "comment"
    assert t.time is None and t.force is None and t.displacement is None


@pytest.mark.parametrize("name, mode, n", [("equibiaxial", "equibiaxial", 16), ("pure_shear", "pure_shear", 13)])
def test_treloar_other_modes(shared_data, name, mode, n):
    f = shared_data / "tensile" / "treloar1944" / f"{name}.csv"
    t = read(f)
    ref = file_numbers(f, "utf-8", skip=1)
    assert t.mode == mode and t.n == n
    np.testing.assert_allclose(t.stretch, ref[:, 0], rtol=1e-15)
    np.testing.assert_allclose(t.stress, ref[:, 1] * 1e6, rtol=1e-15)


def test_budday_brain(shared_data):
    root = shared_data / "tensile" / "budday2017_brain"
    regions = ("basal_ganglia", "corona_radiata", "corpus_callosum", "cortex")
    for region in regions:
        tc = read(root / f"{region}_tension_compression.csv")
        ref = file_numbers(root / f"{region}_tension_compression.csv", "utf-8", skip=1)
        assert tc.mode == "uniaxial" and tc.n == 33
        # tension and compression are both kept
        assert tc.stretch.min() == 0.9 and tc.stretch.max() == 1.1
        assert (tc.stretch < 1).sum() == 16 and (tc.stretch > 1).sum() == 16
        assert np.all(np.sign(tc.stress) == np.sign(tc.stretch - 1))
        np.testing.assert_allclose(tc.stress, ref[:, 1] * 1e3, rtol=1e-15)
        assert tc.metadata["specimen"] == f"budday2017-{region}"

        ss = read(root / f"{region}_simple_shear.csv")
        assert ss.mode == "simple_shear" and ss.n == 33
        gamma, tau = ss.stretch, ss.stress
        assert gamma.min() == -0.2 and gamma.max() == 0.2
        # the averaged shear curves are odd: tau(-gamma) = -tau(gamma)
        np.testing.assert_allclose(tau[::-1], -tau, atol=1e-12)
        assert ss.metadata["stretch_from"] == "shear strain column"


VHB = {  # file stem -> nominal maximum stretch, from the file name
    "lu_0d01_1d5": 1.5, "lu_0d01_2d0": 2.0, "lu_0d01_2d5": 2.5, "lu_0d01_3d0": 3.0,
    "lu_0d05_1d5_1": 1.5, "lu_0d05_1d5_2": 1.5, "lu_0d05_2d0": 2.0, "lu_0d05_2d5_1": 2.5,
    # lu_0d05_2d5_2: the name says 2.5, but its crosshead only reaches 80.2 mm (stretch 2.0)
    # in 40 s at 4 mm/s - the recording is a stretch-2.0 cycle.
    "lu_0d05_2d5_2": 2.0,
    "lu_0d05_3d0": 3.0, "relax_2d0": 2.0,
}


def test_vhb_raw_exports(shared_data):
    root = shared_data / "tensile" / "vhb4910_raw"
    assert {p.stem for p in root.glob("*.csv")} == set(VHB)
    for stem, lam_nominal in VHB.items():
        t = read(root / f"{stem}.csv")
        md = t.metadata
        assert md["raw"] and md["encoding"] == "gbk" and md["headers"] == ["时间", "位移", "力"]
        assert md["columns"] == ["time", "displacement", "force"] and md["units"] == ["s", "mm", "N"]
        assert md["gauge_length"] == pytest.approx(0.080) and md["area"] == pytest.approx(22e-6)
        assert md["sources"]["gauge_length"] == "sidecar" and md["units_row"] == md["header_row"] + 1
        # first sample at the gauge length (lu_0d05_1d5_1 starts at -0.0001 mm)
        assert t.stretch[0] == pytest.approx(1.0, abs=1.5e-6)
        assert t.stretch.max() == pytest.approx(lam_nominal, rel=5e-3)   # relax_2d0 overshoots to 2.009
        assert t.time[0] == 0.0 and np.all(np.diff(t.time) >= 0)
        # 50 Hz sampling
        assert np.median(np.diff(t.time)) == pytest.approx(0.02, rel=1e-9)
        np.testing.assert_allclose(t.stretch, 1 + t.displacement / 0.080, rtol=1e-15)
        np.testing.assert_allclose(t.stress, t.force / 22e-6, rtol=1e-15)


def test_vhb_values_match_the_bytes(shared_data):
    f = shared_data / "tensile" / "vhb4910_raw" / "lu_0d01_1d5.csv"
    t = read(f)
    raw = f.read_bytes().decode("gbk").splitlines()
    # line 1 is blank, 2 the header, 3 the units row; data from line 4
    assert t.metadata["header_row"] == 2 and t.metadata["first_data_row"] == 4
    second = [float(c.strip('"')) for c in raw[4].split(",")]   # "0.0200","0.0001","0.0036"
    assert second == [0.02, 0.0001, 0.0036]
    assert t.time[1] == pytest.approx(0.02, rel=1e-15)
    assert t.displacement[1] == pytest.approx(1e-7, rel=1e-12)
    assert t.stretch[1] == pytest.approx(1 + 0.0001 / 80, rel=1e-15)
    assert t.stress[1] == pytest.approx(0.0036 / 22e-6, rel=1e-12)
    assert t.n == t.metadata["last_data_row"] - 3 == 5006


def test_vhb_relaxation_holds(shared_data):
    t = read(shared_data / "tensile" / "vhb4910_raw" / "relax_2d0.csv")
    hold = t.time > 10.0
    assert t.time[-1] == pytest.approx(1804.04)
    assert np.ptp(t.stretch[hold]) < 0.02                      # held near stretch 2
    peak, end = t.stress.max(), t.stress[-1]
    assert end < 0.7 * peak                                    # relaxation is large


def test_bundled_copies_read_the_same(shared_data, bundled_data):
    for f in sorted(f for f in (shared_data / "tensile").rglob("*.csv") if not _is_measurements_table(f))[:: 3]:
        rel = f.relative_to(shared_data)
        a, b = read(f), read(bundled_data / rel)
        np.testing.assert_array_equal(a.stretch, b.stretch)
        np.testing.assert_array_equal(a.stress, b.stress)


# ---------------------------------------------------------------------------
# committed fixtures (tests/data/tensile, analytic truth)


def test_fixture_instron_like():
    t = read(FIXTURES / "instron_like.csv")
    _, lam, p = truth()
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-6)
    np.testing.assert_allclose(t.stress, p, rtol=1e-5, atol=1e-9)
    md = t.metadata
    assert md["stretch_from"].startswith("strain column") and md["stress_from"] == "stress column"
    assert not md["raw"] and md["headers"][3] == "Tensile strain" and md["units"][3] == "%"
    # raw channels with units are kept, in SI
    np.testing.assert_allclose(t.displacement, (lam - 1) * 25e-3, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(t.force, p * 12e-6, rtol=1e-5, atol=1e-12)


def test_fixture_zwick_semicolon_decimal_comma():
    t = read(FIXTURES / "zwick_de_semicolon.csv")
    tt, lam, p = truth()
    md = t.metadata
    assert md["delimiter"] == ";" and md["decimal"] == "," and md["encoding"] == "cp1252"
    assert md["gauge_length"] == pytest.approx(0.05) and md["area"] == pytest.approx(20e-6)
    assert md["area_from"] == "width x thickness" and md["specimen"] == "zwick-A1"
    assert md["orientation"] == "45 deg" and md["orientation_rad"] == pytest.approx(math.pi / 4)
    assert md["extra"] == {"Prüfer": "M. Muster"}
    assert md["sources"]["gauge_length"] == "comment" and md["sources"]["mode"] == "sidecar"
    np.testing.assert_allclose(t.time, tt, atol=1e-12)
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-6)
    np.testing.assert_allclose(t.stress, p, rtol=1e-5, atol=1e-6)


def test_fixture_gbk():
    t = read(FIXTURES / "gbk_raw.csv")
    _, lam, p = truth()
    assert t.metadata["headers"] == ["时间", "位移", "载荷"] and t.specimen == "gbk-1"
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-6)
    np.testing.assert_allclose(t.stress, p, rtol=1e-5, atol=1e-6)


def test_fixture_columns_by_position_ms_um_mn():
    t = read(FIXTURES / "no_header.csv")
    tt, lam, p = truth()
    assert t.metadata["header_row"] is None and t.metadata["delimiter"] == "\t"
    assert t.metadata["units"] == ["ms", "um", "mN"]
    np.testing.assert_allclose(t.time, tt, atol=1e-12)
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-6)
    np.testing.assert_allclose(t.stress, p, rtol=1e-5, atol=1e-6)


def test_fixture_bom_tab():
    t = read(FIXTURES / "processed_bom_tab.csv")
    _, lam, p = truth()
    assert t.metadata["encoding"] == "utf-8-sig" and t.metadata["sources"] == {"mode": "comment"}
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-6)
    np.testing.assert_allclose(t.stress, p, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------
# format variants, generated


LAM = [1.0, 1.1, 1.25, 1.5]
P_KPA = [0.0, 3.5, 8.25, 15.0]


@pytest.mark.parametrize(
    "header",
    [
        "stretch,nominal stress [kPa]",
        "Stretch,Nominal Stress (kPa)",
        "LAMBDA,Engineering stress [kPa]",
        "stretch ratio,Stress / kPa",
        "λ,stress{kPa}",
        "Stretch,Tensile stress [kPa]",
        "stretch,应力 (kPa)",
        "stretch,应力（kPa）",
        'Stretch,"Stress, kPa"',
    ],
)
def test_header_spellings(tmp_path, header):
    body = "\n".join(f"{a},{b}" for a, b in zip(LAM, P_KPA))
    t = read(write(tmp_path, "t.csv", f"{header}\n{body}\n"))
    np.testing.assert_allclose(t.stretch, LAM)
    np.testing.assert_allclose(t.stress, np.array(P_KPA) * 1e3)


def test_units_row_under_the_header(tmp_path):
    text = "Time,Extension,Load\n(s),(mm),(N)\n0,0,0\n1,2,0.5\n2,4,1.1\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "20 mm", "area": "10 mm2"})
    np.testing.assert_allclose(t.stretch, [1.0, 1.1, 1.2])
    np.testing.assert_allclose(t.stress, [0.0, 0.05e6, 0.11e6])
    np.testing.assert_allclose(t.time, [0, 1, 2])
    assert t.metadata["units_row"] == 2 and t.metadata["raw"]


def test_bare_units_row(tmp_path):
    t = read(write(tmp_path, "t.csv", "strain,stress\n%,MPa\n0,0\n10,0.2\n"))
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 0.2e6])


def test_quoted_values_and_spaces(tmp_path):
    text = '"stretch", "stress [Pa]"\n"1.0", "0"\n"1.2", "1500.5"\n'
    t = read(write(tmp_path, "t.csv", text))
    np.testing.assert_allclose(t.stress, [0.0, 1500.5])


def test_semicolon_decimal_comma(tmp_path):
    text = "time [s];displacement [mm];force [N]\n0,000;0,000;0,000\n0,125;1,50;0,031\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "30 mm", "area": "2 mm2"})
    assert t.metadata["decimal"] == ","
    np.testing.assert_allclose(t.time, [0, 0.125])
    np.testing.assert_allclose(t.stretch, [1.0, 1.05])
    np.testing.assert_allclose(t.stress, [0.0, 0.031 / 2e-6])


def test_comma_delimiter_with_quoted_decimal_commas(tmp_path):
    text = 'stretch,stress [kPa]\n"1,0","0,0"\n"1,5","2,25"\n'
    t = read(write(tmp_path, "t.csv", text))
    assert t.metadata["decimal"] == ","
    np.testing.assert_allclose(t.stretch, [1.0, 1.5])
    np.testing.assert_allclose(t.stress, [0.0, 2250.0])


def test_pipe_delimiter_and_blank_and_comment_lines(tmp_path):
    text = "\n\n# a note\nstretch|stress [kPa]\n\n1.0|0\n# paused\n1.2|4\n   \n1.4|9\n\n"
    t = read(write(tmp_path, "t.csv", text))
    np.testing.assert_allclose(t.stretch, [1.0, 1.2, 1.4])
    assert t.metadata["first_data_row"] == 6 and t.metadata["last_data_row"] == 10


def test_preamble_text_lines_before_header(tmp_path):
    text = "Test report\nOperator,Ann\nstretch,stress [kPa]\n1.0,0\n1.3,5\n"
    t = read(write(tmp_path, "t.csv", text))
    assert t.metadata["header_row"] == 3
    np.testing.assert_allclose(t.stress, [0, 5e3])


def test_excel_sep_line(tmp_path):
    t = read(write(tmp_path, "t.csv", "sep=;\nstretch;stress [kPa]\n1,0;0\n1,5;2,5\n"))
    assert t.metadata["header_row"] == 2 and t.metadata["delimiter"] == ";"
    np.testing.assert_allclose(t.stress, [0.0, 2500.0])


def test_trailing_delimiter(tmp_path):
    t = read(write(tmp_path, "t.csv", "stretch,stress [kPa],\n1.0,0,\n1.3,5,\n"))
    np.testing.assert_allclose(t.stretch, [1.0, 1.3])


def test_utf8_bom_and_crlf(tmp_path):
    p = tmp_path / "t.csv"
    p.write_bytes(b"\xef\xbb\xbfstretch,stress [kPa]\r\n1.0,0\r\n1.3,5\r\n")
    t = read(p)
    assert t.metadata["headers"] == ["stretch", "stress"]


def test_utf16_with_bom(tmp_path):
    p = tmp_path / "t.csv"
    p.write_bytes("stretch\tstress [kPa]\r\n1.0\t0\r\n1.3\t5\r\n".encode("utf-16"))
    t = read(p)
    assert t.metadata["encoding"] == "utf-16"
    np.testing.assert_allclose(t.stress, [0, 5e3])


def test_gbk_with_encoding_argument_and_comment(tmp_path):
    text = "时间,位移,力\n(s),(mm),(N)\n0,0,0\n1,8,2\n"
    p = write(tmp_path, "t.csv", text, encoding="gbk")
    t = read(p, encoding="gbk", overrides={"gauge_length": "80 mm", "area": "20 mm2"})
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 1e5])
    # a '# encoding:' first line does the same
    p2 = write(tmp_path, "u.csv", "# encoding: gbk\n# gauge_length: 80 mm\n# area: 20 mm2\n" + text,
               encoding="gbk")
    assert read(p2).metadata["encoding"] == "gbk"


def test_percent_strain_and_stress_units(tmp_path):
    for unit, fac in (("Pa", 1.0), ("kPa", 1e3), ("MPa", 1e6), ("N/mm2", 1e6), ("psi", 6894.757293168361)):
        t = read(write(tmp_path, f"t_{unit.replace('/', '')}.csv", f"Strain [%],Stress [{unit}]\n0,0\n25,2\n"))
        np.testing.assert_allclose(t.stretch, [1.0, 1.25])
        np.testing.assert_allclose(t.stress, [0.0, 2 * fac], rtol=1e-12)


@pytest.mark.parametrize("tunit, tf", [("s", 1.0), ("ms", 1e-3), ("min", 60.0)])
@pytest.mark.parametrize("dunit, df", [("mm", 1e-3), ("m", 1.0), ("um", 1e-6), ("µm", 1e-6)])
@pytest.mark.parametrize("funit, ff", [("N", 1.0), ("mN", 1e-3), ("kN", 1e3)])
def test_raw_unit_combinations(tmp_path, tunit, tf, dunit, df, funit, ff):
    L, A = 0.02, 5e-6
    d_si = np.array([0.0, 0.002, 0.004])
    f_si = np.array([0.0, 0.3, 0.7])
    rows = [f"{i * 2.0 / tf!r},{float(d / df)!r},{float(f / ff)!r}" for i, (d, f) in enumerate(zip(d_si, f_si))]
    text = f"Time ({tunit}),Displacement ({dunit}),Force ({funit})\n" + "\n".join(rows) + "\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "20 mm", "area": "5 mm2"})
    np.testing.assert_allclose(t.time, [0.0, 2.0, 4.0], rtol=1e-12)
    np.testing.assert_allclose(t.displacement, d_si, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(t.stretch, 1 + d_si / L, rtol=1e-12)
    np.testing.assert_allclose(t.stress, f_si / A, rtol=1e-12)


def test_machine_header_variants(tmp_path):
    text = ("Time (s),Crosshead (mm),Standard force (kN),Cycle count\n"
            "0,0,0,1\n1,1,0.001,1\n2,2,0.0025,1\n")
    rep = ListReporter()
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "10 mm", "width": "5 mm",
                                                          "thickness": "2 mm"}, reporter=rep)
    np.testing.assert_allclose(t.stretch, [1.0, 1.1, 1.2])
    np.testing.assert_allclose(t.stress, [0.0, 1e5, 2.5e5])
    assert t.metadata["columns"] == ["time", "displacement", "force", "ignore"]
    assert any("Cycle count" in w and "ignored" in w for w in rep.warnings)


def test_bluehill_qualifiers_and_quoted_units_row(tmp_path):
    text = ('"Time","Extension","Load","Tensile strain (Extension)","Tensile stress"\r\n'
            '"(s)","(mm)","(N)","(%)","(MPa)"\r\n"0.0","0.0","0.0","0.0","0.0"\r\n"1.0","2.0","5.0","10.0","0.5"\r\n')
    t = read(write(tmp_path, "t.csv", text))
    assert t.metadata["headers"][3] == "Tensile strain" and t.metadata["units"][3] == "%"
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 0.5e6])


def test_mts_like_tab_export_with_unit_words(tmp_path):
    text = "Test data\nRunning Time sec\tAxial Displacement mm\tAxial Force kN\n0\t0\t0\n1\t1.5\t0.02\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "15 mm", "area": "40 mm2"})
    assert t.metadata["preamble"] == ["Test data"]
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 0.02e3 / 40e-6])


def test_channel_numbers_and_abbreviations_in_names(tmp_path):
    """Data-acquisition software names a channel by its number before or after the quantity."""
    text = "Time (s),Ch 1 Displ. (mm),Force Ch2 (N)\n0,0,0\n1,1.5,0.02\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "15 mm", "area": "40 mm2"})
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 0.02 / 40e-6])
    assert [quantity_of(n) for n in ("Load 1", "Ch 2 Load", "Force Chan 3", "Extension 2")] == [
        "force", "force", "force", "displacement"]


def test_german_headers_slash_units(tmp_path):
    text = "Zeit / s;Weg / mm;Kraft / N\n0;0;0\n1;5;10\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "50 mm", "area": "10 mm2"})
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    np.testing.assert_allclose(t.stress, [0.0, 1e6])


def test_absolute_position_is_taken_from_the_first_sample(tmp_path):
    text = "time [s],position [mm],force [N]\n0,152.0,0\n1,155.0,1\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "30 mm", "area": "1 mm2"})
    np.testing.assert_allclose(t.stretch, [1.0, 1.1])
    assert t.metadata["displacement_start"] == pytest.approx(0.152)
    # an "extension" column is already relative to the gauge length: no shift
    text = "time [s],extension [mm],force [N]\n0,3.0,0\n1,6.0,1\n"
    t = read(write(tmp_path, "u.csv", text), overrides={"gauge_length": "30 mm", "area": "1 mm2"})
    np.testing.assert_allclose(t.stretch, [1.1, 1.2])


def test_true_strain_becomes_stretch(tmp_path):
    t = read(write(tmp_path, "t.csv", "true strain,nominal stress [Pa]\n0,0\n0.5,10\n"))
    np.testing.assert_allclose(t.stretch, [1.0, math.exp(0.5)])


def test_time_is_measured_from_the_first_sample_and_may_repeat(tmp_path):
    t = read(write(tmp_path, "t.csv", "t [s],stretch,stress [kPa]\n5,1,0\n5,1.1,1\n6,1.2,2\n"))
    np.testing.assert_allclose(t.time, [0, 0, 1])
    assert t.metadata["time_start"] == 5.0


def test_processed_prefers_processed_columns_over_raw(tmp_path):
    text = "time [s],extension [mm],load [N],stretch,stress [kPa]\n0,0,0,1,0\n1,1,1,1.5,7\n"
    t = read(write(tmp_path, "t.csv", text))  # no geometry needed: processed columns exist
    np.testing.assert_allclose(t.stretch, [1, 1.5])
    np.testing.assert_allclose(t.stress, [0, 7e3])
    assert not t.metadata["raw"]


def test_compression_and_tension_in_one_file(tmp_path):
    text = "time [s],displacement [mm],force [N]\n0,-2,-3\n1,0,0\n2,2,1\n"
    t = read(write(tmp_path, "t.csv", text), overrides={"gauge_length": "20 mm", "area": "10 mm2"})
    np.testing.assert_allclose(t.stretch, [0.9, 1.0, 1.1])
    np.testing.assert_allclose(t.stress, [-3e5, 0, 1e5])
    assert t.mode == "uniaxial"


@pytest.mark.parametrize("given, mode", [("uniaxial", "uniaxial"), ("Tension", "uniaxial"),
                                         ("equibiaxial", "equibiaxial"), ("pure shear", "pure_shear"),
                                         ("planar tension", "pure_shear"), ("simple-shear", "simple_shear")])
def test_modes(tmp_path, given, mode):
    if mode == "simple_shear":
        text = "shear strain,shear stress [kPa]\n0.0,0\n0.1,1\n"
    else:
        text = "stretch,stress [kPa]\n1.0,0\n1.1,1\n"
    t = read(write(tmp_path, "t.csv", f"# mode: {given}\n{text}"))
    assert t.mode == mode


def test_simple_shear_inferred_from_columns(tmp_path):
    t = read(write(tmp_path, "t.csv", "gamma,shear stress [kPa]\n-0.1,-1\n0,0\n0.1,1\n"))
    assert t.mode == "simple_shear" and t.metadata["mode_from"] == "columns"
    np.testing.assert_allclose(t.stretch, [-0.1, 0, 0.1])


def test_raw_simple_shear(tmp_path):
    text = "time [s],displacement [mm],force [N]\n0,0,0\n1,0.5,2\n"
    t = read(write(tmp_path, "t.csv", text),
             overrides={"mode": "simple_shear", "gauge_length": "5 mm", "area": "100 mm2"})
    np.testing.assert_allclose(t.stretch, [0.0, 0.1])     # gamma = u / h
    np.testing.assert_allclose(t.stress, [0.0, 2e4])      # tau = F / A


@pytest.mark.parametrize("given, text, rad", [("x", "x", None), ("Y", "y", None), ("30 deg", "30 deg", math.pi / 6),
                                              ("90°", "90 deg", math.pi / 2), ("0.5 rad", "0.5 rad", 0.5)])
def test_orientation(tmp_path, given, text, rad):
    t = read(write(tmp_path, "t.csv", "stretch,stress [kPa]\n1,0\n1.1,1\n"), overrides={"orientation": given})
    assert t.orientation == text
    assert t.metadata["orientation_rad"] == (None if rad is None else pytest.approx(rad))


def test_text_in_unused_column_is_ignored(tmp_path):
    text = "stretch,stress [kPa],comment\n1,0,start\n1.1,1,\n1.2,2,n/a\n"
    t = read(write(tmp_path, "t.csv", text))
    assert t.n == 3


def test_twenty_thousand_rows(tmp_path):
    n = 20_000
    tt = np.arange(n) * 0.02
    d = 40 * np.sin(np.linspace(0, np.pi, n))
    f = 0.5 * d / 40
    rows = "\r\n".join(f'"{a:.4f}","{b:.4f}","{c:.4f}"' for a, b, c in zip(tt, d, f))
    p = write(tmp_path, "big.csv", "\r\n时间,位移,力\r\n(s),(mm),(N)\r\n" + rows + "\r\n\r\n", encoding="gbk",
              sidecar='encoding = "gbk"\ngauge_length = "80 mm"\narea = "22 mm2"\n')
    t = read(p)
    assert t.n == n
    np.testing.assert_allclose(t.stretch, 1 + np.round(d, 4) / 80, rtol=1e-12)


# ---------------------------------------------------------------------------
# precedence: comment < sidecar < command line


def test_precedence_of_metadata_sources(tmp_path):
    text = ("# gauge_length: 10 mm\n# area: 1 mm2\n# specimen: from-comment\n# tissue: liver\n"
            "time [s],displacement [mm],force [N]\n0,0,0\n1,1,1\n")
    p = write(tmp_path, "t.csv", text)
    t = read(p)
    assert t.stretch[1] == pytest.approx(1.1) and t.stress[1] == pytest.approx(1e6)
    assert t.metadata["sources"]["gauge_length"] == "comment"

    p.with_suffix(".toml").write_text('gauge_length = "20 mm"\nspecimen = "from-sidecar"\n')
    t = read(p)
    assert t.stretch[1] == pytest.approx(1.05) and t.stress[1] == pytest.approx(1e6)
    assert t.specimen == "from-sidecar" and t.metadata["tissue"] == "liver"
    assert t.metadata["sources"] == {"gauge_length": "sidecar", "area": "comment", "specimen": "sidecar",
                                     "tissue": "comment"}
    assert t.metadata["sidecar"] == str(p.with_suffix(".toml"))

    t = read(p, overrides={"gauge_length": "50 mm", "area": "2 mm2", "specimen": None})
    assert t.stretch[1] == pytest.approx(1.02) and t.stress[1] == pytest.approx(5e5)
    assert t.metadata["sources"]["gauge_length"] == "override" and t.specimen == "from-sidecar"


def test_area_from_higher_source_and_width_thickness(tmp_path):
    text = "# width: 10 mm\n# thickness: 2 mm\ntime [s],displacement [mm],force [N]\n0,0,0\n1,1,1\n"
    p = write(tmp_path, "t.csv", text, sidecar='gauge_length = "10 mm"\n')
    assert read(p).metadata["area"] == pytest.approx(20e-6)
    # a consistent area (within 1 %) is accepted alongside width x thickness
    assert read(p, overrides={"area": "20.1 mm2"}).metadata["area"] == pytest.approx(20.1e-6)


def test_sidecar_units_replace_file_units_with_a_warning(tmp_path):
    p = write(tmp_path, "t.csv", "stretch,stress [kPa]\n1,0\n1.1,1\n", sidecar='units = ["", "MPa"]\n')
    rep = ListReporter()
    t = read(p, reporter=rep)
    np.testing.assert_allclose(t.stress, [0, 1e6])
    assert len(rep.warnings) == 1 and "'kPa'" in rep.warnings[0] and "'MPa'" in rep.warnings[0]


def test_overrides_columns_as_text_and_encoding_precedence(tmp_path):
    p = write(tmp_path, "t.csv", "1,0\n1.1,2\n", encoding="utf-8")
    t = read(p, overrides={"columns": "stretch, stress", "units": ["-", "kPa"]})
    np.testing.assert_allclose(t.stress, [0, 2e3])
    # the sidecar's encoding is overridden by the command line, and that by the argument
    p.with_suffix(".toml").write_text('encoding = "latin-1"\ncolumns = ["stretch", "stress"]\nunits = ["", "Pa"]\n')
    assert read(p).metadata["encoding"] == "iso8859-1"
    assert read(p, overrides={"encoding": "utf-8"}).metadata["encoding"] == "utf-8"
    assert read(p, overrides={"encoding": "cp1252"}, encoding="utf-8").metadata["encoding"] == "utf-8"


def test_metadata_keys_are_present_and_si(tmp_path):
    p = write(tmp_path, "t.csv", "stretch,stress [kPa]\n1,0\n1.1,1\n",
              sidecar='gauge_length = "3 cm"\nnotes = "n"\ntemperature = 37\n')
    md = read(p).metadata
    for key in ("specimen", "gauge_length", "area", "orientation", "tissue", "temperature", "notes", "mode",
                "encoding", "columns", "units", "raw", "n_rows", "header_row"):
        assert key in md
    assert md["gauge_length"] == pytest.approx(0.03) and md["temperature"] == "37"


def test_message_lines_are_single(tmp_path):
    # every message the reader produced above and below is one line; spot-check the step report
    rep = ListReporter()
    read(FIXTURES / "instron_like.csv", reporter=rep)
    assert len(rep.steps) == 1 and "\n" not in rep.steps[0] and re.search(r"21 rows", rep.steps[0])


# ---------------------------------------------------------------------------
# round trip over random combinations of the format variants (hypothesis)

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_NAMES = {
    "utf-8": {"time": ["Time", "t", "elapsed time"], "displacement": ["Extension", "Crosshead", "displacement"],
              "force": ["Load", "Standard force", "force"], "stretch": ["stretch", "Lambda"],
              "strain": ["Strain", "Tensile strain"], "stress": ["Stress", "Nominal stress", "engineering stress"]},
    "gbk": {"time": ["时间"], "displacement": ["位移"], "force": ["力", "载荷"], "stretch": ["拉伸比"],
            "strain": ["应变"], "stress": ["应力"]},
    "cp1252": {"time": ["Zeit", "Prüfzeit"], "displacement": ["Standardweg", "Verlängerung"],
               "force": ["Standardkraft", "Kraft"], "stretch": ["stretch"], "strain": ["Dehnung"],
               "stress": ["Spannung"]},
}
_UNITS = {"time": {"s": 1.0, "ms": 1e-3, "min": 60.0}, "displacement": {"mm": 1e-3, "m": 1.0, "um": 1e-6},
          "force": {"N": 1.0, "mN": 1e-3, "kN": 1e3}, "stress": {"Pa": 1.0, "kPa": 1e3, "MPa": 1e6},
          "strain": {"%": 1e-2, "-": 1.0}, "stretch": {"-": 1.0}}


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_round_trip_of_random_format_variants(data):
    import tempfile

    d = data.draw
    n = d(st.integers(2, 25))
    kind = d(st.sampled_from(["raw", "stretch", "strain"]))
    enc = d(st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "gbk", "cp1252"]))
    names_enc = "gbk" if enc == "gbk" else "cp1252" if enc == "cp1252" else "utf-8"
    delim = d(st.sampled_from([",", ";", "\t", "|"]))
    quote = d(st.booleans())
    decimal = d(st.sampled_from([".", ","])) if (delim != "," or quote) else "."
    style = d(st.sampled_from(["brackets", "parens", "row", "slash", "sidecar"]))
    eol = d(st.sampled_from(["\n", "\r\n"]))
    geometry_in = d(st.sampled_from(["comment", "sidecar", "override"]))

    L, A = 0.025, 8e-6
    t_si = np.arange(n) * 0.05
    lam = 1 + 0.8 * np.sin(np.linspace(0, np.pi, n)) ** 2
    p_si = MU * (lam - lam**-2)
    qs = ["time", "displacement", "force"] if kind == "raw" else ["time", kind, "stress"]
    units = [d(st.sampled_from(sorted(_UNITS[q]))) for q in qs]
    names = [d(st.sampled_from(_NAMES[names_enc][q])) for q in qs]
    si = {"time": t_si, "displacement": (lam - 1) * L, "force": p_si * A, "stretch": lam,
          "strain": lam - 1, "stress": p_si}

    def fmt(x: float) -> str:
        s = repr(float(x))
        s = s.replace(".", ",") if decimal == "," else s
        return f'"{s}"' if quote else s

    if style == "brackets":
        header = [f"{nm} [{u}]" for nm, u in zip(names, units)]
    elif style == "parens":
        header = [f"{nm} ({u})" for nm, u in zip(names, units)]
    elif style == "slash":
        header = [f"{nm} / {u}" for nm, u in zip(names, units)]
    else:
        header = list(names)
    lines = []
    side: list[str] = []
    geo = {"gauge_length": "25 mm", "area": "8 mm2"}
    if geometry_in == "comment":
        lines += [f"# {k}: {v}" for k, v in geo.items()]
    elif geometry_in == "sidecar":
        side += [f'{k} = "{v}"' for k, v in geo.items()]
    lines.append(delim.join(header))
    if style == "row":
        lines.append(delim.join(f"({u})" for u in units))
    if style == "sidecar":
        side.append("units = [" + ", ".join(f'"{u}"' for u in units) + "]")
    for i in range(n):
        lines.append(delim.join(fmt(si[q][i] / _UNITS[q][u]) for q, u in zip(qs, units)))
    if enc in ("gbk", "cp1252"):
        side.append(f'encoding = "{enc}"')
    text = eol.join(lines) + eol
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "t.csv"
        p.write_bytes(text.encode(enc))
        if side:
            p.with_suffix(".toml").write_text("\n".join(side) + "\n", encoding="utf-8")
        t = read(p, overrides=geo if geometry_in == "override" else None)
    assert t.n == n and t.mode == "uniaxial"
    assert t.metadata["delimiter"] == delim and t.metadata["decimal"] == decimal
    np.testing.assert_allclose(t.time, t_si, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(t.stretch, lam, rtol=1e-12)
    np.testing.assert_allclose(t.stress, p_si, rtol=1e-12, atol=1e-9)
    assert t.metadata["raw"] == (kind == "raw")


def test_units_compared_by_meaning_not_spelling(tmp_path):
    # header 'kPa', units row 'KPA': the same unit, no conflict; sidecar '-' vs none: no warning
    p = write(tmp_path, "t.csv", "stretch,stress [kPa]\n(),(KPA)\n1,0\n1.1,1\n", sidecar='units = ["-", "kpa"]\n')
    rep = ListReporter()
    t = read(p, reporter=rep)
    np.testing.assert_allclose(t.stress, [0, 1e3])
    assert rep.warnings == []


def test_no_header_with_trailing_delimiter(tmp_path):
    p = write(tmp_path, "t.csv", "1,0,\n1.1,1,\n", sidecar='columns = ["stretch", "stress"]\nunits = ["", "Pa"]\n')
    np.testing.assert_allclose(read(p).stress, [0, 1])


# ---------------------------------------------------------------------------
# exports of other labs' machines (adversarial review: cases that were misread or refused)


def test_a_label_and_a_number_in_the_preamble_is_not_the_first_data_row(tmp_path):
    """Bluehill's numeric specimen label, a Shimadzu 'Batch,1' line: text then a number, above the header."""
    rows = "".join(f'"{i}","{0.3 * i}","{0.02 * i}"\r\n' for i in range(5))
    bluehill = ('Specimen properties : Specimen label,"1"\r\nSpecimen properties : Length,"30.00000",mm\r\n'
                'Specimen properties : Width,"10.00000",mm\r\nSpecimen properties : Thickness,"2.00000",mm\r\n\r\n'
                "Time,Extension,Load\r\n(s),(mm),(N)\r\n" + rows)
    t = read(write(tmp_path, "b.csv", bluehill))
    assert t.metadata["specimen"] == "1" and t.metadata["header_row"] == 6
    np.testing.assert_allclose(t.stretch, 1 + 0.3 * np.arange(5) / 30)
    np.testing.assert_allclose(t.stress, 0.02 * np.arange(5) / 20e-6)
    shimadzu = "Test Speed,5,mm/min\nBatch,1\nSample No,3\n\nTime,Force,Stroke\nsec,N,mm\n0,0,0\n1,0.02,0.3\n2,0.04,0.6\n"
    t = read(write(tmp_path, "s.csv", shimadzu), overrides={"gauge_length": "30 mm", "area": "20 mm2"})
    assert t.metadata["header_row"] == 5 and t.metadata["preamble"][1] == "Batch,1"
    np.testing.assert_allclose(t.stretch, [1.0, 1.01, 1.02])
    two = "Specimen,4\n\nstretch,stress [kPa]\n1.0,0\n1.2,5\n"   # as wide as the data, but a header follows
    np.testing.assert_allclose(read(write(tmp_path, "k.csv", two)).stress, [0, 5e3])


def test_decimal_comma_in_the_files_own_geometry(tmp_path):
    """A European Bluehill export writes its specimen properties with the file's decimal comma."""
    text = ('Specimen properties : Length;"30,00000";mm\r\nSpecimen properties : Width;"10,00000";mm\r\n'
            'Specimen properties : Thickness;"2,00000";mm\r\n\r\nTime;Extension;Load\r\n(s);(mm);(N)\r\n'
            '"0,0";"0,0";"0,0"\r\n"1,0";"0,3";"0,02"\r\n')
    t = read(write(tmp_path, "eu.csv", text))
    assert t.metadata["gauge_length"] == pytest.approx(0.03) and t.metadata["area"] == pytest.approx(20e-6)
    np.testing.assert_allclose(t.stretch, [1.0, 1.01])
    t = read(write(tmp_path, "c.csv", "# gauge_length: 30,5 mm\n# area: 20 mm2\nt [s];displacement [mm];force [N]\n0;0;0\n1;0,305;0,02\n"))
    assert t.metadata["gauge_length"] == pytest.approx(0.0305)


def test_units_row_with_the_unit_of_an_unknown_channel(tmp_path):
    for unit in ("°C", "N/tex", "count", "mm/min"):
        text = f"Time,Extension,Load,Other\ns,mm,N,{unit}\n0,0,0,1\n1,0.3,0.02,1\n"
        t = read(write(tmp_path, "u.csv", text), overrides={"gauge_length": "30 mm", "area": "20 mm2"})
        assert t.metadata["units_row"] == 2 and t.metadata["units"] == ["s", "mm", "N", unit]
        np.testing.assert_allclose(t.stress, [0, 1e3])


def test_rows_of_bare_delimiters_are_blank(tmp_path):
    """Excel leaves ';;' where rows were cleared, at the end and in between."""
    t = read(write(tmp_path, "t.csv", "stretch;stress [kPa]\n1,0;0\n;\n1,5;2,5\n;;\n;;\n"))
    np.testing.assert_allclose(t.stress, [0.0, 2500.0])
    assert t.metadata["last_data_row"] == 4


def test_the_step_names_the_columns_used_and_the_true_stress_conversion(tmp_path):
    rep = ListReporter()
    read(write(tmp_path, "t.csv", "Time (s),Extension (mm),Load (N),Tensile extension (mm)\n0,0,0,0\n1,1,1,1\n"),
         overrides={"gauge_length": "10 mm", "area": "1 mm2"}, reporter=rep)
    assert "from displacement / gauge_length, column 2 'Extension'" in rep.steps[-1]
    assert "from force / area, column 3 'Load'" in rep.steps[-1]
    read(write(tmp_path, "s.csv", "stretch,true stress [kPa]\n1,0\n1.1,1\n"), reporter=rep)
    assert "true stress / stretch, incompressible), column 2 'true stress'" in rep.steps[-1]


# ---------------------------------------------------------------------------
# exports of the second adversarial sweep (clock times, a results block after the data)


def _clock(seconds: float, *, comma: bool = False) -> str:
    h, rest = divmod(seconds, 3600.0)
    m, s = divmod(rest, 60.0)
    text = f"{int(h):02d}:{int(m):02d}:{s:06.3f}"
    return text.replace(".", ",") if comma else text


@pytest.mark.parametrize("delim,comma", [(",", False), (";", True)])
def test_clock_time_column_is_read_in_seconds(tmp_path, delim, comma):
    t, lam, p = truth()
    t = t * 700.0  # past a minute and an hour: 0 .. 1400 s
    rows = [delim.join([_clock(a, comma=comma), f"{b:.6f}", f"{c:.4f}"]) for a, b, c in zip(t, lam, p)]
    text = delim.join(["time", "stretch", "stress [Pa]"]) + "\n" + "\n".join(rows) + "\n"
    if comma:
        text = "\n".join(r if i == 0 else r.replace(".", ",") for i, r in enumerate(text.split("\n")))
    test = read(write(tmp_path, "clock.csv", text))
    np.testing.assert_allclose(test.time, t, atol=1e-3)
    np.testing.assert_allclose(test.stretch, lam, rtol=1e-6)
    assert test.metadata["time_format"] == "hh:mm:ss"


@pytest.mark.parametrize("sep,zone", [(" ", ""), ("T", "Z"), ("T", "+02:00")])
def test_date_and_time_stamps_are_read_in_seconds_across_midnight(tmp_path, sep, zone):
    """A data logger's ISO 8601 timestamps: read in seconds, in order across midnight (the stamps are the
    truth's times after a start two seconds before a leap day's midnight, every one in the same zone)."""
    import datetime as dt
    t, lam, p = truth()
    t = t * 7.0
    start = dt.datetime(2024, 2, 29, 23, 59, 58, 500000)  # a leap day, two seconds before midnight
    stamps = [(start + dt.timedelta(seconds=float(a))).isoformat(sep=sep, timespec="milliseconds") + zone
              for a in t]
    rows = "".join(f"{s},{b:.6f},{c:.4f}\n" for s, b, c in zip(stamps, lam, p))
    test = read(write(tmp_path, "stamps.csv", "Timestamp,stretch,stress [Pa]\n" + rows))
    np.testing.assert_allclose(test.time, t, atol=1e-6)
    assert test.metadata["time_format"] == "date and time"


def test_timestamps_across_a_change_of_utc_offset_stay_continuous(tmp_path):
    """A logger on local time across the change to summer time: 01:59:59 at UTC+1, then 03:00:00 at UTC+2,
    one second later."""
    rows = ["2024-03-31T01:59:58+01:00,1.0,0", "2024-03-31T01:59:59+01:00,1.1,1",
            "2024-03-31T03:00:00+02:00,1.2,2", "2024-03-31T03:00:01.5+02:00,1.3,3"]
    test = read(write(tmp_path, "dst.csv", "Date/Time,stretch,stress [Pa]\n" + "\n".join(rows) + "\n"))
    np.testing.assert_allclose(test.time, [0.0, 1.0, 2.0, 3.5], atol=1e-9)


@pytest.mark.parametrize("delim,decimal,group", [(",", ".", ","), (";", ",", ".")])
def test_thousands_grouped_by_a_spreadsheet_are_read(tmp_path, delim, decimal, group):
    """A spreadsheet's export with its number format's thousands grouping, in English ("1,234.5", quoted in a
    comma-separated file) and in German ("1.234,5"): the grouping mark is dropped, the decimal mark kept."""
    t, lam, p = truth()
    p = p * 5e3  # up to thousands of Pa

    def fmt(v):
        text = f"{v:,.4f}".replace(",", "_").replace(".", decimal).replace("_", group)
        return f'"{text}"' if delim == "," else text

    rows = "".join(delim.join([fmt(a), fmt(b), fmt(c)]) + "\n" for a, b, c in zip(t, lam, p))
    test = read(write(tmp_path, "grouped.csv", delim.join(["time [s]", "stretch", "stress [Pa]"]) + "\n" + rows))
    assert max(p) > 1e4
    np.testing.assert_allclose(test.stress, p, atol=1e-4)
    np.testing.assert_allclose(test.stretch, lam, atol=1e-4)


@pytest.mark.parametrize("comma", [False, True])
def test_columns_aligned_by_blanks_are_read(tmp_path, comma):
    """A fixed-width export (an older controller's ``.dat``): columns aligned by runs of spaces, names that
    hold single spaces (``Time (s)``), and in German a decimal comma with the units on the row below."""
    t, lam, p = truth()
    if comma:
        head = "    Zeit     Dehnung    Spannung\n       s           %          Pa\n"
        rows = "".join(f"{a:8.3f}{(b - 1) * 100:12.5f}{c:12.4f}\n".replace(".", ",") for a, b, c in zip(t, lam, p))
    else:
        head = "# controller export\nTime (s)     Stretch      Stress (Pa)\n"
        rows = "".join(f"  {a:8.3f}  {b:11.6f}  {c:11.4f}  \n" for a, b, c in zip(t, lam, p))
    test = read(write(tmp_path, "aligned.dat", head + rows))
    np.testing.assert_allclose(test.time, t, atol=1e-3)
    np.testing.assert_allclose(test.stretch, lam, atol=1e-6)
    np.testing.assert_allclose(test.stress, p, atol=1e-3)
    assert test.metadata["delimiter"] == "whitespace"


def test_bose_wintest_export_reads_disp_and_load_1(tmp_path):
    """Bose ElectroForce WinTest's layout: a preamble, a sample counter, two clocks, the actuator's
    position ('Disp', not zero at the start) and 'Load 1' (load cell 1: a channel number, not the unit
    '1'), the units in brackets on the row below."""
    t, lam, p = truth()
    L, A = 20.0, 10.0  # mm, mm²
    rows = "".join(f"{i}\t{a:.3f}\t{a % 5:.3f}\t{(b - 1) * L - 2.34:.5f}\t{c * A * 1e-6:.6f}\n"
                   for i, (a, b, c) in enumerate(zip(t, lam, p)))
    text = ("WinTest Data File\nTest: pull\n\nPoints\tElapsed Time \tScan Time \tDisp \tLoad 1 \n"
            "\t(Sec)\t(Sec)\t(mm)\t(N)\n" + rows)
    test = read(write(tmp_path, "bose.txt", text), overrides={"gauge_length": "20 mm", "area": "10 mm2"})
    np.testing.assert_allclose(test.time, t, atol=1e-3)
    np.testing.assert_allclose(test.stretch, lam, atol=1e-6)
    np.testing.assert_allclose(test.stress, p, rtol=1e-4, atol=1e-3)
    assert test.metadata["displacement_start"] == pytest.approx(-2.34e-3)
    assert any("'Points' not used" in n for n in test.metadata["column_notes"])


def test_a_spreadsheets_summary_rows_under_the_data_are_set_aside(tmp_path):
    """Max / Mean / SD rows right under the columns (no blank line between, as a spreadsheet appends them): set
    aside with a warning that names their lines; the data read whole."""
    t, lam, p = truth()
    rows = "".join(f"{a:.2f},{b:.6f},{c:.4f},\n" for a, b, c in zip(t, lam, p))
    summary = f"Maximum,,{max(p):.4f},\nMean:,,{np.mean(p):.4f},\nSD,,{np.std(p):.4f},\n"
    rep = ListReporter()
    test = read(write(tmp_path, "sheet.csv", "time [s],stretch,stress [Pa],\n" + rows + summary), reporter=rep)
    assert test.n == len(t)
    np.testing.assert_allclose(test.stress, p, atol=1e-4)
    assert any(f"lines {len(t) + 2}-{len(t) + 4} after the data" in w for w in rep.warnings)


def test_results_block_after_the_data_is_set_aside(tmp_path):
    t, lam, p = truth()
    rows = "".join(f"{a:.2f},{b:.6f},{c:.4f}\n" for a, b, c in zip(t, lam, p))
    block = "\nResults\nMaximum stress,Modulus,Strain at break\n(Pa),(Pa),(%)\n12.5,0.3,40\n"
    rep = ListReporter()
    test = read(write(tmp_path, "tail.csv", "time [s],stretch,stress [Pa]\n" + rows + block), reporter=rep)
    assert test.n == len(t)
    np.testing.assert_allclose(test.stress, p, atol=1e-4)
    assert test.metadata["trailer"][0] == "Results" and len(test.metadata["trailer"]) == 4
    assert any("lines 24-27 after the data" in w for w in rep.warnings)
