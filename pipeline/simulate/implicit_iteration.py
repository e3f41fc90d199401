r"""The iteration of one implicit step: quasi-Newton on the reused factor, Newton as the fallback.

Each solve of a step's system (:class:`~.implicit_system.StepSystem`) iterates by L-BFGS with the
reused factor (:mod:`.factorcache`) as its first inverse (:class:`QuasiNewton`; one solve per
iteration, no tangent) or by Newton with conjugate gradients preconditioned by that factor
(:class:`Newton`). A quasi-Newton solve that has not converged after as many iterations as a
hand-over has cost so far, or whose residual grew :data:`QN_DIVERGE` times, is handed over: from
its best iterate to a factor taken there where that pays, then to Newton's iteration
(:class:`StepSolver`; docs/design/simulator.md, "The iteration: quasi-Newton on a reused factor").

After each solve the floor's contacts are updated (:mod:`.contact`) and, while their rounds allow,
the step is solved again with them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..linalg.linsolve import pcg
from ..linalg.quasinewton import MEMORY, MIN_STEP, LBFGSMemory, secant_step
from .factorcache import FactorCache
from .implicit_stats import ImplicitStats
from .implicit_system import StepSystem

#: Quasi-Newton iterations of one solve before it is handed over, until a hand-over's cost has been
#: measured (then that cost: :meth:`StepSolver.switch_after`). Chosen over 8 for speed at the same
#: accuracy (docs/design/simulator.md, "The iteration: quasi-Newton on a reused factor").
QN_SWITCH = 12
#: A quasi-Newton solve whose residual grew this many times above its start hands over to Newton.
QN_DIVERGE = 4.0
#: Quasi-Newton iterations of a step not counted as the factor's age (:meth:`.factorcache.FactorCache.age`
#: counts those beyond): about what a step takes on a fresh factor; not tuned.
QN_FRESH = 2
#: Longest step along a quasi-Newton direction, in directions (the secant's extrapolation).
QN_MAX_STEP = 8.0


@dataclass
class SolveRecord:
    """One solve's record (a step's, or a re-solve after the contacts changed).

    Attributes
    ----------
    start : float
        The residual's norm at the solve's start, or at its refresh [N].
    tol : float
        The solve's tolerance [N].
    its : int
        Quasi-Newton iterations since the start or the refresh.
    total : int
        Quasi-Newton iterations of the solve.
    best : tuple or None
        (norm, x, g, exact) of the best quasi-Newton iterate so far.
    refreshed : bool
        A factor was taken at its best iterate.
    newton : bool
        Handed over to Newton's iteration.
    cost0 : tuple or None
        (iterations, factorizations) so far when it was handed over.
    exact : bool
        The current residual is the residual itself, not the secant's model of it.
    """

    start: float
    tol: float
    its: int = 0
    total: int = 0
    best: tuple | None = None
    refreshed: bool = False
    newton: bool = False
    cost0: tuple | None = None
    exact: bool = True


@dataclass(eq=False)
class QuasiNewton:
    """One L-BFGS iteration (:mod:`~esmm.pipeline.linalg.quasinewton`): a solve with the first inverse,
    the secant's step along the direction."""

    stats: ImplicitStats
    pairs: LBFGSMemory = field(default_factory=lambda: LBFGSMemory(MEMORY))

    def update(self, system: StepSystem, x: np.ndarray, g: np.ndarray, norm: float,
               h0: Callable[[np.ndarray], np.ndarray], tol: float):
        """From *x* (residual *g*, |g| = *norm*), *h0* the first inverse: (x, g, |g|, the update's
        largest nodal length, whether g is the residual itself). A residual the secant's model shows
        at or below *tol*, or not below *norm*, is evaluated (a decision rests on it)."""
        b = -g.ravel()
        d = self.pairs.direction(b, h0)
        if not float(b @ d) > 0.0 and len(self.pairs):          # not a descent direction: forget the pairs
            self.pairs.clear()
            d = h0(b)
        self.stats.quasi_newton += 1
        d3 = d.reshape(-1, 3)
        step, xt, gt, exact = self._secant_search(system, x, d3, g, float(b @ d))
        self.pairs.update((xt - x).ravel(), (gt - g).ravel())
        new = system.norm(gt)
        if not exact and (new <= tol or new >= norm):   # converged, or no progress, on the model: it decides
            _, gt = system.residual(xt)
            new = system.norm(gt)
            exact = True
        self.stats.modelled += not exact
        return xt, gt, new, max(1.0, step) * float(np.sqrt(np.einsum("ij,ij->i", d3, d3).max())), exact

    def _secant_search(self, system: StepSystem, x: np.ndarray, d3: np.ndarray, g: np.ndarray, descent: float):
        """The step along *d3* from the residual's slopes (:func:`~esmm.pipeline.linalg.quasinewton.secant_step`;
        *descent* = ``-phi'(0)`` > 0, *g* the residual at *x*); (step, x, g, whether g is the residual itself).

        Where the step is not the full one, the residual there is the secant's model,
        ``g + step (g(x + d) - g)``, exact where the residual is linear along *d* (the model the step
        was chosen on), not a second force pass: about one force pass an iteration instead of two, as
        many iterations, the grasper force as accurate (docs/design/simulator.md, "The iteration:
        quasi-Newton on a reused factor"). The residual itself is evaluated where the secant's zero
        lies beyond the step's range (far from linear, where the model can be wrong by orders of
        magnitude) and wherever a decision rests on it: where the model shows convergence or no
        progress (:meth:`update`), where a solve ends on the update's length, and at a hand-over
        (:class:`StepSolver`). The curvature pair is then the secant's over the full direction scaled
        by the step (which BFGS's update does
        not see)."""
        x1 = x + d3
        _, g1 = system.residual(x1)
        step = secant_step(-descent, float(g1.ravel() @ d3.ravel()), max_step=QN_MAX_STEP)
        if step == 1.0:
            return step, x1, g1, True
        if step < 1.0:
            self.stats.backtracks += 1
        xs = x + step * d3
        if not MIN_STEP < step < QN_MAX_STEP:        # the secant's zero lies beyond the range: far from linear
            _, gs = system.residual(xs)
            return step, xs, gs, True
        return step, xs, g + step * (g1 - g), False


