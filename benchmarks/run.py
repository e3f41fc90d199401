"""Run the benchmarks and write one JSON file (``make bench``).

Each ``benchmarks/bench_*.py`` module exposes ``run() -> dict`` of measured
figures (medians of repeated runs). A module that fails is recorded with its
error and the others still run. Select with ``--only calibrate,simulate``: the
other benchmarks' entries already in the output file are kept, each with its own
``created`` time, so a partial run updates the file instead of emptying it.
``make bench`` then renders benchmarks/RESULTS.md from the file
(benchmarks/results_md.py).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import sys
import time
import traceback
from datetime import UTC, datetime
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"esmm_bench_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def machine() -> dict:
    import numpy

    info = {"python": platform.python_version(), "platform": platform.platform(),
            "cpu_count": os.cpu_count(), "numpy": numpy.__version__}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        import psutil

        info["memory_gib"] = round(psutil.virtual_memory().total / 2**30, 1)
    except ImportError:
        pass
    return info


def _kept(out: Path, only: set[str]) -> dict:
    """With ``--only``: the entries of the other benchmarks in the existing *out* (empty without it)."""
    if not only or not out.is_file():
        return {}
    try:
        previous = json.loads(out.read_text(encoding="utf-8")).get("benchmarks", {})
    except (OSError, ValueError, AttributeError):
        return {}
    return {name: entry for name, entry in previous.items() if name not in only}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default=str(HERE / "results.json"))
    ap.add_argument("--only", default="", help="comma-separated bench names (calibrate, tables, ...)")
    args = ap.parse_args(argv)
    only = {s.strip() for s in args.only.split(",") if s.strip()}
    from esmm.pipeline import __version__

    out = Path(args.out)
    results = {"esmm_version": __version__, "created": datetime.now(UTC).isoformat(timespec="seconds"),
               "machine": machine(), "benchmarks": _kept(out, only)}
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem[len("bench_"):]
        if only and name not in only:
            continue
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        created = datetime.now(UTC).isoformat(timespec="seconds")
        try:
            figures = _load(path).run()
            results["benchmarks"][name] = {"ok": True, "created": created, "figures": figures}
        except Exception as exc:  # noqa: BLE001 - record and go on
            results["benchmarks"][name] = {"ok": False, "created": created, "error": f"{type(exc).__name__}: {exc}",
                                           "traceback": traceback.format_exc()}
        results["benchmarks"][name]["seconds"] = round(time.perf_counter() - t0, 2)
        print(f"[bench] {name}: {results['benchmarks'][name]['seconds']} s", file=sys.stderr, flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2, default=str) + "\n")
    os.replace(tmp, out)
    print(json.dumps({k: v.get("figures", v.get("error")) for k, v in results["benchmarks"].items()}, indent=2, default=str))
    print(f"wrote {out}", file=sys.stderr)
    ran = [v for k, v in results["benchmarks"].items() if not only or k in only]
    return 0 if all(v["ok"] for v in ran) else 1


if __name__ == "__main__":
    sys.exit(main())
