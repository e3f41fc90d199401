"""Discovery: the runtime of one discovery on a 10 000-sample file and on a 100 000-sample record.

``esmm calibrate --discover`` as a user runs it (the library call with the command's defaults:
8 starts, nested held-out errors) on the shared VHB 4910 raw exports
(docs/design/discovery.md, "Runtime"): one load-unload file of 10 007 samples, and a
relaxation record with a load-unload file, 100 211 samples at 25-50 Hz. Goals (2-core machine):
10 000 samples within 30 s, 100 000 samples within 120 s.

What discovery finds, and how often it invents something, is measured on the independent
population (``bench_discover_population.py``); the in-house generator of
``pipeline/discover/population.py`` is a fast regression test of the machinery, not a measure.
"""

from __future__ import annotations

import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "data" / "tensile" / "vhb4910_raw"
#: the 100 000-sample record: a relaxation test and a load-unload test of the same material
LARGE = ("relax_2d0.csv", "lu_0d01_2d0.csv")


def _one(names: tuple[str, ...], goal: float) -> dict:
    from esmm.pipeline.discover import discover
    from esmm.pipeline.tensile import read

    tests = [read(DATA / n) for n in names]
    t0 = time.perf_counter()
    res = discover(tests, n_starts=8)
    seconds = time.perf_counter() - t0
    nested = res.nested or {}
    return {"files": list(names), "samples": sum(t.n for t in tests), "discover_s": round(seconds, 1),
            "nested_s": round(float(nested.get("seconds", 0.0)), 1), "kept": list(res.kept), "goal_s": goal,
            "heldout_nrmse": [res.base.heldout.nrmse, res.final.heldout.nrmse],
            "nested_heldout_nrmse": [(nested.get("before") or {}).get("nrmse"), (nested.get("after") or {}).get("nrmse")]}


def run() -> dict:
    return {"runtime_10k_samples": _one(("lu_0d01_2d0.csv",), 30.0), "runtime_100k_samples": _one(LARGE, 120.0)}
