"""What the implicit stepper counts (:class:`ImplicitStats`) and the threads it runs on (:class:`Threads`).

Both are shared, by reference, by the parts of the stepper (:mod:`.implicit`): its iteration
(:mod:`.implicit_iteration`), its factor cache (:mod:`.factorcache`), the floor's contacts
(:mod:`.contact`) and the step's system (:mod:`.implicit_system`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


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
    thread_fallbacks: int = 0       #: two threads given up for one (:meth:`.factorcache.FactorCache.check_threads`)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Threads:
    """The threads of an implicit run (set by the run's setup, :mod:`.runsetup`).

    Attributes
    ----------
    solve : int
        Threads of the factor's solves (1, or 2: the two halves of the nested dissection at once,
        :mod:`esmm.pipeline.linalg.supernodal`) and of the force pass (2: the springs on one, a volume
        term on the other). The rest of the step runs on one thread.
    factor : int
        Threads of the factorizations (1 or 2, the same halves): long enough that the workers' wake-up
        does not count, unlike a solve's.
    solo_solve_s : float
        A solve's time on one thread, measured where the run's setup chose two: if two threads' solves
        get slower than that, the run goes on with one (:meth:`.factorcache.FactorCache.check_threads`).
        NaN: never.
    """

    solve: int = 1
    factor: int = 1
    solo_solve_s: float = math.nan
