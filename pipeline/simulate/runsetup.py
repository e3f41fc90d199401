"""Setting a run up: the simulation of a scene on a network, its start, grasper and steps.

Each function is one stage of :func:`~.run.simulate_network` before the
frames run, reporting what it decided:

* :func:`prepare_run`: the law, the fixed nodes, the spring term (with the
  scene's material effects), the volume term (when the asset has one and the
  scene keeps it), the compiled kernels, mass scaling, the floor, and the
  :class:`~.simulator.Simulator`;
* :func:`settle_at_start`: the static equilibrium under gravity (``start =
  "equilibrium"``);
* :func:`plan_grasper`: the grasper resolved on the network;
* :func:`plan_steps`: the whole-table bound, the per-frame
  :class:`~.stepper.StepSchedule` (explicit) or the fixed step of the
  :class:`~.implicit.ImplicitSchedule` with its first factorization, the first
  step and the threads.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from .. import cache
from ..errors import ConfigError, SimulationError
from ..network.regions import select_fixed
from .grasper import GraspPlan, plan_grasp
from .implicit import BackwardEuler, ImplicitSchedule
from .model import Floor
from .relax import RelaxNotConverged
from .scene import Scene
from .simulator import Simulator, warm_up
from .springterm import build_spring_term
from .stepper import StepSchedule, mass_scaling, stable_step
from .volumeterm import VolumeTerm, build_volume_term, shape_change

#: Below this many springs one thread is used ("auto"): the parallel pass's
#: fork/join costs more than it saves (benchmarks/bench_simulate.py).
AUTO_PARALLEL_MIN_SPRINGS = 20_000
#: What the implicit stepper factored, in words (:meth:`~.implicit.BackwardEuler.factored`).
FACTORED = {"bound": "the volume term's per-tet bound in it", "exact": "Newton's matrix",
            "mixed": "Newton's matrix from its parts, the volume term's as a saddle point"}


@dataclass
class RunSetup:
    """A run ready to go: its simulator and what was decided on the way."""

    sim: Simulator
    law: str
    fixed: np.ndarray
    scaling: dict              #: mass scaling's ``added_fraction``, ``nodes``, ``gain``
    build_s: float             #: building the spring term [s]
    warm_up_s: float           #: compiling (or loading) the kernels [s]
    schedule: StepSchedule | ImplicitSchedule | None = None
    threads: int = 1
    thread_timing: dict = field(default_factory=dict)
    prefactor_s: float = 0.0   #: the implicit stepper's first factorization, before t = 0 [s]
    start_inertia: np.ndarray | None = None   #: FIRE's masses for the start, if not the stepper's
    tets: np.ndarray | None = None      #: the network's tetrahedra (volume and inversion records)


def threads_available() -> int:
    """Threads numba may use."""
    import numba

    return int(numba.config.NUMBA_NUM_THREADS)


#: How long numba's OpenMP workers wait actively for the next parallel region before they sleep
#: (``GOMP_SPINCOUNT``; tens of milliseconds on a current core): see :func:`keep_workers_awake`.
WORKER_SPIN = "3000000"


def keep_workers_awake() -> None:
    """Let numba's OpenMP workers spin between parallel regions for a while before they sleep.

    By default libgomp's idle workers can go to sleep almost at once (``GOMP_SPINCOUNT`` alone does
    not change that, ``OMP_WAIT_POLICY=ACTIVE`` does), and a sleeping core, on a virtual machine
    especially, can take milliseconds to wake: more than the implicit stepper's whole solve it was
    woken for, so two threads' solves between other work would be slower than one thread's
    (docs/design/simulator.md, "What is factored, and when it is renewed"). ``OMP_WAIT_POLICY=ACTIVE``
    with a finite ``GOMP_SPINCOUNT`` keeps them awake through a run and lets them sleep within
    ~0.1 s after it. Only defaults (a user's own settings win), and only before numba first starts
    its threads.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "ACTIVE")
    os.environ.setdefault("GOMP_SPINCOUNT", WORKER_SPIN)


def fixed_nodes(network, scene: Scene) -> np.ndarray:
    """The scene's fixed nodes on *network* (its own region, or the asset's)."""
    if scene.fixed is None:
        return np.asarray(network.fixed, dtype=np.int64)
    return select_fixed(network.points, scene.fixed, node_kind=getattr(network, "node_kind", None),
                        where="[fixed]")


