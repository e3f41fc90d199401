r"""Steppers: what advances a State under a Model and a Control; the explicit one and its step.

A :class:`Stepper` takes whole steps of ``state.dt`` and reports the force on
the grasper at each; it also says how large a step it may take
(:meth:`Stepper.bound`). :class:`SymplecticEuler` is the explicit stepper:

.. math::

    \mathbf f_n = \mathbf f(\mathbf x_n, \mathbf v_n) + m\mathbf g, \quad
    \mathbf v_{n+1} = \frac{\mathbf v_n + \Delta t\,\mathbf f_n/m}{1 + \alpha\Delta t}, \quad
    \mathbf x_{n+1} = \mathbf x_n + \Delta t\,\mathbf v_{n+1}

(semi-implicit Euler; :math:`\alpha = 1/\tau` is the optional mass-proportional
Rayleigh damping, treated implicitly so that it never limits the step). Fixed
nodes have :math:`1/m = 0`. Its step is bounded by stability.

Stability bound. For a network whose spring ``ij`` has axial tangent
:math:`k^t_{ij}` and force :math:`F_{ij}`, the tangent stiffness
:math:`K = \sum_{ij} [k^t u u^T + (F/L)(I - u u^T)]` (assembled with the usual
signs) satisfies, for any :math:`y = M^{1/2}x`,
:math:`x^TKx \le 2\sum_i |y_i|^2 \sum_j \kappa_{ij}/m_i` with
:math:`\kappa_{ij} = \max(k^t_{ij}, F_{ij}/L_{ij}, 0)`. Hence

.. math::  \omega_{max}^2 \le \Omega^2 = \max_i \frac{1}{m_i} r_i

with the force terms' Gershgorin rows :math:`r_i` (springs: :math:`2\sum_j
\kappa_{ij}`, bounded over every stretch by the tables). With damping rows
:math:`\Gamma = \max_i c_i/m_i`, the semi-implicit Euler step of a mode
:math:`\ddot q + \gamma\dot q + \omega^2 q = 0` is stable iff
:math:`\omega^2\Delta t^2 + 2\gamma\Delta t < 4`, so

.. math::  \Delta t = s\,\frac{4}{\Gamma + \sqrt{\Gamma^2 + 4\Omega^2}}

with a safety factor :math:`s` (default 0.9). The bound holds whatever the
deformation (locking included), because it uses the largest tangent of the
table; it is exact for Rayleigh damping of a linear network and conservative
(Gershgorin) otherwise.

:class:`StepSchedule` chooses the step of each frame of a run ("table": one
step; "adaptive": a bound over a stretch window around the current state,
checked along the frame). The implicit stepper (:mod:`.implicit`) brings its
own schedule (a fixed step, no window) and implements the same methods.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..errors import ConfigError
from . import kernels as K
from .kernels import Clock, Nodes, steps_parallel, steps_serial
from .model import Control, Model, State

DEFAULT_SAFETY = 0.9


@dataclass(frozen=True)
class StepBound:
    """The stable time step and what it is made of."""

    dt: float            #: step used [s] (safety included)
    dt_critical: float   #: bound without the safety factor [s]
    omega_max: float     #: Gershgorin bound of the highest angular frequency [rad/s]
    gamma_max: float     #: bound of the dashpots' damping rate [1/s]
    safety: float
    node: int            #: the node that sets the bound


def _terms(terms) -> Sequence:
    """A force term or a sequence of them, as a sequence."""
    return tuple(terms) if isinstance(terms, (list, tuple)) else (terms,)


def stable_step(terms, mass: np.ndarray, *, free: np.ndarray | None = None,
                extra_stiffness: np.ndarray | None = None, safety: float = DEFAULT_SAFETY,
                x: np.ndarray | None = None, window: float | None = None) -> StepBound:
    """Largest stable semi-implicit Euler step of the force *terms* with node masses *mass*.

    By default each term's tangent is bounded over every configuration (for
    the springs: the whole table and its extrapolation): the step is then safe
    whatever happens. With positions *x* and a stretch *window* delta, each
    spring's tangent is bounded only over ``[lam - delta, lam + delta]``
    around its stretch in *x*: a larger step that is safe as long as no
    stretch moves by more than delta (the caller checks that and redoes the
    interval otherwise).

    Parameters
    ----------
    terms : ForceTerm or sequence of ForceTerm
    mass : ndarray, shape (n,)
        Node masses [kg].
    free : ndarray of bool, shape (n,), optional
        Nodes that move (default: all). Fixed nodes do not limit the step.
    extra_stiffness : ndarray, shape (n,), optional
        Stiffness to the ground per node [N/m] (grasper coupling springs).
    safety : float
        Factor in (0, 1] applied to the critical step.
    """
    if not (0 < safety <= 1):
        raise ConfigError(f"safety: must be in (0, 1], got {safety}", parameter="safety")
    m = np.asarray(mass, dtype=np.float64)
    n = m.size
    row = np.zeros(n)
    crow = np.zeros(n)
    for term in _terms(terms):
        row = row + term.stiffness_rows(x=x, window=window)
        crow = crow + term.damping_rows()
    if extra_stiffness is not None:
        row = row + np.asarray(extra_stiffness, dtype=np.float64)
    mask = np.ones(n, bool) if free is None else np.asarray(free, bool)
    if not mask.any():
        return StepBound(math.inf, math.inf, 0.0, 0.0, safety, -1)
    w2 = np.where(mask, row / m, 0.0)
    g = np.where(mask, crow / m, 0.0)
    node = int(np.argmax(w2))
    omega2 = float(w2.max())
    gamma = float(g.max())
    if omega2 <= 0:
        return StepBound(math.inf, math.inf, 0.0, gamma, safety, node)
    dtc = 4.0 / (gamma + math.sqrt(gamma * gamma + 4.0 * omega2))
    return StepBound(safety * dtc, dtc, math.sqrt(omega2), gamma, safety, node)


def mass_scaling(terms, mass: np.ndarray, *, free: np.ndarray | None = None,
                 budget: float = 1e-3) -> tuple[np.ndarray, dict]:
    """Selective mass scaling: inertial masses that allow a larger stable step.

    The step is limited by the nodes whose stiffness-to-mass ratio is largest
    (typically a few light nodes in slivers of the mesh). For a target step
    ``dt`` a node needs ``m_i >= r_i dt^2 / 4`` with ``r_i`` its Gershgorin
    row (springs: ``2 sum_j kappa_ij``, the whole-table bound, so the gain
    holds for every stretch). This finds the largest ``dt`` whose added mass
    ``sum max(0, r_i dt^2/4 - m_i)`` over the free nodes is at most ``budget``
    times the total mass, and returns the raised masses. They are used for
    inertia only; gravity keeps the true masses.

    Parameters
    ----------
    terms : ForceTerm or sequence of ForceTerm
    mass : ndarray, shape (n,)
        True node masses [kg].
    free : ndarray of bool, shape (n,), optional
    budget : float
        Largest added mass as a fraction of the total (0: no scaling).

    Returns
    -------
    (scaled_mass (n,), info dict with ``added_fraction``, ``nodes``, ``gain``)
    """
    m = np.asarray(mass, dtype=np.float64)
    n = m.size
    mask = np.ones(n, bool) if free is None else np.asarray(free, bool)
    if budget <= 0 or not mask.any():
        return m.copy(), {"added_fraction": 0.0, "nodes": 0, "gain": 1.0}
    r = np.zeros(n)
    for term in _terms(terms):
        r = r + term.stiffness_rows()
    r = np.where(mask, r, 0.0)
    with np.errstate(divide="ignore"):
        dt_node = np.where(r > 0, 2.0 * np.sqrt(m / np.where(r > 0, r, 1.0)), np.inf)
    dt0 = float(dt_node[mask].min())
    if not np.isfinite(dt0):
        return m.copy(), {"added_fraction": 0.0, "nodes": 0, "gain": 1.0}
    total = float(m.sum())

    def added(dt):
        return float(np.maximum(r * dt * dt / 4.0 - m, 0.0)[mask].sum())

    lo, hi = dt0, dt0
    while added(hi * 2) <= budget * total and hi < 1e3 * dt0:
        hi *= 2
    hi *= 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if added(mid) <= budget * total:
            lo = mid
        else:
            hi = mid
    scaled = np.where(mask, np.maximum(m, r * lo * lo / 4.0), m)
    nodes = int(np.count_nonzero(scaled > m))
    return scaled, {"added_fraction": float((scaled - m).sum() / total), "nodes": nodes, "gain": lo / dt0}


class Stepper(Protocol):
    """Advances a :class:`~.model.State` under a :class:`~.model.Model` and a :class:`~.model.Control`."""

    def bound(self, model: Model, control: Control) -> StepBound:
        """The largest step it may take with *control* (an implicit stepper: its own limit, possibly inf)."""

    def advance(self, model: Model, state: State, control: Control, nsteps: int, *,
                record: np.ndarray | None = None) -> np.ndarray:
        """Take *nsteps* steps of ``state.dt``; return the force on the grasper, shape (nsteps * ticks, 3) [N].

        ``ticks = ticks_per_step(state.dt)`` samples per step (row ``k ticks + q``
        at ``t_k + q dt / ticks``). Positions, velocities, the clock, the
        effect state and the contacts advance.
        """

    def ticks_per_step(self, dt: float) -> int:
        """Grasper force samples per step of *dt* (the explicit stepper: 1)."""


@dataclass(eq=False)
class SymplecticEuler:
    """The explicit stepper (module doc): one force pass per step, compiled (:mod:`.kernels`).

    Parameters
    ----------
    safety : float
        Fraction of the critical step :meth:`bound` allows.
    threads : int
        1: the serial step loop; more: the owner/halo parallel loop with that
        many chunks (``numba.set_num_threads``).
    """

    safety: float = DEFAULT_SAFETY
    threads: int = 1
    _f: np.ndarray | None = field(default=None, repr=False)

    @staticmethod
    def ticks_per_step(dt: float) -> int:
        """One grasper force sample per step."""
        return 1

    def bound(self, model: Model, control: Control) -> StepBound:
        """The whole-table stability bound with the grasper's coupling springs."""
        return stable_step(model.terms, model.mass, free=control.free, extra_stiffness=control.coupling_rows(),
                           safety=self.safety)

    def advance(self, model: Model, state: State, control: Control, nsteps: int, *,
                record: np.ndarray | None = None) -> np.ndarray:
        nsteps = int(nsteps)
        rec = np.zeros((max(nsteps, 0), 3)) if record is None else record
        if nsteps <= 0:
            return rec
        if self._f is None or self._f.shape != state.x.shape:
            self._f = np.zeros_like(state.x)
        threads = max(1, int(self.threads))
        if threads > 1:
            import numba

            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        springs = model.springs
        fx = None
        fxs = state.effects
        if fxs is not None:
            # The first step advances the springs' state from the time it was last committed.
            fx = springs.effects.kernel(fxs, mode=K.FX_STEP)
        clock = Clock(nsteps, state.dt, state.t0, state.steps, max(0.0, state.t - fxs.t) if fxs is not None else 0.0,
                      1.0 / (1.0 + model.mass_damping * state.dt))
        nodes = Nodes(state.x, state.v, self._f, model.fext, control.inv_mass)
        run = steps_serial if threads == 1 else steps_parallel
        run(clock, nodes, springs.kernel(), fx, control.grasp_kernel(), control.floor_kernel(model, state),
            springs.layout(threads), rec, model.volume_kernel())
        if fxs is not None:
            fxs.t = state.t0 + (state.steps + nsteps - 1) * state.dt
        state.steps += nsteps
        return rec


