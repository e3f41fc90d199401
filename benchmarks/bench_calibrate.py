"""Calibration speed: one fit of a 10 000-sample raw file; batch time vs number of files."""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parent.parent / "data" / "tensile"


def _median_time(fn, repeats=3):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def run() -> dict:
    from esmm.pipeline.batch.calibrate import calibrate_batch
    from esmm.pipeline.calibrate.fit import fit_material
    from esmm.pipeline.tensile import read

    raw = DATA / "vhb4910_raw" / "lu_0d01_2d0.csv"  # 10 010 samples, raw machine export
    t0 = time.perf_counter()
    test = read(raw)
    read_s = time.perf_counter() - t0
    out = {"raw_file": raw.name, "samples": test.n, "read_s": round(read_s, 4)}
    for model in ("esedf", "arruda-boyce"):
        med, times = _median_time(lambda m=model: fit_material([test], model=m))
        out[f"fit_{model}_s_median"] = round(med, 3)
        out[f"fit_{model}_s_all"] = [round(t, 3) for t in times]
    out["goal_fit_s"] = 2.0

    # Batch scaling: k files, one group each (--by folder would merge; use specimen = file stem).
    files = sorted((DATA / "budday2017_brain").glob("*.csv"))
    scaling = {}
    for k in (2, 4, 8):
        sel = (files * 4)[:k]
        copies = []
        tmp = Path(tempfile.mkdtemp(prefix="esmm-bench-"))
        for i, f in enumerate(sel):
            dst = tmp / f"{i:02d}_{f.name}"
            shutil.copy(f, dst)
            text = dst.read_text(encoding="utf-8")
            dst.write_text(text.replace("# specimen:", f"# specimen: b{i}-"), encoding="utf-8")
            copies.append(dst)
        med, _ = _median_time(lambda c=copies, d=tmp: calibrate_batch(
            c, out_dir=d / "out", by="specimen", fit_kwargs={"model": "esedf"}, workers=2, force=True), 1)
        scaling[str(k)] = round(med, 3)
        shutil.rmtree(tmp, ignore_errors=True)
    out["batch_seconds_by_files_2_workers"] = scaling
    ks = sorted(int(k) for k in scaling)
    out["batch_seconds_per_file"] = {str(k): round(scaling[str(k)] / k, 3) for k in ks}
    return out
