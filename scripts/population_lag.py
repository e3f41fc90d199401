#!/usr/bin/env python3
"""How well discovery reads a force channel's lag: its estimate against the acquisition chain's delay.

Usage::

    .venv/bin/python scripts/population_lag.py FOLDER [--out lag.json]

``FOLDER`` is a generated population (``benchmarks/bench_discover_population.py --work FOLDER``):
every case folder holds its files and ``truth.json``, whose files carry the chain's true delay of
the force channel (``chain.force_lag_s``). Each case is read and prepared as discovery prepares it
(:func:`esmm.pipeline.discover.records.prepare`), and each record with time gives the lag it read
(0 where it reads none: only records that reverse are read) beside the true one. Prints the
relative error's quartiles and how many are more than 5 and 10 % off, by protocol; writes every
record's figures to ``--out``. docs/design/discovery-results.md, "Seed 11", quotes it.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
from esmm.pipeline.discover.records import prepare
from esmm.pipeline.errors import EsmmError
from esmm.pipeline.tensile.files import read_tests


def case_lags(folder: Path) -> list[dict]:
    """Per record with time of the case in *folder*: protocol, true and estimated lag [s]."""
    truth = json.loads((folder / "truth.json").read_text())
    files = truth["files"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        records = prepare(read_tests([folder / f["file"] for f in files]))
    out = []
    for r, f in zip(records, files):
        true = f.get("chain", {}).get("force_lag_s")
        if true is None or r.t is None:
            continue
        out.append({"case": truth["case"], "class": truth["class"], "protocol": truth["protocol"]["kind"],
                    "true_s": float(true), "read_s": float((r.lag or {}).get("seconds", 0.0))})
    return out


def summary(rows: list[dict]) -> str:
    read = [r for r in rows if r["read_s"] > 0]
    rel = np.array([(r["read_s"] - r["true_s"]) / r["true_s"] for r in read])
    lines = [f"{len(rows)} records with time; the lag read on {len(read)} "
             f"({dict(Counter(r['protocol'] for r in read))})"]
    if rel.size:
        q1, q2, q3 = np.percentile(rel, [25, 50, 75])
        lines.append(f"relative error: median {q2:+.2%}, quartiles {q1:+.2%} .. {q3:+.2%}; more than 5 % off: "
                     f"{int(np.sum(abs(rel) > 0.05))}, more than 10 %: {int(np.sum(abs(rel) > 0.1))}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    cases = sorted(p.parent for p in args.folder.glob("case_*/truth.json"))
    if not cases:
        print(f"{args.folder}: no case folders with truth.json; give a population's --work folder", file=sys.stderr)
        return 2
    rows: list[dict] = []
    for c in cases:
        try:
            rows += case_lags(c)
        except EsmmError:
            continue  # a file the reader refuses is the bench's to report
    print(summary(rows))
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
