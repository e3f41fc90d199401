"""The batch runner: keys, caching, failure isolation, logs, summaries; calibrate/prepare batches."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

import cloudpickle
import numpy as np
import pytest
from esmm.pipeline.atomicio import atomic_path, write_text
from esmm.pipeline.batch import Job, cache_key, run_jobs
from esmm.pipeline.batch import cache as bcache
from esmm.pipeline.batch import jobs as bjobs
from esmm.pipeline.batch.local import describe_exit
from esmm.pipeline.batch.runner import parse_scheduler
from esmm.pipeline.errors import ConfigError, FitError, InputError

# Job functions defined here travel to the worker processes by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

BRAIN = Path(__file__).resolve().parent.parent / "data" / "tensile" / "budday2017_brain"


@pytest.fixture(autouse=True)
def pinned_code_version(monkeypatch):
    """Other people edit the tree while tests run: pin the code version for workers and us."""
    monkeypatch.setenv(bjobs.CODE_VERSION_ENV, "test-pinned")
    bjobs.code_version.cache_clear()
    yield
    bjobs.code_version.cache_clear()


# ----------------------------------------------------------------------------- job functions
def job_write(out_dir, name, text, sleep=0.0):
    time.sleep(sleep)
    p = write_text(Path(out_dir) / f"{name}.txt", text)
    return {"outputs": [p], "summary": {"chars": len(text), "value": np.float64(1.5)}}


def job_input_error(name):
    raise InputError(f"{name}.csv: line 3, column 2 'force': 'abc' is not a number; fix the file")


def job_fit_error():
    raise FitError("group g: the fit did not converge from 8 starts; try --starts 32")


def job_bug():
    return 1 / 0


def job_kill():
    os.kill(os.getpid(), signal.SIGKILL)


def job_segfault():
    import ctypes

    ctypes.string_at(0)


def job_sys_exit():
    sys.exit(3)


def job_hang_while_writing(out_dir):
    with atomic_path(Path(out_dir) / "hung.txt") as tmp:
        tmp.write_text("started")
        time.sleep(120)


def job_ctrl_c_while_writing(out_dir):
    with atomic_path(Path(out_dir) / "half.txt") as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt


def write_jobs(out, names, **kw):
    return [Job(name=n, kind="test", fn=job_write, args=(str(out), n, f"text of {n}"), kwargs=kw,
                config={"text": n}) for n in names]


def read_csv(path):
    return list(csv.DictReader(io.StringIO(Path(path).read_text())))


# ----------------------------------------------------------------------------- keys
def test_cache_key_follows_content_name_and_options_not_folder(tmp_path):
    a = tmp_path / "a" / "spec1.csv"
    a.parent.mkdir()
    a.write_text("stretch,stress [kPa]\n1,0\n1.1,2\n")
    job = Job(name="g", kind="calibrate", key_inputs=[a], config={"model": "esedf", "n_starts": 8})
    k0 = cache_key(job)
    assert len(k0) == 64 and int(k0, 16) >= 0
    # Moving the data keeps the key; renaming the file, changing a byte, an option, the kind or name does not.
    b = tmp_path / "b" / "spec1.csv"
    b.parent.mkdir()
    b.write_bytes(a.read_bytes())
    assert cache_key(Job(name="g", kind="calibrate", key_inputs=[b], config={"n_starts": 8, "model": "esedf"})) == k0
    c = tmp_path / "b" / "spec2.csv"
    c.write_bytes(a.read_bytes())
    variants = [
        Job(name="g", kind="calibrate", key_inputs=[c], config=job.config),
        Job(name="g", kind="calibrate", key_inputs=[a], config={"model": "esedf", "n_starts": 9}),
        Job(name="g", kind="prepare", key_inputs=[a], config=job.config),
        Job(name="h", kind="calibrate", key_inputs=[a], config=job.config),
        Job(name="g", kind="calibrate", key_inputs=[a, b], config=job.config),
    ]
    keys = {cache_key(v) for v in variants}
    assert k0 not in keys and len(keys) == len(variants)
    b.write_text("stretch,stress [kPa]\n1,0\n1.1,2.0\n")  # same numbers, other bytes
    assert cache_key(Job(name="g", kind="calibrate", key_inputs=[b], config=job.config)) != k0


def test_canonical_json_is_order_and_type_stable():
    cj = bjobs.canonical_json
    assert cj({"b": 1, "a": [1, 2]}) == cj({"a": (1, 2), "b": 1}) == '{"a":[1,2],"b":1}'
    assert cj({"x": np.float64(0.1), "n": np.int64(3)}) == cj({"x": 0.1, "n": 3})
    assert cj({"s": {"z", "a"}}) == '{"s":["a","z"]}'
    assert cj({"v": math.nan}) == '{"v":"NaN"}' and cj({"v": -math.inf}) == '{"v":"-Infinity"}'
    assert cj({"p": Path("/x/y")}) == '{"p":"/x/y"}'
    with pytest.raises(ConfigError, match=r"config\.fn: builtin_function_or_method values cannot be part"):
        cj({"fn": print})


def test_missing_key_input_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        cache_key(Job(name="g", kind="t", key_inputs=[tmp_path / "gone.csv"]))


def test_code_version_pins_and_source_digest_sees_every_byte(tmp_path, monkeypatch):
    assert bjobs.code_version().endswith("+test-pinned")
    monkeypatch.delenv(bjobs.CODE_VERSION_ENV)
    bjobs.code_version.cache_clear()
    v = bjobs.code_version()
    assert v.startswith(bjobs.__version__ + "+") and len(v.split("+")[1]) == 16
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "notes.txt").write_text("ignored")
    d0 = bjobs.source_digest([tmp_path])
    (tmp_path / "pkg" / "notes.txt").write_text("still ignored")
    assert bjobs.source_digest([tmp_path]) == d0
    (tmp_path / "pkg" / "m.py").write_text("x = 2\n")
    assert bjobs.source_digest([tmp_path]) != d0


# ----------------------------------------------------------------------------- scheduler parsing
@pytest.mark.parametrize("text, kind", [(None, "local"), ("local", "local"), ("serial", "serial"),
                                        ("tcp://10.0.0.5:8786", "dask"), ("node7:8786", "dask")])
def test_parse_scheduler(text, kind):
    assert parse_scheduler(text)[0] == kind


@pytest.mark.parametrize("bad", ["http://x", "tcp:/x:1", "cluster please", 42])
def test_parse_scheduler_refuses(bad):
    with pytest.raises(ConfigError, match="^scheduler: ") as info:
        parse_scheduler(bad)
    assert info.value.parameter == "scheduler"


@pytest.mark.parametrize("args, flag", [(["--scheduler", "http://x"], "--scheduler: "), (["--jobs", "0"], "--jobs: ")])
def test_cli_names_the_flag_of_a_bad_batch_option(tmp_path, capsys, args, flag):
    from esmm.cli.main import main

    code = main(["calibrate", "--by", "specimen", *map(str, _brain("cortex")), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    assert code == 2 and flag in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_prepare_out_named_like_an_asset_file_is_refused(tmp_path, capsys):
    """``--out liver.h5`` for one organ would make a folder called liver.h5: refused, pointing at -o."""
    from esmm.cli.main import main

    out = tmp_path / "liver.h5"
    code = main(["prepare", str(tmp_path / "liver.stl"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and f"give -o {out}" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_refuses_duplicate_names_and_bad_worker_counts(tmp_path):
    with pytest.raises(ConfigError, match="same output 'a'"):
        run_jobs(write_jobs(tmp_path, ["a", "a"]), out_dir=tmp_path / "o", scheduler="serial")
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ConfigError, match="workers"):
            run_jobs([], out_dir=tmp_path / "o", workers=bad)


def test_describe_exit():
    assert describe_exit(-9) == "worker died (killed by SIGKILL: out of memory, or killed by someone)"
    assert "SIGSEGV: a crash in compiled code" in describe_exit(-11)
    assert describe_exit(3) == "worker died (exit code 3 without a result)"


# ----------------------------------------------------------------------------- isolation
def test_one_bad_job_never_costs_the_others(tmp_path):
    out = tmp_path / "out"
    jobs = write_jobs(out, ["ok1", "ok2"]) + [
        Job(name="bad-data", kind="test", fn=job_input_error, args=("spec7",)),
        Job(name="no-fit", kind="test", fn=job_fit_error),
        Job(name="bug", kind="test", fn=job_bug),
        Job(name="killed", kind="test", fn=job_kill),
        Job(name="segfault", kind="test", fn=job_segfault),
        Job(name="sys-exit", kind="test", fn=job_sys_exit),
        Job.failed("unreadable.csv", "test", "unreadable.csv: is not a text file; export it as CSV"),
    ] + write_jobs(out, ["ok3"])
    s = run_jobs(jobs, out_dir=out, workers=2)
    got = {o.name: o for o in s.outcomes}
    assert [o.name for o in s.outcomes] == [j.name for j in jobs]  # job order kept
    for n in ("ok1", "ok2", "ok3"):
        assert got[n].status == "done" and got[n].outputs == [f"{n}.txt"]
        assert (out / f"{n}.txt").read_text() == f"text of {n}"
        assert got[n].summary == {"chars": len(f"text of {n}"), "value": 1.5}
    assert got["bad-data"].status == "failed" and got["bad-data"].exit_code == 2
    assert got["bad-data"].reason.startswith("spec7.csv: line 3, column 2 'force'")
    assert got["no-fit"].exit_code == 3 and "did not converge" in got["no-fit"].reason
    assert got["bug"].reason.startswith("internal error: ZeroDivisionError: division by zero")
    assert got["killed"].reason == "worker died (killed by SIGKILL: out of memory, or killed by someone)"
    assert got["segfault"].reason == "worker died (killed by SIGSEGV: a crash in compiled code)"
    assert "sys.exit(3)" in got["sys-exit"].reason
    assert got["unreadable.csv"].status == "failed" and got["unreadable.csv"].exit_code == 2
    for o in s.outcomes:
        assert "\n" not in o.reason
    assert (s.n_done, s.n_cached, s.n_failed) == (3, 0, 7) and s.exit_code == 5 and not s.ok

    # The table: one row per job plus the counts line.
    table = s.table()
    assert table.splitlines()[-1].startswith("10 job(s): 3 done, 0 skipped (cached), 7 failed in ")
    assert "worker died (killed by SIGSEGV" in table
    rows = read_csv(out / "batch-summary.csv")
    assert [r["name"] for r in rows] == [j.name for j in jobs]
    assert {r["name"]: r["status"] for r in rows}["ok1"] == "done"
    # The log: every job's outcome with its timing, the segfault's Python traceback, the bug's traceback.
    log = s.log_path.read_text()
    assert s.log_path.parent == out.resolve() and s.log_path.name.startswith("esmm-batch-")
    for n in ("ok1", "ok2", "ok3"):
        assert f"job {n}: done in " in log
    for n in ("bad-data", "no-fit", "bug", "killed", "segfault", "sys-exit", "unreadable.csv"):
        assert f"job {n}: failed" in log
    assert "Segmentation fault" in log and "ZeroDivisionError" in log and "batch end: exit code 5" in log


def test_a_hanging_job_times_out_alone_and_leaves_no_temp_file(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    jobs = [Job(name="hang", kind="test", fn=job_hang_while_writing, args=(str(out),))] + write_jobs(out, ["a", "b"])
    s = run_jobs(jobs, out_dir=out, workers=2, job_timeout=2)
    assert [o.status for o in s.outcomes] == ["failed", "done", "done"]
    assert s.outcomes[0].reason == "timed out after 2 s (the worker was killed)"
    assert not list(out.rglob(".hung.txt.tmp-*")) and not (out / "hung.txt").exists()
    with pytest.raises(ConfigError, match="job_timeout"):
        run_jobs(jobs, out_dir=out, job_timeout=0)


class SlowToLoad:
    """A job whose unpickling takes *load* s (as a heavy import would) and whose run takes *run* s."""

    def __init__(self, load, run):
        self.load, self.run = load, run

    def __setstate__(self, state):
        self.__dict__.update(state)
        time.sleep(self.load)

    def __call__(self):
        time.sleep(self.run)
        return "ran"


def test_job_time_limit_counts_from_the_start_of_the_job_not_of_its_worker():
    from esmm.pipeline.batch.local import LocalPool

    # Loading (3 s) and running (8 s) each fit in the 10 s limit, together they do not: the job must
    # not be killed for its worker's start-up. A job that runs past the limit still is.
    with LocalPool(2) as pool:
        pool.submit(1, SlowToLoad(3.0, 8.0))
        pool.submit(2, SlowToLoad(0.0, 60.0))
        events = {tid: (kind, value) for tid, kind, value in pool.events(timeout=10.0)}
    assert events[1] == ("result", "ran")
    assert events[2][0] == "died" and events[2][1][0] == "timed out after 10 s (the worker was killed)"


def test_serial_ctrl_c_is_returned_with_a_summary_and_no_temp_file(tmp_path):
    out = tmp_path / "out"
    jobs = write_jobs(out, ["first"]) + [Job(name="stopped", kind="test", fn=job_ctrl_c_while_writing,
                                             args=(str(out),))] + write_jobs(out, ["never"])
    s = run_jobs(jobs, out_dir=out, scheduler="serial")
    assert s.interrupted and s.exit_code == 130
    assert [o.status for o in s.outcomes] == ["done", "interrupted", "interrupted"]
    assert s.outcomes[2].reason == "not started: the batch was interrupted"
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith("esmm-batch-")) == \
        [".esmm-cache", "batch-summary.csv", "first.txt"]
    assert "INTERRUPTED" in s.log_path.read_text()


# ----------------------------------------------------------------------------- caching
def test_rerun_does_only_what_is_missing(tmp_path):
    out = tmp_path / "out"
    jobs = write_jobs(out, ["a", "b", "c", "d"])
    s1 = run_jobs(jobs, out_dir=out, scheduler="serial")
    assert [o.status for o in s1.outcomes] == ["done"] * 4 and s1.exit_code == 0
    manifests = {o.name: bcache.manifest_path(out, o.key) for o in s1.outcomes}
    assert all(p.is_file() for p in manifests.values())
    doc = json.loads(manifests["a"].read_text())
    assert doc["outputs"] == [{"path": "a.txt", "size": len("text of a"),
                               "sha256": bjobs.sha256_file(out / "a.txt")}]

    # A job killed before its manifest was written; an output edited; an output deleted.
    manifests["b"].unlink()
    (out / "c.txt").write_text("TEXT OF C")  # same size, other bytes
    (out / "d.txt").unlink()
    s2 = run_jobs(jobs, out_dir=out, scheduler="serial")
    assert [o.status for o in s2.outcomes] == ["cached", "done", "done", "done"]
    assert (out / "c.txt").read_text() == "text of c" and (out / "d.txt").is_file()
    assert s2.outcomes[0].summary == s1.outcomes[0].summary and s2.exit_code == 0
    log = s2.log_path.read_text()
    assert "job a: skipped, cached" in log and "output c.txt changed content" in log
    assert "output d.txt is missing" in log
    # Nothing to do, then --force redoes everything; a changed option is a new key.
    assert [o.status for o in run_jobs(jobs, out_dir=out, scheduler="serial").outcomes] == ["cached"] * 4
    assert [o.status for o in run_jobs(jobs, out_dir=out, scheduler="serial", force=True).outcomes] == ["done"] * 4
    changed = write_jobs(out, ["a"], sleep=0.0)
    changed[0].config = {"text": "a", "option": 2}
    assert run_jobs(changed, out_dir=out, scheduler="serial").outcomes[0].status == "done"


def test_corrupt_manifest_is_recomputed(tmp_path):
    out = tmp_path / "out"
    jobs = write_jobs(out, ["a"])
    key = run_jobs(jobs, out_dir=out, scheduler="serial").outcomes[0].key
    bcache.manifest_path(out, key).write_text('{"schema": "esmm.batch-manif')
    s = run_jobs(jobs, out_dir=out, scheduler="serial")
    assert s.outcomes[0].status == "done" and "is not valid JSON" in s.log_path.read_text()


def test_leftover_temp_files_are_swept_and_the_folder_is_locked(tmp_path):
    out = tmp_path / "out"
    (out / "g").mkdir(parents=True)
    leftovers = [out / ".liver.h5.tmp-abc123.h5", out / "g" / ".fit.png.tmp-x9.png"]
    for p in leftovers:
        p.write_bytes(b"half a file")
    keep = out / "g" / "notes.tmp.txt"
    keep.write_text("a user's file")
    s = run_jobs(write_jobs(out, ["a"]), out_dir=out, scheduler="serial")
    assert not any(p.exists() for p in leftovers) and keep.exists()
    assert "removed 2 temporary file(s)" in s.log_path.read_text()
    with bcache.FolderLock(out), pytest.raises(ConfigError, match="another esmm batch .pid \\d+"):
        run_jobs(write_jobs(out, ["a"]), out_dir=out, scheduler="serial")
    assert run_jobs(write_jobs(out, ["a"]), out_dir=out, scheduler="serial").exit_code == 0  # lock released


def test_a_file_system_without_locks_runs_unlocked_and_sweeps_nothing(tmp_path, monkeypatch):
    import errno
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    out = tmp_path / "out"
    out.mkdir()
    (out / ".a.txt.tmp-x.txt").write_text("someone else's?")
    s = run_jobs(write_jobs(out, ["a"]), out_dir=out, scheduler="serial")
    assert s.exit_code == 0 and (out / ".a.txt.tmp-x.txt").exists()
    assert "cannot lock" in s.log_path.read_text()


def test_output_folder_that_cannot_be_made(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="cannot create the output folder"):
        run_jobs(write_jobs(tmp_path, ["a"]), out_dir=tmp_path / "file" / "sub")


# ----------------------------------------------------------------------------- calibrate batch
def _brain(*specimens):
    return [str(p) for s in specimens for p in sorted(BRAIN.glob(f"{s}_*.csv"))]


@pytest.mark.slow
def test_calibrate_batch_equals_direct_fits_and_reruns_from_cache(tmp_path):
    from esmm.pipeline.batch.calibrate import calibrate_batch
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.tensile import read

    fit = dict(model="esedf", n_starts=2, seed=0)
    bad = tmp_path / "spec9.csv"
    bad.write_text("stretch,stress [kPa]\n1,0\n1.1,abc\n")
    files = _brain("cortex", "corpus_callosum") + [str(bad)]
    out = tmp_path / "batch"
    s = calibrate_batch(files, out_dir=out, fit_kwargs=fit, workers=2)
    assert [(o.name, o.status) for o in s.outcomes] == [
        (str(bad), "failed"), ("budday2017-cortex", "done"), ("budday2017-corpus_callosum", "done")]
    assert "line 3" in s.outcomes[0].reason and s.exit_code == 5
    rows = {r["group"]: r for r in read_csv(out / "summary.csv")}
    for spec in ("cortex", "corpus_callosum"):
        direct = fit_material([read(p) for p in _brain(spec)], **fit)
        row = rows[f"budday2017-{spec}"]
        for e in direct.estimates:
            unit = "Pa" if e.kind == "stress" else "1"
            assert float(row[f"{e.key} [{unit}]"]) == pytest.approx(e.value, rel=1e-7)
            assert row[f"{e.key} determined"] == ("yes" if e.identifiable else "no")
        assert float(row["r2 [1]"]) == pytest.approx(direct.r2, rel=1e-6)
        assert row["verdict"] in ("good", "poor", "unusable") and row["reason"].startswith(row["verdict"])
        for f in ("params.toml", "fit.png", "report.md", "fit.json"):
            assert (out / f"budday2017-{spec}" / f).is_file()
    assert rows["mean"]["status"].startswith("2 usable group(s)")

    assert rows[str(bad)]["status"] == "unreadable" and rows["budday2017-cortex"]["cached"] == ""
    s2 = calibrate_batch(files, out_dir=out, fit_kwargs=fit, workers=2)
    assert [o.status for o in s2.outcomes] == ["failed", "cached", "cached"]
    rows2 = {r["group"]: r for r in read_csv(out / "summary.csv")}
    assert rows2["budday2017-cortex"]["cached"] == "yes"
    for g in rows:  # the same numbers from the cache
        assert {k: v for k, v in rows2[g].items() if k not in ("seconds [s]", "cached")} == \
            {k: v for k, v in rows[g].items() if k not in ("seconds [s]", "cached")}
    # A changed option recomputes.
    s3 = calibrate_batch(_brain("cortex"), out_dir=out, fit_kwargs={**fit, "n_starts": 3}, workers=1)
    assert [o.status for o in s3.outcomes] == ["done"]


def test_calibrate_jobs_grouping_and_key_inputs(tmp_path):
    from esmm.pipeline.batch.calibrate import calibrate_jobs, safe_name

    d1, d2 = tmp_path / "lab1" / "left", tmp_path / "lab2" / "left"
    for d in (d1, d2):
        d.mkdir(parents=True)
        (d / "t1.csv").write_text("# specimen: s/1\nstretch,stress [kPa]\n1,0\n1.1,1\n")
        (d / "t2.csv").write_text("stretch,stress [kPa]\n1,0\n1.1,1\n")
    (d1 / "t2.toml").write_text('specimen = "s/1"\n')
    files = [d1 / "t1.csv", d1 / "t2.csv", d2 / "t1.csv", d2 / "t2.csv"]
    jobs = calibrate_jobs(files, by="specimen", out_dir=tmp_path / "o")
    byname = {j.name: j for j in jobs}
    assert sorted(byname) == ["s_1", "t2"]
    assert [Path(p).name for p in byname["s_1"].key_inputs] == ["t1.csv", "t2.csv", "t1.csv", "t2.toml"]
    jobs = calibrate_jobs(files, by="folder", out_dir=tmp_path / "o")
    assert sorted(j.name for j in jobs) == ["lab1_left", "lab2_left"]
    assert safe_name("../a b/c") == "a_b_c" and safe_name("...") == "group"
    with pytest.raises(ConfigError, match="^by: 'colour' is not one of specimen, folder"):
        calibrate_jobs(files, by="colour", out_dir=tmp_path)
    with pytest.raises(ConfigError):
        calibrate_jobs(files, out_dir=tmp_path, read_kwargs={"overrides": {"mode": "sideways"}})


# ----------------------------------------------------------------------------- prepare batch
def test_asset_names(tmp_path):
    from esmm.pipeline.batch.prepare import asset_names

    r = str(tmp_path.resolve())
    assert asset_names([tmp_path / "liver.stl", tmp_path / "kidney.nii.gz"]) == {
        f"{r}/liver.stl": "liver.h5", f"{r}/kidney.nii.gz": "kidney.h5"}
    assert asset_names([tmp_path / "p01" / "liver.stl", tmp_path / "p02" / "a" / "liver.stl"]) == {
        f"{r}/p01/liver.stl": "p01/liver.h5", f"{r}/p02/a/liver.stl": "p02/a/liver.h5"}
    with pytest.raises(ConfigError, match="both make liver.h5"):
        asset_names([tmp_path / "liver.stl", tmp_path / "liver.obj"])
    with pytest.raises(ConfigError, match="given twice"):
        asset_names([tmp_path / "liver.stl", tmp_path / "." / "liver.stl"])


def test_prepare_jobs_key_covers_config_and_material_files(tmp_path, monkeypatch):
    from esmm.pipeline.batch.prepare import prepare_jobs

    monkeypatch.chdir(tmp_path)
    stl = tmp_path / "liver.stl"
    stl.write_bytes(b"solid x\nendsolid x\n")
    mat = tmp_path / "mat.toml"
    mat.write_text('[material]\nmodel = "esedf"\n')
    cfg = tmp_path / "p.toml"
    cfg.write_text('[prepare]\nmaterial = "mat.toml"\n[mesh]\nsize = "20 mm"\n')
    (job,) = prepare_jobs([stl], out_dir="out", options={"config": "p.toml"})
    assert [Path(p).name for p in job.key_inputs] == ["liver.stl", "mat.toml"] or \
        [Path(p).name for p in job.key_inputs] == ["liver.stl", "p.toml", "mat.toml"]
    assert job.args[1] == str((tmp_path / "out" / "liver.h5").resolve())
    assert job.args[2]["config"] == str(cfg.resolve())  # absolute: workers may run elsewhere
    k0 = cache_key(job)
    mat.write_text('[material]\nmodel = "esedf"\nname = "other"\n')
    assert cache_key(prepare_jobs([stl], out_dir="out", options={"config": "p.toml"})[0]) != k0
    k1 = cache_key(prepare_jobs([stl], out_dir="out", options={"config": "p.toml"})[0])
    assert cache_key(prepare_jobs([stl], out_dir="out", options={"config": "p.toml", "force": True})[0]) != k1
    with pytest.raises(ConfigError, match="unknown option.*colour.*known: config, size"):
        prepare_jobs([stl], out_dir="out", options={"colour": "red"})
    with pytest.raises(ConfigError):
        prepare_jobs([stl], out_dir="out", options={"config": "missing.toml"})


def test_prepare_batch_reports_bad_organs(tmp_path):
    from esmm.pipeline.batch.prepare import prepare_batch

    broken = tmp_path / "broken.stl"
    broken.write_bytes(b"solid x\nfacet normal 0 0 1\n outer loop\n vertex 0 0 0\n")
    s = prepare_batch([broken, tmp_path / "absent.stl"], out_dir=tmp_path / "out", options={"config": "coarse"},
                      workers=1)
    got = {o.name: o for o in s.outcomes}
    assert got["broken"].status == "failed" and "not a multiple of 3" in got["broken"].reason
    assert got["absent"].status == "failed" and got["absent"].reason.endswith("absent.stl: no such file")
    assert s.exit_code == 5 and not list((tmp_path / "out").glob("*.h5"))


# ----------------------------------------------------------------------------- Dask
@pytest.mark.slow
def test_dask_local_cluster_runs_the_batch_and_survives_a_dead_worker(tmp_path):
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    from esmm.pipeline.batch.calibrate import calibrate_jobs, params_table

    out = tmp_path / "out"
    fit = dict(model="esedf", n_starts=2, seed=0)
    jobs = calibrate_jobs(_brain("cortex", "corpus_callosum"), out_dir=out, fit_kwargs=fit)
    jobs.append(Job(name="killer", kind="test", fn=job_kill))
    jobs += write_jobs(out, ["w1", "w2", "w3"])  # > 2 x threads: Dask queues the group on the scheduler
    # allowed-failures=3 (Dask's default): the scheduler gives up on the killer after its fourth
    # victim, and retries a job that was on a killed worker; on a loaded machine an innocent job was
    # seen on two killed workers, which failed it with allowed-failures=1.
    # worker-saturation=1: a worker holds only the task it runs.
    with dask.config.set({"distributed.scheduler.allowed-failures": 3,
                          "distributed.scheduler.worker-saturation": 1.0}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                     dashboard_address=None, silence_logs=50) as cluster:
        s = run_jobs(jobs, out_dir=out, scheduler=cluster.scheduler_address)
        got = {o.name: o for o in s.outcomes}
        assert got["killer"].status == "failed" and got["killer"].reason.startswith("worker died")
        assert [got[n].status for n in ("budday2017-cortex", "budday2017-corpus_callosum", "w1", "w2", "w3")] == \
            ["done"] * 5
        assert s.scheduler == f"dask {cluster.scheduler_address}" and s.exit_code == 5
        # Same numbers as the local pool would give (cached on rerun).
        local_out = tmp_path / "local"
        local = run_jobs(calibrate_jobs(_brain("cortex"), out_dir=local_out, fit_kwargs=fit), out_dir=local_out,
                         workers=1)
        est = {e["key"]: e["value"] for e in local.outcomes[0].summary["estimates"]}
        assert {e["key"]: e["value"] for e in got["budday2017-cortex"].summary["estimates"]} == \
            pytest.approx(est, rel=1e-9)
        with distributed.Client(cluster) as client:
            s2 = run_jobs(jobs[:2], out_dir=out, scheduler=client)
        assert [o.status for o in s2.outcomes] == ["cached", "cached"]
        assert "budday2017-cortex" in params_table(s2)


def test_unreachable_dask_scheduler_is_a_config_error(tmp_path):
    import socket

    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with pytest.raises(ConfigError, match=f"scheduler: cannot connect to a Dask scheduler at tcp://127.0.0.1:{port}"):
        run_jobs(write_jobs(tmp_path, ["a"]), out_dir=tmp_path / "o", scheduler=f"tcp://127.0.0.1:{port}",
                 connect_timeout=3)


# ----------------------------------------------------------------------------- adversarial sweep (batch inputs)
UNIAXIAL = "# mode: uniaxial\nstretch,nominal stress [MPa]\n1.1,0.1\n1.2,0.18\n1.4,0.3\n1.8,0.45\n2.2,0.6\n"


def test_calibrate_jobs_skip_what_a_wildcard_picks_up_beside_the_data(tmp_path):
    """`--by folder lab/*` picked up sidecars, measurement tables and editor backups as failed
    files (exit 5); a byte-identical copy doubled a test's weight in its group without a word."""
    from esmm.pipeline.batch.calibrate import calibrate_jobs
    from esmm.pipeline.progress import ListReporter

    d = tmp_path / "lab"
    d.mkdir()
    (d / "t1.csv").write_text(UNIAXIAL)
    (d / "t1.toml").write_text('specimen = "s1"\n')              # its sidecar: read with it
    (d / "stray.toml").write_text("[calibrate]\nstarts = 2\n")    # a TOML without data
    (d / "t1.csv~").write_text(UNIAXIAL)                          # editor backups and locks
    (d / ".t1.csv.swp").write_bytes(b"b0VIM 8.2\0\0")
    (d / ".~lock.t1.csv#").write_text(",user,host,01.01.2026;")
    (d / "t1.csv.bak").write_text(UNIAXIAL)
    (d / "measurements.csv").write_text("W,H,G\n10,2,30\n")       # not a test record
    (d / "t2.csv").write_text(UNIAXIAL)                           # same bytes as t1.csv, no sidecar
    (d / "t2-copy.csv").write_text(UNIAXIAL)                      # same bytes as t2.csv: said, kept
    rep = ListReporter()
    files = sorted(d.iterdir())
    jobs = calibrate_jobs(files, by="folder", out_dir=tmp_path / "o", reporter=rep)
    assert [(j.name, j.error) for j in jobs] == [("lab", None)]
    assert [Path(p).name for p in jobs[0].key_inputs] == ["t1.csv", "t2-copy.csv", "t2.csv", "t1.toml"]
    text = "\n".join(rep.warnings)
    for name in ("stray.toml", "t1.csv~", ".t1.csv.swp", ".~lock.t1.csv#", "t1.csv.bak", "measurements.csv"):
        assert name in text, name
    assert "t2.csv: the same bytes as" in text and "t1.toml" not in text
    with pytest.raises(InputError, match="none of the 2 file"):
        calibrate_jobs([d / "measurements.csv", d / "stray.toml"], by="folder", out_dir=tmp_path / "o")