class FrameSchedule(Protocol):
    """How a run chooses the step of each frame (:func:`~.frames.run_frames` asks it).

    :class:`StepSchedule` is the explicit stepper's; the implicit stepper's
    (:class:`~.implicit.ImplicitSchedule`) returns its fixed step and no window.
    """

    @property
    def first_window(self) -> float | None:
        """The stretch window of the first frame (None: no window check)."""

    def narrowed(self, delta: float | None) -> float | None:
        """The window of the next frame, from the last one's."""

    def bound(self, model: Model, state: State, control: Control, delta: float | None) -> StepBound:
        """The largest step for a frame starting at *state* with window *delta*."""

    def steps_per_frame(self, frame_dt: float, bound: StepBound) -> int:
        """Steps of a frame of *frame_dt* under *bound*."""


@dataclass(eq=False)
class StepSchedule:
    """The step of each frame of a run: one for the whole run ("table") or per frame ("adaptive").

    "adaptive": the bound over a stretch window of half-width ``delta`` around
    the current stretches (never below the whole-table bound), with the
    springs' history forces; the run checks the window along the frame and
    redoes it wider when a stretch leaves it (docs/design/simulator.md, "The explicit stepper (the accuracy
    reference)").

    Parameters
    ----------
    table : StepBound
        The whole-table bound of the run (fixed at its start).
    adaptive : bool
    window : float
        Smallest (and first) window half-width.
    reserve : ndarray, shape (n,), optional
        Stiffness budgeted from the start for springs attached later (the
        grasper's coupling) [N/m].
    safety : float
    """

    table: StepBound
    adaptive: bool
    window: float
    reserve: np.ndarray | None = None
    safety: float = DEFAULT_SAFETY

    @property
    def first_window(self) -> float | None:
        return self.window if self.adaptive else None

    def narrowed(self, delta: float | None) -> float | None:
        """The window of the next frame: it narrows back slowly after a frame was redone wider."""
        return max(self.window, 0.75 * delta) if delta is not None else None

    def bound(self, model: Model, state: State, control: Control, delta: float | None) -> StepBound:
        """The bound for a frame starting at *state* with window *delta* (None: the whole table)."""
        if not self.adaptive or delta is None:
            return self.table
        more = model.springs.state_rows(state.effects, state.x, delta)
        ex = self.reserve if more is None else (more if self.reserve is None else self.reserve + more)
        b = stable_step(model.terms, model.mass, free=control.free, extra_stiffness=ex, safety=self.safety,
                        x=state.x, window=delta)
        return b if b.dt_critical >= self.table.dt_critical else self.table

    @staticmethod
    def steps_per_frame(frame_dt: float, bound: StepBound) -> int:
        """Steps of a frame: ``ceil(frame_dt / dt)`` so that frames fall on steps."""
        return max(1, int(math.ceil(frame_dt / bound.dt * (1 - 1e-12))))
