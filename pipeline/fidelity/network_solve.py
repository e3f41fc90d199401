"""The network side: static equilibrium of the spring network under a load case.

:func:`solve_network` is the one function through which ``esmm validate``
solves the network, so that the method can change without touching the
rest. It is Newton's method on the total potential

.. math::

    \\Pi(\\mathbf x) = \\sum_{\\text{terms}} E(\\mathbf x) - t\\,\\mathbf f_g\\cdot\\mathbf x,

(the springs' potential, :func:`~esmm.pipeline.network.forcelaw.spring_energy`, of
the same tables and force law the simulator uses, plus any further term such as
the volume term) with the exact sparse tangent, the gravity
``f_g = m_i g`` on the network's own lumped masses and the case's Dirichlet
constraints, reached with the load factor t in steps. Each step starts from
the linear predictor (the tangent applied to the prescribed increment), takes
Newton iterations with an Armijo line search on Π (the tangent shifted towards
positive definite when it is not) and is halved when it fails. Its answer is
the simulator's static equilibrium (``Simulator.relax``, FIRE, on the same
forces), to a far tighter tolerance (test: tests/test_fidelity.py).

A term is any object with ``energy(x) -> float`` [J], ``forces(x) -> (n, 3)``
[N] (= −∇E) and ``tangent(x) -> sparse (3n, 3n)`` [N/m] (∇²E):
:class:`SpringPotential` wraps the springs.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..blas import single_threaded_blas
from ..errors import SimulationError
from ..linalg.newton import at_round_off, descent_direction, free_order
from ..linalg.supernodal import LDLT, ZeroPivot, canonical
from ..network import forcelaw
from ..network.springs import tet_volumes
from ..progress import ensure
from .cases import LoadCase
from .solution import Solution, start_scale

__all__ = ["SpringPotential", "solve_network"]


class SpringPotential:
    """The springs of a network with their tables and force law, as a term of the potential."""

    def __init__(self, network, tables, *, law: str | None = None):
        self.network, self.tables = network, tables
        self.law = tables.check_law(law)

    def energy(self, x: np.ndarray) -> float:
        return forcelaw.spring_energy(x, self.network, self.tables, law=self.law)

    def forces(self, x: np.ndarray) -> np.ndarray:
        return forcelaw.spring_forces(x, self.network, self.tables, law=self.law)

    def tangent(self, x: np.ndarray):
        return forcelaw.tangent_stiffness(x, self.network, self.tables, law=self.law)


class _Problem:
    """The potential of the terms and gravity at load factor t, on the free degrees of freedom."""

    def __init__(self, case: LoadCase, terms, mass, start: Solution | None = None):
        self.terms = terms
        self.X = np.asarray(case.points, dtype=np.float64)
        self.fg = np.asarray(mass, dtype=np.float64)[:, None] * np.asarray(case.gravity)[None, :]
        self.mask, self.u = case.prescribed()
        self.free = ~self.mask.ravel()
        self.t = 0.0
        self.order = None                 # of the free dofs, from the first tangent (the pattern stays)
        self.analysis = None              # the LDLᵀ's symbolic analysis of the free tangent's pattern
        self.factorizations = 0
        # The path: from rest (gravity off) or from *start* (its gravity, prescribed values where they are).
        self.g0 = start_scale(start, case.gravity)
        self.u0 = np.zeros_like(self.u) if start is None else start.displacement

    def scale(self, t: float) -> float:
        """Gravity's factor at load factor *t*."""
        return self.g0 + t * (1.0 - self.g0)

    def energy(self, x) -> float:
        return sum(term.energy(x) for term in self.terms) - self.scale(self.t) * float(np.sum(self.fg * x))

    def forces(self, x) -> np.ndarray:
        """Total force on every node (terms + gravity), shape (n, 3) [N]."""
        return sum(term.forces(x) for term in self.terms) + self.scale(self.t) * self.fg

    def tangent(self, x):
        return sum(term.tangent(x) for term in self.terms).tocsr()

    def direction(self, K, g):
        """Newton direction ``-K_ff^-1 g`` of the whole tangent *K* (shifted towards positive definite when needed) or None.

        The free tangent is factored by esmm's supernodal LDLᵀ in its nested-dissection order, the
        symbolic analysis kept while its pattern stays (:mod:`.linear`); when that gives no descent
        direction at round-off, :func:`~esmm.pipeline.linalg.newton.descent_direction` (SuperLU, the
        LU with pivoting, the shifts) decides."""
        self.factorizations += 1
        if self.order is None:
            self.order = free_order(K, self.free)
        Kff = canonical(K[self.free][:, self.free])
        try:
            with single_threaded_blas():
                fac = LDLT.of(Kff, self.analysis, perm=self.order)
            self.analysis = fac.analysis
            x = fac.solve(g)
            if at_round_off(Kff, x, g) and float(g @ x) > 0:
                return -x
        except ZeroPivot:
            pass
        return descent_direction(Kff, g, order=self.order)[0]

    def residual_scale(self, x) -> float:
        g = self.scale(self.t) * self.fg
        return max(float(np.abs(self.forces(x) - g).max()), float(np.abs(g).max()), 1e-300)

    def at(self, x, t: float) -> np.ndarray:
        """*x* with the prescribed components at load factor *t*."""
        out = x.copy()
        out[self.mask] = (self.X + self.u0 + t * (self.u - self.u0))[self.mask]
        return out


