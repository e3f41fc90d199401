"""``scripts/size_floor_trade.py``: which held-out checks a lower size floor would let through, counted on
hand-made population folders whose answer is known."""

from __future__ import annotations

import json
from pathlib import Path

from scriptkit import load_script


def _check(name, units, *, p=1e-9, rep=1e-3, kept=False):
    return {"name": name, "heldout_p": p, "heldout_level": 1e-4, "heldout_p_replication": rep,
            "heldout_noise_units": units, "kept": kept}


def _case(folder: Path, name: str, effect, kept, candidates) -> None:
    case = folder / name
    case.mkdir(parents=True)
    (case / "truth.json").write_text(json.dumps({"effect": effect}))
    (case / "esmm.json").write_text(json.dumps({"effects": kept, "candidates": candidates}))


def test_the_trade_counts_only_checks_the_size_requirement_alone_refused(tmp_path):
    pop = tmp_path / "pop"
    set_ = {"name": "permanent_set", "identifiability": 96.0}
    _case(pop, "case_0000", None, ["toe"], [_check("sensor_offset", 0.6), _check("toe", 0.9)])  # through at 0.5
    _case(pop, "case_0001", None, [], [_check("viscoelastic", 0.3, rep=0.2)])  # not replicated: never through
    _case(pop, "case_0002", None, ["slack"], [_check("slack", 5.0, kept=True)])  # a false positive already
    _case(pop, "case_0003", set_, [], [_check("permanent_set", 0.46), _check("damage", 0.9)])  # the set at 0.25
    _case(pop, "case_0004", set_, ["permanent_set"], [_check("permanent_set", 3.0, kept=True)])  # named
    _case(pop, "case_0005", {**set_, "identifiability": 12.0}, [], [_check("permanent_set", 0.9)])  # not identifiable
    (pop / "case_0006").mkdir()  # a case that did not run
    rows = load_script("size_floor_trade").trade([pop], [0.25, 0.5])
    assert rows[0.25] == {"clean": 2, "clean_reached": 1, "misses": 1, "misses_reached": 1}
    assert rows[0.5] == {"clean": 2, "clean_reached": 1, "misses": 1, "misses_reached": 0}


def test_a_missing_folder_is_one_line_and_exit_2(tmp_path, capsys):
    assert load_script("size_floor_trade").main([str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bench_discover_population.py --work" in err


def test_the_replication_trade_counts_checks_the_replication_alone_refused(tmp_path):
    pop = tmp_path / "pop"
    _case(pop, "case_0000", None, [], [_check("viscoelastic", 3.0, rep=0.08)])  # through at 0.1
    _case(pop, "case_0001", None, [], [_check("viscoelastic", 0.5, rep=0.08)])  # too small as well
    _case(pop, "case_0002", {"name": "damage", "identifiability": 50.0}, [], [_check("damage", 2.0, rep=0.3)])
    rows = load_script("size_floor_trade").trade([pop], [0.1, 0.5], "replication")
    assert rows[0.1] == {"clean": 2, "clean_reached": 1, "misses": 1, "misses_reached": 0}
    assert rows[0.5] == {"clean": 2, "clean_reached": 1, "misses": 1, "misses_reached": 1}
