"""The frame loop of a run: steps per frame, grasper events, the window check and redo, recording.

Each frame (1 / frame_rate of simulated time) gets its step from the run's
:class:`~.stepper.FrameSchedule` (the explicit stepper's
:class:`~.stepper.StepSchedule`, or the implicit one's fixed step); it is advanced in segments cut at the
grasper's events (grasp, release) and, with an adaptive step, at 8 checks of
the stretch window. A frame whose stretches left the window is redone from a
snapshot with a wider window (docs/design/simulator.md, "The explicit stepper
(the accuracy reference)"). After each frame the history gets the displacement
and the tip, and the forces of the steps while something was held.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SimulationError
from .grasper import GraspPlan
from .history import HistoryWriter
from .simulator import Simulator
from .stepper import FrameSchedule


@dataclass
class FrameLog:
    """What the frames did: steps, redos, stepping wall time, steps taken, extremes."""

    steps: int = 0
    redone: int = 0
    wall: float = 0.0                      #: seconds spent stepping
    dts: list = field(default_factory=list)
    max_force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_force_norm: float = 0.0
    contact_max: int = 0
    stretch_lo: float = math.inf
    stretch_hi: float = -math.inf


class RangeCheck:
    """Warn once per run when springs leave the tables' stretch grid; count where it happened."""

    def __init__(self, springs, reporter):
        self.springs = springs
        self.rep = reporter
        self.first = None
        self.checks = 0
        self.outside = 0
        self.lo = math.inf
        self.hi = -math.inf

    def __call__(self, x: np.ndarray, when: str) -> tuple[float, float]:
        """Check positions *x*; return the (min, max) stretch."""
        m = self.springs
        lo, hi = m.stretch_range(x)
        self.checks += 1
        if lo < m.lam_min or hi > m.lam_max:
            self.outside += 1
            self.lo, self.hi = min(self.lo, lo), max(self.hi, hi)
            if self.first is None:
                self.first = when
                lam = m.stretches(x)
                n_out = int(np.count_nonzero((lam < m.lam_min) | (lam > m.lam_max)))
                self.rep.warn(
                    f"{when}, {n_out} of {m.n_springs} springs are outside the tables' stretch range "
                    f"[{m.lam_min:.4g}, {m.lam_max:.4g}] (stretches {lo:.4g}..{hi:.4g}): there the force is "
                    "the tables' extrapolation, not the material (docs/design/simulator.md). The organ deforms more "
                    "than its material can describe: a gentler scene, or a stiffer network (volumetric "
                    "compensation: 'esmm tables ASSET --compensate'). Warned once per run; the summary "
                    "counts the frames")
        return lo, hi

    def summary(self) -> dict:
        return {"frames": self.outside, "of_frames": self.checks, "first": self.first,
                "stretch_min": None if self.first is None else self.lo,
                "stretch_max": None if self.first is None else self.hi}


@dataclass(frozen=True)
class FrameSpec:
    """The frames of a run and its guards."""

    n_frames: int
    frame_dt: float            #: [s]
    events: tuple              #: (name, time [s]) of "grasp" and "release"
    max_steps: int
    organ_size: float          #: largest extent of the rest shape [m] (the blow-up guard)


