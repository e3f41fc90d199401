#!/usr/bin/env python3
"""Regenerate the results of docs/design/discovery.md ("What it achieves"): ``esmm calibrate --discover`` on every real data set.

Usage::

    .venv/bin/python scripts/discover_results.py [--data ../shared/data/tensile] [--only tendon,foam]
        [--seeds 1 2] [--out docs/figures/discover_results.json]

Each row runs the command a user would (``esmm calibrate FILES --discover --out DIR``, the
defaults) and reads its ``discover.json``: NRMSE before and after (fitted and held out), the kept
names, the discovery's own time. ``--seeds`` also runs the generated population
(:func:`esmm.pipeline.discover.population.score`, 114 cases) for each seed given. Prints the
markdown table and writes every figure to ``--out`` (rows and seeds not run are kept from an
existing file). The rows and each seed take minutes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: (key, label of the table, file patterns relative to the data folder)
ROWS = [
    ("tendon_relax_1", "tendon, ramp-hold, 1 file", ["tendon_instron/relax_incubated_1.csv"]),
    ("tendon_relax_2", "tendon, ramp-hold (stress rises late in the hold)", ["tendon_instron/relax_incubated_2.csv"]),
    ("tendon_relax_3", "tendon, ramp-hold, truncated record", ["tendon_instron/relax_incubated_3_truncated.csv"]),
    ("tendon_relax_pair", "tendon, two specimens together",
     ["tendon_instron/relax_incubated_1.csv", "tendon_instron/relax_incubated_2.csv"]),
    ("tendon_relax_all", "tendon, three specimens together", ["tendon_instron/relax_incubated_*.csv"]),
    ("tendon_failure_1", "tendon, ramp to failure (progressive)", ["tendon_instron/failure_incubated_1.csv"]),
    ("tendon_failure_2", "tendon, ramp to failure (slips)", ["tendon_instron/failure_incubated_2.csv"]),
    ("tendon_failure_3", "tendon, ramp to failure (slips)", ["tendon_instron/failure_incubated_3.csv"]),
    ("foam_one", "foam, one specimen", ["foam_cyclic/new-heel-tension-1_1.csv"]),
    ("foam_new", "foam, new heel, 4 specimens", ["foam_cyclic/new-heel-tension-?_1.csv"]),
    ("foam_worn", "foam, worn heel, 4 specimens", ["foam_cyclic/worn-heel-tension-?_1.csv"]),
    ("foam_all", "foam, all 8 (the measurement tables skipped)", ["foam_cyclic/*.csv"]),
    ("brain_cortex", "brain cortex (TC + shear)", ["budday2017_brain/cortex_*.csv"]),
    ("brain_basal_ganglia", "brain basal ganglia", ["budday2017_brain/basal_ganglia_*.csv"]),
    ("brain_corona_radiata", "brain corona radiata", ["budday2017_brain/corona_radiata_*.csv"]),
    ("brain_corpus_callosum", "brain corpus callosum", ["budday2017_brain/corpus_callosum_*.csv"]),
    ("treloar", "Treloar rubber, 3 modes", ["treloar1944/*.csv"]),
    ("vhb", "VHB 4910, 11 raw files", ["vhb4910_raw/*.csv"]),
]


def _files(data: Path, patterns: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in patterns:
        found = sorted(data.glob(p))
        if not found:
            sys.exit(f"discover_results: no file matches {data / p}")
        out += found
    return out


def run_row(data: Path, patterns: list[str]) -> dict:
    """Run ``esmm calibrate FILES --discover`` in a temporary folder and read its discover.json."""
    esmm = Path(sys.executable).with_name("esmm")
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(esmm), "calibrate", *map(str, _files(data, patterns)), "--discover", "--out", tmp]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            return {"ok": False, "error": (proc.stderr or proc.stdout).strip().splitlines()[-1:]}
        d = json.loads((Path(tmp) / "discover.json").read_text())
    b, f = d["base"], d["final"]
    return {"ok": True, "files": len(d["files"]), "samples": d["samples"],
            "base_nrmse": b["nrmse"], "base_heldout_nrmse": b["heldout_nrmse"],
            "final_nrmse": f["nrmse"], "final_heldout_nrmse": f["heldout_nrmse"],
            "kept": list(d["effects"]), "discover_s": round(d["seconds"], 1), "command_s": round(wall, 1),
            "outcome": d.get("outcome", "")}


def _pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def table(rows: dict) -> str:
    """The markdown table of section 10 from the rows' figures."""
    lines = ["| data | base NRMSE (held out) | final NRMSE (held out) | kept | time |",
             "| --- | --- | --- | --- | --- |"]
    for key, label, patterns in ROWS:
        r = rows.get(key)
        if not r or not r.get("ok"):
            continue
        files = " ".join(f"`{p}`" for p in patterns)
        lines.append(f"| {label}: {files} | {_pct(r['base_nrmse'])} ({_pct(r['base_heldout_nrmse'])}) | "
                     f"{_pct(r['final_nrmse'])} ({_pct(r['final_heldout_nrmse'])}) | "
                     f"{', '.join(r['kept']) or 'nothing'} | {r['discover_s']:.0f} s |")
    return "\n".join(lines)


def main(argv=None) -> int:
    shared = ROOT.parent / "shared" / "data" / "tensile"
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=shared if shared.is_dir() else ROOT / "data" / "tensile")
    ap.add_argument("--only", default="", help="comma-separated prefixes of row keys (tendon, foam_new, ...); "
                                              "'none' runs no row")
    ap.add_argument("--seeds", type=int, nargs="*", default=[], help="population seeds to run (114 cases each)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "discover_results.json")
    args = ap.parse_args(argv)
    from esmm.pipeline.atomicio import write_json

    old = json.loads(args.out.read_text()) if args.out.exists() else {}
    rows, population = old.get("rows", {}), old.get("population", {})
    only = [s for s in args.only.split(",") if s]
    for key, label, patterns in ROWS:
        if only and not any(key.startswith(p) for p in only):
            continue
        print(f"[discover_results] {key} ...", file=sys.stderr, flush=True)
        rows[key] = {"label": label, "patterns": patterns, **run_row(args.data, patterns)}
        write_json(args.out, {"rows": rows, "population": population})
    for seed in args.seeds:
        from esmm.pipeline.discover.population import score

        print(f"[discover_results] population seed {seed} ...", file=sys.stderr, flush=True)
        population[str(seed)] = score(114, seed)
        write_json(args.out, {"rows": rows, "population": population})
    print(table(rows))
    for seed, p in sorted(population.items()):
        print(f"population seed {seed}: {p['right']}/{p['cases']} right ({100 * p['right_rate']:.1f} %), "
              f"halved {100 * p['halved_rate']:.1f} %, {p['seconds']} s; wrong: {p['wrong']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
