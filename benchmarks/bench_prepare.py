"""`esmm prepare` end to end: a 1 M-triangle InVesalius-style STL and the 117 k-triangle
partial liver to a ~5 000-node tetra asset; wall time and peak memory of the command.

Each case runs the installed ``esmm`` in a subprocess (imports included, as a user
sees it); peak memory is the child's maximum resident set size. The volumetric
compensation is content-addressed and cached (docs/design/tables.md, "The record, the cache and the cost"): the cases run with a
warm cache, and the one-time cost of the calibration is measured separately.
"""

from __future__ import annotations

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
SHARED = REPO.parent / "shared" / "data" / "meshes"
ESMM = str(Path(sys.executable).with_name("esmm"))


def _run(args, env) -> tuple[float, float]:
    """(wall seconds, peak RSS of the child in MiB) of one esmm command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    proc = subprocess.run([ESMM, "-q", *args], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"esmm {' '.join(args)} failed: {proc.stderr.strip()[-500:]}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return wall, max(peak, before) / 1024.0


def run() -> dict:
    from esmm.pipeline.mesh.synthetic import invesalius_like_surface

    work = Path(tempfile.mkdtemp(prefix="esmm-bench-prepare-"))
    env = dict(os.environ, ESMM_CACHE_DIR=str(work / "cache"))
    out: dict = {}
    try:
        big = work / "invesalius_1M.stl"
        t0 = time.perf_counter()
        surf = invesalius_like_surface(voxel=(0.33, 0.33, 0.66), path=big)
        out["synthetic_1M"] = {"triangles": int(len(surf.faces)), "generate_s": round(time.perf_counter() - t0, 1)}

        # One-time compensation calibration (fills the cache for the cases below).
        small = REPO / "data" / "meshes" / "ts_liver_3mm_closed.stl"
        wall, _ = _run(["prepare", str(small), "--nodes", "5000", "-o", str(work / "warm.h5")], env)
        wall_nc, _ = _run(["prepare", str(small), "--nodes", "5000", "--no-compensate", "-o", str(work / "nc.h5")], env)
        out["compensation_one_time_s"] = round(wall - wall_nc, 1)

        cases = {"invesalius_1M": big}
        partial = SHARED / "ts_liver_partial_1mm.stl"
        if partial.exists():
            cases["partial_liver_117k"] = partial
        for name, path in cases.items():
            walls, peaks = [], []
            for k in range(3):
                w, p = _run(["prepare", str(path), "--nodes", "5000", "-o", str(work / f"{name}{k}.h5")], env)
                walls.append(w)
                peaks.append(p)
            import h5py

            with h5py.File(work / f"{name}0.h5", "r") as f:
                nodes = int(f["mesh/points"].shape[0])
                tets = int(f["mesh/tets"].shape[0])
            out[name] = {"wall_s_median": round(statistics.median(walls), 2),
                         "wall_s_all": [round(w, 2) for w in walls],
                         "peak_rss_mib": round(max(peaks), 0), "nodes": nodes, "tets": tets}
        out["goals_s"] = {"invesalius_1M": 30.0, "partial_liver_117k": 10.0}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out