def test_one_fit_over_a_wildcard_skips_the_same_files_as_the_batch(tmp_path, capsys):
    """`esmm calibrate lab/*` (one fit, no --by) failed on the sidecar TOML the wildcard matched (exit 2):
    the same rule as the batch's now (esmm.pipeline.tensile.files), with one warning per file set aside."""
    from esmm.cli.main import main

    d = tmp_path / "lab"
    d.mkdir()
    (d / "t1.csv").write_text(UNIAXIAL)
    (d / "t1.toml").write_text('specimen = "s1"\n')
    (d / "stray.toml").write_text("[calibrate]\nstarts = 2\n")
    (d / "t1.csv~").write_text(UNIAXIAL)
    (d / "t2.csv").write_text(UNIAXIAL.replace("0.6", "0.61"))
    code = main(["calibrate", *map(str, sorted(d.iterdir())), "--out", str(tmp_path / "o"), "--starts", "2"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "stray.toml: a TOML file without a data file" in err and "t1.csv~: named like an editor backup" in err
    assert "t1.toml: " not in err                  # the sidecar is read with its file, not set aside
    fit = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert len(fit["inputs"]) == 2


def test_an_output_the_system_refuses_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    """Standard output on a full disk (`esmm ... > /dev/full`) gave a traceback; now one line, exit 1."""
    from esmm.cli.main import main

    class Full(io.StringIO):
        def write(self, text):
            raise OSError(28, "No space left on device")

    (tmp_path / "t.csv").write_text(UNIAXIAL)
    monkeypatch.setattr(sys, "stdout", Full())
    code = main(["calibrate", str(tmp_path / "t.csv"), "--out", str(tmp_path / "o"), "--starts", "2"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "the system refused a read or write: No space left on device" in err


def test_group_names_avoid_the_batch_files_failed_rows_and_keep_unicode(tmp_path):
    """A specimen called summary.csv made a folder where the table goes (a traceback at the end); an
    unreadable path equal to a group name aborted the whole batch; non-ASCII ids lost their letters."""
    from esmm.pipeline.batch.calibrate import calibrate_jobs, group_names, safe_name

    names = group_names(["summary.csv", "Batch-Summary.csv", "Leber-ß", "肝臓", "肝臓/"], "specimen")
    assert names == {"summary.csv": "summary.csv-2", "Batch-Summary.csv": "Batch-Summary.csv-2",
                     "Leber-ß": "Leber-ß", "肝臓": "肝臓", "肝臓/": "肝臓-2"}
    assert len(safe_name("肝" * 200).encode()) <= 120
    a = tmp_path / "a"
    a.mkdir()
    (a / "t.csv").write_text(UNIAXIAL)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:  # "t" is both a missing file (failed row) and the group (specimen) of a/t.csv
        jobs = calibrate_jobs(["t", "a/t.csv"], by="specimen", out_dir=tmp_path / "o")
        # a folder given means its files: "a" is a/t.csv, read once
        folder_jobs = calibrate_jobs(["a", "a/t.csv"], by="folder", out_dir=tmp_path / "o")
    finally:
        os.chdir(cwd)
    assert sorted((j.name, j.error is None) for j in jobs) == sorted([("t", True), (str(tmp_path / "t"), False)])
    assert [(j.name, j.error) for j in folder_jobs] == [("a", None)]


def test_a_fit_error_names_the_files_of_its_group(tmp_path):
    """'1 sample cannot determine 2 parameters' did not say which file."""
    from esmm.pipeline.batch.calibrate import fit_group

    f = tmp_path / "r1.csv"
    f.write_text("# mode: uniaxial\nstretch,nominal stress [MPa]\n1.1,0.1\n")
    with pytest.raises(FitError, match=r"^r1\.csv: 1 sample cannot"):
        fit_group([str(f)], str(tmp_path / "o"), "g", {}, {"model": "arruda-boyce", "n_starts": 1})
    assert not (tmp_path / "o").exists()


def test_cli_batch_ctrl_c_and_quiet_failures_end_with_an_error_line(tmp_path, run_cli, monkeypatch):
    """Ctrl-C printed "calibrating: ... done" and no error line; with -q a failed batch printed nothing."""
    import esmm.pipeline.batch.calibrate as bcal

    good, bad = tmp_path / "g" / "t.csv", tmp_path / "b" / "t.csv"
    for p in (good, bad):
        p.parent.mkdir()
    good.write_text(UNIAXIAL)
    bad.write_text("# mode: uniaxial\nstretch,nominal stress [MPa]\n1.1,0.1\n")
    common = ["calibrate", "--by", "folder", good, bad, "--model", "arruda-boyce", "--starts", "1",
              "--scheduler", "serial"]
    code, out, err = run_cli("-q", *common, "--out", tmp_path / "o1")
    errors = [ln for ln in err.splitlines() if ln.startswith("esmm: error: ")]
    assert code == 5 and out == ""
    assert errors[0].startswith("esmm: error: b: t.csv: 1 sample cannot") and "1 of 2 job(s) failed: b" in errors[-1]

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(bcal, "fit_group", interrupted)
    code, out, err = run_cli(*common, "--out", tmp_path / "o2")
    errors = [ln for ln in err.splitlines() if ln.startswith("esmm: error: ")]
    assert code == 130 and "done" not in err
    assert len(errors) == 1 and errors[0].startswith("esmm: error: interrupted: 2 of 2 job(s) not finished")
    assert not list((tmp_path / "o2").rglob(".*.tmp-*")) and not (tmp_path / "o2" / "g").exists()
