"""Bad tensile files: each is refused with one line naming the file, the place, and what to do."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError, EsmmError, InputError
from esmm.pipeline.tensile import NotATestError, read

RAW = "time [s],displacement [mm],force [N]\n0,0,0\n1,1,1\n"
GEOM = {"gauge_length": "10 mm", "area": "1 mm2"}


def refuse(tmp_path: Path, content, *, sidecar: str | None = None, error=InputError, name="bad.csv",
           **kwargs) -> str:
    """Write *content*, read it, check the refusal; return the message."""
    p = tmp_path / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8"))
    side = p.with_suffix(".toml")
    if sidecar is not None:
        side.write_text(sidecar, encoding="utf-8")
    elif side.exists():
        side.unlink()
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(EsmmError) as info:
        read(p, **kwargs)
    assert type(info.value) is error
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 600
    # the file, its sidecar, or the override (the message starts with its key, which the CLI shows as its flag)
    assert name in msg or p.with_suffix(".toml").name in msg or msg.startswith(f"{info.value.parameter}:")
    assert sorted(os.listdir(tmp_path)) == before          # nothing written
    return msg


def test_empty_file(tmp_path):
    assert "empty file" in refuse(tmp_path, b"")
    assert "empty file" in refuse(tmp_path, b"\r\n \t\n")


def test_no_numeric_rows(tmp_path):
    msg = refuse(tmp_path, "# specimen: a\nstretch,stress [kPa]\n")
    assert "no numeric rows" in msg and "line 2" in msg
    assert "no numeric rows" in refuse(tmp_path, "# only a comment\n\n")


def test_unknown_units(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [furlong]\n1,0\n")
    assert "column 2 'stress'" in msg and "'furlong'" in msg and "kPa" in msg
    msg = refuse(tmp_path, "strain [mm],stress [kPa]\n0,0\n")
    assert "unknown strain unit 'mm'" in msg


def test_ambiguous_case_units_are_refused(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [mPa]\n1,0\n")
    assert "millipascal" in msg and "MPa" in msg


def test_missing_units(tmp_path):
    msg = refuse(tmp_path, "stretch,stress\n1,0\n")
    assert "column 2 'stress' has no unit" in msg and "'stress [kPa]'" in msg and "units = [...]" in msg
    msg = refuse(tmp_path, "time,displacement,force\n0,0,0\n", overrides=GEOM)
    assert "column 1 'time' has no unit" in msg
    # an empty cell of a units row is a missing unit too
    msg = refuse(tmp_path, "time,displacement,force\n(s),,(N)\n0,0,0\n", overrides=GEOM)
    assert "column 2 'displacement' has no unit" in msg


def test_missing_geometry(tmp_path, run_cli):
    msg = refuse(tmp_path, RAW, overrides={"area": "1 mm2"})
    assert "missing geometry" in msg and "gauge_length" in msg and msg.startswith("gauge_length:")
    code, _, err = run_cli("calibrate", tmp_path / "bad.csv", "--area", "1 mm2")
    assert code == 2 and "--gauge-length" in err
    msg = refuse(tmp_path, RAW, overrides={"gauge_length": "10 mm"})
    assert "missing geometry" in msg and "area" in msg and "width and thickness" in msg
    msg = refuse(tmp_path, RAW, overrides={"gauge_length": "10 mm", "width": "2 mm"})
    assert "width is given but not thickness" in msg


def test_bare_number_for_a_dimensional_key(tmp_path, run_cli):
    msg = refuse(tmp_path, "# gauge_length: 30\n" + RAW, overrides={"area": "1 mm2"})
    assert "line 1: gauge_length" in msg and "no unit" in msg and '"30 mm"' in msg
    msg = refuse(tmp_path, RAW, sidecar='gauge_length = 30\narea = "1 mm2"\n')
    assert "bad.toml: gauge_length" in msg and "no unit" in msg
    msg = refuse(tmp_path, RAW, overrides={"gauge_length": "30", "area": "1 mm2"}, error=ConfigError)
    assert msg.startswith("gauge_length:")
    code, _, err = run_cli("calibrate", tmp_path / "bad.csv", "--gauge-length", "30", "--area", "1 mm2")
    assert code == 2 and "--gauge-length" in err and "no unit" in err
    # refused even where the value would not be used (a processed file)
    assert "no unit" in refuse(tmp_path, "# area: 22\nstretch,stress [kPa]\n1,0\n")


def test_non_positive_geometry(tmp_path):
    msg = refuse(tmp_path, RAW, overrides={"gauge_length": "-1 mm", "area": "1 mm2"}, error=ConfigError)
    assert "must be positive" in msg


def test_nan_and_text_in_a_numeric_column(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\n1.1,nan\n")
    assert "column 2 'stress', line 3" in msg and "'nan'" in msg and "fix or delete" in msg
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\n1.1,abc\n1.2,3\n")
    assert "column 2 'stress', line 3" in msg and "'abc'" in msg
    msg = refuse(tmp_path, "stretch;stress [kPa]\n1;0\n1.1;\n")
    assert "line 3 is empty" in msg
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\n1.1,-inf\n")
    assert "'-inf' is not a finite number" in msg
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\nPeak,1\n1.2,3\n")   # text within the data
    assert "column 1 'stretch', line 3" in msg and "'Peak'" in msg
    msg = refuse(tmp_path, 'stretch,stress [kPa]\n"1","0"\n"1,1","2"\n"1.2","3"\n')
    assert "numbers mix '.' (line 4) and ',' (line 3)" in msg


def test_short_row_and_header_mismatch(tmp_path):
    assert "line 3 has 1 field(s)" in refuse(tmp_path, "stretch,stress [kPa]\n1,0\n1.1\n")
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0,5\n")
    assert "header on line 1 has 2 columns but the data row on line 2 has 3" in msg


def test_time_going_backwards(tmp_path):
    msg = refuse(tmp_path, "time [ms],stretch,stress [kPa]\n0,1,0\n10,1.1,1\n5,1.2,2\n")
    assert "line 4: time goes backwards (5 ms after 10 ms on line 3)" in msg and "separate files" in msg


def test_binary_files(tmp_path):
    assert "binary data" in refuse(tmp_path, bytes(range(256)) * 4)
    assert "xlsx" in refuse(tmp_path, b"PK\x03\x04" + bytes(100), name="bad.xlsx")
    assert "save the sheet as CSV" in refuse(tmp_path, b"\xd0\xcf\x11\xe0" + bytes(100))
    assert "utf-16-le" in refuse(tmp_path, "stretch,stress [kPa]\n1,0\n".encode("utf-16-le"))
    assert "control bytes" in refuse(tmp_path, bytes([1, 2, 3, 4, 5, 6, 7, 8, 14, 15] * 40))


def test_unknown_column_names(tmp_path):
    msg = refuse(tmp_path, "Kraft2,Weg2\n1,0\n", error=NotATestError)  # no column names a test quantity
    assert "unknown column names 'Kraft2', 'Weg2' (header line 1)" in msg and "columns = [...]" in msg




def test_duplicate_columns(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [kPa],nominal stress [kPa]\n1,0,0\n")
    assert "two stress columns" in msg and "'ignore'" in msg


def test_stress_without_stretch(tmp_path):
    msg = refuse(tmp_path, "time [s],stress [kPa]\n0,0\n1,1\n")
    assert "has stress but no stretch" in msg and "'time', 'stress'" in msg
    msg = refuse(tmp_path, "stretch\t time [s]\n1\t0\n")
    assert "no stress" in msg


def test_no_header_and_no_columns(tmp_path):
    msg = refuse(tmp_path, "1,0\n1.1,1\n")
    assert "no header line" in msg and "columns = [...]" in msg and "bad.toml" in msg


def test_mismatched_sidecar_columns_and_units(tmp_path):
    msg = refuse(tmp_path, RAW, sidecar='columns = ["time", "displacement"]\n')
    assert "bad.toml: columns" in msg and "lists 2 columns but the file has 3" in msg
    msg = refuse(tmp_path, RAW, sidecar='units = ["s", "mm"]\n')
    assert "lists 2 units but the file has 3 columns" in msg
    msg = refuse(tmp_path, "1,0\n", sidecar='columns = ["strech", "stress"]\nunits = ["", "kPa"]\n')
    assert "unknown column quantity 'strech'" in msg


def test_unknown_mode(tmp_path, run_cli):
    msg = refuse(tmp_path, "# mode: biaxial\nstretch,stress [kPa]\n1,0\n")
    assert "line 1: mode" in msg and "unknown mode 'biaxial'" in msg and "equibiaxial" in msg
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\n", overrides={"mode": "torsion"}, error=ConfigError)
    assert msg.startswith("mode:")
    code, _, err = run_cli("calibrate", tmp_path / "bad.csv", "--mode", "torsion")
    assert code == 2 and "--mode" in err


def test_mode_and_columns_disagree(tmp_path):
    msg = refuse(tmp_path, "# mode: uniaxial\ngamma,shear stress [kPa]\n0,0\n")
    assert 'state mode = "simple_shear"' in msg
    msg = refuse(tmp_path, "# mode: simple shear\nstretch,stress [kPa]\n1,0\n")
    assert "needs 'shear strain' and 'shear stress' columns" in msg


def test_non_positive_stretch(tmp_path):
    msg = refuse(tmp_path, "strain [%],stress [kPa]\n0,0\n-120,1\n")
    assert "column 1 'strain', line 3: gives stretch -0.2 <= 0" in msg


def test_encodings(tmp_path):
    gbk = "时间,位移,力\n(s),(mm),(N)\n0,0,0\n".encode("gbk")
    msg = refuse(tmp_path, gbk, overrides=GEOM)
    assert "not UTF-8" in msg and 'encoding = "gbk"' in msg and "line 1" in msg
    msg = refuse(tmp_path, gbk, encoding="utf-8")
    assert "does not decode as utf-8 (stated by encoding argument)" in msg
    msg = refuse(tmp_path, RAW, overrides={"encoding": "klingon"}, error=ConfigError)
    assert "unknown text encoding 'klingon'" in msg


def test_bad_sidecars(tmp_path):
    msg = refuse(tmp_path, RAW, sidecar='guage_length = "10 mm"\n')
    assert "unknown key 'guage_length' (did you mean 'gauge_length'?)" in msg
    msg = refuse(tmp_path, RAW, sidecar="gauge_length = \n")
    assert "not valid TOML" in msg and "bad.toml" in msg
    msg = refuse(tmp_path, RAW, overrides={"colour": "red"}, error=ConfigError)
    assert "unknown key 'colour'" in msg


def test_inconsistent_geometry(tmp_path):
    msg = refuse(tmp_path, RAW, overrides={"gauge_length": "1 mm", "area": "5 mm2", "width": "1 mm",
                                           "thickness": "1 mm"})
    assert "disagrees with width x thickness = 1 mm2" in msg


def test_units_disagree_within_the_file(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [kPa]\n(-),(MPa)\n1,0\n")
    assert "header says unit 'kPa' but the units row on line 2 says 'MPa'" in msg


def test_orientation_needs_a_unit(tmp_path):
    msg = refuse(tmp_path, "stretch,stress [kPa]\n1,0\n", overrides={"orientation": "45"}, error=ConfigError)
    assert '"45 deg"' in msg


def test_single_column(tmp_path):
    assert "cannot find the column delimiter" in refuse(tmp_path, "stretch\n1\n1.1\n")


def test_paths(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read(tmp_path / "missing.csv")
    with pytest.raises(InputError, match="is a folder"):
        read(tmp_path)
    (tmp_path / "x.toml").write_text('gauge_length = "1 mm"\n')
    with pytest.raises(InputError, match="TOML sidecar, not test data"):
        read(tmp_path / "x.toml")


def test_encoding_statements_that_contradict_the_file(tmp_path):
    bom = b"\xef\xbb\xbfstretch,stress [kPa]\n1,0\n"
    msg = refuse(tmp_path, bom, sidecar='encoding = "gbk"\n')
    assert "UTF-8" not in msg and "utf-8-sig byte-order mark but" in msg and "bad.toml: encoding" in msg
    msg = refuse(tmp_path, "# encoding: ascii\nstretch,stress [kPa]\n1,0\n1.1,1 µ\n".encode())
    assert "does not decode as ascii (stated by" in msg and "line 1: encoding" in msg and "line 4" in msg


def test_absurd_true_strain(tmp_path):
    msg = refuse(tmp_path, "true strain,stress [kPa]\n0,0\n1000,1\n")
    assert "line 3: gives a stretch that is not finite" in msg


def test_a_mark_that_could_group_thousands_or_be_decimal_is_refused(tmp_path):
    # '1.234' beside '0,5': a grouped thousand or a decimal point; without a number that has both marks
    # (as '1.234,56' has) there is no telling, and the mix is refused
    msg = refuse(tmp_path, "Dehnung (%);Spannung (Pa)\n0,0;0,5\n1,5;1.234\n3,0;2.468\n")
    assert "numbers mix '.'" in msg and "thousands separators" in msg


def test_the_encoding_hint_of_a_western_file(tmp_path):
    # a latin-1/cp1252 file with µm or °C: the hint was Shift-JIS (which decodes those bytes as half-width kana)
    msg = refuse(tmp_path, "Time (s);Extension (µm);Load (N)\n0;0;0\n1;2;3\n".encode("latin-1"))
    assert "cp1252" in msg and "Shift-JIS" not in msg
    msg = refuse(tmp_path, "時間 (s),変位 (mm),荷重 (N)\n0,0,0\n1,2,3\n".encode("shift_jis"))
    assert "Shift-JIS" in msg


def test_an_ambiguous_decimal_comma_in_the_files_geometry(tmp_path):
    msg = refuse(tmp_path, "# gauge_length: 1,500 mm\n# area: 2 mm2\n" + RAW)
    assert "line 1: gauge_length: '1,500 mm' is ambiguous" in msg and '"1.500 mm" or "1500 mm"' in msg


def test_a_three_digit_decimal_comma_in_a_file_whose_data_use_decimal_commas(tmp_path):
    """A European export (';' between cells, ',' in the numbers): its header's '4,773 mm2' is 4.773 mm², the
    file's own convention, not a thousands separator; the same header beside point-decimal data is refused."""
    body = "Time [s];Extension [mm];Force [N]\n0,0;0,000;0,000\n1,0;0,500;1,250\n2,0;1,000;2,750\n"
    p = tmp_path / "eu.csv"
    p.write_text("# gauge_length: 77,10 mm\n# area: 4,773 mm2\n" + body, encoding="utf-8")
    t = read(p)
    assert t.metadata["area"] == pytest.approx(4.773e-6, rel=1e-12)
    assert t.stress[-1] == pytest.approx(2.75 / 4.773e-6, rel=1e-12)
    msg = refuse(tmp_path, "# gauge_length: 77,10 mm\n# area: 4,773 mm2\n"
                 "Time [s];Extension [mm];Force [N]\n0.0;0.000;0.000\n1.0;0.500;1.250\n2.0;1.000;2.750\n")
    assert "area: '4,773 mm2' is ambiguous" in msg


