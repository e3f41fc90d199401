"""Batch calibration throughput (files per minute): 1 and 2 local workers, a 2-worker Dask LocalCluster.

The workload: the bundled Budday brain (8 files, 4 specimens) and Treloar
rubber (3 files, 1 specimen) data, copied twice under other specimen ids so
that the batch holds 10 groups of 22 files; every group is fitted with the
default ESEDF options (8 starts) and writes its four outputs. Each
configuration runs in a fresh output folder (no cache hits), timed from the
call to the summary, worker start-up included. A fourth figure is the
cached rerun (everything skipped). Scaling is the 2-worker throughput over
the 1-worker one (ideal 2.0 on 2 free cores); ``*_cpus_obtained`` says how
many CPUs the local runs actually got (other work on a shared machine caps
the scaling).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parent.parent / "data" / "tensile"


def _workload(root: Path, copies: int = 2) -> list[str]:
    """*copies* of the brain and Treloar files, each copy under its own specimen ids."""
    files = []
    for c in range(copies):
        for src in sorted((DATA / "budday2017_brain").glob("*.csv")) + sorted((DATA / "treloar1944").glob("*.csv")):
            text = src.read_text(encoding="utf-8")
            lines = text.splitlines(keepends=True)
            lines = [ln.replace("# specimen: ", f"# specimen: copy{c}-", 1) for ln in lines]
            dst = root / f"copy{c}" / src.parent.name / src.name
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_text("".join(lines), encoding="utf-8")
            files.append(str(dst))
    return files


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _timed(files, out, **kw) -> tuple[float, object, float]:
    """Wall time, summary, and CPU seconds of this process and its reaped children (local workers)."""
    from esmm.pipeline.batch.calibrate import calibrate_batch

    c0, t0 = _cpu(), time.perf_counter()
    s = calibrate_batch(files, out_dir=out, **kw)
    return time.perf_counter() - t0, s, _cpu() - c0


def run() -> dict:
    import dask
    from distributed import LocalCluster

    os.environ.setdefault("ESMM_CODE_VERSION", "bench")  # a tree edited meanwhile must not refuse jobs
    from esmm.pipeline.batch.jobs import code_version

    code_version.cache_clear()
    root = Path(tempfile.mkdtemp(prefix="esmm-bench-batch-"))
    try:
        files = _workload(root)
        res: dict = {"files": len(files), "groups": None, "load_average_before": list(os.getloadavg())}
        for name, kw in (("local_1", {"workers": 1}), ("local_2", {"workers": 2})):
            secs, s, cpu = _timed(files, root / name, **kw)
            assert s.exit_code == 0, s.table()
            res["groups"] = len(s.outcomes)
            res[f"{name}_s"] = round(secs, 2)
            res[f"{name}_files_per_min"] = round(60 * len(files) / secs, 1)
            res[f"{name}_job_s_sum"] = round(sum(o.seconds for o in s.outcomes), 2)
            # CPUs actually obtained (cpu seconds / wall seconds): below the worker count when
            # other work shares the machine, which caps the scaling.
            res[f"{name}_cpus_obtained"] = round(cpu / secs, 2)
        t0 = time.perf_counter()
        with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}), \
                LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                             dashboard_address=None, silence_logs=50) as cluster:
            res["dask_cluster_start_s"] = round(time.perf_counter() - t0, 2)
            secs, s, _ = _timed(files, root / "dask_2", scheduler=cluster.scheduler_address)
            assert s.exit_code == 0, s.table()
        res["dask_2_s"] = round(secs, 2)
        res["dask_2_files_per_min"] = round(60 * len(files) / secs, 1)
        secs, s, _ = _timed(files, root / "local_2", workers=2)
        assert s.n_cached == len(s.outcomes)
        res["cached_rerun_s"] = round(secs, 3)
        res["scaling_local_2_over_1"] = round(res["local_2_files_per_min"] / res["local_1_files_per_min"], 2)
        res["scaling_dask_2_over_local_1"] = round(res["dask_2_files_per_min"] / res["local_1_files_per_min"], 2)
        res["cpus"] = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        res["load_average_after"] = list(os.getloadavg())
        return res
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":  # pragma: no cover
    import json

    print(json.dumps(run(), indent=1))
