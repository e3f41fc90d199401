"""Simulator speed: ns per spring per step, memory-bandwidth bound, demo real-time factor, render rate.

Networks are structured (Kuhn) tetrahedral boxes of increasing density built
with ``network_from_tets`` (RCM order), about 5 000, 50 000, 100 000 and
500 000 springs, with the stiffness tables of the bundled porcine-liver
material (secant law). For each: build time, kernel compile/cache-load time
(reported apart), and the median over repeats of the wall time of a block of
steps, single thread and all threads. The ESMM paper needed 3.517 ms per step
for 5 322 elements (~660 ns per element). Goals: < 20 ns per spring per step
on one thread; a step of a >= 100 000-spring network < 1 ms.

Memory-bandwidth bound: bytes streamed per spring per step (spring indices and
data, plus the node arrays divided by the springs per node) over a STREAM-like
copy bandwidth measured with numpy (large arrays: DRAM; 8 MB arrays: cache).

Material effects: the 50k network without effects, with 3 Prony terms per
spring, and with viscoelasticity + Mullins + damage (``bench_effects``).

Volume term (``bench_volume``): on the 5k and 50k boxes and on a box split in
eight (``50k-split``: the fabric of ``esmm prepare --split``), the compiled force
pass of the springs alone and the volume term's pass alone (one thread,
medians of CPU time per call; goal: the volume pass costs at most 2x the
spring pass), the whole step with and without the term, and the stable step
each allows (the term is stiff: docs/design/model.md, "The volume term").

Demo: the paper-sized liver asset (``esmm prepare`` of data/meshes/sofa_liver.stl,
preset "paper") in the default scene for 1 s of simulated time, adaptive and
whole-table step; then the off-screen rendering rate at 960 x 720.

Implicit stepper (``bench_implicit``, docs/design/simulator.md): the bundled
TotalSegmentator liver prepared with the "paper" and "fine" presets, the default
scene run with the implicit and the explicit stepper in the same process
(real-time factors and their ratio), the implicit step's cost at 100 k and
500 k springs (Kuhn boxes), and its memory traffic per step (the GPU note).

Step cost against size (``bench_step_scaling``, part "scaling"): the implicit step of 1/30 s
on Kuhn boxes of about 10 k, 40 k, 100 k and 500 k springs (gravity, the base fixed, the
first steps from rest), with the reused factor up to 100 k and with the Jacobi
preconditioner at every size (the factor of 500 k springs took over an hour and 10 GB): per
size the median wall and thread-CPU time of a step, ns per spring and step, and per series the
growth exponent (least-squares slope of log cost over log springs, and between neighbouring
sizes). A step whose cost grows linearly with the springs has exponent 1. Run alone:
``python benchmarks/bench_simulate.py --parts scaling`` (about ten minutes on two cores);
``--scaling-sizes 10k,40k`` for a quick look.

Two-grid preconditioner (``bench_two_grid``, part "twogrid", not in the default parts): the
default scene on the bundled liver's splits (``--elements 1500 --split`` and the paper preset's
split) with the split matrix's factor and with ``[integrator] preconditioner = "two-grid"``,
alternating in one process after a warm-up of each (docs/design/twogrid.md):
``python benchmarks/bench_simulate.py --parts twogrid``
(``--two-grid-assets a.h5,b.h5`` to use split assets already prepared).

Split organs (``bench_splits``, part "splits", not in the default parts): the default scene on the
coarse parents' splits of the liver, the OpenHELP kidney and spleen (``--elements 1500 --split``)
and on the liver's paper preset, assets taken in turn after a warm-up round, real-time factor per
run and its median against the goal of three times real time (docs/design/realtime.md):
``python benchmarks/bench_simulate.py --parts splits`` (about ten minutes on two cores).

Beside a job (``bench_beside_a_job``, part "beside", not in the default parts): the default scene on
the paper preset of the bundled and SOFA livers and the OpenHELP kidney and spleen, alone and beside
one CPU-bound process, against three times real time alone and real time beside it:
``python benchmarks/bench_simulate.py --parts beside`` (about five minutes on two cores).

Note: on a shared machine the wall times include other processes' load; CPU
(thread) time of the single-thread runs is reported beside them.
"""

from __future__ import annotations

import itertools
import statistics
import tempfile
import time
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np

SIZES = {"5k": 9, "50k": 19, "100k": 24, "500k": 41}       # Kuhn box cells per side
PAPER_NS_PER_ELEMENT = 3.517e-3 / 5322 * 1e9
REPO = Path(__file__).resolve().parent.parent


