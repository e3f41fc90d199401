"""The implicit step's time by phase on assets, with variants of the stepper A/B in one process.

docs/design/realtime.md ("Per phase") reads its tables from this script. Each asset runs the
default scene (``--scene``) with each variant of the implicit stepper, a warm-up run of each first,
then ``--runs`` rounds with the variants taken in turn (pairs under the same load). Per run: the
stepping wall time and the stepping thread's CPU time, the simulated time over each (real-time
factors), the thread CPU time by phase (exclusive: a phase called inside another counts only in
the inner one) and the stepper's counts. Per variant the median run's figures, and its grasper
force against the first variant's median run and, with ``--explicit``, against the explicit
stepper's (``implicit_accuracy`` of benchmarks/bench_simulate.py, over the lift)::

    python scripts/implicit_profile.py A.h5 [B.h5 ...] [--runs 3] [--threads auto]
        [--variant NAME:key=value,key=value ...] [--explicit [--reference DIR]] [--out profile.json]

A variant's keys are :class:`~esmm.pipeline.simulate.implicit.BackwardEuler` keyword arguments
(numbers, booleans, strings), a key ``scene.FIELD`` a field of the scene
(``scene.factor=mixed``), a key ``module.attr`` or ``module.Class.attr`` that attribute;
``base`` (no keyword) is always the first.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

#: (label, module, owner, attribute) of each timed phase.
PHASES = (
    ("solves", "esmm.pipeline.linalg.linsolve", "Constraints", "apply"),
    ("renewals", "esmm.pipeline.simulate.factorcache", "FactorCache", "refactor"),
    ("rows", "esmm.pipeline.simulate.factorcache", "FactorCache", "set_rows"),
    ("residuals", "esmm.pipeline.simulate.implicit_system", "StepSystem", "residual"),
    ("commit", "esmm.pipeline.simulate.implicit", "BackwardEuler", "_commit"),
    ("haptics", "esmm.pipeline.simulate.implicit", None, "patch_stiffness"),
    ("quasi_newton_algebra", "esmm.pipeline.linalg.quasinewton", "LBFGSMemory", "direction"),
    ("newton_products", "esmm.pipeline.simulate.implicit_system", "StepSystem", "operator"),
)
COUNTS = ("steps", "quasi_newton", "newton", "cg", "solves", "factorizations", "fallbacks", "unconverged",
          "modelled", "backtracks", "thread_fallbacks", "factor_nnz")


class PhaseClock:
    """Exclusive thread CPU time per phase: a stack of open phases, each paused while an inner one runs."""

    def __init__(self):
        self.cpu: dict = {}
        self.calls: dict = {}
        self._stack: list = []

    def wrap(self, name: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            now = time.thread_time()
            if self._stack:
                outer, since = self._stack[-1]
                self.cpu[outer] = self.cpu.get(outer, 0.0) + now - since
            self._stack.append([name, now])
            try:
                return fn(*args, **kwargs)
            finally:
                end = time.thread_time()
                _, since = self._stack.pop()
                self.cpu[name] = self.cpu.get(name, 0.0) + end - since
                self.calls[name] = self.calls.get(name, 0) + 1
                if self._stack:
                    self._stack[-1][1] = end

        return timed

    def reset(self) -> None:
        self.cpu, self.calls = {}, {}

    def install(self):
        """Wrap every phase of :data:`PHASES`; returns the undo."""
        import importlib

        undo = []
        for name, mod, owner, attr in PHASES:
            m = importlib.import_module(mod)
            obj = m if owner is None else getattr(m, owner)
            old = getattr(obj, attr)
            setattr(obj, attr, self.wrap(name, old))
            undo.append((obj, attr, old))
        return lambda: [setattr(o, a, v) for o, a, v in undo]


def _value(text: str):
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME:key=value,...``; a key ``module.attr`` (with a dot) sets that module attribute for the
    variant's runs instead (``esmm.pipeline.simulate.implicit_iteration.QN_SWITCH=8``)."""
    name, _, rest = text.partition(":")
    kw = dict(item.split("=", 1) for item in rest.split(",") if item)
    return name, {k: _value(v) for k, v in kw.items()}


def _patched(kwargs: dict):
    """(stepper keyword arguments, module attributes to set) of a variant's *kwargs*."""
    import importlib

    stepper = {k: v for k, v in kwargs.items() if "." not in k}
    mods = []
    for k, v in kwargs.items():
        if "." in k and not k.startswith("scene."):
            owner, _, attr = k.rpartition(".")
            try:
                obj = importlib.import_module(owner)
            except ModuleNotFoundError:                  # module.Class.attr
                mod, _, cls = owner.rpartition(".")
                obj = getattr(importlib.import_module(mod), cls)
            mods.append((obj, attr, v))
    return stepper, mods


