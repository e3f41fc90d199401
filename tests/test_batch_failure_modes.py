"""docs/reference/failure-modes.md is enforced: one check per table row (exit code and message phrase)."""

from __future__ import annotations

import os
import re
import signal
import struct
import sys
import time
from pathlib import Path

import cloudpickle
import pytest
from esmm.pipeline.atomicio import write_text
from esmm.pipeline.batch import Job, run_jobs
from esmm.pipeline.batch import jobs as bjobs
from esmm.pipeline.errors import ConfigError, EsmmError, InputError

cloudpickle.register_pickle_by_value(sys.modules[__name__])

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "reference" / "failure-modes.md"
LIVER = REPO / "data" / "meshes" / "ts_liver_3mm_closed.stl"
BRAIN = REPO / "data" / "tensile" / "budday2017_brain"


def table_rows() -> list[dict]:
    rows = []
    for line in DOC.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\|\s*`([a-z0-9-]+)`\s*\|(.*)\|\s*(\d+)\s*\|\s*$", line)
        if not m:
            continue
        cells = [c.strip() for c in m.group(2).split("|")]
        phrases = re.findall(r"`([^`]+)`", cells[-1])
        rows.append({"id": m.group(1), "what": cells[0], "command": cells[1], "phrase": phrases[0],
                     "exit": int(m.group(3))})
    return rows


ROWS = table_rows()


@pytest.fixture(autouse=True)
def pinned_code_version(monkeypatch):
    monkeypatch.setenv(bjobs.CODE_VERSION_ENV, "failure-modes")
    bjobs.code_version.cache_clear()
    yield
    bjobs.code_version.cache_clear()


# ----------------------------------------------------------------------------- single inputs (CLI)
def stl_binary(tri: list[list[float]]) -> bytes:
    recs = b"".join(struct.pack("<12fH", 0, 0, 0, *t, 0) for t in tri)
    return b"\0" * 80 + struct.pack("<I", len(tri)) + recs


TETRA_MM = [[0, 0, 0, 50, 0, 0, 0, 50, 0], [0, 0, 0, 0, 0, 50, 50, 0, 0],
            [0, 0, 0, 0, 50, 0, 0, 0, 50], [50, 0, 0, 0, 0, 50, 0, 50, 0]]


