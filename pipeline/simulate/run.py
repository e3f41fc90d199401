"""``esmm simulate``: run a scene on an asset and write its outputs.

Outputs in the output folder (each written atomically):

* ``history.h5`` + ``history.xdmf``: displacement per frame (ParaView replay),
  grasper tip per frame and grasper force per integration step
  (:mod:`.history`);
* ``grasper_force.png``: force of the tissue on the grasper vs time;
* ``summary.json``: the figures of the run (step, bound, timings, real-time
  factor, extremes) and the scene;
* the video, when asked for (:mod:`.render`).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomicio import atomic_path, write_text
from ..errors import AssetError, ConfigError, SimulationError
from ..progress import ensure
from . import kernels as K
from .grasper import GraspPlan, plan_grasp
from .history import HistoryWriter
from .integrator import Floor, Simulator, build_force_model, mass_scaling, stable_step, warm_up
from .scene import Scene, load_scene

#: Below this many springs one thread is used ("auto"): the parallel pass's
#: fork/join costs more than it saves (benchmarks/bench_simulate.py).
AUTO_PARALLEL_MIN_SPRINGS = 20_000


@dataclass
class SimulationResult:
    """Files and figures of a run."""

    out_dir: Path
    history: Path
    xdmf: Path
    force_plot: Path | None
    summary_path: Path
    video: Path | None = None
    summary: dict = field(default_factory=dict)


def _threads_available() -> int:
    import numba

    return int(numba.config.NUMBA_NUM_THREADS)


def choose_threads(sim: Simulator, requested, *, trial_steps: int = 30) -> tuple[int, dict]:
    """Resolve ``threads = "auto"`` by timing both kernels on the current state (then restored)."""
    avail = _threads_available()
    if requested != "auto":
        return max(1, min(int(requested), avail)), {}
    if avail == 1 or sim.model.n_springs < AUTO_PARALLEL_MIN_SPRINGS:
        return 1, {}
    state = sim.snapshot()
    timing = {}
    for th in (1, avail):
        sim.threads = th
        sim.advance(2)
        t = time.perf_counter()
        sim.advance(trial_steps)
        timing[th] = (time.perf_counter() - t) / trial_steps
        sim.restore(state)
    best = min(timing, key=timing.get)
    return best, {str(k): v for k, v in timing.items()}


def _fixed_nodes(network, scene: Scene) -> np.ndarray:
    if scene.fixed is None:
        return np.asarray(network.fixed, dtype=np.int64)
    from ..network.regions import select_fixed

    return select_fixed(network.points, scene.fixed, node_kind=getattr(network, "node_kind", None),
                        where="[fixed]")


def simulate_network(network, tables, scene: Scene, out_dir, *, video_path=None, reporter=None,
                     asset_label: str = "", effects=None) -> SimulationResult:
    """Run *scene* on a network with its tables and write the outputs into *out_dir*.

    Parameters
    ----------
    network : SpringNetwork
    tables : StiffnessTables
    scene : Scene
    out_dir : path-like
    video_path : path-like, optional
        Also render the video there.
    reporter : Reporter, optional
    effects : MaterialEffects, optional
        The material's effects (viscoelastic, Mullins, damage), applied per
        spring unless the scene says ``effects = "none"``.

    Returns
    -------
    SimulationResult

    Raises
    ------
    ConfigError
        A scene that does not fit the network (fixed region, grasper).
    SimulationError
        Too many steps, or the run became unstable.
    """
    rep = ensure(reporter)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    law = tables.check_law(None if scene.law == "asset" else scene.law)
    fixed = _fixed_nodes(network, scene)
    if fixed.size == 0 and np.any(scene.gravity) and scene.grasper is None and scene.floor is None:
        rep.warn("no node is fixed and gravity is on: the organ will fall freely")

    use_fx = effects if (scene.effects == "asset" and effects) else None
    if effects and use_fx is None:
        rep.step(f"material effects {', '.join(effects.names)} switched off by the scene (effects = \"none\")")
    t_build = time.perf_counter()
    model = build_force_model(network, tables, law=law, dashpot=scene.dashpot, precision=scene.precision,
                              effects=use_fx)
    build_s = time.perf_counter() - t_build
    if model.effects is not None:
        rep.step(f"material effects: {_describe_effects(model.effects)}")
    warm = warm_up(model, threads=1)
    if _threads_available() > 1 and model.n_springs >= AUTO_PARALLEL_MIN_SPRINGS:
        warm += warm_up(model, threads=_threads_available())
    free0 = np.ones(model.n_nodes, bool)
    free0[fixed] = False
    inertia, scaling = mass_scaling(model, network.mass, free=free0, budget=scene.mass_scaling)
    if scaling["nodes"]:
        rep.step(f"mass scaling: +{scaling['added_fraction'] * 100:.3g} % of the mass on {scaling['nodes']} "
                 f"light nodes (inertia only) raises the stable step {scaling['gain']:.3g}x")
    floor = None if scene.floor is None else Floor.under(network.points, scene.gravity, height=scene.floor.height,
                                                         friction=scene.floor.friction)
    sim = Simulator(model, network.points, inertia, fixed=fixed, gravity=scene.gravity,
                    mass_damping=scene.mass_damping, safety=scene.safety, gravity_mass=network.mass, floor=floor)
    if floor is not None:
        below = int(np.count_nonzero(floor.distance(network.points)[sim.free] < 0))
        rep.step(f"floor: {floor.friction}, plane {floor.height * 1e3:.4g} mm along up"
                 + (f"; {below} free nodes start below it and are put on it at the first step" if below else ""))

    plan: GraspPlan | None = None
    extra = None
    settle = None
    if scene.start == "equilibrium" and np.any(scene.gravity) and (fixed.size or floor is not None):
        # Start from the static equilibrium under gravity (the organ at rest in the scene).
        t = time.perf_counter()
        try:
            info = sim.relax(rtol=1e-4, max_iter=400_000)
            settle = {**info, "seconds": time.perf_counter() - t, "converged": True}
        except SimulationError as exc:
            if "diverged" in str(exc):
                raise
            settle = {"converged": False, "seconds": time.perf_counter() - t}
            rep.warn(f"the equilibrium under gravity was not reached before t = 0 ({exc}); "
                     "starting from the closest state found")
        u = np.linalg.norm(sim.displacement(), axis=1).max()
        settle["max_displacement_m"] = float(u)
        gdir = scene.gravity / np.linalg.norm(scene.gravity)
        height = float(np.ptp(np.asarray(network.points) @ gdir))
        if floor is not None:
            settle["contact_nodes"] = sim.n_contact
        if u > height:
            rep.warn(f"under its own weight the organ sags {u * 1e3:.3g} mm, more than its height along gravity "
                     f"({height * 1e3:.3g} mm): the network is too soft to carry itself in this scene ("
                     + ("the floor holds only what lies on it, " if floor is not None else "no contact holds it, ")
                     + "only the fixed nodes hold the rest). Stiffen it (volumetric compensation: 'esmm tables ASSET "
                     "--compensate') or hold it elsewhere ([fixed])")
        rep.step(f"equilibrium under gravity: largest sag {u * 1e3:.3g} mm "
                 f"({settle.get('iterations', '?')} FIRE iterations, {settle['seconds']:.2g} s)"
                 + ("; long-term (relaxed) response, history relaxed" if model.effects is not None
                    and model.effects.n_terms else ""))
    if scene.grasper is not None:
        plan = plan_grasp(scene.grasper, sim.x, network.surface_faces, fixed, scene.gravity,
                          springs=network.springs)
        rep.step(plan.describe())
        if scene.grasper.mode == "spring":
            # The coupling springs enter the stability bound.
            extra = np.zeros(model.n_nodes)
            extra[plan.nodes] = plan.make_grasp(sim.x, sim.mass).stiffness
    table_bound = stable_step(model, sim.mass, free=sim.free, extra_stiffness=extra, safety=scene.safety)
    frame_dt = 1.0 / scene.frame_rate
    n_frames = scene.n_frames
    adaptive = scene.step == "adaptive"
    span = model.lam_max - model.lam_min        # a window this wide is the whole table

    def frame_bound(delta):
        if not adaptive or delta is None:
            return table_bound
        more = sim.history_stiffness(delta)       # viscoelastic history forces (None without)
        ex = extra if more is None else (more if extra is None else extra + more)
        b = stable_step(model, sim.mass, free=sim.free, extra_stiffness=ex, safety=scene.safety,
                        x=sim.x, window=delta)
        return b if b.dt_critical >= table_bound.dt_critical else table_bound

    first = frame_bound(scene.window)
    spf0 = max(1, int(math.ceil(frame_dt / first.dt * (1 - 1e-12))))
    # The whole-table bound gives the worst case: refuse runs that could need too many steps.
    worst = n_frames * max(1, int(math.ceil(frame_dt / table_bound.dt * (1 - 1e-12))))
    if (worst if not adaptive else n_frames * spf0) > scene.max_steps:
        raise SimulationError(
            f"the scene needs {worst if not adaptive else n_frames * spf0} steps (stability bound of this asset: "
            f"{first.dt_critical:.3g} s, set by node {first.node}); over [integrator] max_steps = "
            f"{scene.max_steps}; shorten the duration, coarsen the asset or raise max_steps")
    sim.set_time_step(frame_dt / spf0, bound=first, t0=0.0)
    threads, thread_timing = choose_threads(sim, scene.threads)
    sim.threads = threads
    rep.step(f"{model.n_springs} springs, {model.n_nodes} nodes ({fixed.size} fixed), law {law}; step "
             f"{sim.dt * 1e6:.4g} us at start ({spf0} per frame; {'adaptive, window ' + format(scene.window, 'g') if adaptive else 'fixed'}); "
             f"whole-table bound {table_bound.dt_critical * 1e6:.4g} us, omega_max {table_bound.omega_max:.4g} rad/s; "
             f"{threads} thread(s)")

    events = []
    if plan is not None:
        events.append(("grasp", scene.grasper.grasp_time))
        if scene.grasper.release_time is not None:
            events.append(("release", scene.grasper.release_time))

    hist_path = out / "history.h5"
    attrs = {
        "asset": asset_label, "law": law, "step_mode": scene.step, "frame_rate": scene.frame_rate,
        "gravity": scene.gravity.tolist(), "scene_source": scene.source, "scene": scene.describe(),
        "units": "SI (m, s, N)",
    }
    if plan is not None:
        attrs["grasper_normal"] = plan.normal.tolist()
        attrs["grasper_direction"] = plan.direction.tolist()
        attrs["grasper_target"] = plan.target
    if model.effects is not None:
        attrs["effects"] = json.dumps(model.effects.describe(), default=_json_default)
    cells = network.tets if getattr(network, "tets", None) is not None and len(network.tets) else network.surface_faces
    lam_lo, lam_hi = math.inf, -math.inf
    step_wall = 0.0
    total_steps = 0
    redone = 0
    dts = []
    fmax = np.zeros(3)
    fmax_norm = 0.0
    contact_max = sim.n_contact
    range_check = _RangeCheck(model, rep)
    range_check(sim, "at the start")
    organ_size = float(np.ptp(np.asarray(network.points), axis=0).max())
    done = set()
    delta = scene.window if adaptive else None
    with HistoryWriter(hist_path, points=network.points, cells=cells, surface=network.surface_faces,
                       fixed=fixed, attrs=attrs) as hw:
        if plan is not None:
            hw.set_grasped(plan.nodes)
        hw.add_frame(0.0, sim.displacement(), tip=None)      # the rest shape, or the equilibrium
        with rep.task("simulating", total=n_frames) as advance:
            for fr in range(n_frames):
                t_start = fr * frame_dt
                # The window widens when a frame had to be redone, and narrows back slowly.
                delta = max(scene.window, 0.75 * delta) if delta is not None else None
                state = sim.snapshot()
                done_before = set(done)
                while True:
                    bound = frame_bound(delta)
                    spf = max(1, int(math.ceil(frame_dt / bound.dt * (1 - 1e-12))))
                    dt = frame_dt / spf
                    sim.set_time_step(dt, bound=bound, t0=t_start)
                    x0 = sim.x.copy()
                    cuts = {0, spf}
                    for name, te in events:
                        k = int(round((te - t_start) / dt))
                        if 0 <= k < spf and name not in done:
                            cuts.add(k)
                    if delta is not None:                 # check the window along the frame
                        cuts |= set(range(0, spf, max(1, spf // 8)))
                    cuts = sorted(cuts)
                    rec = np.zeros((spf, 3))
                    held_rows = np.zeros(spf, bool)
                    moved = 0.0
                    for a, b in zip(cuts[:-1], cuts[1:]):
                        for name, te in events:
                            if name not in done and int(round((te - t_start) / dt)) == a:
                                done.add(name)
                                if name == "grasp":
                                    sim.attach(plan.make_grasp(sim.x, sim.mass), check_step=False)
                                else:
                                    sim.release()
                        held = sim.grasp is not None
                        t = time.perf_counter()
                        sim.advance(b - a, record=rec[a:b])
                        step_wall += time.perf_counter() - t
                        held_rows[a:b] = held
                        if delta is not None:
                            moved = max(moved, float(K.stretch_change(sim.x, x0, model.ij, model.sd)))
                            if moved > delta and delta < span:
                                break
                    if delta is not None and moved > delta and delta < span:
                        # A stretch left the window the step was chosen for: redo the frame
                        # with a wider window (and the step that goes with it).
                        sim.restore(state)
                        done = set(done_before)
                        delta = 2.0 * max(delta, moved)
                        redone += 1
                        continue
                    break
                total_steps += spf
                dts.append(dt)
                if held_rows.any():
                    rows = np.flatnonzero(held_rows)
                    r = rec[rows]
                    hw.add_forces(t_start + rows * dt, r)
                    norms = np.linalg.norm(r, axis=1)
                    k = int(np.argmax(norms))
                    if norms[k] > fmax_norm:
                        fmax_norm = float(norms[k])
                        fmax = r[k].copy()
                disp = sim.displacement()
                if not np.all(np.isfinite(disp)) or np.abs(disp).max() > 10.0 * organ_size:
                    raise SimulationError(
                        f"the simulation became unstable at t = {sim.t:.4g} s (displacements beyond 10 organ "
                        f"sizes or non-finite); lower [integrator] safety or check the asset's masses and tables")
                lo, hi = range_check(sim, f"at t = {sim.t:.3g} s")
                lam_lo, lam_hi = min(lam_lo, lo), max(lam_hi, hi)
                contact_max = max(contact_max, sim.n_contact)
                tip = sim.grasp.tip(sim.t) if sim.grasp is not None else None
                hw.add_frame(sim.t, disp, tip=tip)
                advance(1)
                if total_steps > scene.max_steps:
                    raise SimulationError(
                        f"the run needed more than [integrator] max_steps = {scene.max_steps} steps by "
                        f"t = {sim.t:.3g} s; shorten the duration, coarsen the asset or raise max_steps")
        umax = float(np.linalg.norm(sim.displacement(), axis=1).max())
        sim_time = n_frames * frame_dt
        sim_time_total = sim_time
        summary = {
            "asset": asset_label, "scene": scene.describe(), "scene_source": scene.source,
            "nodes": model.n_nodes, "springs": model.n_springs, "fixed_nodes": int(fixed.size),
            "law": law, "precision": scene.precision, "step_mode": scene.step, "window": scene.window,
            "dt_min_s": min(dts), "dt_max_s": max(dts), "dt_mean_s": sim_time_total / total_steps,
            "steps": total_steps, "frames_redone": redone, "dt_table_bound_s": table_bound.dt_critical,
            "safety": scene.safety, "omega_max_table_rad_s": table_bound.omega_max,
            "gamma_max_1_s": table_bound.gamma_max,
            "dashpot_s": scene.dashpot, "velocity_decay_s": scene.velocity_decay,
            "mass_scaling": {"budget": scene.mass_scaling, **scaling},
            "start": scene.start, "equilibrium": settle,
            "threads": threads, "thread_trial_s_per_step": thread_timing,
            "build_s": build_s, "warm_up_s": warm, "stepping_wall_s": step_wall,
            "wall_per_step_us": step_wall / total_steps * 1e6,
            "ns_per_spring_step": step_wall / total_steps / model.n_springs * 1e9,
            "simulated_s": sim_time, "real_time_factor": sim_time / step_wall if step_wall > 0 else math.inf,
            "stretch_min": lam_lo, "stretch_max": lam_hi, "table_range": [model.lam_min, model.lam_max],
            "outside_table": range_check.summary(),
            "effects": None if model.effects is None else {**model.effects.describe(),
                                                           "final_state": sim.effects_report()},
            "effects_available": None if not effects else list(effects.names),
            "final_max_displacement_m": umax,
            "floor": None if floor is None else {
                "friction": floor.friction, "normal": floor.normal.tolist(), "height_m": floor.height,
                "height_spec": scene.floor.height, "contact_nodes_final": sim.n_contact,
                "contact_nodes_max": contact_max,
                "min_distance_m": float(floor.distance(sim.x)[sim.free].min()) if sim.free.any() else None},
            "grasper": None if plan is None else {
                "target_node": plan.target, "held_nodes": int(plan.nodes.size), "mode": plan.spec.mode,
                "direction": plan.direction.tolist(), "max_force_N": fmax_norm, "force_at_max_N": fmax.tolist()},
        }
        hw.set_attrs(summary=summary)
    rep.step(f"simulated {sim_time:g} s in {step_wall:.3g} s of stepping (real-time factor "
             f"{summary['real_time_factor']:.3g}, {summary['ns_per_spring_step']:.3g} ns per spring per step)")

    force_png = None
    if plan is not None:
        force_png = out / "grasper_force.png"
        plot_forces(hist_path, force_png, plan=plan)
    video = None
    if video_path is not None:
        from .render import render_video

        info = render_video(hist_path, video_path, video=scene.video, reporter=rep)
        video = Path(video_path)
        summary["video"] = {"path": str(video), "frames": info["frames"], "render_s": info["seconds"],
                            "render_fps": info["render_fps"]}
        rep.step(f"video: {info['frames']} frames in {info['seconds']:.3g} s ({info['render_fps']:.3g} frames/s)")
    summary_path = out / "summary.json"
    write_text(summary_path, json.dumps(summary, indent=2, default=_json_default) + "\n")
    return SimulationResult(out_dir=out, history=hist_path, xdmf=hist_path.with_suffix(".xdmf"),
                            force_plot=force_png, summary_path=summary_path, video=video, summary=summary)


def _describe_effects(fx) -> str:
    e = fx.effects
    parts = []
    if e.viscoelastic is not None:
        v = e.viscoelastic
        parts.append("viscoelastic (QLV, " + ", ".join(f"g {g:.3g} tau {t:.3g} s" for g, t in zip(v.g, v.tau))
                     + f"; long-term {v.g_inf:.3g} of the instantaneous response)")
    if e.mullins is not None:
        parts.append(f"Mullins (r {e.mullins.r:.3g}, m {e.mullins.m:.3g} Pa, beta {e.mullins.beta:.3g})")
    if e.damage is not None:
        parts.append(f"damage (onset {e.damage.onset:.3g}, scale {e.damage.scale:.3g}, shape {e.damage.shape:.3g})")
    return "; ".join(parts) + " per spring"


class _RangeCheck:
    """Warn once per run when springs leave the tables' stretch grid; count where it happened."""

    def __init__(self, model, rep):
        self.model = model
        self.rep = rep
        self.first = None
        self.checks = 0
        self.outside = 0
        self.lo = math.inf
        self.hi = -math.inf

    def __call__(self, sim, when: str) -> tuple[float, float]:
        m = self.model
        lo, hi = m.stretch_range(sim.x)
        self.checks += 1
        if lo < m.lam_min or hi > m.lam_max:
            self.outside += 1
            self.lo, self.hi = min(self.lo, lo), max(self.hi, hi)
            if self.first is None:
                self.first = when
                lam = m.stretches(sim.x)
                n_out = int(np.count_nonzero((lam < m.lam_min) | (lam > m.lam_max)))
                self.rep.warn(
                    f"{when}, {n_out} of {m.n_springs} springs are outside the tables' stretch range "
                    f"[{m.lam_min:.4g}, {m.lam_max:.4g}] (stretches {lo:.4g}..{hi:.4g}): there the force is "
                    "the tables' extrapolation, not the material (docs/simulate.md). The organ deforms more "
                    "than its material can describe: a gentler scene, or a stiffer network (volumetric "
                    "compensation: 'esmm tables ASSET --compensate'). Warned once per run; the summary "
                    "counts the frames")
        return lo, hi

    def summary(self) -> dict:
        return {"frames": self.outside, "of_frames": self.checks, "first": self.first,
                "stretch_min": None if self.first is None else self.lo,
                "stretch_max": None if self.first is None else self.hi}


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def plot_forces(history_path, png_path, *, plan: GraspPlan | None = None) -> Path:
    """Plot the grasper force (components and magnitude) vs time into *png_path*."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from .history import History

    with History(history_path) as h:
        t, f = h.forces()
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    if t.size:
        step = max(1, t.size // 20000)          # plot at most ~20 000 points per curve
        ts, fs = t[::step], f[::step]
        for k, (name, col) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"))):
            ax.plot(ts, fs[:, k], color=col, lw=0.8, label=f"F{name}")
        ax.plot(ts, np.linalg.norm(fs, axis=1), color="black", lw=1.2, label="|F|")
        ax.legend(loc="best", fontsize=8)
    else:
        ax.text(0.5, 0.5, "the grasper held nothing", ha="center", va="center", transform=ax.transAxes)
    if plan is not None:
        for tt, lab in ((plan.spec.grasp_time, "grasp"), (plan.spec.release_time, "release")):
            if tt is not None:
                ax.axvline(tt, color="gray", ls=":", lw=0.8)
                ax.text(tt, ax.get_ylim()[1], f" {lab}", va="top", fontsize=7, color="gray")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("force of the tissue on the grasper [N]")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(png_path)


def read_asset_for_simulation(path, *, with_effects: bool = False):
    """(network, tables, label) of an asset file (and its MaterialEffects or None, *with_effects*)."""
    p = Path(path)
    if not p.is_file():
        raise AssetError(f"{p}: no such asset file; build one with 'esmm prepare'")
    try:
        from ..asset import read_asset
    except ImportError:  # pragma: no cover - the asset module is part of esmm
        raise AssetError("this esmm build cannot read assets (esmm.pipeline.asset missing)") from None
    asset = read_asset(p)
    network = getattr(asset, "network", None)
    tables = getattr(asset, "tables", None)
    if network is None or tables is None:
        raise AssetError(f"{p}: the asset has no spring network or no stiffness tables; rebuild it with "
                         "'esmm prepare'")
    if with_effects:
        return network, tables, str(p), getattr(asset, "effects", None)
    return network, tables, str(p)


def simulate(asset_path, *, scene=None, out_dir=None, video_path=None, duration=None, threads=None,
             law=None, effects=None, reporter=None) -> SimulationResult:
    """Run a scene on an asset file (the ``esmm simulate`` command).

    Parameters
    ----------
    asset_path : path-like
        HDF5 asset written by ``esmm prepare``.
    scene : Scene, str or path-like, optional
        A :class:`Scene`, a bundled scene name or a TOML path (default: ``"default"``).
    out_dir : path-like, optional
        Output folder (default: ``<asset stem>-sim`` beside the asset).
    video_path : path-like, optional
    duration : float, optional
        Override of the scene's duration [s].
    threads : "auto" or int, optional
    law : {"asset", "secant", "energy"}, optional
    effects : {"asset", "none"}, optional
        Override of the scene's use of the asset's material effects.
    """
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    sc = sc.with_overrides(duration=duration, threads=threads, law=law, effects=effects)
    network, tables, label, effects = read_asset_for_simulation(asset_path, with_effects=True)
    if out_dir is None:
        out_dir = Path(asset_path).with_name(Path(asset_path).stem + "-sim")
    if video_path is not None and Path(video_path).suffix.lower() not in (".mp4", ".mkv", ".mov", ".avi"):
        raise ConfigError(f"--video: {video_path} should end in .mp4 (or .mkv, .mov, .avi)")
    return simulate_network(network, tables, sc, out_dir, video_path=video_path, reporter=reporter,
                            asset_label=label, effects=effects)