# ---------------------------------------------------------------------------
# second adversarial sweep


def _ramp(n=30):
    lam = np.linspace(1.0, 1.5, n)
    return np.arange(n) * 0.5, (lam - 1) * 10.0, 20e3 * (lam - lam**-2) * 1e-6


def _raw(t, d, f) -> str:
    return "time [s],displacement [mm],force [N]\n" + "".join(f"{a:g},{b:.6f},{c:.8f}\n" for a, b, c in zip(t, d, f))


def test_header_repeated_mid_file_is_refused_as_several_tests(tmp_path):
    t, d, f = _ramp()
    text = _raw(t, d, f)
    msg = refuse(tmp_path, text + text, overrides=GEOM)
    assert "line 32 repeats the header of line 1" in msg and "one file per test" in msg


def test_saturated_channel_is_refused_as_saturated_not_as_a_sign(tmp_path):
    """A load channel pinned at the negative end of its converter's range while the specimen is pulled reads
    the wrong sign on most rows at one value: the refusal names the saturation, not a sign convention."""
    t, d, f = _ramp()
    pinned = np.where(np.arange(f.size) < 25, -1611.32812, f)  # at its end of scale until the last rows
    msg = refuse(tmp_path, _raw(t, d, pinned), overrides=GEOM)
    assert "saturated" in msg and "column 3 'force'" in msg and "change its sign" not in msg