def prepare_run(network, tables, scene: Scene, *, effects, reporter) -> RunSetup:
    """The simulator of *scene* on *network* with *tables* (and the asset's *effects*, unless switched off)."""
    rep = reporter
    law = tables.check_law(None if scene.law == "asset" else scene.law)
    fixed = fixed_nodes(network, scene)
    if fixed.size == 0 and np.any(scene.gravity) and scene.grasper is None and scene.floor is None:
        rep.warn("no node is fixed and gravity is on: the organ will fall freely")
    use_fx = effects if (scene.effects == "asset" and effects) else None
    if effects and use_fx is None:
        rep.step(f"material effects {', '.join(effects.names)} switched off by the scene (effects = \"none\")")
    t = time.perf_counter()
    springs = build_spring_term(network, tables, law=law, dashpot=scene.dashpot, precision=scene.precision,
                                effects=use_fx)
    build_s = time.perf_counter() - t
    if springs.effects is not None:
        rep.step(f"material effects: {springs.effects.explain()}")
    implicit = scene.method == "implicit"
    volume = volume_term(network, tables, scene, rep)
    keep_workers_awake()
    parallel = not implicit and threads_available() > 1 and springs.n_springs >= AUTO_PARALLEL_MIN_SPRINGS
    with rep.task("the compiled kernels (from numba's cache, or compiled once per machine: about half a "
                  "minute)", total=2 if parallel else 1) as advance:
        warm = warm_up(springs, threads=1, volume=volume, implicit=implicit)
        advance()
        if parallel:
            warm += warm_up(springs, threads=threads_available(), volume=volume)
            advance()
    if warm > 5.0:
        rep.step(f"kernels compiled in {warm:.0f} s (cached for the next runs)")
    free0 = np.ones(springs.n_nodes, bool)
    free0[fixed] = False
    terms = [springs] if volume is None else [springs, volume]
    # The implicit step is not bounded by the light nodes: their true inertia is kept. The start's
    # equilibrium is the explicit run's whatever the stepper (FIRE on its masses: on a sticking floor
    # the equilibrium depends on FIRE's path)
    scaled, scaling = mass_scaling(terms, network.mass, free=free0, budget=scene.mass_scaling)
    inertia, start_inertia = scaled, None
    if implicit:
        start_inertia = scaled
        inertia, scaling = mass_scaling(terms, network.mass, free=free0, budget=0.0)
    if scaling["nodes"]:
        rep.step(f"mass scaling: +{scaling['added_fraction'] * 100:.3g} % of the mass on {scaling['nodes']} "
                 f"light nodes (inertia only) raises the stable step {scaling['gain']:.3g}x")
    floor = None if scene.floor is None else Floor.under(network.points, scene.gravity, height=scene.floor.height,
                                                         friction=scene.floor.friction)
    stepper = BackwardEuler(step=scene.solve_step, rtol=scene.newton_tol, haptic_rate=scene.haptic_rate,
                            factor_matrix=scene.factor, iteration=scene.iteration,
                            coarse_cells=_coarse_cells(network, scene)) \
        if implicit else None
    sim = Simulator(springs, network.points, inertia, fixed=fixed, gravity=scene.gravity,
                    mass_damping=scene.mass_damping, safety=scene.safety, gravity_mass=network.mass, floor=floor,
                    stepper=stepper, volume=volume)
    if floor is not None:
        _check_floor(floor, np.asarray(network.points)[sim.free], rep)
    return RunSetup(sim=sim, law=law, fixed=fixed, scaling=scaling, build_s=build_s, warm_up_s=warm,
                    tets=getattr(network, "tets", None), start_inertia=start_inertia)


def _coarse_cells(network, scene):
    """The split asset's parents where the scene asks for the two-grid preconditioner, else None.

    Raises
    ------
    ConfigError
        ``[integrator] preconditioner = "two-grid"`` on an asset that was not split.
    """
    if scene.preconditioner != "two-grid":
        return None
    cells = getattr(network, "quadratic_cells", None)
    if cells is None:
        raise ConfigError("[integrator] preconditioner: \"two-grid\" needs a split asset (esmm prepare --split), "
                          "whose parents are its coarse level; this asset was not split: use \"factor\"")
    return np.asarray(cells, dtype=np.int64)


