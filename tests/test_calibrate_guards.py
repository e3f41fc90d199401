"""Guard rails of esmm calibrate: a folder means its files, every missing metadata key in one message, an
--out that holds another run refused (or cleared with --overwrite), nothing created on a refusal, a unit on
every number of report.md."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

UNIAXIAL = "Time (s),Stretch,Nominal stress (kPa)\n" + "".join(
    f"{i * 0.1:.1f},{lam:.4f},{100 * (lam - 1 / lam**2):.4f}\n" for i, lam in enumerate(np.linspace(1, 1.8, 40)))


def _tree(path):
    return sorted(str(p.relative_to(path)) for p in path.rglob("*")) if path.exists() else None


@pytest.fixture
def vhb_without_sidecar(bundled_data, tmp_path):
    src = bundled_data / "tensile" / "vhb4910_raw" / "lu_0d01_1d5.csv"
    dst = tmp_path / "data" / src.name
    dst.parent.mkdir()
    shutil.copy(src, dst)
    return dst


def test_a_folder_means_its_test_files(run_cli, tmp_path, bundled_data):
    data = tmp_path / "specimen"
    data.mkdir()
    for name in ("a.csv", "b.csv"):
        (data / name).write_text(UNIAXIAL)
    (data / "b.toml").write_text('specimen = "b"\n')                       # a sidecar: read with b.csv
    shutil.copy(bundled_data / "tensile" / "foam_cyclic" / "new-heel-tension-measurements.csv", data / "m.csv")
    code, out, err = run_cli("calibrate", data, "--model", "arruda-boyce", "--starts", "2", "--json", tmp_path / "f.json")
    assert code == 0, err
    doc = json.loads((tmp_path / "f.json").read_text())
    assert sorted(doc["files"]) == [str(data / "a.csv"), str(data / "b.csv")]
    assert "m.csv" in err and "skipped" in err                              # the measurement table
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    code, _, err = run_cli("calibrate", empty, "--out", tmp_path / "o")
    assert code == 2 and "no test files" in err and "sub" in err
    assert not (tmp_path / "o").exists()


def test_every_missing_metadata_key_in_one_message(run_cli, vhb_without_sidecar, tmp_path):
    """A VHB export without its sidecar took three runs (encoding, then gauge length, then area)."""
    out = tmp_path / "out"
    code, stdout, err = run_cli("calibrate", vhb_without_sidecar, "--out", out)
    assert code == 2
    errors = [ln for ln in err.splitlines() if ln.startswith("esmm: error:")]
    assert len(errors) == 1 and "Traceback" not in err
    line = errors[0]
    for key, flag in (("encoding", "--encoding"), ("gauge_length", "--gauge-length"), ("area", "--area")):
        assert key in line and flag in line, line
    assert 'encoding = "gbk"' in line and "lu_0d01_1d5.toml" in line
    assert not out.exists()                                                 # nothing created
    # with one of them given, the other two, still in one message
    code, _, err = run_cli("calibrate", vhb_without_sidecar, "--encoding", "gbk")
    assert code == 2 and "gauge_length" in err and "area" in err and "encoding (" not in err
    # and given all three, it reads and fits
    code, _, err = run_cli("calibrate", vhb_without_sidecar, "--encoding", "gbk", "--gauge-length", "80 mm",
                           "--area", "22 mm2", "--columns", "time,displacement,force", "--units", "s,mm,N",
                           "--model", "arruda-boyce", "--starts", "2")
    assert code == 0, err


def test_missing_metadata_of_several_files_and_in_a_batch(run_cli, vhb_without_sidecar, tmp_path):
    other = vhb_without_sidecar.with_name("copy.csv")
    shutil.copy(vhb_without_sidecar, other)
    out = tmp_path / "batch"
    code, _, err = run_cli("calibrate", "--by", "specimen", vhb_without_sidecar, other, "--out", out)
    assert code == 2 and "lu_0d01_1d5.csv" in err and "copy.csv" in err and "--gauge-length" in err
    assert not out.exists()                                                 # no file could be read: no folder, no log


def test_an_out_folder_with_another_run_is_refused_and_overwrite_clears_it(run_cli, tmp_path):
    data = tmp_path / "t.csv"
    data.write_text(UNIAXIAL)
    out = tmp_path / "fit"
    args = ("calibrate", data, "--model", "arruda-boyce", "--starts", "2", "--out", out)
    assert run_cli(*args)[0] == 0
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    code, _, err = run_cli(*args)
    assert code == 2 and "--overwrite" in err and "fit.json" in err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before  # untouched
    # an earlier discovery's files in the folder (the issue: fit.json beside a new params.toml)
    (out / "discover.json").write_text("{}")
    (out / "params_base.toml").write_text("")
    (out / "corrected").mkdir()
    (out / "corrected" / "t.csv").write_text("")
    (out / "notes.txt").write_text("mine")                                  # not esmm's: kept
    code, _, err = run_cli(*args, "--overwrite")
    assert code == 0, err
    names = {p.name for p in out.iterdir()}
    assert {"params.toml", "fit.json", "fit.png", "report.md", "report.html", "notes.txt"} <= names
    assert not names & {"discover.json", "params_base.toml", "corrected"}


def test_a_batch_reuses_its_own_folder_but_not_another_runs(run_cli, tmp_path):
    data = tmp_path / "t.csv"
    data.write_text(UNIAXIAL)
    out = tmp_path / "b"
    args = ("calibrate", "--by", "specimen", data, "--model", "arruda-boyce", "--starts", "2", "--out", out,
            "--scheduler", "serial")
    assert run_cli(*args)[0] == 0
    code, stdout, _ = run_cli(*args)
    assert code == 0 and "skipped (cached)" in stdout                      # its own cache: reused
    single = tmp_path / "single"
    assert run_cli("calibrate", data, "--model", "arruda-boyce", "--starts", "2", "--out", single)[0] == 0
    code, _, err = run_cli("calibrate", "--by", "specimen", data, "--out", single, "--scheduler", "serial")
    assert code == 2 and "an earlier esmm fit" in err
    assert _tree(single) == sorted(["params.toml", "fit.png", "report.md", "report.html", "fit.json", ".esmm-run.json"])


def test_nothing_is_created_when_the_input_is_refused(run_cli, tmp_path):
    out = tmp_path / "o"
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"\x00\x01binary")
    for argv in (("calibrate", bad, "--out", out), ("calibrate", "--by", "specimen", bad, "--out", out),
                 ("calibrate", tmp_path / "missing.csv", "--out", out)):
        code, _, err = run_cli(*argv)
        assert code == 2, err
        assert not out.exists(), argv


def test_every_number_of_report_md_has_its_unit(run_cli, tmp_path):
    """'mu 6.66e-07 MPa' and 'unbounded around 0.6663' without a unit: each parameter in its own readable
    unit, and a unit (or 'dimensionless', '%') beside every number of the text."""
    x = np.linspace(1.0, 1.04, 200)                                         # N is not determined here
    data = tmp_path / "small.csv"
    y = 0.8 * (x - 1 / x**2)                                                 # a very soft material: below 1 Pa
    data.write_text("Time (s),Stretch,Nominal stress (Pa)\n"
                    + "".join(f"{i * 0.1:.1f},{a:.5f},{s:.6f}\n" for i, (a, s) in enumerate(zip(x, y))))
    code, _, err = run_cli("calibrate", data, "--model", "arruda-boyce", "--starts", "2", "--out", tmp_path / "f")
    assert code == 0, err
    md = (tmp_path / "f" / "report.md").read_text()
    table = md.split("## Parameters")[1].split("##")[0]
    mu = next(ln for ln in table.splitlines() if ln.startswith("| mu "))
    assert mu.split("|")[4].strip() == "Pa"                                 # 0.27 Pa, not 2.7e-07 MPa
    for line in md.split("## Warnings")[1].split("##")[0].splitlines():
        if "around" in line:
            assert re.search(r"around \S+ (Pa|kPa|MPa|GPa|\(dimensionless\))$", line), line
    overall = next(ln for ln in md.splitlines() if ln.startswith("Overall:"))
    for num in re.finditer(r"(-?\d[\d.e+-]*)(\S*)(\s+\S+)?", overall.split(":", 1)[1]):
        assert num.group(2) or num.group(3), overall