def _newton(pb: _Problem, x, rtol: float, max_iter: int):
    """Equilibrium at fixed prescribed values from *x*; ``(converged, x, iterations)``."""
    free = pb.free
    E = pb.energy(x)
    for it in range(1, max_iter + 1):
        g = -pb.forces(x).ravel()[free]
        if not np.all(np.isfinite(g)) or not math.isfinite(E):
            return False, x, it
        if g.size == 0 or float(np.abs(g).max()) <= rtol * pb.residual_scale(x):
            return True, x, it - 1
        d = pb.direction(pb.tangent(x), g)
        if d is None:
            return False, x, it
        a, slope = 1.0, float(g @ d)
        while a >= 1e-8:
            xt = x.copy().ravel()
            xt[free] += a * d
            xt = xt.reshape(-1, 3)
            Et = pb.energy(xt)
            if math.isfinite(Et) and (Et <= E + 1e-4 * a * slope or abs(Et - E) <= 1e-13 * abs(E)):
                break
            a *= 0.5
        else:
            return False, x, it
        x, E = xt, Et
    return False, x, max_iter


def _predict(pb: _Problem, x, t_new: float):
    """The linear predictor: prescribed values moved to *t_new*, free ones by the tangent's answer."""
    xn = pb.at(x, t_new)
    dp = (xn - x).ravel()
    if not np.any(dp):
        return xn
    free = pb.free
    K = pb.tangent(x)
    g = -(pb.forces(x) + (pb.scale(t_new) - pb.scale(pb.t)) * pb.fg).ravel()[free] + K[free][:, ~free] @ dp[~free]
    d = pb.direction(K, g)
    if d is None:
        return xn
    out = xn.ravel()
    out[free] += d
    return out.reshape(-1, 3)


def solve_network(case: LoadCase, network, tables, *, law: str | None = None, terms=(), steps: int = 8,
                  rtol: float = 1e-9, max_iter: int = 40, max_cuts: int = 12, start: Solution | None = None,
                  reporter=None) -> Solution:
    """Static equilibrium of *network* under *case* (Newton on the potential, load stepping).

    Parameters
    ----------
    case : LoadCase
        On the network's own nodes (``case.points`` are ``network.points``).
    network : SpringNetwork
    tables : StiffnessTables
        With their volume factor and stretch correction.
    law : {"secant", "energy"}, optional
        Default: the tables' own.
    terms : sequence
        Further terms of the potential (``energy``, ``forces``, ``tangent``):
        the volume term.
    steps : int
        Load steps (equal increments of the load factor, halved on failure).
    rtol : float
        Converged when the largest free residual force is below *rtol* times
        the largest term or gravity force.
    start : Solution, optional
        A network solution of the same case with fewer constraints (a
        previous round of the floor's active set): the solve starts there
        with gravity on and moves the prescribed values from where they are
        to the case's.

    Returns
    -------
    Solution

    Raises
    ------
    SimulationError
        No equilibrium after *max_cuts* step halvings.
    """
    rep = ensure(reporter)
    t_start = time.perf_counter()
    springs = SpringPotential(network, tables, law=law)
    pb = _Problem(case, (springs, *terms), network.mass, start)
    x = pb.X + pb.u0
    t, dt, cuts, iterations, done = 0.0, 1.0 / max(1, int(steps)), 0, 0, 0
    with rep.task(f"network {case.name} ({network.n_springs} springs)", total=1.0) as advance:
        while t < 1.0 - 1e-12:
            t1 = min(1.0, t + dt)
            trial = _predict(pb, x, t1)
            pb.t = t1
            ok, trial, its = _newton(pb, trial, rtol, max_iter)
            iterations += its
            if not ok:
                pb.t = t
                cuts += 1
                if cuts > max_cuts:
                    raise SimulationError(
                        f"network: no equilibrium for case {case.name!r} at load factor {t1:.4g} after "
                        f"{max_cuts} step halvings; the network may have a mechanism or collapse under this load")
                dt /= 2.0
                continue
            x = trial
            advance(t1 - t)
            t, done = t1, done + 1
    f = pb.forces(x)
    reactions = {c.name: f[c.nodes].sum(axis=0) for c in case.constraints}
    V = tet_volumes(case.points, case.tets)
    J = tet_volumes(x, case.tets) / V
    return Solution(solver="network", displacement=x - pb.X, reactions=reactions,
                    volume_ratio=float(np.sum(J * V) / np.sum(V)), element_J=J,
                    gravity=np.asarray(case.gravity, dtype=np.float64).copy(),
                    info={"law": springs.law, "volume_factor": float(tables.volume_factor),
                          "terms": ["springs"] + [type(tm).__name__ for tm in terms], "load_steps": done,
                          "step_cuts": cuts, "newton_iterations": iterations,
                          "factorizations": pb.factorizations,
                          "warm_start": start is not None, "seconds": time.perf_counter() - t_start})

