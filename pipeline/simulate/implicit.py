r"""The implicit stepper: backward Euler, quasi-Newton or Newton iterations on a reused factorization.

One step of :math:`h` from :math:`(\mathbf x_n, \mathbf v_n)` solves the step's nonlinear system
:math:`\mathbf g(\mathbf x_{n+1}) = 0` for the positions at its end, then
:math:`\mathbf v_{n+1} = (\mathbf x_{n+1} - \mathbf x_n)/h` (docs/design/simulator.md,
"Scheme"). Unconditionally stable for a linear network; the iterations (with their line
searches, and Newton's as the fallback) carry it through the tables' nonlinearity and locking.

:class:`BackwardEuler` is a thin stepper over five parts, each in its own module:

* the step's system (:mod:`.implicit_system`): the residual with the force terms, their dashpots
  and material effects, subject to the fixed nodes, the prescribed grasp and the floor's contacts;
  Newton's matrix as a product and as the matrix to factor;
* its iteration (:mod:`.implicit_iteration`): by default L-BFGS with the reused factor as its
  first inverse (one solve per iteration, no tangent); a solve it does not finish goes on with a
  factor taken at its best iterate, then with Newton's iteration (conjugate gradients
  preconditioned with the factor);
* the factor cache (:mod:`.factorcache`): the supernodal :math:`LDL^T` of Newton's matrix (with
  the volume term's per-tet bound in place of its nodal tangent by default), taken at an earlier
  state and renewed when the iterations lost to its age cost more than a new one; the constraints
  join it through the capacitance matrix, so it does not change with the grasp or the contacts;
* the floor's contacts (:mod:`.contact`): an active set, with slides on a sticking floor;
* the grasper force at the haptic rate between solves (:mod:`.haptics`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..blas import single_threaded_blas
from ..errors import ConfigError
from ..linalg.quasinewton import MEMORY
from . import kernels as K
from .contact import FloorContact
from .factorcache import FactorCache
from .haptics import HAPTIC_RATE, Haptics, patch_stiffness
from .implicit_iteration import StepSolver
from .implicit_stats import ImplicitStats, Threads
from .implicit_system import StepSystem, forces
from .model import Control, Model, State
from .scene import FACTORS, ITERATIONS
from .stepper import StepBound

#: Default step of the deformation solve: one frame at 30 frames/s [s].
DEFAULT_STEP = 1.0 / 30.0
PRECONDITIONERS = ("factor", "fresh", "jacobi")


def _threads_field(name: str, doc: str) -> property:
    """A property of the stepper that reads and sets one field of its shared :class:`Threads` record."""

    def get(self):
        return getattr(self._threads, name)

    def set_(self, value) -> None:
        setattr(self._threads, name, value)

    return property(get, set_, doc=doc)


class BackwardEuler:
    """The implicit stepper (module doc); a :class:`~.stepper.Stepper`.

    The options are read when the stepper is made, except the threads (``threads``,
    ``factor_threads``, ``solo_solve_s``), which the run's setup sets afterwards.

    Parameters
    ----------
    step : float
        The step it proposes (:meth:`bound`) [s]; any step is stable.
    rtol : float
        Newton tolerance: the largest residual force on a node, as a fraction of
        the largest nodal weight ...
    xtol : float
        ... or the largest update of a node, as a fraction of the organ's size
        (whichever is met first).
    contact_rounds : int or None
        Times a step is solved again after its contacts changed. None (default): once on a
        frictionless floor (a node the lift peels off leaves in the step it is let go, not a step
        later), three times on a sticking one (a pulled node slides, then stops or leaves,
        :class:`~.contact.Slides`); docs/design/simulator.md, "Floor contact, with slides".
    iteration : {"quasi-newton", "newton"}
        How each solve iterates (:mod:`.implicit_iteration`). "quasi-newton" (default): L-BFGS
        with the reused factor as its first inverse, handed over to a fresh factor and then to
        Newton where it does not converge; "newton": Newton with conjugate gradients (also what
        a preconditioner other than "factor" gets). The quasi-Newton iteration is the faster
        at the same accuracy against the explicit reference (docs/design/simulator.md, "The
        iteration: quasi-Newton on a reused factor").
    memory : int
        Quasi-Newton: curvature pairs kept.
    max_newton : int
        Newton iterations of a solve before the step is accepted unconverged
        (which the statistics count).
    cg_rtol : float
        Relative tolerance of each linear solve (inexact Newton).
    max_cg : int
    preconditioner : {"factor", "fresh", "jacobi"}
        "factor": the reused factorization (default); "fresh": factored at every
        Newton iteration (exact Newton with a direct solve); "jacobi": the
        diagonal (no factorization; the 1 kHz force then holds its last value).
    haptic_rate : float
        Grasper force samples per second of simulated time (:mod:`.haptics`).
    haptic_drift : bool
        Extrapolate the last step's unexplained change between solves.
    definite : bool
        Newton's matrix with each spring block made positive semi-definite
        (negative axial and geometric stiffness dropped: a descent direction
        whatever the compression).
    single : bool
        Factor in float32 (faster solves; the factor is a preconditioner).
    factor_matrix : {"bound", "exact", "mixed"}
        What the reused factor is taken of. "bound" (default): Newton's matrix
        with each term's ``tangent_bound`` where it has one (the volume term:
        per-tet instead of nodal, a matrix above its tangent with the sparsity
        of the tets): a third of the fill and faster solves, but more
        conjugate-gradient iterations. "exact": Newton's matrix itself.
        "mixed": Newton's matrix too, with each term's ``tangent_parts`` as a
        saddle point (:class:`~esmm.pipeline.linalg.linsolve.MixedFactor`; about half the exact fill).
        Which is fastest depends on the mesh: the bound on most organs, where the volume term's
        fill dominates (docs/design/simulator.md, "What is factored, and when it is renewed").
        The "fresh" preconditioner always factors the exact matrix.
    threads : int
        Threads of the factor's solves and the force pass: 1 or 2 (:class:`~.implicit_stats.Threads`).
    factor_threads : int
        Threads of the factorizations: 1 or 2.
    solo_solve_s : float
        A solve's time on one thread, measured where the run's setup chose two threads: if two
        threads' solves get slower than that, the run goes on with one. NaN: never.
    stats : ImplicitStats, optional
        Where the steps' costs are counted (default: new).
    coarse_cells : ndarray of int, shape (p, 10), or None
        A split network's parents (its ``quadratic_cells``): the reused preconditioner is then the
        two-grid operator on them, not the matrix's factor (:class:`.factorcache.FactorCache`;
        docs/design/twogrid.md).
    carry_pairs : bool
        Quasi-Newton: carry the curvature pairs over steps and contact changes, projected
        (docs/design/realtime.md: fewer iterations, a dearer recursion; off).
    slip : bool
        On a sticking floor, a sliding node that the floor pushes again stops at the farther of where
        it slips to (its neighbours held) and where it creeps to (:meth:`.contact.Slides.slip`;
        default); False: where it creeps to only (docs/design/simulator.md, "Floor contact, with
        slides").
    """

    def __init__(self, step: float = DEFAULT_STEP, rtol: float = 0.01, xtol: float = 1e-4,
                 contact_rounds: int | None = None, iteration: str = "quasi-newton", memory: int = MEMORY,
                 max_newton: int = 4, cg_rtol: float = 0.1, max_cg: int = 20, preconditioner: str = "factor",
                 haptic_rate: float = HAPTIC_RATE, haptic_drift: bool = True, definite: bool = True,
                 single: bool = True, factor_matrix: str = "bound", threads: int = 1, factor_threads: int = 1,
                 solo_solve_s: float = math.nan, stats: ImplicitStats | None = None,
                 coarse_cells: np.ndarray | None = None, carry_pairs: bool = False, *, slip: bool = True):
        _check_options(step, iteration, preconditioner, factor_matrix, haptic_rate)
        self.step, self.rtol, self.xtol, self.contact_rounds = step, rtol, xtol, contact_rounds
        self.iteration, self.memory, self.max_newton = iteration, memory, max_newton
        self.cg_rtol, self.max_cg, self.preconditioner = cg_rtol, max_cg, preconditioner
        self.haptic_rate, self.haptic_drift = haptic_rate, haptic_drift
        self.definite, self.single, self.factor_matrix = definite, single, factor_matrix
        self.stats = ImplicitStats() if stats is None else stats
        self._threads = Threads(threads, factor_threads, solo_solve_s)
        #: The reused factor and its life cycle.
        self.factors = FactorCache(preconditioner, factor_matrix, single, self._threads, self.stats,
                                   coarse_cells=coarse_cells)
        #: The iteration of each step's system.
        self.solver = StepSolver(self.factors, self.stats, rtol=rtol, xtol=xtol, max_newton=max_newton,
                                 quasi=self.quasi, memory=memory, cg_rtol=cg_rtol, max_cg=max_cg,
                                 carry_pairs=carry_pairs, slip=slip)
        #: The grasper force between solves.
        self.haptics = Haptics(rate=haptic_rate, drift=haptic_drift)

    def __repr__(self) -> str:
        return (f"BackwardEuler(step={self.step!r}, iteration={self.iteration!r}, preconditioner="
                f"{self.preconditioner!r}, factor_matrix={self.factor_matrix!r}, threads={self.threads})")

    @property
    def quasi(self) -> bool:
        """Whether solves iterate by quasi-Newton (it needs the reused factor; else Newton's)."""
        return self.iteration == "quasi-newton" and self.preconditioner == "factor"

    threads = _threads_field("solve", "Threads of the factor's solves and the force pass (1 or 2; lowered to 1 "
                                      "where two got slower).")
    factor_threads = _threads_field("factor", "Threads of the factorizations (1 or 2).")
    solo_solve_s = _threads_field("solo_solve_s", "A solve's time on one thread in the run's trial [s] (NaN: none).")

    # -- the Stepper interface ------------------------------------------------------
    def bound(self, model: Model, control: Control) -> StepBound:
        """Its proposed step; no stability limit (``dt_critical`` is infinite)."""
        return StepBound(self.step, math.inf, 0.0, 0.0, 1.0, -1)

    def report(self) -> dict:
        """The statistics so far (JSON-ready), solves with the current factor included."""
        self.stats.solves = self.factors.solves()
        return {"method": "implicit", "preconditioner": self.preconditioner, "step_s": self.step,
                "haptic_rate_hz": self.haptic_rate, "rtol": self.rtol, "factor_matrix": self.factor_matrix,
                **({"preconditioner_levels": "two-grid"} if self.factors.coarse_cells is not None else {}),
                **self.stats.as_dict()}

    def ticks_per_step(self, dt: float) -> int:
        """Grasper force samples per step of *dt*: ``ceil(dt * haptic_rate)`` (spacing <= 1/haptic_rate)."""
        return self.haptics.ticks_per_step(dt)

    def factored(self, model: Model) -> str:
        """What the factor is taken of on *model*: "bound", "mixed" or "exact"
        (:meth:`.factorcache.FactorCache.factored`)."""
        return self.factors.factored(model)

    def solve_timing(self, threads=(1, 2), *, repeats: int = 7, warm: int = 3) -> dict:
        """Median seconds of a solve with the current factor on each number of *threads*
        (:meth:`.factorcache.FactorCache.solve_timing`)."""
        return self.factors.solve_timing(threads, repeats=repeats, warm=warm)

    def advance(self, model: Model, state: State, control: Control, nsteps: int, *,
                record: np.ndarray | None = None) -> np.ndarray:
        """Take *nsteps* steps of ``state.dt``; the grasper force at ``ticks_per_step`` samples per step.

        Returns
        -------
        ndarray, shape (nsteps * ticks, 3)
            Row ``k * ticks + q`` is the force at ``t_k + q dt / ticks`` [N].
        """
        nsteps = int(nsteps)
        T = self.ticks_per_step(state.dt)
        rec = np.zeros((max(nsteps, 0) * T, 3)) if record is None else record
        for k in range(max(nsteps, 0)):
            self._step(model, state, control, rec[k * T:(k + 1) * T])
        return rec

    def prepare(self, model: Model, state: State, control: Control) -> float:
        """Factor the matrix of a step of ``state.dt`` at the current state now (before the run); seconds spent."""
        if self.preconditioner != "factor":
            return 0.0
        t = time.perf_counter()
        system = self._system(model, state, control)
        with single_threaded_blas():             # as while stepping: its time sets the renewals' price
            self.factors.refactor(system, system.x0)
        return time.perf_counter() - t

    # -- one step ------------------------------------------------------------------
    def _system(self, model: Model, state: State, control: Control) -> StepSystem:
        """The system of a step of ``state.dt`` from *state*, with the floor's contacts at its start."""
        contact = FloorContact.begin(model, state, control, rounds=self.contact_rounds, stats=self.stats)
        return StepSystem.begin(model, state, control, contact, threads=self._threads, definite=self.definite)

    def _step(self, model: Model, state: State, control: Control, rec: np.ndarray) -> None:
        """One step of ``state.dt``: the factor, the predictor, the grasper force's samples (into *rec*),
        the solve, the floor, the commit."""
        system = self._system(model, state, control)
        self.factors.begin_step(system)
        F0 = self.haptics.start_force(system)
        x = self._predictor(system)
        self.solver.set_rows(system)
        S = patch_stiffness(model, control, self.factors.constraints, system.h)
        self.haptics.fill(rec, F0, S, control.grasp, system.t, system.h)
        x = self.solver.solve(system, x)
        system.contact.touchdown(system.x0, x)
        self._commit(system, x, F0, S)

    @staticmethod
    def _predictor(system: StepSystem) -> np.ndarray:
        """The iteration's start: inertial motion, held nodes on the path, contacts on the floor."""
        model, x0, g_ = system.model, system.x0, system.control.grasp
        x = x0 + system.h * system.v0
        x[~model.movable] = x0[~model.movable]
        if g_ is not None and g_.mode == "prescribed":
            x[g_.nodes] = g_.tip(system.t1) + g_.offsets
        system.contact.place(x0, x)
        return x

    def _commit(self, system: StepSystem, x: np.ndarray, F0: np.ndarray, S: np.ndarray) -> None:
        """Write the step into its state: positions, velocities, effect state, contacts, clock; remember
        the grasper force (:meth:`.haptics.Haptics.remember`)."""
        model, state, control, h, x0 = system.model, system.state, system.control, system.h, system.x0
        g_ = control.grasp
        t1 = system.t1
        spring_grasp = g_ is not None and g_.mode == "spring"
        v = (x - x0) / h
        v[~model.movable] = 0.0
        if g_ is not None and not spring_grasp:
            v[g_.nodes] = g_.tip_velocity(system.t + 0.5 * h)
        fxs = state.effects
        f = forces(model, state, x, (x - x0) / h, system.dt_fx, mode=K.FX_STEP if fxs is not None else K.FX_PEEK,
                   threads=self._threads.solve)
        if fxs is not None:
            fxs.t = t1
        state.x[:] = x
        state.v[:] = v
        state.contact[:] = system.contact.active.astype(np.uint8)
        state.steps += 1
        self.stats.steps += 1
        self.haptics.remember(control, f, x, t1, h, F0, S)


def _check_options(step: float, iteration: str, preconditioner: str, factor_matrix: str, haptic_rate: float) -> None:
    """The stepper's options checked, each error naming its parameter."""
    if iteration not in ITERATIONS:
        raise ConfigError(f"iteration: {iteration!r} is not one of {', '.join(ITERATIONS)}", parameter="iteration")
    if not (math.isfinite(step) and step > 0):
        raise ConfigError(f"implicit_step: must be a positive time, got {step}", parameter="implicit_step")
    if preconditioner not in PRECONDITIONERS:
        raise ConfigError(f"preconditioner: {preconditioner!r} is not one of {', '.join(PRECONDITIONERS)}",
                          parameter="preconditioner")
    if factor_matrix not in FACTORS:
        raise ConfigError(f"factor_matrix: {factor_matrix!r} is not one of {', '.join(FACTORS)}",
                          parameter="factor_matrix")
    if not (math.isfinite(haptic_rate) and haptic_rate > 0):
        raise ConfigError(f"haptic_rate: must be positive, got {haptic_rate}", parameter="haptic_rate")


@dataclass(frozen=True)
class ImplicitSchedule:
    """The implicit stepper's :class:`~.stepper.FrameSchedule`: a fixed step, no stretch window.

    Attributes
    ----------
    step : float
        The deformation solve's step [s] (frames get ``ceil(frame_dt / step)`` steps).
    table : StepBound
        The explicit whole-table bound of the same model, for the record.
    """

    step: float
    table: StepBound

    @property
    def first_window(self) -> None:
        return None

    def narrowed(self, delta):
        return None

    def bound(self, model: Model, state: State, control: Control, delta) -> StepBound:
        return StepBound(self.step, math.inf, 0.0, 0.0, 1.0, -1)

    @staticmethod
    def steps_per_frame(frame_dt: float, bound: StepBound) -> int:
        return max(1, int(math.ceil(frame_dt / bound.dt * (1 - 1e-12))))
