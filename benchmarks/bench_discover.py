"""Discovery: the runtime of one discovery on a 10 000-sample file, and the confusion table of a seeded
population of generated cases with hidden effects (docs/design/discovery.md, "What it achieves").

Goals: one discovery on a 10 000-sample file under 30 s on a 2-core machine; at least 95 % of
the population's cases with the right names, the error at least halved where an effect is hidden.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

DATA = Path(__file__).resolve().parent.parent / "data" / "tensile"
#: population size and seed (every class of pipeline/discover/population.py six times)
POPULATION = 114
SEED = 0


def _runtime() -> dict:
    from esmm.pipeline.discover import discover
    from esmm.pipeline.tensile import read

    raw = DATA / "vhb4910_raw" / "lu_0d01_2d0.csv"  # 10 010 samples, a raw machine export
    test = read(raw)
    times, kept = [], None
    for _ in range(2):
        t0 = time.perf_counter()
        res = discover([test])
        times.append(time.perf_counter() - t0)
        kept = res.kept
    return {"file": raw.name, "samples": test.n, "discover_s_median": round(statistics.median(times), 2),
            "discover_s_all": [round(t, 2) for t in times], "kept": kept, "goal_s": 30.0}


def _population() -> dict:
    from esmm.pipeline.discover.population import score

    table = score(POPULATION, SEED)
    table["goal_right_rate"] = 0.95
    return table


def run() -> dict:
    return {"runtime_10k_samples": _runtime(), "population": _population()}