def _check_floor(floor: Floor, free_points: np.ndarray, reporter) -> None:
    """Refuse a floor above the whole organ; warn about free nodes that start below it (they are put on it).

    Raises
    ------
    ConfigError
        ``[floor] height`` puts the plane at or above every free node (the organ would start inside it).
    """
    d = floor.distance(free_points)
    h = floor.height * 1e3
    if d.size and d.max() <= 0:
        raise ConfigError(f"[floor] height: the plane at {h:.4g} mm along up is above the whole organ (its free "
                          f"nodes are at {h + d.min() * 1e3:.4g}..{h + d.max() * 1e3:.4g} mm along up): it would "
                          "start inside the floor; give a height below its lowest node, or \"auto\"")
    below = int(np.count_nonzero(d < 0))
    reporter.step(f"floor: {floor.friction}, plane {h:.4g} mm along up")
    if below:
        reporter.warn(f"[floor] height: {below} of {d.size} free nodes start below the plane at {h:.4g} mm along "
                      f"up (the deepest {-d.min() * 1e3:.3g} mm) and are put on it at the first step, which "
                      "crushes that part of the organ; \"auto\" puts the plane under its lowest node")


def _check_path_above_floor(plan: GraspPlan, floor: Floor | None, x: np.ndarray, reporter) -> None:
    """Warn when the grasper's path takes its tip below the floor (the held nodes are exempt from it)."""
    if floor is None:
        return
    d = floor.distance(np.asarray(x[plan.target]) + plan.offsets)
    k = int(np.argmin(d))
    if d[k] < 0:
        reporter.warn(f"[grasper] waypoints: the path takes the tip {-d[k] * 1e3:.3g} mm below the floor (at "
                      f"{plan.times[k]:g} s, from the grasp point's place at the start): the held nodes are exempt "
                      "from the floor and go through it; keep the path above it")


def volume_term(network, tables, scene: Scene, reporter) -> VolumeTerm | None:
    """The network's volume term for this run (None: the asset has none, or the scene says ``volume = "none"``)."""
    spec = getattr(network, "volume_term", None)
    if spec is None:
        if getattr(network, "tets", None) is not None:
            reporter.step("no volume term in the asset: the network is compressible (Poisson ratio ~1/4); "
                          "rebuild it with 'esmm prepare' to keep the organ's volume")
        return None
    if scene.volume == "none":
        reporter.step("volume term switched off by the scene (volume = \"none\"): springs alone")
        return None
    vol = build_volume_term(network.points, network.tets, spec, lam_max=tables.lam_max)
    nu = "" if spec.poisson_ratio is None else f", Poisson ratio {spec.poisson_ratio:g} at the stiffest state"
    reporter.step(f"volume term: {spec.formulation} elements on {vol.n_tets} tets, bulk modulus "
                  f"{spec.bulk_modulus / 1e3:.4g} kPa{nu}")
    return vol


def settle_at_start(run: RunSetup, scene: Scene, network, reporter) -> dict | None:
    """Start from the static equilibrium under gravity (``start = "equilibrium"``); its record, or None."""
    sim, rep = run.sim, reporter
    if not (scene.start == "equilibrium" and np.any(scene.gravity) and (run.fixed.size or sim.floor is not None)):
        return None
    t = time.perf_counter()
    try:
        info = sim.relax(rtol=1e-4, max_iter=400_000, inertia=run.start_inertia, reporter=rep,
                         cache=cache.folder("settle"))
        settle = {**info, "seconds": time.perf_counter() - t, "converged": True}
    except RelaxNotConverged as exc:    # (diverged: raised as it is)
        settle = {"converged": False, "seconds": time.perf_counter() - t}
        # FIRE's own advice ("raise max_iter or the tolerance") names knobs no scene or option sets.
        weight = float(np.linalg.norm(sim.fext, axis=1).sum())
        rep.warn(f"the equilibrium under gravity was not reached before t = 0 ({exc.summary}; the organ weighs "
                 f"{weight:.3g} N); starting from the closest state found, which its residual forces move at "
                 "t = 0 ([scene] start = \"rest\" starts from the asset's shape instead)")
    u = np.linalg.norm(sim.displacement(), axis=1).max()
    settle["max_displacement_m"] = float(u)
    settle["shape"] = shape_change(network.points, getattr(network, "tets", None), sim.x, scene.gravity)
    gdir = scene.gravity / np.linalg.norm(scene.gravity)
    height = float(np.ptp(np.asarray(network.points) @ gdir))
    if sim.floor is not None:
        settle["contact_nodes"] = sim.n_contact
    if u > height:
        rep.warn(f"under its own weight the organ sags {u * 1e3:.3g} mm, more than its height along gravity "
                 f"({height * 1e3:.3g} mm): the network is too soft to carry itself in this scene ("
                 + ("the floor holds only what lies on it, " if sim.floor is not None else "no contact holds it, ")
                 + "only the fixed nodes hold the rest). Stiffen it (volumetric compensation: 'esmm tables ASSET "
                 "--compensate') or hold it elsewhere ([fixed])")
    fx = sim.model.springs.effects
    shape = settle["shape"]
    kept = "" if shape["volume_ratio"] is None else (
        f", volume {100 * (shape['volume_ratio'] - 1):+.2g} %, {shape['inverted_tets']} inverted tets")
    head = "equilibrium under gravity" if settle["converged"] else "start (FIRE's closest state, not converged)"
    fire = f"{settle['iterations']} FIRE iterations" if "iterations" in settle else "FIRE unconverged"
    rep.step(f"{head}: largest sag {u * 1e3:.3g} mm, median {shape['sag_median_m'] * 1e3:.3g} mm"
             f"{kept} ({fire}, "
             + ("taken from the cache of equilibria found before" if settle.get("cached") else
                f"{settle['seconds']:.2g} s") + ")"
             + ("; long-term (relaxed) response, history relaxed" if fx is not None and fx.n_terms else ""))
    return settle