def _asset(tmp: Path) -> Path:
    import numpy as np
    from esmm.pipeline.asset import write_asset
    from esmm.pipeline.network.springs import network_from_tets

    pts = np.array([[0, 0, 0], [0.04, 0, 0], [0, 0.04, 0], [0, 0, 0.04], [0.04, 0.04, 0.04]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    from types import SimpleNamespace

    net = network_from_tets(SimpleNamespace(points=pts, tets=tets), density=1060.0).with_fixed(np.array([0]))
    return write_asset(tmp / "organ.h5", net)


def cli_case(row_id: str, tmp: Path) -> list[str]:
    """The command line of a single-input row, with its input made in *tmp*."""
    def f(name: str, data: bytes | str) -> str:
        p = tmp / name
        p.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
        return str(p)

    if row_id == "tensile-missing":
        return ["calibrate", str(tmp / "absent.csv")]
    if row_id == "tensile-empty":
        return ["calibrate", f("t.csv", "\n \n")]
    if row_id == "tensile-binary":
        return ["calibrate", f("t.csv", b"PK\x03\x04\x14\x00\x06\x00" + bytes(200))]
    if row_id == "tensile-not-utf8":
        return ["calibrate", f("t.csv", "stretch;Spannung µ [kPa]\n1;0\n1,1;1\n".encode("latin-1"))]
    if row_id == "tensile-no-units":
        return ["calibrate", f("t.csv", "stretch,stress\n1,0\n1.1,1\n")]
    if row_id == "tensile-nan":
        return ["calibrate", f("t.csv", "stretch,stress [kPa]\n1,0\n1.1,nan\n1.2,2\n")]
    if row_id == "tensile-time-backwards":
        return ["calibrate", f("t.csv", "time [s],stretch,stress [kPa]\n0,1,0\n2,1.1,1\n1,1.2,2\n")]
    if row_id == "tensile-no-geometry":
        return ["calibrate", f("t.csv", "time [s],displacement [mm],force [N]\n0,0,0\n1,1,1\n")]
    if row_id == "calibrate-unknown-model":
        return ["calibrate", f("t.csv", "stretch,stress [kPa]\n1,0\n1.1,1\n"), "--model", "ogden9"]
    if row_id == "tensile-missing-metadata":
        return ["calibrate", f("t.csv", "时间,位移,力\n(s),(mm),(N)\n0,0,0\n1,1,1\n".encode("gbk"))]
    if row_id == "calibrate-folder-without-tests":
        (tmp / "tests" / "day1").mkdir(parents=True)
        return ["calibrate", str(tmp / "tests")]
    if row_id == "calibrate-out-holds-a-run":
        (tmp / "fit").mkdir()
        (tmp / "fit" / "fit.json").write_text("{}")
        return ["calibrate", f("t.csv", "stretch,stress [kPa]\n1,0\n1.1,1\n1.2,2\n"), "--out", str(tmp / "fit")]
    out = ["-o", str(tmp / "out.h5")]
    if row_id == "mesh-missing":
        return ["prepare", str(tmp / "absent.stl"), *out]
    if row_id == "mesh-empty":
        return ["prepare", f("organ.stl", b""), *out]
    if row_id == "mesh-truncated":
        return ["prepare", f("organ.stl", stl_binary(TETRA_MM)[:-30]), *out]
    if row_id == "mesh-nan":
        return ["prepare", f("organ.stl", stl_binary([[float("nan")] + t[1:] for t in TETRA_MM])), *out]
    if row_id == "mesh-unknown-format":
        return ["prepare", f("organ.xyz", "0 0 0\n"), *out]
    if row_id == "mesh-wrong-unit":
        return ["prepare", f("organ.stl", stl_binary([[v / 1000 for v in t] for t in TETRA_MM])), *out]
    if row_id == "mesh-below-quality":
        cfg = f("floors.toml", "[quality]\nmin_dihedral_deg = 89.0\n")
        return ["prepare", str(LIVER), *out, "--config", cfg, "--size", "25"]
    if row_id == "asset-missing":
        return ["info", str(tmp / "absent.h5")]
    if row_id == "asset-not-hdf5":
        return ["info", f("organ.h5", "not an asset\n")]
    if row_id == "asset-truncated":
        p = _asset(tmp)
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
        return ["info", str(p)]
    if row_id == "asset-tampered":
        import h5py

        p = _asset(tmp)
        with h5py.File(p, "r+") as fh:
            fh["/nodes/mass"][0] *= 1.5
        return ["info", str(p)]
    raise KeyError(row_id)


# ----------------------------------------------------------------------------- batches (library)
def job_ok(out, name):
    return {"outputs": [write_text(Path(out) / f"{name}.txt", name)]}


def job_raise():
    raise InputError("spec3.csv: line 4: 'x' is not a number; fix the file")


def job_kill():
    os.kill(os.getpid(), signal.SIGKILL)


def job_sleep():
    time.sleep(60)


def job_interrupt():
    raise KeyboardInterrupt


def _jobs(out, *extra):
    return [Job(name="ok", kind="t", fn=job_ok, args=(str(out), "ok"), config={"v": 1}), *extra]


def _run_row(fn_job, tmp, **kw) -> tuple[int, str]:
    out = tmp / "out"
    s = run_jobs(_jobs(out, Job(name="x", kind="t", fn=fn_job)), out_dir=out, **kw)
    assert s.by_name()["ok"].status == "done"
    return s.exit_code, s.by_name()["x"].reason + " " + s.table()


def _error_of(call, kind: type[EsmmError] = ConfigError) -> tuple[int, str]:
    """Run *call*, which must raise a *kind* error: (its exit code, its message)."""
    try:
        call()
    except kind as exc:
        return exc.exit_code, str(exc)
    raise AssertionError("no error")


def _one_bad_file(tmp: Path, out: Path) -> tuple[int, str]:
    from esmm.cli.main import main

    bad = tmp / "broken.csv"
    bad.write_bytes(b"\x00\x01binary")
    files = [str(p) for p in sorted(BRAIN.glob("cortex_*.csv"))] + [str(bad)]
    code = main(["calibrate", "--by", "specimen", *files, "--out", str(out), "--starts", "2", "--jobs", "1"])
    return code, (out / "summary.csv").read_text()


def _interrupted(tmp: Path, out: Path) -> tuple[int, str]:
    s = run_jobs([Job(name="x", kind="t", fn=job_interrupt)] + _jobs(out), out_dir=out, scheduler="serial")
    return s.exit_code, s.by_name()["x"].status + " " + s.log_path.read_text()


def _killed(tmp: Path, out: Path) -> tuple[int, str]:
    out.mkdir()
    (out / ".ok.txt.tmp-dead1.txt").write_text("half")
    s = run_jobs(_jobs(out), out_dir=out, scheduler="serial")
    assert not list(out.glob(".*.tmp-*"))
    return s.exit_code, s.log_path.read_text()


def _rerun(tmp: Path, out: Path) -> tuple[int, str]:
    run_jobs(_jobs(out), out_dir=out, scheduler="serial")
    s = run_jobs(_jobs(out), out_dir=out, scheduler="serial")
    return s.exit_code, s.table()


def _output_edited(tmp: Path, out: Path) -> tuple[int, str]:
    run_jobs(_jobs(out), out_dir=out, scheduler="serial")
    (out / "ok.txt").write_text("OK")
    s = run_jobs(_jobs(out), out_dir=out, scheduler="serial")
    assert s.by_name()["ok"].status == "done"
    return s.exit_code, s.log_path.read_text()


def _stale_task(tmp: Path, out: Path, *, input_changed: bool) -> tuple[int, str]:
    """A task whose input changed, or whose code version is not this one, since its key was made."""
    from esmm.pipeline.batch.worker import execute

    src = tmp / "in.csv"
    src.write_text("a")
    out.mkdir()
    task = {"name": "x", "kind": "t", "key": "0" * 64, "fn": job_ok, "args": (str(out), "x"), "kwargs": {},
            "out_dir": str(out), "key_inputs": [str(src)], "digests": [("in.csv", bjobs.sha256_file(src))],
            "config": {}, "code_version": bjobs.code_version()}
    if input_changed:
        src.write_text("b")
    else:
        task["code_version"] = "0.0.0+elsewhere"
    res = execute(task)
    assert res["status"] == "failed"
    return bjobs.EXIT_FAILED, res["reason"]


def _locked(tmp: Path, out: Path) -> tuple[int, str]:
    from esmm.pipeline.batch import cache as bcache

    with bcache.FolderLock(out):
        return _error_of(lambda: run_jobs(_jobs(out), out_dir=out, scheduler="serial"), EsmmError)


def _scheduler_unreachable(tmp: Path, out: Path) -> tuple[int, str]:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return _error_of(lambda: run_jobs(_jobs(out), out_dir=out, scheduler=f"tcp://127.0.0.1:{port}",
                                      connect_timeout=2))


def _name_clash(tmp: Path, out: Path) -> tuple[int, str]:
    from esmm.pipeline.batch.prepare import prepare_jobs

    return _error_of(lambda: prepare_jobs([tmp / "liver.stl", tmp / "liver.obj"], out_dir=out))


#: Each batch row of the table: a function of (tmp, out folder) -> (exit code, text with the phrase).
BATCH_CASES = {
    "batch-one-bad-file": _one_bad_file,
    "batch-job-fails": lambda tmp, out: _run_row(job_raise, tmp, scheduler="serial"),
    "batch-worker-killed": lambda tmp, out: _run_row(job_kill, tmp, workers=1),
    "batch-job-timeout": lambda tmp, out: _run_row(job_sleep, tmp, workers=2, job_timeout=1),
    "batch-interrupted": _interrupted,
    "batch-killed": _killed,
    "batch-rerun": _rerun,
    "batch-output-edited": _output_edited,
    "batch-input-changed": lambda tmp, out: _stale_task(tmp, out, input_changed=True),
    "batch-code-mismatch": lambda tmp, out: _stale_task(tmp, out, input_changed=False),
    "batch-locked": _locked,
    "batch-bad-scheduler": lambda tmp, out: _error_of(
        lambda: run_jobs(_jobs(out), out_dir=out, scheduler="cluster please")),
    "batch-scheduler-unreachable": _scheduler_unreachable,
    "batch-name-clash": _name_clash,
}


def batch_case(row_id: str, tmp: Path) -> tuple[int, str]:
    """Run a batch row; return (exit code, text that must contain the phrase)."""
    return BATCH_CASES[row_id](tmp, tmp / "out")


SLOW = {"mesh-below-quality", "batch-one-bad-file", "batch-scheduler-unreachable"}


def test_the_table_is_complete():
    ids = [r["id"] for r in ROWS]
    assert len(ids) == len(set(ids)) and len(ids) >= 30
    for r in ROWS:
        assert r["phrase"] and r["exit"] in (0, 1, 2, 3, 4, 5, 130)
    single = [r["id"] for r in ROWS if not r["id"].startswith("batch-")]
    for rid in single:  # every row has a check (a KeyError here is a row without one)
        assert callable(cli_case) and rid
    assert {"batch-interrupted", "batch-worker-killed", "batch-rerun", "tensile-nan", "asset-truncated"} <= set(ids)


@pytest.mark.parametrize("row", [pytest.param(r, id=r["id"], marks=[pytest.mark.slow] if r["id"] in SLOW else [])
                                 for r in ROWS])
def test_row(row, tmp_path, run_cli):
    if row["id"].startswith("batch-"):
        code, text = batch_case(row["id"], tmp_path)
        assert code == row["exit"], (code, text[-600:])
        assert row["phrase"] in text, text[-800:]
        return
    argv = cli_case(row["id"], tmp_path)
    code, out, err = run_cli(*argv)
    assert code == row["exit"], (code, err[-800:])
    assert "Traceback" not in err
    errors = [ln for ln in err.splitlines() if ln.startswith("esmm: error: ")]
    assert len(errors) == 1 and "\n" not in errors[0], err
    assert row["phrase"] in errors[0], errors[0]
    assert not (tmp_path / "out.h5").exists()