def box_tets(n: int, size: float = 0.1):
    xs = np.linspace(0.0, size, n + 1)
    X, Y, Z = np.meshgrid(xs, xs, xs, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(pts.shape[0]).reshape(n + 1, n + 1, n + 1)
    cells = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for perm in itertools.permutations(range(3)):
        corners = [cells]
        c = cells
        for ax in perm:
            c = c.copy()
            c[:, ax] += 1
            corners.append(c)
        tets.append(np.stack([idx[q[:, 0], q[:, 1], q[:, 2]] for q in corners], axis=1))
    return SimpleNamespace(points=pts, tets=np.concatenate(tets))


def _tables():
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.network.tables import build_tables

    return build_tables(load_material("porcine_liver_paper"))


def copy_bandwidth(nbytes: int, repeats: int = 5) -> float:
    """STREAM-like copy bandwidth [GB/s] (bytes read + written) of float64 arrays of *nbytes*."""
    src = np.random.default_rng(0).random(nbytes // 8)
    dst = np.empty_like(src)
    np.copyto(dst, src)
    best = []
    for _ in range(repeats):
        t = time.perf_counter()
        np.copyto(dst, src)
        best.append(time.perf_counter() - t)
    return 2 * nbytes / statistics.median(best) / 1e9


def _time_steps(sim, steps: int, repeats: int) -> tuple[float, float]:
    """Median wall and thread-CPU seconds per step."""
    sim.advance(max(2, steps // 10))
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.thread_time()
        sim.advance(steps)
        walls.append((time.perf_counter() - t) / steps)
        cpus.append((time.thread_time() - c) / steps)
    return statistics.median(walls), statistics.median(cpus)


def bench_sizes(tables, threads_all: int, *, sizes=None, repeats: int = 5) -> dict:
    import numba
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.simulate.simulator import Simulator, warm_up
    from esmm.pipeline.simulate.springterm import build_spring_term

    out = {}
    for name, n in (SIZES if sizes is None else {k: SIZES[k] for k in sizes}).items():
        t = time.perf_counter()
        net = network_from_tets(box_tets(n))
        t_net = time.perf_counter() - t
        t = time.perf_counter()
        model = build_spring_term(net, tables)
        t_model = time.perf_counter() - t
        warm = warm_up(model, threads=1) + (warm_up(model, threads=threads_all) if threads_all > 1 else 0.0)
        fixed = np.flatnonzero(net.points[:, 2] < 1e-9)
        sim = Simulator(model, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81), mass_damping=5.0)
        s = model.n_springs
        steps = int(np.clip(3e7 / s / 10, 10, 4000))          # ~0.1 s per repeat at 10 ns/spring
        row = {"springs": s, "nodes": net.n_nodes, "network_build_s": t_net, "model_build_s": t_model,
               "warm_up_s": warm, "steps_per_repeat": steps,
               "halo_springs_2_threads": int(model.layout(2).halo_start[-1]) if threads_all > 1 else 0}
        sim.threads = 1
        w, c = _time_steps(sim, steps, repeats)
        row.update({"t1_us_per_step": w * 1e6, "t1_ns_per_spring_step": w / s * 1e9,
                    "t1_cpu_ns_per_spring_step": c / s * 1e9})
        if threads_all > 1:
            sim.threads = threads_all
            w2, _ = _time_steps(sim, steps, repeats)
            row.update({f"t{threads_all}_us_per_step": w2 * 1e6, f"t{threads_all}_ns_per_spring_step": w2 / s * 1e9,
                        "speedup": w / w2})
        if name == "50k":   # float32 spring data
            m32 = build_spring_term(net, tables, precision="float32")
            warm_up(m32)
            sim32 = Simulator(m32, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81))
            w32, c32 = _time_steps(sim32, steps, repeats)
            row["float32_t1_ns_per_spring_step"] = w32 / s * 1e9
            row["float32_t1_cpu_ns_per_spring_step"] = c32 / s * 1e9
        row["bytes_per_spring_step"] = bytes_touched(model, net)
        out[name] = row
    numba.set_num_threads(threads_all)
    return out


def bench_effects(tables, n: int = SIZES["50k"], steps: int = 60, repeats: int = 7) -> dict:
    """ns per spring per step, one thread, without and with material effects (same network).

    The plain run uses the elastic kernels (what a material without effects gets);
    "visco3" carries 3 Prony terms per spring; "all" adds Mullins and damage.
    """
    from esmm.pipeline.materials.effects import (
        DamageEffect,
        MaterialEffects,
        MullinsEffect,
        ViscoelasticEffect,
    )
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.simulate.simulator import Simulator, warm_up
    from esmm.pipeline.simulate.springterm import build_spring_term

    net = network_from_tets(box_tets(n))
    fixed = np.flatnonzero(net.points[:, 2] < 1e-9)
    visco = ViscoelasticEffect((0.3, 0.2, 0.1), (0.05, 0.5, 5.0))
    variants = {"plain": None, "visco3": MaterialEffects(visco),
                "all": MaterialEffects(visco, MullinsEffect(2.0, 500.0, 0.1), DamageEffect(1.3, 0.2, 2.0))}
    out: dict = {}
    for name, fx in variants.items():
        model = build_spring_term(net, tables, effects=fx)
        out[f"{name}_warm_up_s"] = warm_up(model)
        sim = Simulator(model, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81), mass_damping=5.0)
        w, c = _time_steps(sim, steps, repeats)
        s = model.n_springs
        out[name] = {"springs": s, "wall_ns_per_spring_step": w / s * 1e9, "cpu_ns_per_spring_step": c / s * 1e9}
    for name in ("visco3", "all"):
        out[name]["cpu_ratio_to_plain"] = out[name]["cpu_ns_per_spring_step"] / out["plain"]["cpu_ns_per_spring_step"]
    return out


def _median_call(fn, calls: int, repeats: int) -> tuple[float, float]:
    """Median wall and thread-CPU seconds per call of *fn* (after one warm call)."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.thread_time()
        for _ in range(calls):
            fn()
        walls.append((time.perf_counter() - t) / calls)
        cpus.append((time.thread_time() - c) / calls)
    return statistics.median(walls), statistics.median(cpus)


def _bench_mesh(name: str):
    """The box of *name*; ``"<size>-split"``: a box of half the cells per side, every tet split in eight
    (the fabric of ``esmm prepare --split``, about as many tets as ``<size>``)."""
    if not name.endswith("-split"):
        return box_tets(SIZES[name])
    from esmm.pipeline.mesh.refine import split_in_eight

    base = box_tets(SIZES[name.removesuffix("-split")] // 2)
    points, tets, cells = split_in_eight(base.points, base.tets)
    return SimpleNamespace(points=points, tets=tets, quadratic_cells=cells)


def bench_volume(tables, *, sizes=("5k", "50k", "50k-split"), repeats: int = 7) -> dict:
    """The volume term against the spring pass, one thread (module doc)."""
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.network.volume import bulk_modulus
    from esmm.pipeline.simulate import kernels as K
    from esmm.pipeline.simulate.simulator import Simulator, warm_up
    from esmm.pipeline.simulate.springterm import build_spring_term
    from esmm.pipeline.simulate.stepper import stable_step
    from esmm.pipeline.simulate.volumeterm import build_volume_term

    spec = bulk_modulus(tables)
    out: dict = {"bulk_modulus_pa": spec.bulk_modulus}
    for name in sizes:
        net = network_from_tets(_bench_mesh(name))
        springs = build_spring_term(net, tables)
        vol = build_volume_term(net.points, net.tets, spec, lam_max=tables.lam_max)
        warm = warm_up(springs) + warm_up(springs, volume=vol)
        x = net.points * 1.001
        v = np.zeros_like(x)
        f = np.zeros_like(x)
        sk, vk, lay = springs.kernel(), vol.kernel(), springs.layout(1)
        calls = int(np.clip(3e6 / springs.n_springs, 5, 500))
        ws, cs = _median_call(partial(K.forces_serial, x, v, f, v, sk, None, lay), calls, repeats)
        wv, cv = _median_call(partial(K.volume_forces_serial, x, f, vk), calls, repeats)
        fixed = np.flatnonzero(net.points[:, 2] < 1e-9)
        steps = {}
        for label, term in (("springs", None), ("springs+volume", vol)):
            sim = Simulator(springs, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81), mass_damping=5.0,
                            volume=term)
            sim.set_time_step(0.5 * sim.bound.dt)
            w, c = _time_steps(sim, calls, repeats)
            terms = [springs] if term is None else [springs, term]
            steps[label] = {"cpu_us_per_step": c * 1e6, "wall_us_per_step": w * 1e6,
                            "dt_whole_run_us": stable_step(terms, net.mass).dt * 1e6,
                            "dt_window_at_rest_us": stable_step(terms, net.mass, x=net.points, window=0.05).dt * 1e6}
        out[name] = {"springs": springs.n_springs, "tets": vol.n_tets, "nodes": net.n_nodes, "warm_up_s": warm,
                     "spring_pass_cpu_us": cs * 1e6, "volume_pass_cpu_us": cv * 1e6,
                     "spring_pass_wall_us": ws * 1e6, "volume_pass_wall_us": wv * 1e6,
                     "volume_over_spring_pass_cpu": cv / cs, "goal_volume_le_2x_spring_pass": cv / cs <= 2.0,
                     "volume_ns_per_tet": cv / vol.n_tets * 1e9, "steps": steps,
                     "step_cost_ratio_cpu": steps["springs+volume"]["cpu_us_per_step"]
                     / steps["springs"]["cpu_us_per_step"],
                     "stable_step_ratio_window": steps["springs+volume"]["dt_window_at_rest_us"]
                     / steps["springs"]["dt_window_at_rest_us"]}
    return out


def bytes_touched(model, net) -> float:
    """Bytes moved per spring per step: spring stream + node arrays (x r/w, v r/w, f r/w, fext r, 1/m r)."""
    node_bytes = 8 * (3 * 2 + 3 * 2 + 3 * 2 + 3 + 1)
    return model.bytes_per_spring() + node_bytes * net.n_nodes / model.n_springs


def bench_demo(tables_unused=None) -> dict:
    from dataclasses import replace

    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.prepare import prepare
    from esmm.pipeline.simulate.render import render_video
    from esmm.pipeline.simulate.run import simulate_network
    from esmm.pipeline.simulate.scene import VideoSpec, load_scene

    src = REPO / "data" / "meshes" / "sofa_liver.stl"
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        prepare(src, output=Path(d) / "liver.h5")
        out["prepare_s"] = time.perf_counter() - t
        asset = read_asset(Path(d) / "liver.h5")
        base = load_scene("default").with_overrides(duration=1.0, method="explicit")   # its step modes
        for mode in ("adaptive", "table"):
            sc = replace(base, step=mode)
            res = simulate_network(asset.network, asset.tables, sc, Path(d) / mode)
            s = res.summary
            out[mode] = {k: getattr(s, k) for k in ("springs", "nodes", "threads", "steps", "dt_min_s", "dt_max_s",
                                           "dt_mean_s", "dt_table_bound_s", "frames_redone", "stepping_wall_s",
                                           "wall_per_step_us", "ns_per_spring_step", "real_time_factor",
                                           "warm_up_s")}
        t = time.perf_counter()
        info = render_video(Path(d) / "adaptive" / "history.h5", Path(d) / "demo.mp4", video=VideoSpec())
        out["render"] = {"frames": info["frames"], "seconds": info["seconds"], "fps_960x720": info["render_fps"]}
    return out


LIVER = REPO / "data" / "meshes" / "ts_liver_3mm_closed.stl"
#: Kuhn boxes of the implicit step's size rows: (cells per side, preconditioner). "500k" with the
#: reused factor did not finish factoring in an hour (10 GB); "500k-jacobi" needs no factorization.
IMPLICIT_SIZES = {"100k": (24, "factor"), "500k": (41, "factor"), "100k-jacobi": (24, "jacobi"),
                  "500k-jacobi": (41, "jacobi")}


def _liver_asset(preset: str, folder: Path):
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.prepare import prepare

    path = folder / f"liver-{preset}.h5"
    prepare(LIVER, output=path, config=preset)
    return read_asset(path)


def _run_figures(summary) -> dict:
    keys = ("springs", "nodes", "method", "steps", "dt_min_s", "dt_max_s", "stepping_wall_s", "wall_per_step_us",
            "real_time_factor", "threads")
    out = {k: getattr(summary, k) for k in keys}
    if summary.grasper is not None:
        out["max_grasper_force_N"] = summary.grasper.max_force_N
    if summary.method == "implicit":
        out["integrator"] = summary.integrator
    return out


def implicit_traffic(stats: dict, springs: int, nnz_tangent: int) -> dict:
    """Bytes moved per implicit step (the GPU note): factor sweeps, tangent products, force passes.

    A solve streams L twice (forward, backward; the supernodal factor's float32 blocks, their row
    indices read once per block, not per entry: ~4 bytes per entry per sweep); a conjugate-gradient
    product reads the tangent (12 bytes per entry); a Newton iteration assembles it and passes the
    forces (~50 bytes per spring each).
    """
    steps = max(1, stats["steps"])
    solves = stats["solves"] / steps
    newton = stats["newton"] / steps
    quasi = stats.get("quasi_newton", 0) / steps
    cg = stats["cg"] / steps
    factor = 2 * 4 * stats["factor_nnz"]
    # a quasi-Newton iteration: its solve (counted in solves) and one or two force passes, no tangent
    b = (solves * factor + cg * 12 * nnz_tangent + newton * (2 * 50 * springs + 12 * nnz_tangent)
         + quasi * 2 * 50 * springs)
    return {"solves_per_step": solves, "newton_per_step": newton, "quasi_newton_per_step": quasi,
            "cg_per_step": cg, "bytes_per_solve": factor, "bytes_per_step": b}


def implicit_accuracy(hist_implicit: Path, hist_explicit: Path, lift_end: float, frame_dt: float) -> dict:
    """The implicit run against the explicit one over the lift (t <= *lift_end*): the grasper force at
    1 kHz and at the solves (max and rms of |F_i - F_e| over the largest |F_e|), and the displacement
    (largest nodal difference over the frames, over the largest displacement and the largest motion)."""
    from esmm.pipeline.simulate.history import History

    with History(hist_implicit) as hi, History(hist_explicit) as he:
        ti, Fi = hi.forces()
        te, Fe = he.forces()
        Fe_i = np.stack([np.interp(ti, te, Fe[:, d]) for d in range(3)], axis=1)
        lift = ti <= lift_end + 1e-9
        scale = float(np.linalg.norm(Fe[te <= lift_end + 1e-9], axis=1).max())
        err = np.linalg.norm(Fi - Fe_i, axis=1)[lift]
        solves = lift & (np.abs(ti / frame_dt - np.round(ti / frame_dt)) < 1e-6)
        err_s = np.linalg.norm(Fi - Fe_i, axis=1)[solves]
        frames = [k for k in range(min(hi.n_frames, he.n_frames)) if hi.times[k] <= lift_end + 1e-9]
        ui = np.array([hi.displacement(k) for k in frames])
        ue = np.array([he.displacement(k) for k in frames])
    du = float(np.linalg.norm(ui - ue, axis=2).max())
    umax = float(np.linalg.norm(ue, axis=2).max())
    motion = float(np.linalg.norm(ue - ue[0], axis=2).max())
    return {"lift_end_s": lift_end, "force_scale_N": scale, "haptic_samples": int(lift.sum()),
            "force_err_max_frac": float(err.max()) / scale, "force_err_rms_frac": float(np.sqrt(np.mean(err ** 2))) / scale,
            "force_err_at_solves_max_frac": float(err_s.max()) / scale if err_s.size else None,
            "force_within_5pct": bool(err.max() <= 0.05 * scale),
            "displacement_err_max_m": du, "largest_displacement_m": umax, "largest_motion_m": motion,
            "displacement_err_frac_of_largest": du / umax, "displacement_err_frac_of_motion": du / motion,
            "displacement_within_5pct": bool(du <= 0.05 * umax)}


def bench_implicit(*, duration: float = 3.0, sizes=("100k", "500k-jacobi"), steps: int = 3, runs: int = 3) -> dict:
    """Real-time factors of the default and the interactive scene (the default on a frictionless bed,
    docs/design/simulator.md) on the bundled liver (paper and fine presets), implicit and explicit in one
    run (the implicit scene *runs* times: the figures are those of the run with the median stepping
    time, every run's time listed; a run's time varies from run to run), the implicit stepper with
    its other iteration (Newton or quasi-Newton) and, on the interactive
    scene, its other factor, each run's accuracy against the explicit one over the lift; the implicit step on
    the Kuhn boxes of *sizes* (:data:`IMPLICIT_SIZES`: 100 k with the factor, 500 k with the Jacobi
    preconditioner; 500 k with the factor only on request, its factorization took over an hour and
    10 GB here); the memory traffic per step."""
    import os

    from esmm.pipeline.simulate.run import simulate_network
    from esmm.pipeline.simulate.scene import load_scene
    from esmm.pipeline.simulate.springterm import build_spring_term

    out: dict = {"load_average_at_start": os.getloadavg()}
    base = load_scene("default").with_overrides(duration=duration)
    lift_end = base.grasper.waypoints[-1].time
    interactive = load_scene("interactive").with_overrides(duration=duration)
    variants = (("paper", "paper", base), ("paper_interactive", "paper", interactive), ("fine", "fine", base),
                ("fine_interactive", "fine", interactive))
    with tempfile.TemporaryDirectory() as d:
        assets = {}
        for key, preset, scene in variants:
            if preset not in assets:
                assets[preset] = _liver_asset(preset, Path(d))
            asset = assets[preset]
            row, hist = {}, {}
            for method in ("implicit", "explicit"):
                done = []
                for i in range(runs if method == "implicit" else 1):
                    res = simulate_network(asset.network, asset.tables, scene.with_overrides(method=method),
                                           Path(d) / f"{key}-{method}-{i}")
                    done.append((_run_figures(res.summary), res.history))
                    done[-1][0]["load_average_after"] = os.getloadavg()
                walls = [f["stepping_wall_s"] for f, _ in done]
                row[method], hist[method] = sorted(done, key=lambda fh: fh[0]["stepping_wall_s"])[len(done) // 2]
                row[method]["stepping_wall_s_runs"] = walls
            imp, exp = row["implicit"], row["explicit"]
            row["speedup_implicit_over_explicit"] = exp["stepping_wall_s"] / imp["stepping_wall_s"]
            run = (asset, scene, Path(d) / key, hist["explicit"], lift_end, imp)
            other = "newton" if scene.iteration == "quasi-newton" else "quasi-newton"   # the other iteration
            row.update(_implicit_variant(*run, other, scene.iteration, iteration=other))
            if key.endswith("_interactive"):      # the other [integrator] factor, in the same run
                other = "mixed" if scene.factor == "bound" else "bound"   # the haptic-margin choice (docs/design/simulator.md)
                row.update(_implicit_variant(*run, f"{other}_factor", scene.factor, factor=other))
            row["accuracy_over_lift"] = implicit_accuracy(hist["implicit"], hist["explicit"], lift_end,
                                                          imp["dt_max_s"])
            term = build_spring_term(asset.network, asset.tables)
            row["traffic"] = implicit_traffic(imp["integrator"], term.n_springs, term.pattern.nnz)
            out[key] = row
    out["sizes"] = {}
    for name in sizes:
        try:
            out["sizes"][name] = _implicit_box(*IMPLICIT_SIZES[name], steps)
        except Exception as exc:  # 500k may not fit or take too long: report, keep the rest
            out["sizes"][name] = {"error": f"{type(exc).__name__}: {exc}"}
        out["sizes"][name]["load_average_after"] = os.getloadavg()
    return out


#: Kuhn boxes of the step-cost series: cells per side (about 10 k, 40 k, 100 k and 500 k springs).
STEP_SCALING = {"10k": 11, "40k": 17, "100k": 24, "500k": 41}
#: The largest box factored in the step-cost series (a larger factorization took over an hour).
FACTOR_LIMIT = 150_000


def growth_exponent(springs, cost) -> dict:
    """How a cost grows with the springs: the least-squares slope of log(cost) over log(springs)
    (``exponent``; 1 is linear) and the slope between each pair of neighbouring sizes (``pairwise``)."""
    x, y = np.log(np.asarray(springs, float)), np.log(np.asarray(cost, float))
    if x.size < 2:
        return {"exponent": None, "pairwise": []}
    return {"exponent": float(np.polyfit(x, y, 1)[0]),
            "pairwise": [float((y[i + 1] - y[i]) / (x[i + 1] - x[i])) for i in range(x.size - 1)]}


def bench_step_scaling(*, sizes=tuple(STEP_SCALING), preconditioners=("factor", "jacobi"), steps: int = 3) -> dict:
    """The implicit step's cost on Kuhn boxes of *sizes* (:data:`STEP_SCALING`) with each of
    *preconditioners* (the factor only up to :data:`FACTOR_LIMIT` springs): per size the median wall
    and CPU time of a step (:func:`_implicit_box`), ns per spring and step; per series the growth
    exponent (:func:`growth_exponent`)."""
    import os

    out: dict = {"load_average_at_start": os.getloadavg(), "steps": steps}
    for pre in preconditioners:
        rows = {}
        for name in sizes:
            n = STEP_SCALING[name]
            if pre == "factor" and _kuhn_springs(n) > FACTOR_LIMIT:
                rows[name] = {"skipped": f"over {FACTOR_LIMIT} springs: the factorization takes too long"}
                continue
            row = _implicit_box(n, pre, steps)
            row["ns_per_spring_step"] = row["step_ms_median"] * 1e6 / row["springs"]
            row["cpu_ns_per_spring_step"] = row["step_cpu_ms_median"] * 1e6 / row["springs"]
            row["load_average_after"] = os.getloadavg()
            rows[name] = row
        done = [r for r in rows.values() if "springs" in r]
        springs = [r["springs"] for r in done]
        out[pre] = {"sizes": rows,
                    "growth_wall": growth_exponent(springs, [r["step_ms_median"] for r in done]),
                    "growth_cpu": growth_exponent(springs, [r["step_cpu_ms_median"] for r in done])}
    return out


def _kuhn_springs(n: int) -> int:
    """Springs (edges) of the Kuhn box of n cells per side: axis edges, face and body diagonals."""
    return 3 * n * (n + 1) ** 2 + 3 * n * n * (n + 1) + n ** 3


def _implicit_variant(asset, scene, out: Path, explicit_history, lift_end: float, figures: dict, label: str,
                      own: str, **change) -> dict:
    """The implicit run of *scene* with *change* (another iteration or factor), in the same run as the
    scene's own implicit run (its *figures*, named *own*): its figures, the speed-up and its accuracy."""
    from dataclasses import replace

    from esmm.pipeline.simulate.run import simulate_network

    res = simulate_network(asset.network, asset.tables, replace(scene, method="implicit", **change),
                           out.with_name(f"{out.name}-{label}"))
    mine = _run_figures(res.summary)
    return {f"implicit_{label}": mine,
            f"speedup_{own}_over_{label}": mine["stepping_wall_s"] / figures["stepping_wall_s"],
            f"accuracy_{label}": implicit_accuracy(res.history, explicit_history, lift_end, figures["dt_max_s"])}


def _implicit_box(n: int, preconditioner: str, steps: int) -> dict:
    """Implicit steps of 1/30 s on a Kuhn box of n cells per side, gravity, the base fixed: the first
    factorization (none with "jacobi") and the median wall time per step."""
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.simulate.implicit import BackwardEuler
    from esmm.pipeline.simulate.simulator import Simulator
    from esmm.pipeline.simulate.springterm import build_spring_term

    net = network_from_tets(box_tets(n))
    term = build_spring_term(net, _tables(), dashpot=5e-4)
    fixed = np.flatnonzero(net.points[:, 2] < 1e-9)
    stepper = BackwardEuler(preconditioner=preconditioner)
    sim = Simulator(term, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81), mass_damping=1 / 0.15,
                    stepper=stepper)
    t = time.perf_counter()
    stepper.prepare(sim.model, sim.state, sim.control)
    prefactor = time.perf_counter() - t
    walls, cpus = [], []
    for _ in range(steps):
        t, c = time.perf_counter(), time.thread_time()
        sim.advance(1)
        walls.append(time.perf_counter() - t)
        cpus.append(time.thread_time() - c)
    rep = stepper.report()
    return {"springs": term.n_springs, "nodes": net.n_nodes, "prefactor_s": prefactor,
            "step_ms_median": 1e3 * statistics.median(walls), "step_ms": [1e3 * w for w in walls],
            "step_cpu_ms_median": 1e3 * statistics.median(cpus),
            "real_time_factor_at_30Hz": (1 / 30) / statistics.median(walls),
            "traffic": implicit_traffic(rep, term.n_springs, term.pattern.nnz), "integrator": rep}


