r"""The implicit stepper: backward Euler, quasi-Newton or Newton iterations on a reused factorization.

One step of :math:`h` from :math:`(\mathbf x_n, \mathbf v_n)` solves for
:math:`\mathbf x = \mathbf x_{n+1}` (docs/simulate.md §2b)

.. math::

    \mathbf g(\mathbf x) = M\frac{\mathbf x - \mathbf x_n - h\mathbf v_n}{h^2}
        + \alpha M\frac{\mathbf x - \mathbf x_n}{h}
        - \mathbf f\Bigl(\mathbf x, \frac{\mathbf x - \mathbf x_n}{h}\Bigr) - \mathbf f_{ext} = 0,
    \qquad \mathbf v_{n+1} = \frac{\mathbf x_{n+1} - \mathbf x_n}{h}

(:math:`\alpha` the mass-proportional damping, :math:`\mathbf f` the force terms
with their dashpots and material effects), subject to the fixed nodes, the
prescribed grasp (held nodes on the tip's path at :math:`t_{n+1}`) and the
floor's contacts (active set: a node that crosses the plane is held on it;
one the floor would have to pull is let go, on a sticking floor after sliding
on it within the step, :class:`Slides`). Newton's matrix is
:math:`A = M/h^2 + (\alpha M + C)/h + K(\mathbf x)` with
:math:`K = \sum_{terms} K_{term}` (each term's ``tangent``) and :math:`C` the
dashpots' damping matrix; each Newton update is solved by conjugate gradients
preconditioned with a sparse factorization of :math:`A` with the volume
term's per-tet bound in place of its nodal tangent (a third of the fill; or
of :math:`A` itself, ``factor_matrix``), taken at an earlier state and
reused for as long as it keeps the iterations few (then refactored at the
current state). By default each solve iterates by L-BFGS with that factor
as its first inverse instead (:mod:`~esmm.pipeline.linalg.quasinewton`: one solve per iteration,
no tangent); a solve it does not finish goes on with a factor taken at its best
iterate, then with Newton's iteration (``iteration``). The factor is the
supernodal :math:`LDL^T` of :mod:`esmm.pipeline.linalg.supernodal`, factored
on two threads (``factor_threads``) and solved on two where that is faster
(``threads``). Constraints join through the capacitance matrix
(:class:`~esmm.pipeline.linalg.linsolve.Constraints`), so the factor does not change with the
grasp or the contacts. Unconditionally stable for a linear network; the
iterations (with their line searches, and Newton's as the fallback) carry it
through the tables' nonlinearity and locking.

The force on the grasper is reported at ``haptic_rate`` (1 kHz) whatever the
step: at the step's start the force at the solved state, then, until the next
solve, that force moved by the grasped patch's stiffness in the step's linear
model, :math:`\mathbf F(t_n + \tau) = \mathbf F_n - S\,(\mathbf p(t_n + \tau) -
\mathbf p(t_n)) + \tfrac{\tau}{h}\mathbf D_n`, with :math:`S` the Schur
complement of the factored matrix on the patch's translation (from the
capacitance matrix, no extra solve; with the volume term's bound in it, a
little stiffer than :math:`A`'s) and :math:`\mathbf D_n` the part of the
last step's change that the tip's motion did not explain.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sps

from ..errors import ConfigError
from ..linalg.linsolve import Constraints, MixedFactor, SparseFactor, mixed_ordering, pcg
from ..linalg.newton import node_ordering
from ..linalg.quasinewton import MEMORY, MIN_STEP, LBFGSMemory, secant_step
from . import kernels as K
from .model import Control, Model, State
from .scene import FACTORS, ITERATIONS
from .stepper import StepBound
from .volumeterm import VolumeTerm

#: Default step of the deformation solve: one frame at 30 frames/s [s].
DEFAULT_STEP = 1.0 / 30.0
#: Default rate of the grasper force [Hz] (a haptic device's loop).
HAPTIC_RATE = 1000.0
PRECONDITIONERS = ("factor", "fresh", "jacobi")
#: Quasi-Newton iterations of one solve before Newton's iteration takes over, until a hand-over's
#: cost has been measured (:meth:`BackwardEuler._switch_after`: then that cost, the break-even rule).
#: 12 was 1.0-1.35x faster than 8 on five organs and both scenes, within the same accuracy
#: (docs/simulate.md §2b).
QN_SWITCH = 12
#: A quasi-Newton solve whose residual grew this many times above its start hands over to Newton.
QN_DIVERGE = 4.0
#: Quasi-Newton iterations of a step not counted as the factor's age (:meth:`BackwardEuler._refactor_pays`
#: counts those beyond): a step's median on the livers and the kidney is 2-3, 3 right after a
#: refactorization (docs/simulate.md §2b); not tuned.
QN_FRESH = 2
#: Longest step along a quasi-Newton direction, in directions (the secant's extrapolation).
QN_MAX_STEP = 8.0


@dataclass
class ImplicitStats:
    """What the implicit steps cost (cumulative over a stepper's life)."""

    steps: int = 0
    newton: int = 0                 #: Newton iterations (each: one force pass, one tangent, one linear solve)
    quasi_newton: int = 0           #: quasi-Newton iterations (each: one solve, one or two force passes)
    fallbacks: int = 0              #: solves the quasi-Newton iteration handed over (a fresh factor, then Newton)
    cg: int = 0                     #: conjugate-gradient iterations
    solves: int = 0                 #: triangular solves with the factor (preconditioner, constraint columns)
    factorizations: int = 0
    factor_s: float = 0.0           #: seconds spent factoring
    factor_nnz: int = 0             #: fill of the last factor
    unconverged: int = 0            #: steps that ended above the tolerance
    contact_changes: int = 0        #: nodes added to or released from the floor's contact set
    slides: int = 0                 #: sticking contacts let slide within a step (the floor pulled them)
    max_newton: int = 0
    backtracks: int = 0
    modelled: int = 0               #: quasi-Newton iterates left with the secant's model of their residual
    thread_fallbacks: int = 0       #: two threads given up for one (:meth:`BackwardEuler._check_threads`)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(eq=False)
class BackwardEuler:
    """The implicit stepper (module doc); a :class:`~.stepper.Stepper`.

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
    iteration : {"quasi-newton", "newton"}
        How each solve iterates. "quasi-newton" (default): L-BFGS with the
        reused factor as its first inverse (:mod:`~esmm.pipeline.linalg.quasinewton`; one solve
        per iteration), a solve that has not converged after as many
        iterations as a hand-over has cost so far (:meth:`_switch_after`) or
        whose residual grew :data:`QN_DIVERGE` times handed over: to a factor
        taken at its best iterate where that pays (:meth:`_refresh_pays`),
        then to Newton's iteration; "newton": Newton with conjugate gradients
        (also what a preconditioner other than "factor" gets).
        1.7-2.3x faster on five organs, within the same accuracy against the
        explicit reference (docs/simulate.md §2b).
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
        Grasper force samples per second of simulated time.
    haptic_drift : bool
        Extrapolate the last step's unexplained change between solves (module doc).
    contact_rounds : int or None
        Times a step is solved again after its contacts changed. None
        (default): once on a frictionless floor (a node the lift peels off
        leaves in the step it is let go, not a step later: measured on a slab
        lifted off its bed, displacement error against explicit 6.6 % -> 0.7 %);
        twice on a sticking one (a pulled node slides, then stops or leaves,
        :class:`Slides`: grasper force against explicit on the paper liver
        29 % -> 2.7 %; docs/simulate.md §2b).
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
        Measured over the interactive scene (3 s, medians of 3-5 runs each):
        the bound is 1.58x faster on the fine liver (fill 17.3 M -> 5.0 M),
        1.05-1.22x on three paper-preset organs, 0.92x on the spleen and
        0.86x on the OpenHELP liver; the mixed factor 0.6-1.2x the bound's
        speed (docs/simulate.md §2b). The "fresh" preconditioner always factors the
        exact matrix.
    threads : int
        Threads of the factor's solves: 1, or 2 (the two halves of the nested dissection at once,
        :mod:`esmm.pipeline.linalg.supernodal`; on the fine liver's factor 1.3-1.9 against
        2.1-3.2 ms back to back, but 4-6 ms against 2.6-7 ms between other work on this VM; on the
        paper liver's 0.13 against 0.21 ms in a run). The rest of the step runs on one thread.
    factor_threads : int
        Threads of the factorizations: 1 or 2 (the same halves; the fine liver's 59 against 87 ms,
        the paper liver's 4.5 against 6.5 ms, 2026-11-27). Long enough that the workers' wake-up
        does not count, unlike a solve's.
    solo_solve_s : float
        A solve's time on one thread, measured where ``threads = "auto"`` chose two: if two threads'
        solves get slower than that, the run goes on with one (:meth:`_check_threads`). NaN: never.
    """

    step: float = DEFAULT_STEP
    rtol: float = 0.01
    xtol: float = 1e-4
    contact_rounds: int | None = None
    iteration: str = "quasi-newton"
    memory: int = MEMORY
    max_newton: int = 4
    cg_rtol: float = 0.1
    max_cg: int = 20
    preconditioner: str = "factor"
    haptic_rate: float = HAPTIC_RATE
    haptic_drift: bool = True
    definite: bool = True
    single: bool = True
    factor_matrix: str = "bound"
    threads: int = 1
    factor_threads: int = 1
    solo_solve_s: float = math.nan
    stats: ImplicitStats = field(default_factory=ImplicitStats)
    _factor: SparseFactor | None = field(default=None, repr=False)
    _factor_h: float = field(default=math.nan, repr=False)
    _cons: Constraints | None = field(default=None, repr=False)
    _perm: np.ndarray | None = field(default=None, repr=False)
    _last: tuple | None = field(default=None, repr=False)
    _solves_before: int = field(default=0, repr=False)
    _stale: bool = field(default=False, repr=False)
    _excess: int = field(default=0, repr=False)
    _slides: Slides | None = field(default=None, repr=False)
    _pairs: LBFGSMemory | None = field(default=None, repr=False)
    _qn: dict = field(default_factory=dict, repr=False)       #: this solve's quasi-Newton record
    _qn_step: int = field(default=0, repr=False)              #: this step's quasi-Newton iterations
    _handover: list = field(default_factory=lambda: [0, 0], repr=False)  #: hand-overs' cost, and their count

    def __post_init__(self):
        if self.iteration not in ITERATIONS:
            raise ConfigError(f"iteration: {self.iteration!r} is not one of {', '.join(ITERATIONS)}",
                              parameter="iteration")
        self._pairs = LBFGSMemory(int(self.memory))
        if not (math.isfinite(self.step) and self.step > 0):
            raise ConfigError(f"implicit_step: must be a positive time, got {self.step}", parameter="implicit_step")
        if self.preconditioner not in PRECONDITIONERS:
            raise ConfigError(f"preconditioner: {self.preconditioner!r} is not one of {', '.join(PRECONDITIONERS)}",
                              parameter="preconditioner")
        if self.factor_matrix not in FACTORS:
            raise ConfigError(f"factor_matrix: {self.factor_matrix!r} is not one of {', '.join(FACTORS)}",
                              parameter="factor_matrix")
        if not (math.isfinite(self.haptic_rate) and self.haptic_rate > 0):
            raise ConfigError(f"haptic_rate: must be positive, got {self.haptic_rate}", parameter="haptic_rate")

    @property
    def _quasi(self) -> bool:
        """Whether solves iterate by quasi-Newton (it needs the reused factor; else Newton's)."""
        return self.iteration == "quasi-newton" and self.preconditioner == "factor"

    # -- the Stepper interface ------------------------------------------------------
    def bound(self, model: Model, control: Control) -> StepBound:
        """Its proposed step; no stability limit (``dt_critical`` is infinite)."""
        return StepBound(self.step, math.inf, 0.0, 0.0, 1.0, -1)

    def report(self) -> dict:
        """The statistics so far (JSON-ready), solves with the current factor included."""
        self.stats.solves = self._solves_before + (0 if self._cons is None else self._cons.solves)
        return {"method": "implicit", "preconditioner": self.preconditioner, "step_s": self.step,
                "haptic_rate_hz": self.haptic_rate, "rtol": self.rtol, "factor_matrix": self.factor_matrix,
                **self.stats.as_dict()}

    def ticks_per_step(self, dt: float) -> int:
        """Grasper force samples per step of *dt*: ``ceil(dt * haptic_rate)`` (spacing <= 1/haptic_rate)."""
        return max(1, int(math.ceil(dt * self.haptic_rate * (1 - 1e-9))))

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
        self._refactor(model, state, state.x, self._dt_fx(state, state.dt))
        return time.perf_counter() - t

    # -- one step ------------------------------------------------------------------
    def _step(self, model: Model, state: State, control: Control, rec: np.ndarray) -> None:
        """One step of ``state.dt``: predictor, the grasper force's samples, Newton, the floor, commit."""
        h, t = state.dt, state.t
        x0, v0 = state.x.copy(), state.v.copy()
        g_ = control.grasp
        fmask = (control.floor_mask > 0) & model.movable
        if g_ is not None:
            fmask[g_.nodes] = False
        floor = model.floor
        contact = (state.contact > 0) & fmask if floor is not None else np.zeros(model.n_nodes, bool)
        self._slides = Slides.none(model.n_nodes)
        dt_fx = self._dt_fx(state, h)
        if self.preconditioner == "factor" and (self._factor is None or self._factor_h != h or self._stale):
            self._refactor(model, state, x0, dt_fx)
        if self._factor is not None:
            self._factor.ldl.threads = self.threads      # as set since it was taken (the run's choice, a fall-back)
        F0 = self._start_force(model, state, control, t)
        x = self._predictor(model, control, x0, v0, h, contact, t + h)
        self._set_rows(model, control, contact, h)
        S = self._patch_stiffness(model, control, h)
        self._haptic_ticks(rec, F0, S, g_, t, h)
        self._qn_step = 0
        x = self._converge(model, state, control, x, x0, v0, h, dt_fx, contact, np.repeat(~model.movable, 3))
        if self._quasi:
            self._excess += max(0, self._qn_step - QN_FRESH)
            self._stale = self._stale or self._refactor_pays()
        if floor is not None:
            # free nodes that went below the plane are put back on it (where their path crossed
            # it, with "stick") and held from the next step on: the explicit step's rule, per step
            landed = self._touchdown(floor, x0, x, fmask & ~contact)
            contact |= landed
            self.stats.contact_changes += int(landed.sum())
        self._commit(model, state, control, x, x0, h, dt_fx, contact, F0, S)

    def _predictor(self, model, control, x0, v0, h, contact, t1):
        """The Newton iteration's start: inertial motion, held nodes on the path, contacts on the floor."""
        g_ = control.grasp
        x = x0 + h * v0
        x[~model.movable] = x0[~model.movable]
        if g_ is not None and g_.mode == "prescribed":
            x[g_.nodes] = g_.tip(t1) + g_.offsets
        if contact.any():
            x[contact] = self._on_floor(model.floor, x0[contact], x[contact])
        return x

    def _converge(self, model, state, control, x, x0, v0, h, dt_fx, contact, fixed_dof):
        """Newton's iteration from *x* until the residual or the update is small (module doc); then the
        floor's contacts are updated (:meth:`_contact_update`, *contact* in place) and, while
        ``contact_rounds`` allow, the step is solved again with them.

        The step's first solve takes one iteration even where the predictor's residual is already
        below the tolerance: accepted as it is, a state at rest whose forces are out of balance by
        less than ``rtol`` of the largest weight never moved again, however soft the mode they drive
        (a box at rest whose load rose by half the tolerance stayed where it was, at 1/30 s and at
        1 ms steps). One iteration moves it by the linearized step, so the stepper's resting states
        are the equilibria (docs/simulate.md §2b)."""
        st = self.stats
        floor = model.floor
        tol = self.rtol * self._force_scale(model)
        xtol = self.xtol * float(np.ptp(model.rest, axis=0).max())
        mass_dof = np.repeat(model.mass * (1.0 / (h * h) + model.mass_damping / h), 3)
        coupling = self._coupling_dofs(control, model.n_nodes)
        _, g = self._residual(model, state, control, x, x0, v0, h, dt_fx)
        norm = self._norm(g, control, contact, floor)
        it = 0
        moved = math.inf
        extra = self._contact_rounds(floor)
        for rounds in range(extra + 1):
            start = it
            moved = math.inf
            self._begin_solve(norm, tol)
            # max_newton Newton iterations per solve, after the quasi-Newton ones; the step's first
            # solve takes one at least (:meth:`_converge`'s doc)
            while (norm > tol or it == 0) and moved > xtol and it - start < self.max_newton + self._qn["all"]:
                x, g, norm, moved = self._iterate(model, state, control, x, x0, v0, h, dt_fx, g, norm, contact,
                                                  mass_dof, coupling, fixed_dof)
                it += 1
            if not self._qn["exact"]:                    # ended on the update's length at a modelled residual
                g, norm = self._exact_residual(model, state, control, x, x0, v0, h, dt_fx, contact)
            self._end_solve()
            changed, moved = self._contact_update(floor, g, x, contact, final=rounds == extra)
            if changed:
                self._set_rows(model, control, contact, h)
                if moved:
                    _, g = self._residual(model, state, control, x, x0, v0, h, dt_fx)
                norm = self._norm(g, control, contact, floor)
            if not changed or rounds == extra:
                break
        if norm > tol and moved > xtol:
            st.unconverged += 1
        st.max_newton = max(st.max_newton, it)
        return x

    def _begin_solve(self, norm: float, tol: float) -> None:
        """A new solve (a step, or a re-solve after the contacts changed) from a residual of *norm*, to
        *tol*; its constraint rows were just set, which forgot the last solve's pairs (:meth:`_set_rows`).
        ``exact``: whether the current residual is the residual itself, not the secant's model of it
        (:meth:`_secant_search`)."""
        self._qn = {"its": 0, "all": 0, "start": norm, "best": None, "refreshed": False, "newton": False,
                    "cost0": None, "tol": tol, "exact": True}

    def _end_solve(self) -> None:
        """Record what the solve cost after its hand-over, if it was handed over (:meth:`_switch_after`):
        its iterations since (quasi-Newton, Newton, conjugate gradients: about a solve each) and the
        fresh factor, in solves (its factorization's and constraint columns' seconds over a solve's)."""
        qn = self._qn
        if qn["cost0"] is None:
            return
        its, factorizations = qn["cost0"]
        fresh = self._factor_in_solves() if self.stats.factorizations > factorizations else 0.0
        self._handover[0] += self._iterations() - its + (fresh if math.isfinite(fresh) else 0.0)
        self._handover[1] += 1

    def _iterations(self) -> int:
        st = self.stats
        return st.quasi_newton + st.newton + st.cg

    def _switch_after(self) -> float:
        """Quasi-Newton iterations a solve gets before it is handed over (:meth:`_iterate`): what a
        hand-over has cost so far, on average, in solves (:meth:`_end_solve`; an iteration of any kind
        costing about a solve); :data:`QN_SWITCH` until one has been measured.

        The break-even rule of renting against buying (the ski-rental problem; Karlin et al. 1988):
        going on until what the quasi-Newton iterations cost equals the hand-over's cost is never
        more than twice what the better of the two would have cost, whichever it is (where a hand-over
        costs the same whenever it is made and that cost is known; here it is the run's estimate).
        """
        cost, count = self._handover
        return cost / count if count else QN_SWITCH

    def _iterate(self, model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, mass_dof, coupling, fixed_dof):
        """One iteration of the solve: quasi-Newton while it converges; else, from its best iterate,
        quasi-Newton again on a factor taken there (once per solve), then Newton; (x, g, |g|, the
        update's largest nodal length).

        Why the fresh factor first: the quasi-Newton iterations stall where the matrix has changed
        since the factor was taken (the release, a lift peeling the organ off its bed), and Newton's
        iteration cost 7-12 conjugate-gradient iterations, each a solve and a product, per iteration
        (the fine liver: 107 ms, a factorization 88 ms; docs/simulate.md §2b). Where a factorization
        costs more than Newton's iteration may (:meth:`_refresh_pays`), Newton's iteration at once.
        """
        qn = self._qn
        if self._quasi and not qn["newton"]:
            if qn["best"] is None or norm < qn["best"][0]:
                qn["best"] = (norm, x, g, qn["exact"])
            if qn["its"] < self._switch_after() and norm <= QN_DIVERGE * qn["start"]:
                return self._quasi_newton(model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, fixed_dof)
            if qn["cost0"] is None:                      # the hand-over: its cost counted from here
                qn["cost0"] = (self._iterations(), self.stats.factorizations)
                self.stats.fallbacks += 1
            norm, x, g, exact = qn["best"]
            if not exact:                                # the hand-over starts from the residual itself
                g, norm = self._exact_residual(model, state, control, x, x0, v0, h, dt_fx, contact)
            if not qn["refreshed"] and self._refresh_pays():
                qn.update(refreshed=True, its=0, start=norm, best=None)
                self._stale = True                       # refactored at x by the next iteration
                return self._quasi_newton(model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, fixed_dof)
            qn["newton"] = True
        qn["exact"] = True                               # Newton's line search evaluates the residual
        return self._newton(model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, mass_dof, coupling,
                            fixed_dof)

    def _refresh_pays(self) -> bool:
        """Whether a fresh factor (its factorization and constraint columns, as last measured, in solves)
        costs less than Newton's iteration may spend on a solve: ``max_newton`` iterations of at most
        ``max_cg`` conjugate-gradient iterations and a tangent product each. The livers' factor costs
        24-35 solves; the 100 k Kuhn box's, 660 (docs/simulate.md §2b)."""
        budget = self.max_newton * (self.max_cg + 1)
        return self.preconditioner == "factor" and self._factor_in_solves() < budget

    def _quasi_newton(self, model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, fixed_dof):
        """One L-BFGS iteration (:mod:`~esmm.pipeline.linalg.quasinewton`): a solve with the factor, the secant's step."""
        self._renew_factor(model, state, control, x, dt_fx, contact, h)
        b = -g.ravel()
        cons = self._cons

        def h0(r):
            return cons.apply(r, fixed_dof)

        d = self._pairs.direction(b, h0)
        if not float(b @ d) > 0.0 and len(self._pairs):          # not a descent direction: forget the pairs
            self._pairs.clear()
            d = h0(b)
        self.stats.quasi_newton += 1
        self._qn["its"] += 1
        self._qn["all"] += 1
        self._qn_step += 1
        d3 = d.reshape(-1, 3)
        step, xt, gt, exact = self._secant_search(model, state, control, x, x0, v0, h, dt_fx, d3, g,
                                                  float(b @ d))
        self._pairs.update((xt - x).ravel(), (gt - g).ravel())
        new = self._norm(gt, control, contact, model.floor)
        if not exact and (new <= self._qn["tol"] or new >= norm):   # converged, or no progress, on the model:
            gt, new = self._exact_residual(model, state, control, xt, x0, v0, h, dt_fx, contact)   # it decides
            exact = True
        self.stats.modelled += not exact
        self._qn["exact"] = exact
        return xt, gt, new, max(1.0, step) * float(np.sqrt(np.einsum("ij,ij->i", d3, d3).max()))

    def _exact_residual(self, model, state, control, x, x0, v0, h, dt_fx, contact):
        """(g, |g|): the residual itself at *x*, where a decision rests on it (:meth:`_secant_search`);
        the solve's current residual is exact again."""
        _, g = self._residual(model, state, control, x, x0, v0, h, dt_fx)
        self._qn["exact"] = True
        return g, self._norm(g, control, contact, model.floor)

    def _secant_search(self, model, state, control, x, x0, v0, h, dt_fx, d3, g, descent):
        """The step along *d3* from the residual's slopes (:func:`~esmm.pipeline.linalg.quasinewton.secant_step`; *descent*
        = ``-phi'(0)`` > 0, *g* the residual at *x*); (step, x, g, whether g is the residual itself).

        Where the step is not the full one, the residual there is the secant's model,
        ``g + step (g(x + d) - g)``, exact where the residual is linear along *d* (the model the step
        was chosen on), not a second force pass: on the paper liver's default scene 2.16 force passes
        an iteration became about one, the run 1.15x faster, the iterations as many and the grasper
        force as close to the explicit reference (docs/simulate.md §2b, "The secant's residual"). The
        residual itself is evaluated where the secant's zero lies beyond the step's range (far from
        linear: a release step's model read 1.9e4 where the residual was 30) and wherever a decision
        rests on it: where the model shows convergence or no progress (:meth:`_quasi_newton`), where a
        solve ends on the update's length, and at a hand-over (:meth:`_converge`, :meth:`_iterate`).
        The curvature pair is then the secant's over the full direction scaled by the step (which
        BFGS's update does not see)."""
        x1 = x + d3
        _, g1 = self._residual(model, state, control, x1, x0, v0, h, dt_fx)
        step = secant_step(-descent, float(g1.ravel() @ d3.ravel()), max_step=QN_MAX_STEP)
        if step == 1.0:
            return step, x1, g1, True
        if step < 1.0:
            self.stats.backtracks += 1
        xs = x + step * d3
        if not MIN_STEP < step < QN_MAX_STEP:        # the secant's zero lies beyond the range: far from linear
            _, gs = self._residual(model, state, control, xs, x0, v0, h, dt_fx)
            return step, xs, gs, True
        return step, xs, g + step * (g1 - g), False

    def _newton(self, model, state, control, x, x0, v0, h, dt_fx, g, norm, contact, mass_dof, coupling, fixed_dof):
        """One Newton iteration from x (residual g, |g| = norm): the update's solve and its line search."""
        st = self.stats
        self._renew_factor(model, state, control, x, dt_fx, contact, h)
        precond = self._preconditioner(model, state, x, h, dt_fx, mass_dof, coupling, fixed_dof, contact, control)
        b = -g.ravel()
        b[fixed_dof] = 0.0
        if self.max_cg == 0:                 # the chord step: the reused matrix itself
            dx, its = precond(b), 1
        else:
            matvec = self._operator(model, state, x, h, dt_fx, mass_dof, coupling, fixed_dof)
            dx, its, _ = pcg(matvec, precond, b, rtol=self.cg_rtol,
                             max_iter=self.max_cg if self.preconditioner != "jacobi" else 50 * self.max_cg)
        st.cg += its
        st.newton += 1
        x, g, new = self._line_search(model, state, control, x, x0, v0, h, dt_fx, dx.reshape(-1, 3), norm, contact,
                                      model.floor)
        self._excess += max(0, its - 1)
        if self._refactor_pays() or (self.max_cg == 0 and new > 0.5 * norm):
            self._stale = True
        return x, g, new, float(np.sqrt(np.einsum("ij,ij->i", dx.reshape(-1, 3), dx.reshape(-1, 3)).max()))

    def _contact_rounds(self, floor) -> int:
        """Re-solves after the contacts changed within a step: as set, or by the floor (class doc):
        one on a frictionless floor (let go), two on a sticking one (slide, then stop or let go)."""
        if self.contact_rounds is not None:
            return int(self.contact_rounds)
        if floor is None:
            return 0
        return 2 if floor.friction == "stick" else 1

    def _contact_update(self, floor, g: np.ndarray, x: np.ndarray, contact: np.ndarray, *,
                        final: bool) -> tuple[bool, bool]:
        """The floor's contacts after a solve (*contact* in place; *x* too where a slide stops); whether
        they changed, and whether *x* moved. ``lam = g . n`` is the floor's reaction on a node (> 0: it pushes). A contact it
        would have to pull leaves it, except on a sticking floor where the step is solved again
        (:class:`Slides`; with ``contact_rounds`` 0 it leaves at the step's end, the rule before them)."""
        if floor is None or not contact.any():
            return False, False
        lam = g @ floor.normal
        moved = False
        if floor.friction == "stick" and self._contact_rounds(floor) > 0:
            leave, changed, started = self._slides.update(lam, x, contact, final=final)
            self.stats.slides += started
            moved = self._slides.moved
        else:
            leave = contact & (lam < 0.0)
            changed = bool(leave.any())
        contact &= ~leave
        self.stats.contact_changes += int(leave.sum())
        return changed, moved

    def _holds(self, contact: np.ndarray, floor) -> tuple[np.ndarray, np.ndarray]:
        """(held in place, held along the normal only): the floor's contacts by its friction and the
        step's slides."""
        none = np.zeros_like(contact)
        if floor is None or not contact.any():
            return none, none
        if floor.friction == "stick":
            slide = contact & self._slides.sliding
            return contact & ~slide, slide
        return none, contact

    def _refactor_pays(self) -> bool:
        """Whether the conjugate-gradient iterations lost to the factor's age (beyond one per Newton
        iteration) since it was taken have cost more than taking it again (its factorization and
        constraint columns, as measured): then the factor is renewed."""
        return self.preconditioner == "factor" and self._excess > self._factor_in_solves()

    def _factor_in_solves(self) -> float:
        """What taking the factor again costs (its numeric factorization and constraint columns, as
        measured for the current one), in the current factor's mean solves; infinite before any solve.

        Without the symbolic analysis, which only the run's first factor does (with the analysis
        kernels' first calls: the paper liver's 0.11 s against 4-7 ms for the numeric phase): with it
        the factor counted as ~400 solves instead of ~25 until its first renewal, and a run renewed
        it or not by its timing (the paper liver's default scene, 2026-11-27: 0 or 5 renewals, 2 031
        or 1 008 quasi-Newton iterations, 1.71 or 0.99 s of stepping). Nor the matrix's assembly:
        counted, it renewed the factor less often and the runs were slower, and the grasper force at
        1 kHz, predicted from the factor's patch stiffness, missed the explicit reference by more
        (docs/simulate.md §2b, "What a renewal costs").
        """
        cons, fac = self._cons, self._factor
        if fac is None or cons is None or cons.solves == 0 or cons.solve_s <= 0.0:
            return math.inf
        return (fac.seconds - fac.analysis_s + cons.columns_s) / (cons.solve_s / cons.solves)

    # -- pieces of a step ------------------------------------------------------------
    @staticmethod
    def _dt_fx(state: State, h: float) -> float:
        """How far the springs' effect state must advance to reach the end of a step of *h*."""
        fxs = state.effects
        return h if fxs is None else max(0.0, state.t + h - fxs.t)

    @staticmethod
    def _forces(model: Model, state: State, x: np.ndarray, v: np.ndarray, dt_fx: float,
                mode: int = K.FX_PEEK, *, threads: int = 1) -> np.ndarray:
        """Every term's force at (x, v) plus the external forces (n, 3) [N]; effects over *dt_fx*.

        On two *threads*, where the only other term is a volume term, the springs on one and the volume
        term on the other (:func:`~.kernels.forces_beside_volume`, the same sum bit for bit): the fine
        liver's 0.53 against 0.27 ms, the paper liver's 115 against 60 us (medians of 200 back to back,
        2026-11-27). The explicit stepper's chunked two-thread pass was slower here (0.91 against
        0.81 ms; docs/simulate.md §2b): its chunks share nodes and need a halo pass.
        """
        sp = model.springs
        others = [term for term in model.terms if term is not sp]
        beside = None
        if threads > 1 and len(others) == 1 and isinstance(others[0], VolumeTerm):
            beside, others = others[0].kernel(), []
        if state.effects is None:
            f = sp.forces(x, v, fext=model.fext, beside=beside)
        else:
            f = sp.forces(x, v, fext=model.fext, state=state.effects, mode=mode, dt=dt_fx, beside=beside)
        for term in others:
            f += term.forces(x, v)
        return f

    def _residual(self, model, state, control, x, x0, v0, h, dt_fx):
        """(f, g): the forces at x and the residual g (n, 3) (zero on fixed nodes)."""
        v = (x - x0) / h
        f = self._forces(model, state, x, v, dt_fx, threads=self.threads)
        fc = self._coupling_force(control, x, state.t + h)
        if fc is not None:
            f = f + fc
        m = model.mass[:, None]
        g = m * ((x - x0 - h * v0) / (h * h) + model.mass_damping * (x - x0) / h) - f
        g[~model.movable] = 0.0
        return f, g

    @staticmethod
    def _coupling_force(control: Control, x: np.ndarray, t1: float) -> np.ndarray | None:
        """The grasper's coupling springs' forces at time *t1* (mode "spring"), or None."""
        g_ = control.grasp
        if g_ is None or g_.mode != "spring":
            return None
        out = np.zeros_like(x)
        out[g_.nodes] = g_.stiffness[:, None] * (g_.tip(t1) + g_.offsets - x[g_.nodes])
        return out

    @staticmethod
    def _coupling_dofs(control: Control, n: int) -> np.ndarray | None:
        k = control.coupling_rows()
        return None if k is None else np.repeat(k, 3)

    @staticmethod
    def _force_scale(model: Model) -> float:
        """The largest nodal weight on a moving node [N] (the residual's scale); a spring force scale without gravity."""
        mov = model.movable
        w = float(np.linalg.norm(model.fext[mov], axis=1).max()) if mov.any() else 0.0
        if w > 0.0:
            return w
        sp = model.springs
        return 1e-3 * float(np.median(sp.rest_tangent / sp.sd[0].astype(np.float64)))

    def _norm(self, g: np.ndarray, control: Control, contact: np.ndarray, floor) -> float:
        """The largest residual force on a node that no constraint holds [N]."""
        r = g.copy()
        gr = control.grasp
        if gr is not None and gr.mode == "prescribed":
            r[gr.nodes] = 0.0
        held, normal = self._holds(contact, floor)
        if held.any():
            r[held] = 0.0
        if normal.any():
            nrm = floor.normal
            r[normal] -= (r[normal] @ nrm)[:, None] * nrm
        return float(np.sqrt(np.einsum("ij,ij->i", r, r)).max()) if r.size else 0.0

    @staticmethod
    def _on_floor(floor, x0: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Nodes put on the plane: "stick" where their path from *x0* crossed it, "slip" along the normal."""
        nrm = floor.normal
        d = x @ nrm - floor.height
        if floor.friction == "stick":
            d0 = x0 @ nrm - floor.height
            r = np.where(d0 > 0.0, d0 / np.where(d0 - d > 0, d0 - d, 1.0), 0.0)
            y = x0 + np.clip(r, 0.0, 1.0)[:, None] * (x - x0)
            return y - (y @ nrm - floor.height)[:, None] * nrm
        return x - d[:, None] * nrm

    def _touchdown(self, floor, x0: np.ndarray, x: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Candidate nodes below the plane after an update: put on it (in *x*) and returned as new contacts."""
        below = candidates & (floor.distance(x) < 0.0)
        if below.any():
            x[below] = self._on_floor(floor, x0[below], x[below])
        return below

    def _line_search(self, model, state, control, x, x0, v0, h, dt_fx, dx, norm, contact, floor):
        """x + s dx with s = 1, 1/2, 1/4 (the first that lowers the residual; else the last); (x, g, |g|)."""
        s = 1.0
        for k in range(3):
            xt = x + s * dx
            _, g = self._residual(model, state, control, xt, x0, v0, h, dt_fx)
            nt = self._norm(g, control, contact, floor)
            if nt < norm or k == 2:
                if k:
                    self.stats.backtracks += k
                return xt, g, nt
            s *= 0.5
        return xt, g, nt

    # -- matrices ------------------------------------------------------------------
    def _tangent(self, model: Model, state: State, x: np.ndarray, dt_fx: float, *, definite: bool,
                 bound: bool = False, skip: tuple = ()):
        """Sum of the terms' tangent stiffness at x (CSR (3n, 3n)); the springs' with their effect state.
        *bound*: each term's ``tangent_bound`` instead where it has one (a sparser matrix above it);
        the terms in *skip* left out."""
        sp = model.springs
        Kt = sp.tangent(x, state=state.effects, dt=dt_fx, definite=definite)
        for term in model.terms:
            if term is not sp and not any(term is k for k in skip):
                upper = getattr(term, "tangent_bound", None) if bound else None
                Kt = Kt + (upper(x) if upper is not None else term.tangent(x, definite=definite))
        return Kt

    def _operator(self, model, state, x, h, dt_fx, mass_dof, coupling, fixed_dof):
        """Newton's matrix at x as a product ``p -> A p`` (zero on fixed dofs)."""
        sp = model.springs
        Kt = sp.tangent(x, state=state.effects, dt=dt_fx, definite=self.definite)
        others = [_product(term, x, self.definite) for term in model.terms if term is not sp]
        C = sp.damping_matrix(x) if sp.damped else None
        diag = mass_dof if coupling is None else mass_dof + coupling

        def matvec(p):
            y = Kt @ p + diag * p
            for product in others:
                y += product(p)
            if C is not None:
                y += (C @ p) / h
            y[fixed_dof] = 0.0
            return y

        return matvec

    def factored(self, model: Model) -> str:
        """What the factor is taken of on *model*: with the reused factor and ``factor_matrix`` "mixed"
        or "bound", that, where a term has ``tangent_parts`` (mixed) or ``tangent_bound`` (bound);
        else "exact"."""
        if self.preconditioner != "factor" or self.factor_matrix == "exact":
            return "exact"
        attr = "tangent_parts" if self.factor_matrix == "mixed" else "tangent_bound"
        has = any(getattr(t, attr, None) is not None for t in model.terms if t is not model.springs)
        return self.factor_matrix if has else "exact"

    def _system_matrix(self, model, state, x, h, dt_fx, *, skip: tuple = ()):
        """The factored matrix: ``M/h^2 + (alpha M + C)/h + K(x)`` (definite springs; the terms' bounds
        where :meth:`factored` says so; without the terms in *skip*), identity on fixed dofs."""
        A = self._tangent(model, state, x, dt_fx, definite=self.definite, bound=self.factored(model) == "bound",
                          skip=skip)
        if model.springs.damped:
            A = A + model.springs.damping_matrix(x) / h
        mass_dof = np.repeat(model.mass * (1.0 / (h * h) + model.mass_damping / h), 3)
        mov = np.repeat(model.movable, 3).astype(np.float64)
        A = sps.csr_matrix(A)
        A.data *= np.repeat(mov, np.diff(A.indptr)) * mov[A.indices]     # D A D, D = diag(mov), in place
        return (A + sps.diags(mass_dof * mov + (1.0 - mov))).tocsr()

    def _mixed_factor(self, model, state, x, h, dt_fx) -> MixedFactor:
        """Newton's matrix factored from its parts (:class:`~esmm.pipeline.linalg.linsolve.MixedFactor`): the system matrix
        without the terms that have ``tangent_parts``, and their ``B^T diag(w) B`` (fixed dofs' columns
        of B zero)."""
        parts = [t for t in model.terms if t is not model.springs and getattr(t, "tangent_parts", None) is not None]
        A = self._system_matrix(model, state, x, h, dt_fx, skip=tuple(parts))
        Bs, ws = zip(*(t.tangent_parts(x) for t in parts))
        B = sps.vstack(Bs).tocsr() @ sps.diags(np.repeat(model.movable, 3).astype(np.float64))
        w = np.concatenate(ws)
        if self._perm is None or self._perm.size != A.shape[0] + B.shape[0]:
            self._perm = mixed_ordering(A, B)
        return MixedFactor.of_parts(A, B, w, self._perm, single=self.single, analysis=self._analysis(),
                                    threads=self.factor_threads)

    def _refactor(self, model: Model, state: State, x: np.ndarray, dt_fx: float) -> None:
        """Take the factor at *x*: the system matrix assembled and factored."""
        h = state.dt
        self._check_threads()
        if self.factored(model) == "mixed":
            fac = self._mixed_factor(model, state, x, h, dt_fx)
        else:
            A = self._system_matrix(model, state, x, h, dt_fx)
            if self._perm is None or self._perm.size != A.shape[0]:
                self._perm = node_ordering(A)
            fac = SparseFactor.of(A, self._perm, single=self.single, analysis=self._analysis(),
                                  threads=self.factor_threads)
        fac.ldl.threads = self.threads                   # its solves'
        st = self.stats
        st.factorizations += 1
        st.factor_s += fac.seconds
        st.factor_nnz = fac.nnz
        if self._cons is not None:
            self._solves_before += self._cons.solves
        self._factor, self._factor_h = fac, h
        self._cons = Constraints(fac, model.n_nodes)
        self._stale = False
        self._excess = 0

    def _check_threads(self) -> None:
        """Two threads given up for one, for the rest of the run, where the last factor's solves on two
        took longer (their median) than a solve on one did in the run's trial (:attr:`solo_solve_s`,
        set where ``threads = "auto"`` chose two). Another process on the second core makes the two
        threads wait for each other: beside a CPU hog the paper liver's solve took 12.5 ms on two
        threads against 0.41 ms on one, and a run whose hog started after the trial 11.4 s instead of
        0.9 s (2026-11-27). The median, not the mean: a factor's first solves on two threads are slow
        (the workers waking; the paper liver's first 60 averaged 0.70 ms, their median 0.12 ms)."""
        cons = self._cons
        if self.threads > 1 and cons is not None and cons.apply_s and np.median(cons.apply_s) > self.solo_solve_s:
            self.threads = 1
            self.stats.thread_fallbacks += 1

    def solve_timing(self, threads=(1, 2), *, repeats: int = 7, warm: int = 3) -> dict:
        """Median seconds of a solve with the current factor on each number of *threads* (a random
        right-hand side, alternating; the first *warm* rounds not counted: a sleeping thread's first
        solves are slow). The factor's own setting is restored."""
        fac = self._factor
        if fac is None:
            return {}
        keep = fac.ldl.threads
        b = np.random.default_rng(0).standard_normal(fac.ldl.analysis.n)
        times = {th: [] for th in threads}
        for rep in range(warm + repeats):
            for th in threads:
                fac.ldl.threads = th
                t = time.perf_counter()
                fac.ldl.solve(b)
                if rep >= warm:
                    times[th].append(time.perf_counter() - t)
        fac.ldl.threads = keep
        return {th: float(np.median(v)) for th, v in times.items()}

    def _analysis(self):
        """The last factor's symbolic analysis (its pattern's: a run's matrices share one), or None."""
        return None if self._factor is None else self._factor.analysis

    def _renew_factor(self, model, state, control, x, dt_fx, contact, h) -> None:
        """Factor at *x* (with the constraint rows again) when the factor is stale, or at every
        iteration with the "fresh" preconditioner."""
        if self.preconditioner == "fresh" or (self._stale and self.preconditioner == "factor"):
            self._refactor(model, state, x, dt_fx)
            self._set_rows(model, control, contact, h)

    def _set_rows(self, model: Model, control: Control, contact: np.ndarray, h: float) -> None:
        """Constraint rows of the grasp (hard, or coupling springs) and the floor's contacts (the
        quasi-Newton pairs, taken in the old rows' null space, are forgotten)."""
        self._pairs.clear()
        if self._cons is None:
            return
        eye = np.eye(3)
        held, normal = self._holds(contact, model.floor)
        g_ = control.grasp
        grasped = np.zeros(0, np.int64) if g_ is None else np.asarray(g_.nodes, np.int64)
        if g_ is None or g_.mode == "prescribed":
            grasp_comp = np.zeros(grasped.size)
        else:
            grasp_comp = 1.0 / np.asarray(g_.stiffness, dtype=np.float64)
        held = np.flatnonzero(held)
        normal = np.flatnonzero(normal)
        # each grasped and each held node: three rows along the axes; each sliding contact: its normal
        nodes = np.concatenate([np.repeat(grasped, 3), np.repeat(held, 3), normal])
        es = np.concatenate([np.tile(eye, (grasped.size + held.size, 1)),
                             np.tile(np.zeros(3) if model.floor is None else model.floor.normal, (normal.size, 1))])
        comp = np.concatenate([np.repeat(grasp_comp, 3), np.zeros(3 * held.size + normal.size)])
        self._cons.set_rows(nodes, es, comp)

    def _preconditioner(self, model, state, x, h, dt_fx, mass_dof, coupling, fixed_dof, contact, control):
        """``r -> z``: the constrained preconditioner (factor + capacitance, or the diagonal)."""
        if self.preconditioner != "jacobi":
            cons = self._cons
            return lambda r: cons.apply(r, fixed_dof)
        Kt = self._tangent(model, state, x, dt_fx, definite=False)
        d = Kt.diagonal() + mass_dof + (0.0 if coupling is None else coupling)
        if model.springs.damped:
            d = d + model.springs.damping_matrix(x).diagonal() / h
        d = np.repeat(d.reshape(-1, 3).mean(axis=1), 3)          # per node: commutes with a normal projection
        hold = fixed_dof.copy()
        g_ = control.grasp
        if g_ is not None and g_.mode == "prescribed":
            hold.reshape(-1, 3)[g_.nodes] = True
        held, normal = self._holds(contact, model.floor)
        hold.reshape(-1, 3)[held] = True

        def apply(r):
            z = r / d
            z[hold] = 0.0
            if normal.any():
                zz = z.reshape(-1, 3)
                nrm = model.floor.normal
                zz[normal] -= (zz[normal] @ nrm)[:, None] * nrm
            return z

        return apply

    # -- the grasper force at the haptic rate -------------------------------------
    def _grasp_force(self, control: Control, f: np.ndarray, x: np.ndarray, t: float) -> np.ndarray:
        """Force of the tissue on the grasper from the nodal forces *f* (springs, weight) at positions *x*."""
        g_ = control.grasp
        if g_ is None:
            return np.zeros(3)
        if g_.mode == "spring":
            return -(g_.stiffness[:, None] * (g_.tip(t) + g_.offsets - x[g_.nodes])).sum(axis=0)
        return f[g_.nodes].sum(axis=0)

    def _start_force(self, model: Model, state: State, control: Control, t: float) -> np.ndarray:
        """The grasper force at the step's start: the last step's, or computed now (first step, new grasp)."""
        g_ = control.grasp
        if g_ is None:
            return np.zeros(3)
        last = self._last
        if last is not None and last[0] is g_ and abs(last[1] - t) <= 1e-9 * max(1.0, abs(t)):
            return last[2]
        fxs = state.effects
        f = self._forces(model, state, state.x, state.v, 0.0 if fxs is None else max(0.0, t - fxs.t))
        return self._grasp_force(control, f, state.x, t)

    def _patch_stiffness(self, model: Model, control: Control, h: float) -> np.ndarray:
        """S (3, 3): minus the change of the grasper force per tip displacement in the step's linear model."""
        g_ = control.grasp
        cons = self._cons
        if g_ is None or cons is None or cons.cap_inv is None:
            return np.zeros((3, 3))
        rows = np.arange(3 * g_.nodes.size)
        S = cons.block_stiffness(rows)
        if g_.mode == "prescribed":
            mg = float(model.mass[g_.nodes].sum())
            S = S - mg * (1.0 / (h * h) + model.mass_damping / h) * np.eye(3)
        return S

    def _haptic_ticks(self, rec: np.ndarray, F0: np.ndarray, S: np.ndarray, g_, t: float, h: float) -> None:
        """The grasper force at the step's ticks: F0 moved by the patch stiffness along the tip's path (+ drift)."""
        rec[0] = F0
        T = rec.shape[0]
        if g_ is None or T == 1:
            rec[1:] = F0
            return
        last = self._last
        drift = last[3] if (self.haptic_drift and last is not None and last[0] is g_) else np.zeros(3)
        p0 = g_.tip(t)
        for q in range(1, T):
            tau = q * h / T
            rec[q] = F0 - S @ (g_.tip(t + tau) - p0) + (tau / h) * drift

    def _commit(self, model, state, control, x, x0, h, dt_fx, contact, F0, S) -> None:
        """Write the step into *state*: positions, velocities, effect state, contacts, clock; remember the force."""
        g_ = control.grasp
        t1 = state.t + h
        spring_grasp = g_ is not None and g_.mode == "spring"
        v = (x - x0) / h
        v[~model.movable] = 0.0
        if g_ is not None and not spring_grasp:
            v[g_.nodes] = g_.tip_velocity(state.t + 0.5 * h)
        fxs = state.effects
        f = self._forces(model, state, x, (x - x0) / h, dt_fx, mode=K.FX_STEP if fxs is not None else K.FX_PEEK,
                         threads=self.threads)
        if fxs is not None:
            fxs.t = t1
        state.x[:] = x
        state.v[:] = v
        state.contact[:] = contact.astype(np.uint8)
        state.steps += 1
        self.stats.steps += 1
        if g_ is not None:
            F1 = self._grasp_force(control, f, x, t1)
            drift = F1 - F0 + S @ (g_.tip(t1) - g_.tip(t1 - h))
            self._last = (g_, t1, F1, drift)
        else:
            self._last = None


@dataclass
class Slides:
    """A sticking floor's contacts within one implicit step (docs/simulate.md §2b, Floor).

    The explicit stepper lets go of a held node the moment the floor would pull it and holds it
    again where it is back on the plane: where a lift peels the organ off its bed, such nodes
    creep along the floor at no normal force. Backward Euler's step is too long to follow that
    creep, and holding them until the step's end makes the peel line chatter (a node let go,
    landed a step later, pulled again). So within a step, after each solve (``lam`` the floor's
    reaction, > 0 where it pushes):

    * a held node the floor pulls slides on it (held along the normal only; once per step);
    * a sliding node it pushes again sticks where its reaction, taken as linear along the slide,
      is zero (``s = lam0 / (lam0 - lam)`` of the way from where it was held); Newton restarts
      from the whole field taken back by the mean ``s`` (its linear response), the node there;
    * a sliding node it still pulls leaves the floor.

    The final check of a step (no solve follows) lets pulled sliding nodes go and moves no node;
    a held node pulled then stays held (it slides in the next step).
    """

    sliding: np.ndarray                 #: (n,) held along the normal only
    slid: np.ndarray                    #: (n,) has slid this step
    lam0: np.ndarray                    #: (n,) the reaction when its slide began (< 0) [N]
    x0: np.ndarray                      #: (n, 3) where it was held then [m]
    field0: np.ndarray | None = None    #: (n, 3) every node then [m]
    moved: bool = False                 #: the last update moved nodes (slides stopped)

    @classmethod
    def none(cls, n: int) -> Slides:
        return cls(np.zeros(n, bool), np.zeros(n, bool), np.zeros(n), np.zeros((n, 3)))

    def update(self, lam: np.ndarray, x: np.ndarray, contact: np.ndarray, *, final: bool):
        """The rule above after a solve (*x* moved in place where slides stop): (contacts to let go,
        whether anything changed, slides begun)."""
        pulled = contact & (lam < 0.0)
        leave = pulled & self.sliding
        stop = contact & self.sliding & ~pulled
        start = pulled & ~self.slid
        self.sliding &= ~leave
        self.moved = bool(stop.any()) and not final
        if final:
            return leave, bool(leave.any()), 0
        if stop.any():
            s = self.lam0[stop] / (self.lam0[stop] - lam[stop])
            x_stop = self.x0[stop] + s[:, None] * (x[stop] - self.x0[stop])
            x[:] = self.field0 + float(np.mean(s)) * (x - self.field0)
            x[stop] = x_stop
            self.sliding &= ~stop
        if start.any():
            self.lam0[start] = lam[start]
            self.x0[start] = x[start]
            self.field0 = x.copy()
            self.sliding |= start
            self.slid |= start
        return leave, bool(leave.any() or stop.any() or start.any()), int(start.sum())


def _product(term, x: np.ndarray, definite: bool):
    """``p -> K p`` of a term's tangent at x: its matrix-free product when it has one (the volume
    term: its matrix couples nodes two tets apart), else its sparse matrix's."""
    op = getattr(term, "tangent_operator", None)
    if op is not None:
        return op(x, definite=definite)
    return term.tangent(x, definite=definite).__matmul__


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