@dataclass(eq=False)
class Newton:
    """One Newton iteration: the update by conjugate gradients (inexact Newton) and its line search.

    Parameters
    ----------
    stats : ImplicitStats
    cg_rtol : float
        Relative tolerance of each linear solve.
    max_cg : int
        Conjugate-gradient iterations per update (0: the chord step, the preconditioner itself).
    jacobi : bool
        The preconditioner is the diagonal (fifty times as many iterations allowed).
    """

    stats: ImplicitStats
    cg_rtol: float = 0.1
    max_cg: int = 20
    jacobi: bool = False

    def update(self, system: StepSystem, x: np.ndarray, g: np.ndarray, norm: float,
               precond: Callable[[np.ndarray], np.ndarray]):
        """From *x* (residual *g*, |g| = *norm*) with *precond* (``r -> z``): (x, g, |g|, the update's
        largest nodal length, conjugate-gradient iterations)."""
        st = self.stats
        b = -g.ravel()
        b[system.fixed_dof] = 0.0
        if self.max_cg == 0:                 # the chord step: the reused matrix itself
            dx, its = precond(b), 1
        else:
            dx, its, _ = pcg(system.operator(x), precond, b, rtol=self.cg_rtol,
                             max_iter=self.max_cg if not self.jacobi else 50 * self.max_cg)
        st.cg += its
        st.newton += 1
        x, g, new = self._line_search(system, x, dx.reshape(-1, 3), norm)
        return x, g, new, float(np.sqrt(np.einsum("ij,ij->i", dx.reshape(-1, 3), dx.reshape(-1, 3)).max())), its

    def _line_search(self, system: StepSystem, x: np.ndarray, dx: np.ndarray, norm: float):
        """x + s dx with s = 1, 1/2, 1/4 (the first that lowers the residual; else the last); (x, g, |g|)."""
        s = 1.0
        for k in range(3):
            xt = x + s * dx
            _, g = system.residual(xt)
            nt = system.norm(g)
            if nt < norm or k == 2:
                if k:
                    self.stats.backtracks += k
                return xt, g, nt
            s *= 0.5
        return xt, g, nt