#: The split livers of the two-grid comparison: name -> prepare keywords.
TWO_GRID_ASSETS = {"split_1500": {"config": "paper", "elements": 1500, "split": True},
                   "paper_split": {"config": "paper", "split": True}}


def _force_difference(hist: Path, ref: Path, frame_dt: float) -> dict:
    """The grasper force of *hist* against *ref*'s (same scene): largest and rms difference over the
    largest reference force, at the solves and over all samples."""
    from esmm.pipeline.simulate.history import History

    with History(hist) as h, History(ref) as r:
        t, F = h.forces()
        _, Fr = r.forces()
    k = min(len(F), len(Fr))
    d = np.linalg.norm(F[:k] - Fr[:k], axis=1)
    scale = float(np.linalg.norm(Fr[:k], axis=1).max())
    solves = np.abs(t[:k] / frame_dt - np.round(t[:k] / frame_dt)) < 1e-6
    return {"max_frac": float(d.max()) / scale, "rms_frac": float(np.sqrt(np.mean(d ** 2))) / scale,
            "at_solves_max_frac": float(d[solves].max()) / scale,
            "at_solves_rms_frac": float(np.sqrt(np.mean(d[solves] ** 2))) / scale}


def bench_two_grid(*, assets=None, runs: int = 3) -> dict:
    """The default scene on split livers with the split matrix's factor and with the two-grid
    preconditioner: a warm-up run of each, then *runs* runs of each, alternating (pairs under the same
    load); per preconditioner the run with the median stepping time's figures and every run's
    real-time factor, and the two-grid's grasper force against the factor's (median runs).
    *assets*: paths of split assets (default: :data:`TWO_GRID_ASSETS` prepared here)."""
    import dataclasses
    import os

    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.prepare import prepare
    from esmm.pipeline.simulate.run import simulate_network
    from esmm.pipeline.simulate.scene import load_scene

    out: dict = {"load_average_at_start": os.getloadavg()}
    scene = load_scene("default")
    with tempfile.TemporaryDirectory() as d:
        if assets is None:
            assets = {}
            for name, kw in TWO_GRID_ASSETS.items():
                assets[name] = Path(d) / f"liver-{name}.h5"
                prepare(LIVER, output=assets[name], **kw)
        else:
            assets = {Path(a).stem: Path(a) for a in assets}
        for name, path in assets.items():
            asset = read_asset(path)
            runs_of: dict = {"factor": [], "two-grid": []}
            for i in range(runs + 1):
                for pre in runs_of:
                    res = simulate_network(asset.network, asset.tables,
                                           dataclasses.replace(scene, preconditioner=pre), Path(d) / f"{name}-{pre}-{i}")
                    if i:                                  # the first run of each is the warm-up
                        runs_of[pre].append((_run_figures(res.summary), res.history))
            row: dict = {"nodes": asset.network.n_nodes}
            hist = {}
            for pre, done in runs_of.items():
                row[pre], hist[pre] = sorted(done, key=lambda fh: fh[0]["stepping_wall_s"])[len(done) // 2]
                row[pre]["real_time_factor_runs"] = [f["real_time_factor"] for f, _ in done]
            row["two_grid_force_against_factor"] = _force_difference(hist["two-grid"], hist["factor"],
                                                                     row["factor"]["dt_max_s"])
            row["load_average_after"] = os.getloadavg()
            out[name] = row
    return out


#: The split organs of part "splits": name -> (surface, prepare keywords); the OpenHELP organs where
#: ../shared/data is present.
SPLIT_ORGANS = {"liver_paper": (LIVER, {"config": "paper"}),
                "liver_split_1500": (LIVER, {"config": "paper", "elements": 1500, "split": True}),
                "kidney_split_1500": (REPO.parent / "shared" / "data" / "meshes" / "openhelp_Kidney_left.stl",
                                      {"config": "paper", "elements": 1500, "split": True}),
                "spleen_split_1500": (REPO.parent / "shared" / "data" / "meshes" / "openhelp_Spleen.stl",
                                      {"config": "paper", "elements": 1500, "split": True})}


def _prepared(organs: dict, folder: Path) -> dict:
    """The assets of *organs* (name -> (surface, prepare keywords)) prepared in *folder* and read; an organ
    whose surface is absent (../shared not beside the checkout) is left out."""
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.prepare import prepare

    assets = {}
    for name, (surface, kw) in organs.items():
        if surface.is_file():
            prepare(surface, output=folder / f"{name}.h5", **kw)
            assets[name] = read_asset(folder / f"{name}.h5")
    return assets


def _scene_rounds(assets: dict, folder: Path, *, runs: int, tag: str = "") -> dict:
    """The default scene on every asset, a warm-up round then *runs* rounds with the assets taken in turn:
    name -> the measured rounds' summaries."""
    from esmm.pipeline.simulate.run import simulate_network
    from esmm.pipeline.simulate.scene import load_scene

    scene = load_scene("default")
    done: dict = {name: [] for name in assets}
    for i in range(runs + 1):
        for name, asset in assets.items():
            res = simulate_network(asset.network, asset.tables, scene, folder / f"{name}{tag}-{i}")
            if i:                                               # the first round is the warm-up
                done[name].append(res.summary)
    return done


def bench_splits(*, runs: int = 3) -> dict:
    """The default scene on the coarse parents' splits (``esmm prepare --elements 1500 --split``) of the
    organs of :data:`SPLIT_ORGANS` and on the liver's paper preset (the reference), ``threads = "auto"``:
    a warm-up round, then *runs* rounds with the assets taken in turn; per asset every run's real-time
    factor and the median, the median run's iteration counts, the load average. Goal: three times real
    time (docs/design/realtime.md, "The split networks' step made cheaper"); the scene's figures move
    with the machine's load, which is recorded beside them."""
    import os

    out: dict = {"load_average_at_start": os.getloadavg()}
    with tempfile.TemporaryDirectory() as d:
        done = _scene_rounds(_prepared(SPLIT_ORGANS, Path(d)), Path(d), runs=runs)
        for name, summaries in done.items():
            figs = [_run_figures(s) for s in summaries]
            med = sorted(figs, key=lambda f: f["real_time_factor"])[len(figs) // 2]
            out[name] = {**med, "real_time_factor_runs": [f["real_time_factor"] for f in figs],
                         "goal_3x_real_time": med["real_time_factor"] >= 3.0}
    out["load_average_at_end"] = os.getloadavg()
    return out


#: The organs of part "beside": name -> (surface, prepare keywords), the paper preset (the default asset).
BESIDE_ORGANS = {"liver": (LIVER, {"config": "paper"}),
                 "kidney": (REPO.parent / "shared" / "data" / "meshes" / "openhelp_Kidney_left.stl", {"config": "paper"}),
                 "spleen": (REPO.parent / "shared" / "data" / "meshes" / "openhelp_Spleen.stl", {"config": "paper"}),
                 "sofa_liver": (REPO / "data" / "meshes" / "sofa_liver.stl", {"config": "paper"})}


def bench_beside_a_job(*, runs: int = 3) -> dict:
    """The default scene on the paper preset of the organs of :data:`BESIDE_ORGANS`, alone and beside one
    CPU-bound process (a busy Python loop, as another program on a two-core machine): per condition a
    warm-up round, then *runs* rounds with the assets taken in turn; every run's real-time factor, its
    quasi-Newton iterations, factorizations and threads, and the median. Goals: three times real time
    alone, real time beside one job (docs/design/realtime.md)."""
    import os
    import subprocess
    import sys

    out: dict = {"load_average_at_start": os.getloadavg(), "runs": runs}
    with tempfile.TemporaryDirectory() as d:
        assets = _prepared(BESIDE_ORGANS, Path(d))
        for cond in ("alone", "beside_one_job"):
            hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if cond != "alone" else None
            try:
                done = _scene_rounds(assets, Path(d), runs=runs, tag=f"-{cond}")
            finally:
                if hog is not None:
                    hog.kill()
                    hog.wait()
            got = {name: [{"real_time_factor": s.real_time_factor, "threads": s.threads,
                           "quasi_newton": s.integrator["quasi_newton"],
                           "factorizations": s.integrator["factorizations"]} for s in summaries]
                   for name, summaries in done.items()}
            out[cond] = {name: {"real_time_factor": statistics.median(r["real_time_factor"] for r in v), "runs": v}
                         for name, v in got.items()}
    out["goal_3x_alone"] = {n: v["real_time_factor"] >= 3.0 for n, v in out.get("alone", {}).items()}
    out["goal_1x_beside_one_job"] = {n: v["real_time_factor"] >= 1.0 for n, v in out.get("beside_one_job", {}).items()}
    out["load_average_at_end"] = os.getloadavg()
    return out


def run(*, parts=("sizes", "effects", "volume", "demo", "implicit", "scaling"), sizes=None, repeats: int = 5,
        threads: int | None = None, implicit_sizes=("100k", "500k-jacobi"), scaling_sizes=tuple(STEP_SCALING),
        two_grid_assets=None) -> dict:
    """The benchmark's figures; ``make bench`` runs everything (see :func:`main` for a quick subset).

    Parameters
    ----------
    parts : subset of {"sizes", "effects", "volume", "demo", "implicit", "scaling", "twogrid", "splits", "beside"}
    sizes : subset of :data:`SIZES` keys, optional
    repeats : int
        Timed repeats per figure (medians).
    threads : int, optional
        Threads for the multi-thread rows (default: all numba has; 1 skips them).
    implicit_sizes : subset of :data:`IMPLICIT_SIZES` keys
        Kuhn boxes of the implicit step (500k with the factor: over an hour and 10 GB here).
    scaling_sizes : subset of :data:`STEP_SCALING` keys
        Kuhn boxes of the step-cost series (:func:`bench_step_scaling`).
    two_grid_assets : sequence of paths, optional
        Split assets of part "twogrid" (default: the bundled liver's splits, prepared).
    """
    import numba

    threads_all = int(numba.config.NUMBA_NUM_THREADS) if threads is None else int(threads)
    t0 = time.perf_counter()
    tables = _tables()
    res: dict = {"threads_available": threads_all, "threading_layer": None}
    if "sizes" in parts:
        res["sizes"] = bench_sizes(tables, threads_all, sizes=sizes, repeats=repeats)
        try:
            res["threading_layer"] = numba.threading_layer()
        except ValueError:
            pass
        bw_dram = copy_bandwidth(1 << 30, repeats=3)
        bw_cache = copy_bandwidth(8 << 20, repeats=20)
        res["copy_bandwidth_GBps"] = {"dram_1GiB": bw_dram, "cache_8MiB": bw_cache}
        for row in res["sizes"].values():
            b = row["bytes_per_spring_step"]
            row["bandwidth_bound_ns_dram"] = b / bw_dram
            row["bandwidth_bound_ns_cache"] = b / bw_cache
            row["fraction_of_dram_bound"] = row["bandwidth_bound_ns_dram"] / row["t1_ns_per_spring_step"]
        res["paper_ns_per_element_step"] = PAPER_NS_PER_ELEMENT
        res["goal_lt_20ns_single_thread"] = all(r["t1_ns_per_spring_step"] < 20 for r in res["sizes"].values())
        if "5k" in res["sizes"]:
            res["speedup_vs_paper_5k"] = PAPER_NS_PER_ELEMENT / res["sizes"]["5k"]["t1_ns_per_spring_step"]
        if "100k" in res["sizes"]:
            r100 = res["sizes"]["100k"]
            best100 = min(r100["t1_us_per_step"], r100.get(f"t{threads_all}_us_per_step", np.inf))
            res["step_100k_best_us"] = best100
            res["goal_100k_step_lt_1ms"] = best100 < 1000.0
    if "effects" in parts:
        res["effects_50k"] = bench_effects(tables, repeats=max(repeats, 7))
    if "volume" in parts:
        res["volume"] = bench_volume(tables, repeats=max(repeats, 7))
    if "demo" in parts:
        try:
            res["demo"] = bench_demo()
        except Exception as exc:  # the demo needs gmsh and the bundled liver; report, don't fail the rest
            res["demo"] = {"error": f"{type(exc).__name__}: {exc}"}
    if "implicit" in parts:
        try:
            res["implicit"] = bench_implicit(sizes=implicit_sizes)
        except Exception as exc:  # needs gmsh and the bundled liver; report, don't fail the rest
            res["implicit"] = {"error": f"{type(exc).__name__}: {exc}"}
    if "scaling" in parts:
        res["scaling"] = bench_step_scaling(sizes=scaling_sizes)
    if "twogrid" in parts:
        res["twogrid"] = bench_two_grid(assets=two_grid_assets)
    if "splits" in parts:
        res["splits"] = bench_splits()
    if "beside" in parts:
        res["beside"] = bench_beside_a_job()
    res["bench_seconds"] = time.perf_counter() - t0
    return res


def main(argv=None) -> int:
    """``python benchmarks/bench_simulate.py [--parts sizes] [--sizes 5k,50k] [--repeats 5] [--threads 1]``."""
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="quick: --parts sizes --sizes 5k,50k --threads 1 (about a minute)")
    ap.add_argument("--parts", default="sizes,effects,volume,demo,implicit,scaling",
                    help="any of sizes, effects, volume, demo, implicit, scaling, twogrid, splits, beside "
                         "(default: all but twogrid, splits and beside)")
    ap.add_argument("--sizes", default=None, help=f"networks to time, any of {', '.join(SIZES)} (default: all)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per figure (default 5)")
    ap.add_argument("--threads", type=int, default=None, help="threads of the multi-thread rows (1: none)")
    ap.add_argument("--implicit-sizes", default="100k,500k-jacobi",
                    help=f"Kuhn boxes of the implicit step, any of {', '.join(IMPLICIT_SIZES)} "
                         "(500k with the factor: over an hour, 10 GB)")
    ap.add_argument("--scaling-sizes", default=",".join(STEP_SCALING),
                    help=f"Kuhn boxes of the step-cost series, any of {', '.join(STEP_SCALING)} (default: all)")
    ap.add_argument("--two-grid-assets", default=None,
                    help="split assets of part twogrid, comma-separated (default: the bundled liver's splits, prepared)")
    args = ap.parse_args(argv)
    parts = tuple(p.strip() for p in args.parts.split(",") if p.strip())
    sizes = None if args.sizes is None else [s.strip() for s in args.sizes.split(",") if s.strip()]
    implicit_sizes = tuple(s.strip() for s in args.implicit_sizes.split(",") if s.strip())
    scaling_sizes = tuple(s.strip() for s in args.scaling_sizes.split(",") if s.strip())
    print(json.dumps(run(parts=parts, sizes=sizes, repeats=args.repeats, threads=args.threads,
                         implicit_sizes=implicit_sizes, scaling_sizes=scaling_sizes,
                         two_grid_assets=None if args.two_grid_assets is None else args.two_grid_assets.split(",")),
                     indent=2,
                     default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
