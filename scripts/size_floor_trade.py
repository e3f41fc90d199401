#!/usr/bin/env python3
"""What the held-out test's size requirement (or its replication check) costs and buys: identifiable effects it
alone refuses, and clean records a looser setting would let a candidate through on.

Usage::

    .venv/bin/python scripts/size_floor_trade.py FOLDER [FOLDER ...] [--floors 0.25 0.5 0.75 0.9]
    .venv/bin/python scripts/size_floor_trade.py FOLDER [FOLDER ...] --check replication --floors 0.1 0.2 0.5

Each ``FOLDER`` is a population run by ``benchmarks/bench_discover_population.py --work FOLDER``: every
case folder holds ``truth.json`` and the discovery's ``esmm.json``. A candidate's held-out check is read from
``esmm.json`` (its last check: round 1 on a record where nothing was kept). For each floor below the
default of one squared resolution per sample it counts

* the **identifiable misses** (d_id >= 30, the true effect not named alone) whose true class passed the
  noise test and the replication check but not the size requirement, and had at least the floor;
* the **clean records** (nothing kept) on which a material effect or an artefact passed the first two
  checks with at least the floor: a candidate that a lower floor could have kept first, before the history
  test and the artefacts' own checks (an upper bound).

With ``--check replication`` the same for the replication check: the noise test and the size requirement
passed, the replication p-value above its level of 0.05 but at most the value given.

docs/design/discovery-results.md, "What the size requirement and the replication check cost", quotes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_discover_population import DETECT_BINS, judge  # noqa: E402
from esmm.pipeline.discover.trials import passes  # noqa: E402
from esmm.pipeline.materials.terms import TERM_NAMES  # noqa: E402


def _short(c: dict, lo: float, check: str = "size") -> bool:
    """Was candidate *c* refused by *check* alone, and would the looser value *lo* let it through (the size
    floor in squared resolutions, or the replication level)? The decision is the search's own
    (:func:`~esmm.pipeline.discover.trials.passes`) on the check as ``esmm.json`` records it."""
    if c.get("kept") or any(c.get(k) is None for k in ("heldout_p", "heldout_level", "heldout_p_replication")):
        return False
    h = {"p": c["heldout_p"], "p_replication": c["heldout_p_replication"],
         "resolution_units": c.get("heldout_noise_units") or 0.0}
    level = c["heldout_level"]
    if passes(h, level):
        return False
    if check == "replication":
        return passes({**h, "p_replication": 0.0}, level) and h["p_replication"] <= lo
    return passes(h, level, lo)


def _cases(folders: list[Path]):
    """(truth effect or None, esmm.json) of every case that ran."""
    for folder in folders:
        for case in sorted(folder.glob("case_*")):
            out = case / "esmm.json"
            if not out.exists():
                continue
            truth = json.loads((case / "truth.json").read_text())
            yield truth.get("effect"), json.loads(out.read_text())


def trade(folders: list[Path], floors: list[float], check: str = "size") -> dict:
    """{floor: {clean, clean_reached, misses, misses_reached}} over the cases of *folders* (:func:`_short`)."""
    out = {f: {"clean": 0, "clean_reached": 0, "misses": 0, "misses_reached": 0} for f in floors}
    for effect, res in _cases(folders):
        kept = [k for k in res.get("effects") or [] if k not in TERM_NAMES]
        cands = res.get("candidates") or []
        for f, row in out.items():
            if effect is None:
                if kept:
                    continue
                row["clean"] += 1
                row["clean_reached"] += any(c["name"] not in TERM_NAMES and _short(c, f, check) for c in cands)
                continue
            if (effect.get("identifiability") or 0.0) < DETECT_BINS[1]:
                continue
            if judge(effect["name"], kept, effect.get("variant"))[0]:
                continue
            row["misses"] += 1
            row["misses_reached"] += any(c["name"] == effect["name"] and _short(c, f, check) for c in cands)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--floors", nargs="+", type=float, default=[0.25, 0.5, 0.75, 0.9],
                    help="looser settings: size floors in squared resolutions, or replication levels")
    ap.add_argument("--check", choices=("size", "replication"), default="size")
    args = ap.parse_args(argv)
    missing = [str(f) for f in args.folders if not f.is_dir()]
    if missing:
        print(f"size_floor_trade: no population folder {missing[0]}; run bench_discover_population.py "
              "--work FOLDER first", file=sys.stderr)
        return 2
    for f, row in trade(args.folders, args.floors, args.check).items():
        print(f"{args.check} {f:g}: identifiable misses reached {row['misses_reached']} of {row['misses']}; "
              f"clean records with a candidate through {row['clean_reached']} of {row['clean']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