def stepper_with(stepper_kw: dict):
    """The implicit stepper's constructor with the variant's keyword arguments, which win over those the run's
    setup passes from the scene (``factor_matrix``, ``iteration``, ``rtol``, ...)."""
    from esmm.pipeline.simulate.implicit import BackwardEuler

    def make(*a, **k):
        return BackwardEuler(*a, **{**k, **stepper_kw})
    return make


def one_run(asset, scene, out: Path, kwargs: dict, clock: PhaseClock) -> dict:
    """The scene on *asset* with the implicit stepper made with *kwargs*; its figures."""
    import esmm.pipeline.simulate.frames as frames
    import esmm.pipeline.simulate.runsetup as runsetup
    from esmm.pipeline.simulate.implicit import BackwardEuler
    from esmm.pipeline.simulate.run import simulate_network

    cpu = [0.0]
    advance = BackwardEuler.advance

    def timed_advance(self, *a, **k):
        if cpu[0] == 0.0:               # the phases before the first step (the first factor) not counted
            clock.reset()
        c = time.thread_time()
        try:
            return advance(self, *a, **k)
        finally:
            cpu[0] += time.thread_time() - c

    import dataclasses

    scene = dataclasses.replace(scene, **{k[6:]: v for k, v in kwargs.items() if k.startswith("scene.")})
    stepper_kw, mods = _patched(kwargs)
    saved = [(m, a, getattr(m, a)) for m, a, _ in mods]
    for m, a, v in mods:
        setattr(m, a, v)
    runsetup.BackwardEuler = stepper_with(stepper_kw)
    BackwardEuler.advance = timed_advance
    clock.reset()
    undo = clock.install()
    try:
        res = simulate_network(asset.network, asset.tables, scene, out)
    finally:
        undo()
        for m, a, v in saved:
            setattr(m, a, v)
        BackwardEuler.advance = advance
        runsetup.BackwardEuler = BackwardEuler
    del frames
    s = res.summary
    stats = s.integrator
    phases = {k: v for k, v in clock.cpu.items()}
    return {"stepping_wall_s": s.stepping_wall_s, "stepping_cpu_s": cpu[0],
            "real_time_factor": s.real_time_factor, "real_time_factor_cpu": s.simulated_s / cpu[0],
            "simulated_s": s.simulated_s, "threads": s.threads,
            "phases_cpu_s": phases, "phases_other_cpu_s": cpu[0] - sum(phases.values()),
            "phase_calls": dict(clock.calls), "counts": {k: stats.get(k) for k in COUNTS},
            "history": str(res.history), "load_average_after": os.getloadavg()}


