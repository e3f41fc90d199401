"""The figures of a run: :class:`SimulationSummary` (written as ``summary.json`` and into the history).

Every field is one key of ``summary.json``, in the file's order; nested
records are small dataclasses (:class:`GrasperSummary`, :class:`FloorSummary`,
:class:`VideoSummary`) or, for the records other parts produce (mass scaling,
equilibrium, thread trial, range check, effects), plain dicts.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .frames import FrameLog, RangeCheck
from .grasper import GraspPlan
from .runsetup import RunSetup
from .scene import Scene
from .volumeterm import shape_change


@dataclass
class GrasperSummary:
    """The grasper of a run: where it held, how, and the largest force it felt."""

    target_node: int
    held_nodes: int
    mode: str
    direction: list
    max_force_N: float
    force_at_max_N: list


@dataclass
class FloorSummary:
    """The floor of a run and its contacts."""

    friction: str
    normal: list
    height_m: float
    height_spec: Any
    contact_nodes_final: int
    contact_nodes_max: int
    min_distance_m: float | None


@dataclass
class VideoSummary:
    """The rendered video."""

    path: str
    frames: int
    render_s: float
    render_fps: float


@dataclass
class SimulationSummary:
    """What ``summary.json`` records (units in the names: s, us, ns, m, N, rad/s, 1/s)."""

    asset: str
    scene: str
    scene_source: str
    nodes: int
    springs: int
    fixed_nodes: int
    law: str
    method: str
    precision: str
    step_mode: str
    window: float
    dt_min_s: float
    dt_max_s: float
    dt_mean_s: float
    steps: int
    frames_redone: int
    dt_table_bound_s: float
    safety: float
    omega_max_table_rad_s: float
    gamma_max_1_s: float
    dashpot_s: float
    velocity_decay_s: float | None
    mass_scaling: dict
    start: str
    equilibrium: dict | None
    threads: int
    thread_trial_s_per_step: dict
    build_s: float
    warm_up_s: float
    stepping_wall_s: float
    wall_per_step_us: float
    ns_per_spring_step: float
    simulated_s: float
    real_time_factor: float
    stretch_min: float
    stretch_max: float
    table_range: list
    outside_table: dict
    effects: dict | None
    effects_available: list | None
    final_max_displacement_m: float
    floor: FloorSummary | None
    grasper: GrasperSummary | None
    integrator: dict | None = None
    video: VideoSummary | None = None
    volume: dict | None = None
    fixed: dict | None = None

    @property
    def real_time(self) -> str:
        """The real-time factor in words (:func:`real_time_words`)."""
        return real_time_words(self.real_time_factor)

    def fixed_words(self) -> str:
        """Where the fixed nodes came from, in words: the asset's, or the scene's region in place of them."""
        fx = self.fixed or {}
        if fx.get("source") != "scene":
            return f"{self.fixed_nodes} fixed nodes: the asset's own"
        asset = fx.get("asset_nodes")
        instead = "" if asset is None else f" in place of the asset's {asset}"
        return (f"{self.fixed_nodes} fixed nodes from the scene's [fixed] region ({fx.get('region', '')}){instead}; "
                "[fixed] kind = \"asset\" keeps the asset's")

    @property
    def effect_names(self) -> list[str]:
        """The material effects applied (empty when none)."""
        return [] if self.effects is None else list(self.effects["final_state"]["effects"])

    def to_dict(self) -> dict:
        """The JSON document (``video`` only when a video was rendered)."""
        d = asdict(self)
        if self.video is None:
            del d["video"]
        return d

    def describe(self) -> str:
        """One line for the reporter."""
        line = (f"simulated {self.simulated_s:g} s in {self.stepping_wall_s:.3g} s of stepping (real-time factor "
                f"{self.real_time_factor:.3g}, {self.real_time}; {self.method}, ")
        it = self.integrator
        if self.method == "implicit" and it:
            return line + (f"{self.steps} steps of {self.dt_max_s * 1e3:.4g} ms, {iterations_per_step(it)} and "
                           f"{it['solves'] / max(1, it['steps']):.3g} solves per step, "
                           f"{it['factorizations']} factorizations; grasper force at {it['haptic_rate_hz']:g} Hz)")
        return line + f"{self.ns_per_spring_step:.3g} ns per spring per step)"


def real_time_words(factor: float) -> str:
    """Simulated over stepping time, in words: ``0.27x real time: 3.7 times slower than real time``.

    Above 1 the simulation keeps up with the clock (what an interactive simulator needs); below 1
    a second of simulated time takes more than a second.
    """
    if not math.isfinite(factor) or factor <= 0:
        return f"real-time factor {factor:g}: not measured (no stepping time)"
    head = f"{factor:.2g}x real time" if factor < 1 else f"{factor:.3g}x real time"
    if abs(factor - 1.0) < 0.005:
        return f"{head}: as fast as real time"
    ratio = factor if factor > 1 else 1 / factor
    times = f"{ratio:.3g}" if ratio < 2 else f"{ratio:.2g}" if ratio < 100 else f"{ratio:.0f}"
    return f"{head}: {times} times {'faster' if factor > 1 else 'slower'} than real time"


def iterations_per_step(stats: dict) -> str:
    """The implicit stepper's iterations per step, in words: "2.1 quasi-Newton + 0.3 Newton iterations"."""
    steps = max(1, stats["steps"])
    newton = f"{stats['newton'] / steps:.3g} Newton iterations"
    if not stats.get("quasi_newton"):
        return newton
    return f"{stats['quasi_newton'] / steps:.3g} quasi-Newton + {newton}"


