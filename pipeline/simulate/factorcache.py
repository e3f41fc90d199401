r"""The implicit stepper's reused factor: what it is taken of, when it is renewed, its constraint rows.

The step's iterations (:mod:`.implicit_iteration`) precondition with a sparse :math:`LDL^T` of
Newton's matrix (:mod:`esmm.pipeline.linalg.supernodal`) taken at an earlier state and kept for as
long as it keeps the iterations few (docs/design/simulator.md, "What is factored, and when it is renewed"):

* what is factored (:meth:`FactorCache.factored`): by default Newton's matrix with the volume
  term's per-tet bound in place of its nodal tangent (a third of the fill, faster solves, a few
  more iterations); or the matrix itself, or the matrix with the volume term as a saddle point of
  its parts (:class:`~esmm.pipeline.linalg.linsolve.MixedFactor`);
* when it is renewed: when the iterations lost to its age have cost more than taking it again
  (:meth:`FactorCache.refactor_pays`), both counted in the current factor's solves
  (:meth:`FactorCache.factor_in_solves`, from the times measured as the factor was taken and used);
* its constraint rows (the grasp, the floor's contacts) join it through the capacitance matrix
  (:class:`~esmm.pipeline.linalg.linsolve.Constraints`), so the factor does not change with them;
* its threads: two threads are given up for one where their solves got slower than one thread's
  (:meth:`FactorCache.check_threads`);
* on a split asset, on request, the two-grid operator on the parents in its place
  (:class:`~esmm.pipeline.linalg.twogrid.TwoGrid`, its rows by
  :class:`~esmm.pipeline.linalg.twogrid.TwoGridConstraints`; docs/design/twogrid.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sps

from ..linalg import twogrid
from ..linalg.linsolve import Constraints, MixedFactor, SparseFactor, mixed_ordering
from ..linalg.newton import node_ordering
from ..linalg.twogrid import TwoGrid, TwoGridConstraints, prolongation
from .assembly import BoundAssembly
from .implicit_stats import ImplicitStats, Threads
from .implicit_system import StepSystem
from .model import Model


@dataclass(eq=False)
class FactorCache:
    """The reused factor of the implicit steps and its life cycle (module doc).

    Parameters
    ----------
    preconditioner : {"factor", "fresh", "jacobi"}
        "factor": a factor reused over steps; "fresh": taken at every Newton iteration; "jacobi":
        none (the cache then holds nothing).
    factor_matrix : {"bound", "exact", "mixed"}
        What the reused factor is taken of (:meth:`factored`).
    single : bool
        Factor in float32 (the factor is a preconditioner).
    threads : Threads
        The run's threads (shared with the stepper; :meth:`check_threads` may lower ``solve``).
    stats : ImplicitStats
        Where factorizations and thread fall-backs are counted.
    coarse_cells : ndarray of int, shape (p, 10), or None
        A split network's parents as 10-node cells on its nodes: with them, the reused
        preconditioner is the two-grid operator on the parents (:class:`~esmm.pipeline.linalg.twogrid.TwoGrid`;
        the matrix as ``factor_matrix`` says, "bound" or "exact") instead of the matrix's factor.

    Attributes
    ----------
    factor : SparseFactor or None
        The current factor.
    constraints : Constraints or None
        Its constraint rows.
    stale : bool
        To be renewed at the next chance (:meth:`begin_step`, :meth:`renew`).
    excess : int
        Iterations lost to the factor's age since it was taken (:meth:`age`).
    """

    preconditioner: str
    factor_matrix: str
    single: bool
    threads: Threads
    stats: ImplicitStats
    factor: SparseFactor | None = None
    factor_h: float = math.nan              #: the step the factor was taken for [s]
    constraints: Constraints | None = None
    perm: np.ndarray | None = field(default=None, repr=False)   #: the matrix's fill-reducing order
    solves_before: int = 0                  #: solves with the factors before the current one
    stale: bool = False
    excess: int = 0
    coarse_cells: np.ndarray | None = field(default=None, repr=False)
    _prolong: object = field(default=None, repr=False)   #: the two-grid's prolongation, once per run
    _assembly: tuple | None = field(default=None, repr=False)   #: (model, its BoundAssembly or None)

    def factored(self, model: Model) -> str:
        """What the factor is taken of on *model*: with the reused factor and ``factor_matrix`` "mixed"
        or "bound", that, where a term has ``tangent_parts`` (mixed) or ``tangent_bound`` (bound);
        else "exact"."""
        if self.preconditioner != "factor" or self.factor_matrix == "exact":
            return "exact"
        if self.coarse_cells is not None and self.factor_matrix == "mixed":
            return "exact"
        attr = "tangent_parts" if self.factor_matrix == "mixed" else "tangent_bound"
        has = any(getattr(t, attr, None) is not None for t in model.terms if t is not model.springs)
        return self.factor_matrix if has else "exact"

    def solves(self) -> int:
        """Triangular solves with all factors so far (preconditioner, constraint columns)."""
        return self.solves_before + (0 if self.constraints is None else self.constraints.solves)

    # -- renewal --------------------------------------------------------------------
    def begin_step(self, system: StepSystem) -> None:
        """At a step's start: the factor taken at the start where there is none yet, it was taken for
        another step or it is stale; its solves on the run's threads (as set since it was taken)."""
        if self.preconditioner == "factor" and (self.factor is None or self.factor_h != system.h or self.stale):
            self.refactor(system, system.x0)
        if self.factor is not None:
            self.factor.ldl.threads = self.threads.solve

    def renew(self, system: StepSystem, x: np.ndarray) -> bool:
        """Within a step: the factor taken at *x* with the constraint rows again where it is stale, or at
        every iteration with the "fresh" preconditioner; whether it was (the rows were then set again)."""
        if self.preconditioner == "fresh" or (self.stale and self.preconditioner == "factor"):
            self.refactor(system, x)
            self.set_rows(system)
            return True
        return False

    def age(self, iterations: int) -> None:
        """Count *iterations* lost to the factor's age; it turns stale once they cost more than a new one."""
        self.excess += iterations
        if self.refactor_pays():
            self.stale = True

    def refactor_pays(self) -> bool:
        """Whether the iterations lost to the factor's age since it was taken have cost more than taking
        it again (:meth:`factor_in_solves`)."""
        return self.preconditioner == "factor" and self.excess > self.factor_in_solves()

    def factor_in_solves(self) -> float:
        """What taking the factor again costs (its numeric factorization and constraint columns, as
        measured for the current one), in the current factor's mean solves; infinite before any solve.

        Neither the symbolic analysis, which only the run's first factor does (with the analysis
        kernels' first calls, many numeric factorizations' time) and a renewal reuses, nor the matrix's
        assembly is counted: with the analysis the first factor would look many times dearer than its
        renewals and whether a run renews it would depend on that one timing; with the assembly the
        factor is renewed less often, and the 1 kHz grasper force, predicted from the factor's patch
        stiffness (:mod:`.haptics`), gets less accurate (docs/design/simulator.md, "What is factored,
        and when it is renewed").
        """
        cons, fac = self.constraints, self.factor
        if fac is None or cons is None or cons.solves == 0 or cons.solve_s <= 0.0:
            return math.inf
        return (fac.seconds - fac.analysis_s + cons.columns_s) / (cons.solve_s / cons.solves)

    # -- taking the factor ----------------------------------------------------------
    def refactor(self, system: StepSystem, x: np.ndarray) -> None:
        """Take the factor at *x*: the system's matrix assembled and factored."""
        model = system.model
        self.check_threads()
        if self.coarse_cells is not None:
            fac = self._two_grid(system, x)
        elif self.factored(model) == "mixed":
            fac = self._mixed_factor(system, x)
        else:
            A = self._matrix(system, x)
            if self.perm is None or self.perm.size != A.shape[0]:
                self.perm = node_ordering(A)
            fac = SparseFactor.of(A, self.perm, single=self.single, analysis=self._analysis(),
                                  threads=self.threads.factor)
        fac.ldl.threads = self.threads.solve                 # its solves'
        st = self.stats
        st.factorizations += 1
        st.factor_s += fac.seconds
        st.factor_nnz = fac.nnz
        if self.constraints is not None:
            self.solves_before += self.constraints.solves
        self.factor, self.factor_h = fac, system.h
        self.constraints = (TwoGridConstraints if isinstance(fac, TwoGrid) else Constraints)(fac, model.n_nodes)
        self.stale = False
        self.excess = 0

    def _matrix(self, system: StepSystem, x: np.ndarray):
        """The matrix factored at *x*: the bound's in one compiled pass where the model allows
        (:class:`~.assembly.BoundAssembly`, found once per model), else the system's sparse sums."""
        model = system.model
        if self.factored(model) != "bound":
            return system.matrix(x, bound=False)
        if self._assembly is None or self._assembly[0] is not model:
            self._assembly = (model, BoundAssembly.of(model))
        asm = self._assembly[1]
        return system.matrix(x, bound=True) if asm is None else asm.matrix(system, x)

    def _mixed_factor(self, system: StepSystem, x: np.ndarray) -> MixedFactor:
        """Newton's matrix factored from its parts (:class:`~esmm.pipeline.linalg.linsolve.MixedFactor`):
        the system's matrix without the terms that have ``tangent_parts``, and their ``B^T diag(w) B``
        (fixed dofs' columns of B zero)."""
        model = system.model
        parts = [t for t in model.terms if t is not model.springs and getattr(t, "tangent_parts", None) is not None]
        A = system.matrix(x, bound=False, skip=tuple(parts))
        Bs, ws = zip(*(t.tangent_parts(x) for t in parts))
        B = sps.vstack(Bs).tocsr() @ sps.diags(np.repeat(model.movable, 3).astype(np.float64))
        w = np.concatenate(ws)
        if self.perm is None or self.perm.size != A.shape[0] + B.shape[0]:
            self.perm = mixed_ordering(A, B)
        return MixedFactor.of_parts(A, B, w, self.perm, single=self.single, analysis=self._analysis(),
                                    threads=self.threads.factor)

    def _two_grid(self, system: StepSystem, x: np.ndarray) -> TwoGrid:
        """The two-grid operator of the system's matrix on the parents (:class:`~esmm.pipeline.linalg.twogrid.TwoGrid`),
        with the last one's Galerkin map and coarse analysis; the fixed nodes' rows of the prolongation zero."""
        model = system.model
        if self._prolong is None:
            self._prolong, _ = prolongation(self.coarse_cells, model.n_nodes, model.movable)
        A = system.matrix(x, bound=self.factored(model) == "bound")
        last = self.factor if isinstance(self.factor, TwoGrid) else None
        return TwoGrid.of(A, self._prolong, sweeps=twogrid.SWEEPS, single=self.single,
                          previous=last, threads=self.threads.factor)

    def _analysis(self):
        """The last factor's symbolic analysis (its pattern's: a run's matrices share one), or None."""
        return None if self.factor is None else self.factor.analysis

    # -- constraint rows ------------------------------------------------------------
    def set_rows(self, system: StepSystem) -> None:
        """Constraint rows of the grasp (hard, or coupling springs) and the floor's contacts."""
        cons = self.constraints
        if cons is None:
            return
        model, g_ = system.model, system.control.grasp
        eye = np.eye(3)
        held, normal = system.contact.holds()
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
        cons.set_rows(nodes, es, comp)

    # -- threads --------------------------------------------------------------------
    def check_threads(self) -> None:
        """Two threads given up for one, for the rest of the run, where the last factor's solves on two
        took longer (their median) than a solve on one did in the run's trial (``threads.solo_solve_s``).

        Another process on the second core makes the two threads wait for each other, many times
        longer than a solve on one thread. The median, not the mean: a factor's first solves on two
        threads are slow (the workers waking)."""
        cons, th = self.constraints, self.threads
        if isinstance(self.factor, TwoGrid):    # its applications are not the coarse solves the trial timed
            return
        if th.solve > 1 and cons is not None and cons.apply_s and np.median(cons.apply_s) > th.solo_solve_s:
            th.solve = 1
            self.stats.thread_fallbacks += 1

    def solve_timing(self, threads=(1, 2), *, repeats: int = 7, warm: int = 3) -> dict:
        """Median seconds of a solve with the current factor on each number of *threads* (a random
        right-hand side, alternating; the first *warm* rounds not counted: a sleeping thread's first
        solves are slow). The factor's own setting is restored."""
        fac = self.factor
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
