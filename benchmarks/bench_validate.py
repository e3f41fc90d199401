"""`esmm validate` end to end: the default liver asset (gravity and lift) and the 2.5 mm specimen cube.

The asset is the bundled liver prepared with the default preset (``esmm prepare
data/meshes/ts_liver_3mm_closed.stl``, as ``make demo`` does). Each run is the
installed ``esmm validate`` in a subprocess (imports included, as a user sees
it), timed by the wall clock and by the CPU time of the command and its worker
processes (user + system: on a shared machine the CPU time moves less than the
wall time). The liver is validated with the default ``--jobs`` (its cases at
once, one process each, where the process may use two cores) and once with
``--jobs 1`` (one after the other); the figures of merit of each run are
recorded beside the times, so that a change of solver that changes the answers
shows here. The goal: the default liver asset under 5 minutes on a 2-core
machine. ``ESMM_BENCH_VALIDATE_REPEATS`` sets the repeats of the default runs
(3).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ESMM = str(Path(sys.executable).with_name("esmm"))
GOAL_S = 300.0


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _esmm(args: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the command and its children) of one esmm command."""
    c0, t0 = _cpu_children(), time.perf_counter()
    proc = subprocess.run([ESMM, "-q", *args], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"esmm {' '.join(args)} failed: {proc.stderr.strip()[-500:]}")
    return wall, _cpu_children() - c0


def _validate(args: list[str], out: Path, repeats: int) -> dict:
    """Medians of *repeats* runs of ``esmm validate ARGS --out OUT``, the cases' times and figures of the last."""
    walls, cpus = [], []
    for _ in range(repeats):
        shutil.rmtree(out, ignore_errors=True)
        w, c = _esmm(["validate", *args, "--out", str(out)])
        walls.append(w)
        cpus.append(c)
    doc = json.loads((out / "validation.json").read_text())
    cases = {c["case"]: {"l2_error": c["l2_error"], "force_error": c["force_error"],
                         "continuum_newton_iterations": c["continuum"]["newton_iterations"],
                         "seconds": doc.get("case_seconds", {}).get(c["case"])} for c in doc["cases"]}
    return {"wall_s_median": round(statistics.median(walls), 1), "wall_s_all": [round(w, 1) for w in walls],
            "cpu_s_median": round(statistics.median(cpus), 1), "cpu_s_all": [round(c, 1) for c in cpus],
            "cases": cases, "failed": doc.get("failed", {})}


def run() -> dict:
    repeats = int(os.environ.get("ESMM_BENCH_VALIDATE_REPEATS", "3"))
    work = Path(tempfile.mkdtemp(prefix="esmm-bench-validate-"))
    try:
        asset = work / "liver.h5"
        _esmm(["prepare", str(REPO / "data" / "meshes" / "ts_liver_3mm_closed.stl"), "-o", str(asset)])
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        out = {"load_average_1min_at_start": load, "cpu_count": os.cpu_count(),
               "liver": _validate([str(asset)], work / "liver-validate", repeats),
               "liver_jobs1": _validate([str(asset), "--jobs", "1"], work / "liver-validate-1", 1),
               "specimen_2.5mm": _validate(["--specimen"], work / "specimen-validate", repeats)}
        out["goal_s"] = GOAL_S
        out["meets_goal"] = out["liver"]["wall_s_median"] < GOAL_S
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(run(), indent=2))