def plan_grasper(run: RunSetup, scene: Scene, network, reporter) -> GraspPlan | None:
    """The scene's grasper resolved on the (settled) network, or None."""
    if scene.grasper is None:
        return None
    plan = plan_grasp(scene.grasper, run.sim.x, network.surface_faces, run.fixed, scene.gravity,
                      springs=network.springs)
    reporter.step(plan.describe())
    _check_path_above_floor(plan, run.sim.floor, run.sim.x, reporter)
    late = plan.times[plan.times > scene.duration * (1 + 1e-9)]
    if late.size:
        reporter.warn(f"[grasper] waypoints: {late.size} of them come after the end of the run ({scene.duration:g} s; "
                      f"the first at {late[0]:g} s): the tip follows the path up to the end only; lengthen the "
                      "duration or drop them")
    return plan


def _as_asked(requested, avail: int) -> int:
    """A thread count as asked, at least one and at most *avail*."""
    return max(1, min(int(requested), avail))


def _chosen(requested, avail: int, trial) -> tuple[int, dict]:
    """Threads as *requested* (at most *avail*), or for ``"auto"`` the fastest of *trial()*'s timings
    (``{threads: seconds}``; empty: one thread); and those timings for the summary."""
    if requested != "auto":
        return _as_asked(requested, avail), {}
    timing = trial() if avail > 1 else {}
    if not timing:
        return 1, {}
    return min(timing, key=timing.get), {str(k): v for k, v in timing.items()}


def choose_threads(sim: Simulator, requested, *, trial_steps: int = 30) -> tuple[int, dict]:
    """Resolve ``threads = "auto"`` by timing both step loops on the current state (then restored)."""
    avail = threads_available()

    def trial() -> dict:
        if sim.model.springs.n_springs < AUTO_PARALLEL_MIN_SPRINGS:
            return {}
        state = sim.snapshot()
        timing = {}
        for th in (1, avail):
            sim.threads = th
            sim.advance(2)
            t = time.perf_counter()
            sim.advance(trial_steps)
            timing[th] = (time.perf_counter() - t) / trial_steps
            sim.restore(state)
        return timing

    return _chosen(requested, avail, trial)


def choose_solve_threads(sim: Simulator, requested) -> tuple[int, dict]:
    """The implicit stepper's solve threads (1 or 2): as *requested*, or for ``"auto"`` the faster on
    its first factor, timed (on a busy machine two threads wait for each other longer than they save)."""
    return _chosen(requested, min(2, threads_available()), lambda: sim.stepper.solve_timing((1, 2)))


def choose_factor_threads(requested) -> int:
    """The implicit stepper's factorization threads (1 or 2): as *requested*, or for ``"auto"`` two where
    numba has them, untimed: a factorization takes tens of milliseconds, so the workers' wake-up (a
    few milliseconds at most) does not count as it does for a solve, and two threads factor at least
    as fast as one even beside another busy process (docs/design/simulator.md, "What is factored, and
    when it is renewed")."""
    return _as_asked(2 if requested == "auto" else requested, min(2, threads_available()))