def test_compression_positive_channel_is_refused(tmp_path):
    t, d, f = _ramp()
    msg = refuse(tmp_path, _raw(t, d, -f), overrides=GEOM)
    assert "opposite sign to the deformation" in msg and "column 3 'force'" in msg and "change its sign" in msg
    lam = np.linspace(1.0, 1.5, 30)
    text = "strain [%],stress [kPa]\n" + "".join(f"{(x - 1) * 100:.3f},{-(x - x**-2) * 20:.5f}\n" for x in lam)
    assert "the stress column is recorded compression-positive" in refuse(tmp_path, text)
    # both channels negative is a consistent compression test, and a load-cell offset is no sign error
    assert read(_write(tmp_path, "c.csv", _raw(t, -d, -f)), overrides=GEOM).stretch.min() < 1
    assert read(_write(tmp_path, "o.csv", _raw(t, d, f - 0.3 * f.max())), overrides=GEOM).n == 30


def test_dead_load_channel_is_refused(tmp_path):
    t, d, f = _ramp()
    msg = refuse(tmp_path, _raw(t, d, 0 * f), overrides=GEOM)
    assert "column 3 'force'" in msg and "0 Pa on every row (30 rows)" in msg and "load cell" in msg


def _write(folder: Path, name: str, text: str) -> Path:
    p = folder / name
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize("option,target", [("--out", "a_file.txt"), ("--out", "a_file.txt/sub"),
                                           ("--json", "folder"), ("--json", "a_file.txt/fit.json")])
def test_calibrate_refuses_an_unwritable_output_before_fitting(tmp_path, run_cli, option, target):
    t, d, f = _ramp()
    data = _write(tmp_path, "ok.csv", _raw(t, d, f))
    (tmp_path / "a_file.txt").write_text("keep\n")
    (tmp_path / "folder").mkdir()
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    code, out, err = run_cli("calibrate", data, "--gauge-length", "10 mm", "--area", "1 mm2", "--starts", "1",
                             option, tmp_path / target)
    assert code == 2 and "Traceback" not in err and "fitting" not in err + out
    assert err.strip().count("\n") == 0 and option in err
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before