def run_frames(sim: Simulator, schedule: FrameSchedule, spec: FrameSpec, plan: GraspPlan | None,
               writer: HistoryWriter, range_check: RangeCheck, reporter) -> FrameLog:
    """Advance *sim* frame by frame, writing each frame (and the held steps' forces) to *writer*.

    Raises
    ------
    SimulationError
        The run became unstable, or needed more than ``spec.max_steps`` steps.
    """
    log = FrameLog(contact_max=sim.n_contact)
    done: set = set()
    delta = schedule.first_window
    with reporter.task("simulating", total=spec.n_frames) as advance:
        for fr in range(spec.n_frames):
            t_start = fr * spec.frame_dt
            delta = schedule.narrowed(delta)
            rec, held, dt, spf, delta = _frame(sim, schedule, spec, plan, done, t_start, delta, log)
            log.steps += spf
            log.dts.append(dt)
            _record_forces(writer, log, rec, held, t_start, dt / (rec.shape[0] // spf))
            disp = sim.displacement()
            if not np.all(np.isfinite(disp)) or np.abs(disp).max() > 10.0 * spec.organ_size:
                raise SimulationError(
                    f"the simulation became unstable at t = {sim.t:.4g} s (displacements beyond 10 organ "
                    f"sizes or non-finite); lower [integrator] safety or check the asset's masses and tables")
            lo, hi = range_check(sim.x, f"at t = {sim.t:.3g} s")
            log.stretch_lo, log.stretch_hi = min(log.stretch_lo, lo), max(log.stretch_hi, hi)
            log.contact_max = max(log.contact_max, sim.n_contact)
            writer.add_frame(sim.t, disp, tip=sim.grasp.tip(sim.t) if sim.grasp is not None else None)
            advance(1)
            if log.steps > spec.max_steps:
                raise SimulationError(
                    f"the run needed more than [integrator] max_steps = {spec.max_steps} steps by "
                    f"t = {sim.t:.3g} s; shorten the duration, coarsen the asset or raise max_steps")
    return log


def _frame(sim: Simulator, schedule: FrameSchedule, spec: FrameSpec, plan: GraspPlan | None, done: set,
           t_start: float, delta: float | None, log: FrameLog):
    """One frame from *t_start*, redone wider while a stretch leaves the window; (rec, held, dt, spf, delta)."""
    springs = sim.model.springs
    span = springs.lam_max - springs.lam_min        # a window this wide is the whole table
    snapshot = sim.snapshot()
    done_before = set(done)
    while True:
        bound = schedule.bound(sim.model, sim.state, sim.control, delta)
        spf = schedule.steps_per_frame(spec.frame_dt, bound)
        dt = spec.frame_dt / spf
        sim.set_time_step(dt, bound=bound, t0=t_start)
        x0 = sim.x.copy()
        cuts = {0, spf}
        for name, te in spec.events:
            k = int(round((te - t_start) / dt))
            if 0 <= k < spf and name not in done:
                cuts.add(k)
        if delta is not None:                 # check the window along the frame
            cuts |= set(range(0, spf, max(1, spf // 8)))
        cuts = sorted(cuts)
        ticks = sim.stepper.ticks_per_step(dt)       # grasper force samples per step
        rec = np.zeros((spf * ticks, 3))
        held_rows = np.zeros(spf * ticks, bool)
        moved = 0.0
        for a, b in zip(cuts[:-1], cuts[1:]):
            _fire_events(sim, spec, plan, done, t_start, dt, a)
            held = sim.grasp is not None
            t = time.perf_counter()
            sim.advance(b - a, record=rec[a * ticks:b * ticks])
            log.wall += time.perf_counter() - t
            held_rows[a * ticks:b * ticks] = held
            if delta is not None:
                moved = max(moved, springs.stretch_change(sim.x, x0))
                if moved > delta and delta < span:
                    break
        if delta is not None and moved > delta and delta < span:
            # A stretch left the window the step was chosen for: redo the frame
            # with a wider window (and the step that goes with it).
            sim.restore(snapshot)
            done.clear()
            done.update(done_before)
            delta = 2.0 * max(delta, moved)
            log.redone += 1
            continue
        return rec, held_rows, dt, spf, delta


def _fire_events(sim: Simulator, spec: FrameSpec, plan: GraspPlan | None, done: set, t_start: float,
                 dt: float, step: int) -> None:
    """Close or open the grasper when one of its events falls on *step* of the frame."""
    for name, te in spec.events:
        if name not in done and int(round((te - t_start) / dt)) == step:
            done.add(name)
            if name == "grasp":
                sim.attach(plan.make_grasp(sim.x, sim.mass), check_step=False)
            else:
                sim.release()


def _record_forces(writer: HistoryWriter, log: FrameLog, rec: np.ndarray, held: np.ndarray, t_start: float,
                   dt: float) -> None:
    """Write the forces of the held samples (*dt* apart) and keep the largest."""
    if not held.any():
        return
    rows = np.flatnonzero(held)
    r = rec[rows]
    writer.add_forces(t_start + rows * dt, r)
    norms = np.linalg.norm(r, axis=1)
    k = int(np.argmax(norms))
    if norms[k] > log.max_force_norm:
        log.max_force_norm = float(norms[k])
        log.max_force = r[k].copy()