def plan_steps(run: RunSetup, scene: Scene, plan: GraspPlan | None, reporter) -> None:
    """The run's step schedule, its first step and threads (into *run*).

    Raises
    ------
    SimulationError
        The scene could need more than ``[integrator] max_steps`` steps.
    """
    sim = run.sim
    springs = sim.model.springs
    # The grasper's coupling springs (mode "spring") enter the bound from the start.
    reserve = None if plan is None else plan.coupling_rows(sim.x, sim.mass)
    table = stable_step(sim.model.terms, sim.mass, free=sim.free, extra_stiffness=reserve, safety=scene.safety)
    if scene.method == "implicit":
        _plan_implicit(run, scene, table, reporter)
        return
    adaptive = scene.step == "adaptive"
    schedule = StepSchedule(table=table, adaptive=adaptive, window=scene.window, reserve=reserve,
                            safety=scene.safety)
    frame_dt = 1.0 / scene.frame_rate
    first = schedule.bound(sim.model, sim.state, sim.control, schedule.first_window)
    spf0 = schedule.steps_per_frame(frame_dt, first)
    # The whole-table bound gives the worst case: refuse runs that could need too many steps.
    need = scene.n_frames * (spf0 if adaptive else schedule.steps_per_frame(frame_dt, table))
    if need > scene.max_steps:
        raise SimulationError(
            f"the scene needs {need} steps (stability bound of this asset: "
            f"{first.dt_critical:.3g} s, set by node {first.node}); over [integrator] max_steps = "
            f"{scene.max_steps}; shorten the duration, coarsen the asset or raise max_steps")
    sim.set_time_step(frame_dt / spf0, bound=first, t0=0.0)
    run.threads, run.thread_timing = choose_threads(sim, scene.threads)
    sim.threads = run.threads
    run.schedule = schedule
    window = "adaptive, window " + format(scene.window, "g") if adaptive else "fixed"
    reporter.step(f"{springs.n_springs} springs, {springs.n_nodes} nodes ({run.fixed.size} fixed), law {run.law}; "
                  f"step {sim.dt * 1e6:.4g} us at start ({spf0} per frame; {window}); whole-table bound "
                  f"{table.dt_critical * 1e6:.4g} us, omega_max {table.omega_max:.4g} rad/s; {run.threads} thread(s)")


def _plan_implicit(run: RunSetup, scene: Scene, table, reporter) -> None:
    """The implicit run's fixed step and its first factorization (before t = 0)."""
    sim = run.sim
    springs = sim.model.springs
    schedule = ImplicitSchedule(step=scene.solve_step, table=table)
    frame_dt = 1.0 / scene.frame_rate
    spf = schedule.steps_per_frame(frame_dt, schedule.bound(sim.model, sim.state, sim.control, None))
    if scene.n_frames * spf > scene.max_steps:
        raise SimulationError(f"the scene needs {scene.n_frames * spf} implicit steps; over [integrator] max_steps = "
                              f"{scene.max_steps}; lengthen implicit_step or raise max_steps")
    sim.set_time_step(frame_dt / spf, bound=schedule.bound(sim.model, sim.state, sim.control, None), t0=0.0)
    if scene.solve_step > frame_dt * (1 + 1e-9):
        reporter.warn(f"[integrator] implicit_step: {scene.solve_step * 1e3:.4g} ms is longer than a frame "
                      f"({frame_dt * 1e3:.4g} ms at {scene.frame_rate:g} frames/s): the solve steps once per frame, "
                      f"at {sim.dt * 1e3:.4g} ms; give at most a frame (or \"frame\")")
    run.schedule = schedule
    sim.stepper.factor_threads = choose_factor_threads(scene.threads)
    run.prefactor_s = sim.stepper.prepare(sim.model, sim.state, sim.control)
    run.threads, run.thread_timing = choose_solve_threads(sim, scene.threads)
    sim.threads = run.threads
    if run.threads > 1 and "1" in run.thread_timing:
        sim.stepper.solo_solve_s = run.thread_timing["1"]      # two threads fall back to one if they get slower
    if isinstance(scene.threads, int) and scene.threads > 2:
        reporter.warn(f"[integrator] threads = {scene.threads}: the implicit stepper's solves use at most 2 "
                      "(the two halves of the factor's nested dissection); the rest of its step, one")
    st = sim.stepper.stats
    factored = FACTORED[sim.stepper.factored(sim.model)]
    reporter.step(f"{springs.n_springs} springs, {springs.n_nodes} nodes ({run.fixed.size} fixed), law {run.law}; "
                  f"implicit (backward Euler), step {sim.dt * 1e3:.4g} ms ({spf} per frame; the explicit bound "
                  f"would be {table.dt_critical * 1e6:.4g} us), grasper force at {scene.haptic_rate:g} Hz; "
                  f"factored in {run.prefactor_s:.2g} s (fill {st.factor_nnz / 1e6:.3g} M, {factored}); "
                  f"{run.threads} thread(s)")