@dataclass(eq=False)
class StepSolver:
    """Solves a step's system (module doc): the iteration, its hand-overs, the contacts' rounds.

    Parameters
    ----------
    cache : FactorCache
        The reused factor (renewed from here where it is stale).
    stats : ImplicitStats
    rtol, xtol : float
        Converged: the largest residual force on a node below *rtol* of the largest nodal weight, or
        the largest update of a node below *xtol* of the organ's size.
    max_newton : int
        Newton iterations of a solve (after its quasi-Newton ones) before the step is accepted
        unconverged.
    quasi : bool
        Iterate by quasi-Newton first (it needs the reused factor).
    memory : int
        Quasi-Newton: curvature pairs kept.
    cg_rtol, max_cg : float, int
        Newton: each update's linear solve (:class:`Newton`).
    carry_pairs : bool
        Quasi-Newton: the pairs carried over contact changes, projected.
    slip : bool
        The floor's slides stop where they slip to, or creep to if farther (:meth:`.contact.Slides.slip`);
        False: where they creep to.
    """

    cache: FactorCache
    stats: ImplicitStats
    rtol: float = 0.01
    xtol: float = 1e-4
    max_newton: int = 4
    quasi: bool = True
    memory: int = MEMORY
    cg_rtol: float = 0.1
    max_cg: int = 20
    carry_pairs: bool = False
    slip: bool = True
    record: SolveRecord | None = None       #: the current solve's
    step_quasi: int = 0                     #: the current step's quasi-Newton iterations
    handover_cost: float = 0                #: what the hand-overs cost, in solves (:meth:`_end_solve`)
    handovers: int = 0
    qn: QuasiNewton = field(init=False)
    newton: Newton = field(init=False)

    def __post_init__(self):
        self.qn = QuasiNewton(self.stats, LBFGSMemory(int(self.memory)))
        self.newton = Newton(self.stats, self.cg_rtol, self.max_cg, self.cache.preconditioner == "jacobi")

    def solve(self, system: StepSystem, x: np.ndarray) -> np.ndarray:
        """The step's solution from the predictor *x*: iterations until the residual or the update is
        small; then the floor's contacts are updated (``system.contact``) and, while its rounds allow,
        the step is solved again with them. The iterations beyond :data:`QN_FRESH` age the factor.

        The step's first solve takes one iteration even where the predictor's residual is already
        below the tolerance: accepted as it is, a state at rest whose forces are out of balance by
        less than ``rtol`` of the largest weight would never move again, however soft the mode they
        drive. One iteration moves it by the linearized step, so the stepper's resting states are the
        equilibria (docs/design/simulator.md, "The iteration: quasi-Newton on a reused factor")."""
        st = self.stats
        self.step_quasi = 0
        tol, xtol = system.tolerances(self.rtol, self.xtol)
        _, g = system.residual(x)
        norm = system.norm(g)
        it = 0
        moved = math.inf
        extra = system.contact.rounds
        for rounds in range(extra + 1):
            start = it
            moved = math.inf
            rec = self.record = SolveRecord(start=norm, tol=tol)
            # max_newton Newton iterations per solve, after the quasi-Newton ones; the step's first
            # solve takes one at least
            while (norm > tol or it == 0) and moved > xtol and it - start < self.max_newton + rec.total:
                x, g, norm, moved = self._iterate(system, x, g, norm)
                it += 1
            if not rec.exact:                    # ended on the update's length at a modelled residual
                g, norm = self._exact_residual(system, x)
            self._end_solve()
            changed, moved = system.contact.update(g, x, final=rounds == extra,
                                                   residual=self._residual(system))
            if changed:
                self.set_rows(system)
                if moved:
                    _, g = system.residual(x)
                norm = system.norm(g)
            if not changed or rounds == extra:
                break
        if norm > tol and moved > xtol:
            st.unconverged += 1
        st.max_newton = max(st.max_newton, it)
        if self.quasi:
            self.cache.age(max(0, self.step_quasi - QN_FRESH))
        return x

    def _residual(self, system: StepSystem):
        """``y -> g``, the step's residual, for the floor's slides (:meth:`.contact.Slides.slip`), or None
        (``slip`` off)."""
        return (lambda y: system.residual(y)[1]) if self.slip else None

    def set_rows(self, system: StepSystem) -> None:
        """The constraint rows set again (:meth:`.factorcache.FactorCache.set_rows`); the quasi-Newton
        pairs, taken in the old rows' null space, are forgotten."""
        self.cache.set_rows(system)
        if self.carry_pairs and self.cache.constraints is not None:
            self.qn.pairs.project(self.cache.constraints.project)
        else:
            self.qn.pairs.clear()

    def _end_solve(self) -> None:
        """Record what the solve cost after its hand-over, if it was handed over (:meth:`switch_after`):
        its iterations since (quasi-Newton, Newton, conjugate gradients: about a solve each) and the
        fresh factor, in solves (:meth:`.factorcache.FactorCache.factor_in_solves`)."""
        rec = self.record
        if rec.cost0 is None:
            return
        its, factorizations = rec.cost0
        fresh = self.cache.factor_in_solves() if self.stats.factorizations > factorizations else 0.0
        self.handover_cost += self._iterations() - its + (fresh if math.isfinite(fresh) else 0.0)
        self.handovers += 1

    def _iterations(self) -> int:
        st = self.stats
        return st.quasi_newton + st.newton + st.cg

    def switch_after(self) -> float:
        """Quasi-Newton iterations a solve gets before it is handed over (:meth:`_iterate`): what a
        hand-over has cost so far, on average, in solves (:meth:`_end_solve`; an iteration of any kind
        costing about a solve); :data:`QN_SWITCH` until one has been measured.

        The break-even rule of renting against buying (the ski-rental problem; Karlin et al. 1988):
        going on until what the quasi-Newton iterations cost equals the hand-over's cost is never
        more than twice what the better of the two would have cost, whichever it is (where a hand-over
        costs the same whenever it is made and that cost is known; here it is the run's estimate).
        """
        return self.handover_cost / self.handovers if self.handovers else QN_SWITCH

    def refresh_pays(self) -> bool:
        """Whether a fresh factor (its factorization and constraint columns, in solves) costs less than
        Newton's iteration may spend on a solve: ``max_newton`` iterations of at most ``max_cg``
        conjugate-gradient iterations and a tangent product each. On small and mid-sized meshes a
        factorization costs tens of solves; on large ones hundreds, more than Newton's budget."""
        budget = self.max_newton * (self.max_cg + 1)
        return self.cache.preconditioner == "factor" and self.cache.factor_in_solves() < budget

    def _iterate(self, system: StepSystem, x: np.ndarray, g: np.ndarray, norm: float):
        """One iteration of the solve: quasi-Newton while it converges; else, from its best iterate,
        quasi-Newton again on a factor taken there (once per solve), then Newton; (x, g, |g|, the
        update's largest nodal length).

        Why the fresh factor first: the quasi-Newton iterations stall where the matrix has changed
        since the factor was taken (the release, a lift peeling the organ off its bed), and Newton's
        iteration costs several conjugate-gradient iterations, each a solve and a product, per
        iteration: together often more than a factorization. Where a factorization costs more than
        Newton's iteration may (:meth:`refresh_pays`), Newton's iteration at once.
        """
        rec = self.record
        if self.quasi and not rec.newton:
            if rec.best is None or norm < rec.best[0]:
                rec.best = (norm, x, g, rec.exact)
            if rec.its < self.switch_after() and norm <= QN_DIVERGE * rec.start:
                return self._quasi_newton(system, x, g, norm)
            if rec.cost0 is None:                        # the hand-over: its cost counted from here
                rec.cost0 = (self._iterations(), self.stats.factorizations)
                self.stats.fallbacks += 1
            norm, x, g, exact = rec.best
            if not exact:                                # the hand-over starts from the residual itself
                g, norm = self._exact_residual(system, x)
            if not rec.refreshed and self.refresh_pays():
                rec.refreshed, rec.its, rec.start, rec.best = True, 0, norm, None
                self.cache.stale = True                  # refactored at x by the next iteration
                return self._quasi_newton(system, x, g, norm)
            rec.newton = True
        rec.exact = True                                 # Newton's line search evaluates the residual
        return self._newton(system, x, g, norm)

    def _exact_residual(self, system: StepSystem, x: np.ndarray):
        """(g, |g|): the residual itself at *x*, where a decision rests on it; the solve's current
        residual is exact again."""
        _, g = system.residual(x)
        self.record.exact = True
        return g, system.norm(g)

    def _renew(self, system: StepSystem, x: np.ndarray) -> None:
        """The factor renewed at *x* where it is due (:meth:`.factorcache.FactorCache.renew`): its rows
        set again, the quasi-Newton pairs forgotten."""
        if self.cache.renew(system, x):
            self.qn.pairs.clear()

    def _quasi_newton(self, system: StepSystem, x: np.ndarray, g: np.ndarray, norm: float):
        """One quasi-Newton iteration (:class:`QuasiNewton`) with the constrained factor as its first inverse."""
        self._renew(system, x)
        cons, fixed_dof = self.cache.constraints, system.fixed_dof
        rec = self.record
        rec.its += 1
        rec.total += 1
        self.step_quasi += 1

        def h0(r):
            return cons.apply(r, fixed_dof)

        x, g, new, moved, rec.exact = self.qn.update(system, x, g, norm, h0, rec.tol)
        return x, g, new, moved

    def _newton(self, system: StepSystem, x: np.ndarray, g: np.ndarray, norm: float):
        """One Newton iteration (:class:`Newton`) preconditioned by the constrained factor (or the
        diagonal); the conjugate-gradient iterations beyond one age the factor, and a chord step
        that did not halve the residual makes it stale."""
        self._renew(system, x)
        if self.newton.jacobi:
            precond = system.jacobi(x)
        else:
            cons, fixed_dof = self.cache.constraints, system.fixed_dof

            def precond(r):
                return cons.apply(r, fixed_dof)

        x, g, new, moved, its = self.newton.update(system, x, g, norm, precond)
        self.cache.age(max(0, its - 1))
        if self.newton.max_cg == 0 and new > 0.5 * norm:
            self.cache.stale = True
        return x, g, new, moved
