"""Discovery's force-lag estimate against an independent acquisition chain's delay.

The generated population (benchmarks/population, no esmm code) records every case through a chain
whose force channel lags the position by its filters' and decimator's group delays, and writes that
delay in ``truth.json``. ``scripts/population_lag.py`` reads each case as discovery reads it; on clean
cycling records, which reverse at every peak, the lag read must be the chain's.
"""

from __future__ import annotations

import numpy as np
import pytest
from scriptkit import load_script


@pytest.mark.slow
def test_the_lag_read_on_generated_cycles_is_the_chains_delay(tmp_path):
    from population import make_case

    mod = load_script("population_lag")
    rows = []
    for k, seq in enumerate(np.random.SeedSequence(31).spawn(12)):
        make_case(seq, "clean", tmp_path / f"c{k}", kind="cycles")
        rows += mod.case_lags(tmp_path / f"c{k}")
    read = [r for r in rows if r["read_s"] > 0]
    rel = np.array([(r["read_s"] - r["true_s"]) / r["true_s"] for r in read])
    assert len(read) >= 9, rows
    assert abs(float(np.median(rel))) < 0.03 and float(np.percentile(np.abs(rel), 75)) < 0.08, rel
    assert "relative error: median" in mod.summary(rows)