def _median_run(runs: list) -> dict:
    return sorted(runs, key=lambda r: r["stepping_cpu_s"])[len(runs) // 2]


def profile_asset(path: Path, variants: list, scene, runs: int, explicit: bool, work: Path,
                  reference: Path | None = None) -> dict:
    from bench_simulate import _force_difference, implicit_accuracy
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.simulate.run import simulate_network

    asset = read_asset(path)
    clock = PhaseClock()
    done = {name: [] for name, _ in variants}
    row = {"nodes": asset.network.n_nodes, "springs": int(len(asset.network.springs)), "variants": {}}
    ref = None
    if explicit:
        keep = work if reference is None else reference
        keep.mkdir(parents=True, exist_ok=True)
        ref = keep / f"{path.stem}-explicit" / "history.h5"
        if not ref.is_file():
            res = simulate_network(asset.network, asset.tables, scene.with_overrides(method="explicit"),
                                   ref.parent)
            row["explicit_wall_s"] = res.summary.stepping_wall_s
        row["explicit_history"] = str(ref)
    lift_end = scene.grasper.waypoints[-1].time
    frame_dt = 1.0 / scene.frame_rate
    for i in range(runs + 1):
        for name, kw in variants:
            r = one_run(asset, scene, work / f"{path.stem}-{name}-{i}", kw, clock)
            acc = ""
            if ref is not None:         # every run's (the median run's is kept below, whole)
                a = r["accuracy_against_explicit"] = implicit_accuracy(Path(r["history"]), ref, lift_end, frame_dt)
                acc = (f"; vs explicit force {100 * a['force_err_max_frac']:.2f} % max, "
                       f"{100 * a['force_err_rms_frac']:.2f} % rms, {100 * a['force_err_at_solves_max_frac']:.2f} % "
                       f"at the solves, displacement {100 * a['displacement_err_frac_of_largest']:.2f} %")
            print(f"{path.stem} {name} run {i}: CPU rtf {r['real_time_factor_cpu']:.3g}, wall rtf "
                  f"{r['real_time_factor']:.3g}, solves {r['counts']['solves']}, factorizations "
                  f"{r['counts']['factorizations']}, load {r['load_average_after'][0]:.2f}{acc}", flush=True)
            if i:
                done[name].append(r)
    base_hist = None
    for name, kw in variants:
        med = dict(_median_run(done[name]))
        med["kwargs"] = kw
        med["real_time_factor_runs"] = [r["real_time_factor"] for r in done[name]]
        med["real_time_factor_cpu_runs"] = [r["real_time_factor_cpu"] for r in done[name]]
        med["real_time_factor_cpu_median"] = statistics.median(med["real_time_factor_cpu_runs"])
        med["real_time_factor_median"] = statistics.median(med["real_time_factor_runs"])
        if ref is not None:
            med["accuracy_against_explicit_runs"] = [r["accuracy_against_explicit"] for r in done[name]]
        med["counts_runs"] = [r["counts"] for r in done[name]]
        hist = Path(med.pop("history"))
        if base_hist is None:
            base_hist = hist
        else:
            med["force_against_base"] = _force_difference(hist, base_hist, frame_dt)
        if ref is not None:
            med["accuracy_against_explicit"] = implicit_accuracy(hist, ref, lift_end, frame_dt)
        row["variants"][name] = med
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("assets", nargs="+", type=Path)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", default="auto")
    ap.add_argument("--scene", default="default")
    ap.add_argument("--duration", default=None)
    ap.add_argument("--variant", action="append", default=[], help="NAME:key=value,... (BackwardEuler kwargs)")
    ap.add_argument("--explicit", action="store_true", help="also the explicit reference, once")
    ap.add_argument("--reference", type=Path, default=None,
                    help="folder that keeps the explicit runs (<asset stem>-explicit/history.h5) between calls")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    from esmm.pipeline.simulate.scene import load_scene

    scene = load_scene(a.scene).with_overrides(threads=a.threads, duration=a.duration)
    variants = [("base", {})] + [parse_variant(v) for v in a.variant]
    out = {"command": " ".join(["python scripts/implicit_profile.py", *(argv or sys.argv[1:])]),
           "load_average_at_start": os.getloadavg(), "assets": {}}
    with tempfile.TemporaryDirectory() as d:
        for path in a.assets:
            out["assets"][path.stem] = row = profile_asset(path, variants, scene, a.runs, a.explicit, Path(d),
                                                                a.reference)
            for name, v in row["variants"].items():
                ph = v["phases_cpu_s"]
                tot = v["stepping_cpu_s"]
                share = ", ".join(f"{k} {100 * t / tot:.0f} %" for k, t in sorted(ph.items(), key=lambda kv: -kv[1]))
                extra = ""
                if "accuracy_against_explicit" in v:
                    acc = v["accuracy_against_explicit"]
                    extra += f"; vs explicit force {100 * acc['force_err_max_frac']:.2f} % max"
                    runs_ = v["accuracy_against_explicit_runs"]
                    extra += "".join(f" ({key} {100 * min(a[k] for a in runs_):.1f}-{100 * max(a[k] for a in runs_):.1f} %)"
                                     for key, k in (("runs: max", "force_err_max_frac"), ("rms", "force_err_rms_frac"),
                                                    ("at the solves", "force_err_at_solves_max_frac"),
                                                    ("displacement", "displacement_err_frac_of_largest")))
                if "force_against_base" in v:
                    extra += f"; vs base force {100 * v['force_against_base']['max_frac']:.2f} % max"
                print(f"{path.stem} {name}: CPU rtf {v['real_time_factor_cpu_median']:.3g} "
                      f"(runs {', '.join(f'{x:.3g}' for x in v['real_time_factor_cpu_runs'])}), wall rtf "
                      f"{v['real_time_factor_median']:.3g}; {share}, other "
                      f"{100 * v['phases_other_cpu_s'] / tot:.0f} %; counts {v['counts']}{extra}", flush=True)
    out["load_average_at_end"] = os.getloadavg()
    if a.out is not None:
        a.out.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
