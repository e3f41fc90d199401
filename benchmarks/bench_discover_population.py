"""Discovery on an independent population: its false-positive rate on clean cases and its
confusion table on cases with one effect.

The population comes from ``benchmarks/population`` (a generator written from the literature,
recording through realistic acquisition chains and exporting in machine formats; it shares no
code with esmm). Each case is run the way a user runs it, ``esmm calibrate <files> --discover
--out <dir> --json <file>`` (the esmm installed beside this Python), one process per case, ``J``
at a time, each with a time limit; the score reads the JSON's ``effects`` (what discovery kept)
and ``final.terms`` (which of those are elastic-law terms).

Scoring:

* clean cases: a false positive is any history effect or artefact kept; elastic-law terms are
  counted separately (the base laws are not esmm's, so a term may be right). The rate has a 95 %
  Clopper-Pearson interval.
* effect cases: strict = the true effect kept and no other effect or artefact; lenient = the
  true effect among those kept. ``nonlinear_viscoelastic`` includes ``viscoelastic`` (stretch-
  dependent relaxation is relaxation), so for a true ``nonlinear_viscoelastic`` a kept
  ``viscoelastic`` beside it is not an extra; named as plain ``viscoelastic`` alone it is counted
  in its own column ("viscoelastic, not nonlinear"), not as right.
* a Mullins effect drawn as Miehe's discontinuous damage, ``P = (1 - D(max W0)) P_e``, is by its
  equations esmm's ``damage`` class (``P = (1 - D(max xi)) P_e``: the primary curve lowered too, the
  driver a running maximum of a monotone function of the stretch in these uniaxial tests), not its
  ``mullins`` (Ogden-Roxburgh: the primary curve is the elastic one); either name is right for it.
  Continuum damage (Simo 1987) must be named ``damage``.
* every effect case carries its detectability (``population/cases.py``, ``_detectability``: the
  signal-to-noise ratio of the known effect in the recorded force, correlated noise counted as the
  fewer independent samples it is); the effect cases are also scored by detectability bins, so that
  misses below the noise are told from misses of an effect that stands out of it; and its
  identifiability (the part of the detectability that no smooth elastic law of the stretch can take):
  the cases are scored by its bins too (with how many kept nothing, the right answer where it is below
  3), and by class where it is at least 30; of those, also where the part that neither an elastic law
  nor the class's neighbour takes is at least 30 (a stretch-dependent relaxation told from a plain one,
  a load cell's drift from a relaxation, a Mullins softening from a damage and back; ``population/cases.py``,
  ``NEIGHBOURS``); and, of those, the cases whose files were written without a time column, which esmm
  reads as processed curves with no loading history and no machine artefacts (every class but a specimen
  scale, ``READ_WITHOUT_TIME``), counted apart.
* runtimes, timeouts, errors (non-zero exits with their last message line), seeds.

``python benchmarks/bench_discover_population.py --cases N --seed S --jobs J --out results.json
[--timeout 300] [--clean-fraction 0.5] [--work DIR] [--no-nested]`` (``--no-nested``: esmm skips the nested
held-out errors, which only report, so the scores are the same and the runtimes the choice's alone; the
cases, with esmm's outputs beside them,
stay in ``--work``, by default a new temporary folder named in the JSON); ``make bench-discover``
runs 303 cases, 200 of them clean. ``run()`` is what ``benchmarks/run.py`` (``make bench``) calls:
a smaller population (``BENCH_CASES``) in a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from population import CLASSES, GENERATOR_VERSION, generate  # noqa: E402

#: ``make bench``'s population (override with ESMM_BENCH_POPULATION_CASES); ``make bench-discover``
#: runs 303 cases, 200 of them clean (103 with an effect).
BENCH_CASES, BENCH_SEED, BENCH_CLEAN = 60, 0, 2.0 / 3.0
NL, VE = "nonlinear_viscoelastic", "viscoelastic"
PLAIN_VE = "viscoelastic, not nonlinear"


def esmm_command() -> str:
    exe = Path(sys.executable).parent / "esmm"
    return str(exe) if exe.exists() else (shutil.which("esmm") or "esmm")


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1][:500] if lines else ""


def run_case(case: Path, files: list[str], *, timeout: float, exe: str, threads: int,
             cores: set[int] | None = None, nested: bool = True) -> dict:
    """Run discovery on one case folder (confined to *cores* where given); returns status, seconds, kept
    effects and terms."""
    out, js = case / "esmm_out", case / "esmm.json"
    js.unlink(missing_ok=True)
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[k] = str(threads)
    cmd = [exe, "calibrate", *files, "--discover", "--out", str(out), "--json", str(js)]
    if not nested:
        cmd.append("--no-nested")
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=case, capture_output=True, text=True, timeout=timeout, env=env,
                           preexec_fn=None if cores is None else (lambda: os.sched_setaffinity(0, cores)))
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "seconds": round(time.perf_counter() - t0, 2)}
    sec = round(time.perf_counter() - t0, 2)
    if p.returncode != 0 or not js.exists():
        return {"status": "error", "seconds": sec, "rc": p.returncode,
                "message": _last_line(p.stderr) or _last_line(p.stdout)}
    doc = json.loads(js.read_text())
    terms = list((doc.get("final") or {}).get("terms") or [])
    kept = list(doc.get("effects") or [])
    return {"status": "ok", "seconds": sec, "effects": [k for k in kept if k not in terms],
            "terms": [k for k in kept if k in terms], "ruptures": sorted(doc.get("ruptures") or {}),
            "warnings": len(doc.get("warnings") or [])}


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float | None, float | None]:
    """Exact binomial interval of a rate k/n."""
    if n == 0:
        return None, None
    from scipy.stats import beta

    a = 1.0 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


#: (class, variant) -> the other name that is right for it (module docstring).
SAME_CLASS = {("mullins", "discontinuous_damage"): "damage"}
#: detectability bins of the effect cases (signal-to-noise ratio of the known effect).
DETECT_BINS = (3.0, 30.0)
#: the classes esmm names from curves written without their time column: it reads such a curve as processed
#: (docs/design/discovery.md: no loading history, not even in a cyclic file, and no machine artefacts); the
#: identifiable cases of other classes whose files have no time are counted apart (``without_time``)
READ_WITHOUT_TIME = frozenset({"specimen_scale"})


def judge(true: str, effects: list[str], variant: str | None = None) -> tuple[bool, bool, list[str]]:
    """(strict, lenient, confusion columns) of one effect case (module docstring); the columns name what was
    kept, the other right name of a variant (:data:`SAME_CLASS`) included."""
    kept = set(effects)
    if true == NL and NL in kept:
        kept.discard(VE)
    cols = sorted(kept)
    if true == NL and NL not in kept and VE in kept:
        cols = [PLAIN_VE if c == VE else c for c in cols]
    alias = SAME_CLASS.get((true, variant))
    if alias is not None and alias in kept and true not in kept:
        kept = (kept - {alias}) | {true}
    return kept == {true}, true in kept, cols or ["nothing"]


def _by(rows: list[dict], key) -> dict:
    """{value: [cases, false positives]} of the clean cases by one attribute."""
    out: dict = {}
    for r in rows:
        v = str(key(r))
        n, k = out.get(v, [0, 0])
        out[v] = [n + 1, k + int(bool(r["effects"]))]
    return dict(sorted(out.items()))


def _bin(v: float, edges: tuple[float, float], what: str) -> str:
    lo, hi = edges
    return (f"< {100 * lo:g} % {what}" if v < lo else f"{100 * lo:g}-{100 * hi:g} % {what}" if v < hi
            else f">= {100 * hi:g} % {what}")


def score_clean(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["status"] == "ok"]
    fp = [r for r in ok if r["effects"]]
    lo, hi = clopper_pearson(len(fp), len(ok))
    invented: dict[str, int] = {}
    terms: dict[str, int] = {}
    for r in ok:
        for e in r["effects"]:
            invented[e] = invented.get(e, 0) + 1
        for e in r["terms"]:
            terms[e] = terms.get(e, 0) + 1
    return {"cases": len(rows), "ran": len(ok), "false_positives": len(fp),
            "fp_rate": len(fp) / len(ok) if ok else None, "fp_ci95": [lo, hi],
            "invented": dict(sorted(invented.items(), key=lambda kv: -kv[1])),
            "with_terms": sum(1 for r in ok if r["terms"]), "terms": terms,
            "fp_by_protocol": _by(ok, lambda r: r["protocol"]), "fp_by_mode": _by(ok, lambda r: r["mode"]),
            "fp_by_format": _by(ok, lambda r: r["format"]), "fp_by_filter": _by(ok, lambda r: r["chain"]["filter"]),
            "fp_by_bits": _by(ok, lambda r: r["chain"]["bits"]),
            "fp_by_quantize_at": _by(ok, lambda r: r["chain"]["quantize_at"]),
            "fp_by_hum": _by(ok, lambda r: r["chain"]["hum_of_noise"] > 0),
            "fp_by_family": _by(ok, lambda r: r["family"]),
            "fp_by_force_lag": _by(ok, lambda r: _bin(r["chain"]["force_lag_of_segment"], (1e-3, 1e-2), "of segment")),
            "fp_by_acquisition_error": _by(ok, lambda r: _bin(r["acquisition_error_of_range"], (1e-3, 1e-2), "of range")),
            "fp_cases": [r["case"] for r in fp]}


def score_effects(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["status"] == "ok"]
    confusion: dict[str, dict[str, int]] = {}
    by_class: dict[str, dict] = {}
    for r in ok:
        strict, lenient, cols = judge(r["class"], r["effects"], r.get("variant"))
        r["strict"], r["lenient"] = strict, lenient
        row = confusion.setdefault(r["class"], {})
        for c in cols:
            row[c] = row.get(c, 0) + 1
    for cls in CLASSES:
        rs = [r for r in rows if r["class"] == cls]
        good = [r for r in rs if r["status"] == "ok"]
        if not rs:
            continue
        by_class[cls] = {"cases": len(rs), "ran": len(good),
                         "strict": sum(r["strict"] for r in good), "lenient": sum(r["lenient"] for r in good),
                         "strict_rate": sum(r["strict"] for r in good) / len(good) if good else None,
                         "lenient_rate": sum(r["lenient"] for r in good) / len(good) if good else None}
    n = len(ok)
    return {"cases": len(rows), "ran": n, "strict_rate": sum(r["strict"] for r in ok) / n if n else None,
            "lenient_rate": sum(r["lenient"] for r in ok) / n if n else None, "by_class": by_class,
            "by_detectability": _by_detectability(ok),
            "by_identifiability": _by_detectability(ok, key="identifiability", symbol="d_id"),
            "by_class_identifiable": _by_class_identifiable(ok), "confusion": {k: confusion[k] for k in sorted(confusion)}}


def _by_detectability(ok: list[dict], *, key: str = "detectability", symbol: str = "d") -> dict:
    """{bin: {cases, strict, lenient, nothing}} of the effect cases by their effect's detectability (or, with
    *key* ``identifiability``, by the part of it no elastic law can take: ``population/cases.py``,
    ``_detectability``); ``nothing``: cases where discovery kept nothing, the right answer where the record
    cannot tell the effect from an elastic law."""
    lo, hi = DETECT_BINS
    keys = (f"{symbol} < {lo:g}", f"{lo:g} <= {symbol} < {hi:g}", f"{symbol} >= {hi:g}", "unknown")
    out: dict = {k: {"cases": 0, "strict": 0, "lenient": 0, "nothing": 0} for k in keys}
    for r in ok:
        d = r.get(key)
        b = out[keys[3] if d is None else keys[0] if d < lo else keys[1] if d < hi else keys[2]]
        b["cases"] += 1
        b["strict"] += int(r["strict"])
        b["lenient"] += int(r["lenient"])
        b["nothing"] += int(not r["effects"])
    return {k: v for k, v in out.items() if v["cases"]}


def _by_class_identifiable(ok: list[dict]) -> dict:
    """{class: {cases, strict, from_neighbour: {cases, strict}}} of the effect cases whose records can tell
    the effect from an elastic law (identifiability at least the upper detectability bin's edge,
    :data:`DETECT_BINS`); ``from_neighbour`` counts those of them that can also be told from the class's
    neighbour (``population/cases.py``, ``NEIGHBOURS``: a stretch-dependent relaxation from a plain one, a
    load cell's drift from a relaxation, a Mullins softening from a damage and back), at the same edge; a class
    without a neighbour, or whose variant the neighbour's name is right for (:data:`SAME_CLASS`), counts
    them all; ``without_time`` counts those whose files were written without a time column, of a class esmm
    does not read from such files (:data:`READ_WITHOUT_TIME`; only rows that say whether they have time)."""
    out: dict = {}
    for r in ok:
        if (r.get("identifiability") or 0.0) >= DETECT_BINS[1]:
            b = out.setdefault(r["class"], {"cases": 0, "strict": 0, "from_neighbour": {"cases": 0, "strict": 0},
                                            "without_time": {"cases": 0, "strict": 0}})
            b["cases"] += 1
            b["strict"] += int(r["strict"])
            if r.get("timed") is False and r["class"] not in READ_WITHOUT_TIME:
                b["without_time"]["cases"] += 1
                b["without_time"]["strict"] += int(r["strict"])
            alias = SAME_CLASS.get((r["class"], r.get("variant")))
            if all(v >= DETECT_BINS[1] for k, v in (r.get("identifiability_from") or {}).items() if k != alias):
                b["from_neighbour"]["cases"] += 1
                b["from_neighbour"]["strict"] += int(r["strict"])
    return {k: out[k] for k in CLASSES if k in out}


def _row(t: dict, res: dict) -> dict:
    """One case's record: its truth in brief and what discovery did."""
    ch = t["files"][0]["chain"]
    return {"case": t["case"], "class": t["class"], "protocol": t["protocol"]["kind"], "mode": t["mode"],
            "family": t["family"], "law": t["base_law"]["name"], "format": t["format"],
            "variant": (t["effect"] or {}).get("variant"), "effect_size": (t["effect"] or {}).get("size"),
            "detectability": (t["effect"] or {}).get("detectability"),
            "identifiability": (t["effect"] or {}).get("identifiability"),
            "identifiability_from": (t["effect"] or {}).get("identifiability_from"),
            "files": len(t["files"]), "samples": sum(f["samples"] for f in t["files"]),
            "timed": all((f.get("export") or {}).get("time", True) for f in t["files"]),
            "acquisition_error_of_range": max(f["acquisition_error_of_range"] for f in t["files"]),
            "chain": {k: ch.get(k) for k in ("filter", "order", "f_out", "bits", "quantize_at", "hum_of_noise",
                                             "decimator", "position", "force_lag_s", "force_lag_of_segment")},
            "seed": t["seed"], **{"effects": [], "terms": []}, **res}


def _core_slots(jobs: int, threads: int) -> queue.Queue | None:
    """One set of *threads* cores per job, so that concurrent cases never share a core (each case sees only
    its own cores and starts no more workers than it has); None where the platform cannot confine a process."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < jobs * threads:
        return None
    q: queue.Queue = queue.Queue()
    for j in range(jobs):
        q.put(set(cpus[j * threads:(j + 1) * threads]))
    return q


def evaluate(n_cases: int, seed: int, *, jobs: int, timeout: float, work: Path, clean_fraction: float,
             shard: tuple[int, int] = (0, 1), nested: bool = True) -> dict:
    """Generate the population into ``work``, run discovery on every case (or on shard ``k`` of ``n``: the
    cases whose index is ``k`` modulo ``n``), score it."""
    index = generate(seed, n_cases, work, clean_fraction=clean_fraction)
    exe = esmm_command()
    threads = max(1, (os.cpu_count() or 1) // max(jobs, 1))
    k, n = shard
    truths = [json.loads((work / c["case"] / "truth.json").read_text()) for i, c in enumerate(index) if i % n == k]

    slots = _core_slots(jobs, threads)

    def one(t: dict) -> dict:
        cores = slots.get() if slots else None
        try:
            res = run_case(work / t["case"], [f["file"] for f in t["files"]], timeout=timeout, exe=exe,
                           threads=threads, cores=cores, nested=nested)
        finally:
            if slots:
                slots.put(cores)
        print(f"[population] {t['case']} {t['class']}: {res['status']} {res['seconds']} s "
              f"{res.get('effects', res.get('message', ''))}", file=sys.stderr, flush=True)
        return _row(t, res)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(jobs, 1)) as pool:
        rows = list(pool.map(one, truths))
    wall = time.perf_counter() - t0
    res = {"population": {"seed": seed, "cases": n_cases, "clean_fraction": clean_fraction,
                          "generator_version": GENERATOR_VERSION, "folder": str(work),
                          "shard": f"{k}/{n}"},
           "esmm": exe, "jobs": jobs, "timeout_s": timeout, "nested": nested, "wall_s": round(wall, 1)}
    return {**res, **score(rows)}


def score(rows: list[dict]) -> dict:
    """The clean cases' false-positive rate, the effect cases' confusion table, runtimes and errors of *rows*."""
    secs = [r["seconds"] for r in rows if r["status"] != "timeout"]
    return {"clean": score_clean([r for r in rows if r["class"] == "clean"]),
            "effects": score_effects([r for r in rows if r["class"] != "clean"]),
            "runtime": {"median_s": statistics.median(secs) if secs else None, "max_s": max(secs) if secs else None,
                        "timeouts": [r["case"] for r in rows if r["status"] == "timeout"]},
            "errors": [{"case": r["case"], "class": r["class"], "rc": r["rc"], "message": r["message"]}
                       for r in rows if r["status"] == "error"],
            "cases": rows}


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def table(res: dict) -> str:
    c, e, rt = res["clean"], res["effects"], res["runtime"]
    lo, hi = c["fp_ci95"]
    lines = [f"population seed {res['population']['seed']}: {res['population']['cases']} cases, "
             f"generator {res['population']['generator_version']}; esmm {res['esmm']}; cases in "
             f"{res['population']['folder']}",
             f"clean: false positives {c['false_positives']}/{c['ran']} = {_pct(c['fp_rate'])} "
             f"(95 % CI {_pct(lo)} - {_pct(hi)}); elastic terms added on {c['with_terms']}/{c['ran']}",
             "  invented: " + (", ".join(f"{k} {v}" for k, v in c["invented"].items()) or "nothing"),
             f"effect cases: strict {_pct(e['strict_rate'])}, lenient {_pct(e['lenient_rate'])} of {e['ran']}",
             f"  {'true class':24s} {'n':>3s} {'strict':>7s} {'lenient':>8s}  kept"]
    for cls, b in e["by_class"].items():
        kept = ", ".join(f"{k} {v}" for k, v in sorted(e["confusion"].get(cls, {}).items(), key=lambda kv: -kv[1]))
        lines.append(f"  {cls:24s} {b['ran']:3d} {b['strict']:7d} {b['lenient']:8d}  {kept}")
    lines.append("  by detectability: " + "; ".join(f"{k}: {v['strict']}/{v['lenient']} of {v['cases']}"
                                                    for k, v in e.get("by_detectability", {}).items()))
    if e.get("by_identifiability"):
        lines.append("  by identifiability (the part no elastic law takes): " + "; ".join(
            f"{k}: {v['strict']}/{v['lenient']} of {v['cases']}, nothing kept {v['nothing']}"
            for k, v in e["by_identifiability"].items()))
        ids = e.get("by_class_identifiable", {})
        n, k = (sum(v[f] for v in ids.values()) for f in ("cases", "strict"))
        nb = [v.get("from_neighbour", v) for v in ids.values()]
        wt = [v.get("without_time", {"cases": 0, "strict": 0}) for v in ids.values()]
        lines.append(f"  named alone where d_id >= {DETECT_BINS[1]:g}: {k}/{n}; where the neighbouring class's "
                     f"d_id is too: {sum(v['strict'] for v in nb)}/{sum(v['cases'] for v in nb)}; written without "
                     f"time (no history or artefact read): {sum(v['strict'] for v in wt)}/{sum(v['cases'] for v in wt)}")
    lines.append(f"runtime: median {rt['median_s']} s, max {rt['max_s']} s, timeouts {len(rt['timeouts'])}, "
                 f"errors {len(res['errors'])}, wall {res['wall_s']} s with {res['jobs']} jobs")
    lines += [f"  error {x['case']} ({x['class']}): {x['message']}" for x in res["errors"]]
    return "\n".join(lines)


def run() -> dict:
    """``make bench``: a smaller population (ESMM_BENCH_POPULATION_CASES, default BENCH_CASES)."""
    n = int(os.environ.get("ESMM_BENCH_POPULATION_CASES", BENCH_CASES))
    with tempfile.TemporaryDirectory(prefix="esmm-population-") as work:
        res = evaluate(n, BENCH_SEED, jobs=max(1, os.cpu_count() or 1), timeout=300.0, work=Path(work),
                       clean_fraction=BENCH_CLEAN)
    res.pop("cases")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=max(1, os.cpu_count() or 1))
    ap.add_argument("--timeout", type=float, default=300.0, help="per case [s]")
    ap.add_argument("--clean-fraction", type=float, default=0.5, help="at least 0.5")
    ap.add_argument("--out", default=str(HERE / "population_results.json"))
    ap.add_argument("--work", default=None, help="folder for the cases, kept (default: a new temporary folder)")
    ap.add_argument("--shard", default="0/1", help="K/N: run only the cases whose index is K modulo N")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="score the shards' results together (one population, every shard once) into --out")
    ap.add_argument("--no-nested", action="store_true",
                    help="run esmm with --no-nested: the same choices without the nested errors, which only report "
                         "(the runtimes are then the choice's alone)")
    ap.add_argument("--rescore", default=None, metavar="JSON",
                    help="score a finished run's esmm outputs again with this version's judge and truths into --out")
    ap.add_argument("--classes", default=None, metavar="A,B",
                    help="with --rescore: regenerate only the cases of these classes (the others keep the run's rows)")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, Path(args.out))
    if args.rescore:
        classes = [c.strip() for c in args.classes.split(",") if c.strip()] if args.classes else None
        bad = [c for c in classes or () if c not in CLASSES]
        if bad:
            ap.error(f"--classes: unknown class {bad[0]!r}; the classes are {', '.join(CLASSES)}")
        return rescore(Path(args.rescore), Path(args.out), classes=classes)
    try:
        k, n = (int(v) for v in args.shard.split("/"))
        if not 0 <= k < n:
            raise ValueError
    except ValueError:
        ap.error(f"--shard {args.shard!r}: give K/N with 0 <= K < N, e.g. 0/2")
    out = Path(args.out)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="esmm-population-"))
    if work.exists() and any(work.iterdir()):
        if not (work / "index.json").exists():
            ap.error(f"--work {work}: not empty and not a population folder (no index.json); give a new folder")
        shutil.rmtree(work)  # an earlier population: regenerated from its seed
    res = evaluate(args.cases, args.seed, jobs=args.jobs, timeout=args.timeout, work=work,
                   clean_fraction=args.clean_fraction, shard=(k, n), nested=not args.no_nested)
    _write(out, res)
    print(table(res))
    return 0


def _write(out: Path, res: dict) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(res, indent=1) + "\n")
    os.replace(tmp, out)


def merge(paths: list[str], out: Path) -> int:
    """Score the shards *paths* of one population together; refuses shards of different populations or
    esmm versions, and a case met twice."""
    docs = [json.loads(Path(p).read_text()) for p in paths]
    pops = {(d["population"]["seed"], d["population"]["cases"], d["population"]["clean_fraction"],
             d["population"]["generator_version"]) for d in docs}
    if len(pops) != 1:
        raise SystemExit(f"--merge: the shards come from different populations {sorted(pops)}")
    rows = [r for d in docs for r in d["cases"]]
    names = [r["case"] for r in rows]
    if len(set(names)) != len(names):
        raise SystemExit("--merge: a case appears in two shards")
    first = docs[0]
    res = {"population": {**first["population"], "shard": "+".join(d["population"]["shard"] for d in docs),
                          "folder": [d["population"]["folder"] for d in docs]},
           "esmm": [d["esmm"] for d in docs], "jobs": [d["jobs"] for d in docs], "timeout_s": first["timeout_s"],
           "wall_s": [d["wall_s"] for d in docs], **score(sorted(rows, key=lambda r: r["case"]))}
    _write(out, res)
    print(table(res))
    return 0


#: what a row holds of esmm's run (the rest is the case's truth, :func:`_row`)
RUN_KEYS = ("status", "seconds", "effects", "terms", "ruptures", "warnings", "rc", "message")


def rescore(path: Path, out: Path, *, classes: list[str] | None = None) -> int:
    """Score the esmm outputs of a finished run (*path*) again: its population regenerated from its seed
    (a temporary folder), each row rebuilt from the case's truth of this generator and the run's own result.
    With *classes*, only the cases of those classes are regenerated and rebuilt (a case depends only on the
    seed, its index and its line of the plan), the others keeping the run's rows: for a run whose generator
    wrote other records for another class; the classes and commands of an earlier partial rescore are kept
    beside this one's. Refuses a population whose records differ from the run's (sample counts per case)."""
    doc = json.loads(path.read_text())
    pop = doc["population"]
    redo = [r for r in doc["cases"] if classes is None or r["class"] in classes]
    with tempfile.TemporaryDirectory(prefix="esmm-rescore-") as work:
        generate(pop["seed"], pop["cases"], Path(work), clean_fraction=pop["clean_fraction"],
                 only=None if classes is None else [int(r["case"].rsplit("_", 1)[1]) for r in redo])
        truths = {r["case"]: json.loads((Path(work) / r["case"] / "truth.json").read_text()) for r in redo}
    rows = [_row(truths[r["case"]], {k: r[k] for k in RUN_KEYS if k in r}) if r["case"] in truths else r
            for r in doc["cases"]]
    moved = [r["case"] for r, old in zip(rows, doc["cases"]) if r["samples"] != old["samples"]]
    if moved:
        raise SystemExit(f"--rescore: this generator writes other records than the run's ({', '.join(moved[:5])})")
    kept = {k: v for k, v in doc.items()
            if k not in ("clean", "effects", "runtime", "errors", "cases", "rescore_command", "rescored_classes")}
    command = (f"python benchmarks/bench_discover_population.py --rescore {path} --out {out}"
               + (f" --classes {','.join(classes)}" if classes else ""))
    before = doc.get("rescore_command") if doc.get("rescored_classes") and classes else None
    res = {**kept, "population": {**pop, "generator_version": GENERATOR_VERSION,
                                  "run_generator_version": pop.get("run_generator_version",
                                                                   pop["generator_version"])},
           "rescore_command": command if before is None else [*([before] if isinstance(before, str) else before),
                                                              command],
           **({"rescored_classes": list(dict.fromkeys([*doc.get("rescored_classes", []), *classes]))}
              if classes else {}), **score(rows)}
    _write(out, res)
    print(table({"esmm": "-", "jobs": "-", "wall_s": "-", **res,
                 "population": {**res["population"], "folder": "-"}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
