"""A seeded slice of the generated population (the benchmark runs all of it, benchmarks/bench_discover.py):
each hidden class is named right, nothing is added to clean data, and the error is halved."""

from __future__ import annotations

import warnings

import pytest
from esmm.pipeline.discover.population import CLASSES, Case, confusion, population, run_case, score

#: the slice: one case of each class, from the benchmark's own population (seed 0)
SLICE = dict(zip(CLASSES, population(len(CLASSES), 0)))


def _run(case: Case) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_case(case)


@pytest.mark.parametrize("name", ["none", "viscoelastic"])
def test_population_quick_cases(name):
    r = _run(SLICE[name])
    assert r["right"], r
    assert r["halved"], r


#: Slice cases the search gets wrong where the data do separate the truth (docs/design/discovery.md,
#: "Assumptions and limits", a per-file artefact or a toe kept as a proxy): strict, so a fix shows.
PROXY_KEPT = {
    # Truth: a slack per file (found) and a relaxation (g 0.59) at one rate. A toe term (elastic, tried
    # first) is kept in round 1; the relaxation, kept in round 2, is removed by the backward elimination
    # (held out one file of two: 22.1 -> 15.1 %, noise test p 0, replication p 0.13 on two files'
    # segments). A toe cannot make hysteresis: the data tell the relaxation from a toe.
    "viscoelastic + slack": "a toe term is kept in the first round and the relaxation, on two files' "
                            "held-out segments, does not replicate given it",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=f"search defect, not a limit of the data: {PROXY_KEPT[n]}"))
    if n in PROXY_KEPT else n for n in sorted(set(CLASSES) - {"none", "viscoelastic"})])
def test_population_slice(name):
    r = _run(SLICE[name])
    assert r["right"], r
    assert r["halved"], r


def test_population_is_seeded_and_covers_every_class():
    a, b = population(2 * len(CLASSES), 3), population(2 * len(CLASSES), 3)
    assert [c.truth for c in a] == [c.truth for c in b] and [c.vary for c in a] == [c.vary for c in b]
    assert {c.name.split(" (")[0] for c in a} == set(CLASSES)
    assert population(2 * len(CLASSES), 4)[1].truth != a[1].truth


def test_confusion_counts():
    rows = [{"class": "a", "hidden": ["viscoelastic"], "kept": ["viscoelastic"], "right": True, "exact": True,
             "halved": True},
            {"class": "a", "hidden": ["mooney"], "kept": ["i2exp"], "right": True, "exact": False, "halved": True},
            {"class": "none", "hidden": [], "kept": ["slack"], "right": False, "exact": False, "halved": True}]
    t = confusion(rows)
    assert t["right"] == 2 and t["per_class"]["a"] == {"right": 2, "cases": 2}
    assert t["per_name"]["slack"]["added_wrongly"] == 1 and t["per_name"]["I2 term"]["found"] == 1


def test_score_tabulates_a_seeded_run():
    t = score(1, 5)  # one case: the first class, nothing hidden
    assert t["cases"] == 1 and t["seed"] == 5 and t["per_class"] == {"none": {"right": t["right"], "cases": 1}}
    assert len(t["wrong"]) == 1 - t["right"] and t["not_halved"] == []


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known limit (docs/design/discovery.md): the pair pool misses a "
                                       "relaxation masked by per-file offsets that do not help alone")
def test_population_seed1_masked_pair():
    case = population(71, 1)[70]
    assert case.name == "viscoelastic + sensor_offset"
    assert _run(case)["right"]