def summarize(run: RunSetup, scene: Scene, log: FrameLog, range_check: RangeCheck, *,
              plan: GraspPlan | None, settle: dict | None, asset_label: str,
              effects_available=None, asset_fixed: int | None = None) -> SimulationSummary:
    """The summary of a finished run (*run* as it ends, its frames' *log*; *asset_fixed*: how many
    fixed nodes the asset itself has, said when the scene's region replaces them)."""
    sim, springs = run.sim, run.sim.model.springs
    sim_time = scene.n_frames * (1.0 / scene.frame_rate)
    table = run.schedule.table
    fx = springs.effects
    return SimulationSummary(
        asset=asset_label, scene=scene.describe(), scene_source=scene.source,
        nodes=springs.n_nodes, springs=springs.n_springs, fixed_nodes=int(run.fixed.size),
        law=run.law, method=scene.method, precision=scene.precision,
        step_mode="fixed" if scene.method == "implicit" else scene.step, window=scene.window,
        dt_min_s=min(log.dts), dt_max_s=max(log.dts), dt_mean_s=sim_time / log.steps,
        steps=log.steps, frames_redone=log.redone, dt_table_bound_s=table.dt_critical,
        safety=scene.safety, omega_max_table_rad_s=table.omega_max, gamma_max_1_s=table.gamma_max,
        dashpot_s=scene.dashpot, velocity_decay_s=scene.velocity_decay,
        mass_scaling={"budget": scene.mass_scaling, **run.scaling},
        start=scene.start, equilibrium=settle,
        threads=run.threads, thread_trial_s_per_step=run.thread_timing,
        build_s=run.build_s, warm_up_s=run.warm_up_s, stepping_wall_s=log.wall,
        wall_per_step_us=log.wall / log.steps * 1e6,
        ns_per_spring_step=log.wall / log.steps / springs.n_springs * 1e9,
        simulated_s=sim_time, real_time_factor=sim_time / log.wall if log.wall > 0 else math.inf,
        stretch_min=log.stretch_lo, stretch_max=log.stretch_hi, table_range=[springs.lam_min, springs.lam_max],
        outside_table=range_check.summary(),
        effects=None if fx is None else {**fx.describe(), "final_state": fx.report(sim.state.effects)},
        effects_available=None if not effects_available else list(effects_available.names),
        final_max_displacement_m=float(np.linalg.norm(sim.displacement(), axis=1).max()),
        floor=_floor_summary(sim, scene, log),
        grasper=None if plan is None else GrasperSummary(
            target_node=plan.target, held_nodes=int(plan.nodes.size), mode=plan.spec.mode,
            direction=plan.direction.tolist(), max_force_N=log.max_force_norm,
            force_at_max_N=log.max_force.tolist()),
        integrator=_integrator(run, scene),
        volume=_volume_summary(run, scene),
        fixed={"source": "asset", "asset_nodes": asset_fixed} if scene.fixed is None else
        {"source": "scene", "region": scene.fixed.describe(), "asset_nodes": asset_fixed},
    )


def _integrator(run: RunSetup, scene: Scene) -> dict:
    """The integrator's record: the implicit stepper's statistics, or the explicit step's settings."""
    st = run.sim.stepper
    if scene.method == "implicit":
        return {**st.report(), "prefactor_s": run.prefactor_s}
    return {"method": "explicit", "step": scene.step, "safety": scene.safety}


def _volume_summary(run: RunSetup, scene: Scene) -> dict:
    """The volume term used (or why none) and the organ's shape at the end: volume, inverted tets, sag."""
    sim = run.sim
    vol = sim.model.volume
    tets = run.tets if vol is None else vol.elements.tets
    return {"term": None if vol is None else vol.spec.describe(), "scene": scene.volume,
            "final": shape_change(sim.rest, tets, sim.x, scene.gravity)}


def _floor_summary(sim, scene: Scene, log: FrameLog) -> FloorSummary | None:
    floor = sim.model.floor
    if floor is None:
        return None
    free = sim.free
    return FloorSummary(friction=floor.friction, normal=floor.normal.tolist(), height_m=floor.height,
                        height_spec=scene.floor.height, contact_nodes_final=sim.n_contact,
                        contact_nodes_max=log.contact_max,
                        min_distance_m=float(floor.distance(sim.x)[free].min()) if free.any() else None)
