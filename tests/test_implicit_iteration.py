"""The iteration of one implicit step (pipeline/simulate/implicit_iteration.py) against an independent solver.

One backward-Euler step of a clamped slab of stiffening springs falling from rest under gravity (a
nonlinear system) is solved by :class:`StepSolver` in each of its ways (quasi-Newton on the reused
factor, Newton with conjugate gradients, solves handed over to a fresh factor or to Newton) and by
scipy's MINPACK ``hybr`` on the same residual (finite-difference Jacobian, no tangent): the same
root. The hand-over rule is checked on its own.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.simulate import implicit_iteration
from esmm.pipeline.simulate.contact import FloorContact
from esmm.pipeline.simulate.factorcache import FactorCache
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_iteration import QN_SWITCH, StepSolver
from esmm.pipeline.simulate.implicit_stats import ImplicitStats, Threads
from esmm.pipeline.simulate.implicit_system import StepSystem
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from scipy.optimize import root
from simkit import make_tables


@pytest.fixture(scope="module")
def sim():
    """A 40 x 20 x 10 mm slab of stiffening springs fixed at x = 0, at rest in its rest shape, 1/30 s steps."""
    net = network_from_tets(box_tets(4, 2, 2, (0.04, 0.02, 0.01)))
    p = net.points
    term = build_spring_term(net, make_tables("nonlinear", mu0=2.0e3), dashpot=2e-4)
    s = Simulator(term, p, net.mass, fixed=np.flatnonzero(p[:, 0] < 1e-9), gravity=(0, 0, -9.81),
                  mass_damping=5.0, stepper=BackwardEuler())
    s.set_time_step(1 / 30, bound=s.stepper.bound(s.model, s.control), t0=0.0)
    return s


def system_of(sim):
    contact = FloorContact.begin(sim.model, sim.state, sim.control, rounds=None, stats=ImplicitStats())
    return StepSystem.begin(sim.model, sim.state, sim.control, contact, threads=Threads(), definite=True)


@pytest.fixture(scope="module")
def reference(sim):
    """The step's root by MINPACK on the movable nodes' residual."""
    system = system_of(sim)
    mov = sim.model.movable

    def g(y):
        x = system.x0.copy()
        x[mov] = y.reshape(-1, 3)
        return system.residual(x)[1][mov].ravel()

    sol = root(g, system.x0[mov].ravel(), method="hybr", options={"xtol": 1e-13})
    assert sol.success
    x = system.x0.copy()
    x[mov] = sol.x.reshape(-1, 3)
    return x


def solve_step(sim, *, quasi=True, preconditioner="factor"):
    """One step solved to a tight tolerance from the inertial predictor; (x, solver)."""
    system = system_of(sim)
    stats = ImplicitStats()
    cache = FactorCache(preconditioner, "exact", False, system.threads, stats)
    solver = StepSolver(cache, stats, rtol=1e-9, xtol=1e-13, max_newton=40, quasi=quasi, max_cg=50, cg_rtol=1e-3)
    cache.begin_step(system)
    solver.set_rows(system)
    x = solver.solve(system, system.x0 + system.h * system.v0)
    return x, solver, system


@pytest.mark.parametrize("way", ["quasi-newton", "newton", "fresh", "jacobi", "handed-over-to-a-fresh-factor",
                                 "handed-over-to-newton"])
def test_a_step_is_the_root_of_its_system(sim, reference, monkeypatch, way):
    if way.startswith("handed-over"):
        monkeypatch.setattr(StepSolver, "switch_after", lambda self: 1)
        monkeypatch.setattr(StepSolver, "refresh_pays", lambda self: way.endswith("fresh-factor"))
    quasi = way not in ("newton", "fresh", "jacobi")
    precond = way if way in ("fresh", "jacobi") else "factor"
    x, solver, system = solve_step(sim, quasi=quasi, preconditioner=precond)
    st = solver.stats
    sag = np.abs(reference - system.x0).max()
    assert sag > 1e-4                                                   # a step that moves: 0.1 mm at least
    np.testing.assert_allclose(x, reference, rtol=0, atol=1e-7 * sag)
    assert st.unconverged == 0
    assert (st.quasi_newton > 0) == quasi
    if not quasi or way == "handed-over-to-newton":
        assert st.newton > 0
    if way.startswith("handed-over"):
        # one quasi-Newton iteration before the hand-over, one more on the fresh factor where it pays
        assert st.fallbacks == 1 and st.quasi_newton == (2 if way.endswith("fresh-factor") else 1)
        assert st.factorizations >= (2 if way.endswith("fresh-factor") else 1)
    if way == "fresh":
        assert st.factorizations == st.newton                          # one per Newton iteration
    if way == "jacobi":
        assert st.factorizations == 0


def test_the_first_solve_of_a_step_iterates_once_even_at_its_tolerance(sim):
    """A step from its own root (a predictor already within the tolerance) still takes an iteration."""
    system = system_of(sim)
    stats = ImplicitStats()
    cache = FactorCache("factor", "exact", False, system.threads, stats)
    solver = StepSolver(cache, stats, rtol=1e6)                 # any residual is below this tolerance
    cache.begin_step(system)
    solver.set_rows(system)
    solver.solve(system, system.x0.copy())
    assert stats.quasi_newton == 1 and stats.max_newton == 1


def test_the_hand_over_comes_after_what_hand_overs_cost():
    """QN_SWITCH quasi-Newton iterations before any hand-over was measured; then their mean cost (the
    break-even rule)."""
    solver = StepSolver(FactorCache("factor", "exact", False, Threads(), ImplicitStats()), ImplicitStats())
    assert solver.switch_after() == QN_SWITCH
    solver.handover_cost, solver.handovers = 30.0, 4
    assert solver.switch_after() == 7.5


@pytest.mark.parametrize("cost, pays", [(10.0, True), (4 * 21 - 1e-9, True), (4 * 21, False), (math.inf, False)])
def test_a_fresh_factor_pays_where_it_costs_less_than_newtons_budget(cost, pays):
    """The budget: max_newton iterations of max_cg conjugate gradients and a product each (4 x 21 solves)."""
    cache = FactorCache("factor", "exact", False, Threads(), ImplicitStats())
    cache.factor_in_solves = lambda: cost
    assert StepSolver(cache, ImplicitStats(), max_newton=4, max_cg=20).refresh_pays() == pays
    cache.preconditioner = "fresh"
    assert not StepSolver(cache, ImplicitStats()).refresh_pays()


def test_the_iterations_beyond_the_fresh_ones_age_the_factor(sim, monkeypatch):
    """A step's quasi-Newton iterations beyond QN_FRESH count as the factor's age (here with QN_FRESH 0:
    all of them)."""
    monkeypatch.setattr(implicit_iteration, "QN_FRESH", 0)
    _, solver, _ = solve_step(sim)
    assert solver.cache.excess == solver.stats.quasi_newton > 0


def test_carried_pairs_reach_the_same_root(sim, reference):
    """``carry_pairs``: the pairs of earlier solves kept over steps and contact changes (projected into
    the rows' null space, :meth:`StepSolver.set_rows`): the step's root is the same, the held nodes
    stay where the rows hold them, and the pairs of a first solve are there at the second one's start."""
    system = system_of(sim)
    stats = ImplicitStats()
    cache = FactorCache("factor", "exact", False, system.threads, stats)
    solver = StepSolver(cache, stats, rtol=1e-9, xtol=1e-13, max_newton=40, carry_pairs=True)
    cache.begin_step(system)
    solver.set_rows(system)
    x = solver.solve(system, system.x0 + system.h * system.v0)
    sag = np.abs(reference - system.x0).max()
    np.testing.assert_allclose(x, reference, rtol=0, atol=1e-7 * sag)
    kept = len(solver.qn.pairs)
    assert kept > 0
    solver.set_rows(system)                              # the same rows: every pair carried
    assert len(solver.qn.pairs) == kept
    x2 = solver.solve(system, system.x0 + system.h * system.v0)
    np.testing.assert_allclose(x2, reference, rtol=0, atol=1e-7 * sag)
    assert np.array_equal(x2[~sim.model.movable], system.x0[~sim.model.movable])
