#!/usr/bin/env python3
"""Regenerate the results of docs/design/discovery-results.md ("On the shared real records"): ``esmm calibrate --discover`` on every real data set.

Usage::

    .venv/bin/python scripts/discover_results.py [--data ../shared/data/tensile] [--only tendon,foam]
        [--seeds 1 2] [--out docs/figures/discover_results.json]

Each row runs the command a user would (``esmm calibrate FILES --discover --out DIR``, the
defaults) and reads its ``discover.json``: NRMSE before and after (fitted, held out, and nested:
held out of the whole selection), the kept names, the discovery's own time and the command's
wall time. ``--from DIR`` reads ``DIR/<row>.json`` instead of running (the ``--json`` of that
same command, run by hand; its wall time from ``DIR/<row>.wall`` if there). ``--seeds`` also runs
the in-house generated population (:func:`esmm.pipeline.discover.population.score`, 114 cases;
a regression check of the machinery, not a figure to quote) for each seed given. Prints the
markdown table and writes every figure to ``--out`` (rows and seeds not run are kept from an
existing file, and so is its ``before`` block: the same rows as recorded by the selection that
docs/design/discovery-results.md, "On the shared real records", compares against). The rows take minutes.
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
    return row_figures(d, wall)


def row_figures(d: dict, wall: float | None) -> dict:
    """The figures of one row from a ``discover.json`` (schema ``esmm.discover/1``)."""
    b, f = d["base"], d["final"]
    return {"ok": True, "files": len(d["files"]), "samples": d["samples"],
            "base_nrmse": b["nrmse"], "base_heldout_nrmse": b["heldout_nrmse"],
            "base_nested_nrmse": b.get("nested_heldout_nrmse"),
            "final_nrmse": f["nrmse"], "final_heldout_nrmse": f["heldout_nrmse"],
            "final_nested_nrmse": f.get("nested_heldout_nrmse"),
            "kept": list(d["effects"]), "discover_s": round(d["seconds"], 1),
            "command_s": round(wall, 1) if wall is not None else None,
            "ruptures": sorted(d.get("ruptures", {})), "slips": {k: len(v) for k, v in d.get("slips", {}).items()},
            "not_identifiable": d.get("not_identifiable", []), "outcome": d.get("outcome", "")}


def read_row(folder: Path, key: str) -> dict:
    """A row from ``folder/<key>.json`` written by the row's command with ``--json``."""
    wall = folder / f"{key}.wall"
    return row_figures(json.loads((folder / f"{key}.json").read_text()),
                       float(wall.read_text()) if wall.exists() else None)


def _pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def _errors(r: dict, which: str, nested: bool) -> str:
    out = f"{_pct(r[which + '_nrmse'])} / {_pct(r[which + '_heldout_nrmse'])}"
    n = r.get(which + "_nested_nrmse")
    return out + (f" / {_pct(n)}" if nested and n is not None else (" / –" if nested else ""))


def table(rows: dict, before: dict | None = None) -> str:
    """The markdown table of docs/design/discovery-results.md, "On the shared real records": before and after.

    Errors are NRMSE fitted / held out / nested (held out of the whole selection); the
    recorded ``before`` rows have no nested error.
    """
    before = before or {}
    lines = ["| data | kept before | kept now | base: fitted / held out / nested | final before: fitted / "
             "held out | final now: fitted / held out / nested | time before → now (discovery; command) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for key, label, patterns in ROWS:
        r, b = rows.get(key), before.get(key)
        if not r or not r.get("ok"):
            continue
        files = " ".join(f"`{p}`" for p in patterns)
        was = (", ".join(b["kept"]) or "nothing") if b else "–"
        fin_was = _errors(b, "final", False) if b else "–"
        t_was = f"{b['discover_s']:.0f} s" if b else "–"
        cmd = f"; {r['command_s']:.0f} s" if r.get("command_s") is not None else ""
        lines.append(f"| {label}: {files} | {was} | {', '.join(r['kept']) or 'nothing'} | "
                     f"{_errors(r, 'base', True)} | {fin_was} | {_errors(r, 'final', True)} | "
                     f"{t_was} → {r['discover_s']:.0f} s{cmd} |")
    return "\n".join(lines)


def _write(out: Path, rows: dict, population: dict, before: dict | None) -> None:
    from esmm.pipeline.atomicio import write_json

    doc = {"rows": rows, "population": population}
    if before is not None:
        doc["before"] = before
    write_json(out, doc)


def main(argv=None) -> int:
    shared = ROOT.parent / "shared" / "data" / "tensile"
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=shared if shared.is_dir() else ROOT / "data" / "tensile")
    ap.add_argument("--only", default="", help="comma-separated prefixes of row keys (tendon, foam_new, ...); "
                                              "'none' runs no row")
    ap.add_argument("--seeds", type=int, nargs="*", default=[], help="population seeds to run (114 cases each)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "discover_results.json")
    ap.add_argument("--from", dest="src", type=Path, default=None,
                    help="read each row from DIR/<row>.json (the row's command run by hand with --json)")
    args = ap.parse_args(argv)

    old = json.loads(args.out.read_text()) if args.out.exists() else {}
    rows, population, before = old.get("rows", {}), old.get("population", {}), old.get("before")
    only = [s for s in args.only.split(",") if s]
    for key, label, patterns in ROWS:
        if only and not any(key.startswith(p) for p in only):
            continue
        print(f"[discover_results] {key} ...", file=sys.stderr, flush=True)
        if args.src is not None:
            if not (args.src / f"{key}.json").exists():
                continue
            figures = read_row(args.src, key)
        else:
            figures = run_row(args.data, patterns)
        rows[key] = {"label": label, "patterns": patterns, **figures}
        _write(args.out, rows, population, before)
    for seed in args.seeds:
        from esmm.pipeline.discover.population import score

        print(f"[discover_results] population seed {seed} ...", file=sys.stderr, flush=True)
        population[str(seed)] = score(114, seed)
        _write(args.out, rows, population, before)
    print(table(rows, (before or {}).get("rows")))
    for seed, p in sorted(population.items()):
        print(f"population seed {seed}: {p['right']}/{p['cases']} right ({100 * p['right_rate']:.1f} %), "
              f"halved {100 * p['halved_rate']:.1f} %, {p['seconds']} s; wrong: {p['wrong']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
