"""The implicit stepper's reused factor (pipeline/simulate/factorcache.py): what it is taken of, when it
is renewed, its constraint rows and its threads.

The renewal rule weighs measured times; a fake clock (every ``time.perf_counter`` call one tick later)
makes them exact here: a solve costs one tick, and the factor's cost in solves is known.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.volume import VolumeSpec
from esmm.pipeline.simulate.contact import FloorContact
from esmm.pipeline.simulate.factorcache import FactorCache
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_stats import ImplicitStats, Threads
from esmm.pipeline.simulate.implicit_system import StepSystem
from esmm.pipeline.simulate.model import Floor, Grasp
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.volumeterm import build_volume_term
from simkit import make_tables

TICK = 1e-3


class Clock:
    """A ``perf_counter`` that advances one tick at each call."""

    def __init__(self):
        self.calls = 0

    def __call__(self) -> float:
        self.calls += 1
        return self.calls * TICK


def slab(*, volume=False, floor=None, grasp_mode=None, dt=1 / 30):
    """A small slab fixed at x = 0 (optionally with a volume term, a floor, a grasp of its free end's top)."""
    net = network_from_tets(box_tets(4, 2, 2, (0.04, 0.02, 0.01)))
    p = net.points
    tables = make_tables()
    vol = build_volume_term(p, net.tets, VolumeSpec(1e5), lam_max=tables.lam_max) if volume else None
    sim = Simulator(build_spring_term(net, tables), p, net.mass, fixed=np.flatnonzero(p[:, 0] < 1e-9),
                    gravity=(0, 0, -9.81), volume=vol, floor=floor, stepper=BackwardEuler())
    if grasp_mode is not None:
        nodes = np.flatnonzero((p[:, 0] > p[:, 0].max() - 1e-9) & (p[:, 2] > p[:, 2].max() - 1e-9))
        sim.attach(Grasp(nodes=nodes, offsets=np.zeros((nodes.size, 3)), wp_t=np.array([0.0, 1.0]),
                         wp_x=np.repeat(p[nodes].mean(axis=0, keepdims=True), 2, axis=0), mode=grasp_mode,
                         stiffness=None if grasp_mode == "prescribed" else np.full(nodes.size, 50.0)),
                   check_step=False)
    sim.set_time_step(dt, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    return sim


def system_of(sim, threads=None):
    contact = FloorContact.begin(sim.model, sim.state, sim.control, rounds=None, stats=ImplicitStats())
    return StepSystem.begin(sim.model, sim.state, sim.control, contact, threads=threads or Threads(), definite=True)


def cache_of(preconditioner="factor", factor_matrix="bound", threads=None):
    return FactorCache(preconditioner, factor_matrix, False, threads or Threads(), ImplicitStats())


def use(cache, n, solves=5):
    """*solves* preconditioner solves with the cache's factor."""
    rng = np.random.default_rng(0)
    for _ in range(solves):
        cache.constraints.apply(rng.normal(size=3 * n))


def test_the_factor_is_renewed_when_its_age_costs_more_than_a_new_one_and_not_before(monkeypatch):
    """The factor's cost in solves is its numeric factorization and constraint columns over a mean
    solve (the first factor's symbolic analysis left out); iterations lost to its age up to that cost
    keep it, one more makes it stale, and the next step renews it (reusing the analysis)."""
    clock = Clock()
    monkeypatch.setattr(time, "perf_counter", clock)
    sim = slab(grasp_mode="prescribed")
    system = system_of(sim)
    cache = cache_of()
    cache.begin_step(system)                                   # the first factor
    assert cache.stats.factorizations == 1 and cache.factor.analysis_s > 0
    cache.set_rows(system)
    use(cache, sim.model.n_nodes)
    fac, cons = cache.factor, cache.constraints
    assert cons.solve_s == pytest.approx(5 * TICK)             # each preconditioner solve: one tick
    cost = cache.factor_in_solves()
    # the mean over the solves counted, the constraint columns' among them
    assert cost == pytest.approx((fac.seconds - fac.analysis_s + cons.columns_s) / (5 * TICK / cons.solves))
    assert 0 < cost < (fac.seconds + cons.columns_s) / (5 * TICK / cons.solves)   # the analysis is not counted
    cache.age(math.floor(cost))
    assert not cache.stale and not cache.refactor_pays()
    cache.begin_step(system)
    assert cache.stats.factorizations == 1 and cache.factor is fac       # kept
    cache.age(1)
    assert cache.stale
    cache.begin_step(system)
    assert cache.stats.factorizations == 2 and cache.factor is not fac   # renewed
    assert not cache.stale and cache.excess == 0
    assert cache.factor.analysis is fac.analysis and cache.factor.analysis_s == 0.0


def test_before_any_solve_the_factor_is_kept_whatever_the_iterations_lost(monkeypatch):
    monkeypatch.setattr(time, "perf_counter", Clock())
    sim = slab()
    cache = cache_of()
    cache.begin_step(system_of(sim))
    assert cache.factor_in_solves() == math.inf
    cache.age(10**6)
    assert not cache.stale


def test_a_factor_for_another_step_is_renewed():
    sim = slab()
    cache = cache_of()
    cache.begin_step(system_of(sim))
    cache.begin_step(system_of(sim))
    assert cache.stats.factorizations == 1
    sim.set_time_step(1e-3, bound=sim.stepper.bound(sim.model, sim.control))
    cache.begin_step(system_of(sim))
    assert cache.stats.factorizations == 2 and cache.factor_h == 1e-3


def test_fresh_factors_at_every_iteration_and_jacobi_factors_nothing():
    sim = slab()
    system = system_of(sim)
    fresh = cache_of("fresh")
    fresh.begin_step(system)
    assert fresh.factor is None                               # taken by the iterations
    assert fresh.renew(system, system.x0) and fresh.renew(system, system.x0)
    assert fresh.stats.factorizations == 2
    factor = cache_of("factor")
    factor.begin_step(system)
    assert not factor.renew(system, system.x0)                 # not stale
    factor.stale = True
    assert factor.renew(system, system.x0) and factor.stats.factorizations == 2
    jacobi = cache_of("jacobi")
    jacobi.begin_step(system)
    jacobi.age(10**6)
    assert jacobi.factor is None and not jacobi.stale and not jacobi.renew(system, system.x0)
    assert jacobi.solves() == 0


def test_solves_are_counted_over_renewals():
    sim = slab()
    system = system_of(sim)
    cache = cache_of()
    cache.begin_step(system)
    use(cache, sim.model.n_nodes, solves=3)
    cache.stale = True
    cache.begin_step(system)
    use(cache, sim.model.n_nodes, solves=2)
    assert cache.solves() == 5


@pytest.mark.parametrize("factor_matrix", ["bound", "exact", "mixed"])
def test_what_is_factored(factor_matrix):
    """The bound or the mixed factor where a term has them (the volume term); else Newton's matrix."""
    with_volume, springs_only = slab(volume=True), slab()
    assert cache_of(factor_matrix=factor_matrix).factored(with_volume.model) == factor_matrix
    assert cache_of(factor_matrix=factor_matrix).factored(springs_only.model) == "exact"
    assert cache_of("fresh", factor_matrix).factored(with_volume.model) == "exact"
    cache = cache_of(factor_matrix=factor_matrix)
    cache.begin_step(system_of(with_volume))
    exact = cache_of(factor_matrix="exact")
    exact.begin_step(system_of(with_volume))
    if factor_matrix == "exact":
        assert cache.factor.nnz == exact.factor.nnz
    else:
        assert cache.factor.nnz < exact.factor.nnz             # less fill than Newton's matrix itself


@pytest.mark.parametrize("mode", ["prescribed", "spring"])
def test_constraint_rows_of_the_grasp_and_the_floor(mode):
    """Each grasped node: three rows along the axes (hard, or the coupling spring's compliance 1/k);
    each contact held in place: three hard rows; each sliding contact: one hard row along the normal."""
    fl = Floor(normal=np.array([0.0, 0.0, 1.0]), height=0.0, friction="stick")
    sim = slab(floor=fl, grasp_mode=mode)
    bottom = np.flatnonzero((sim.x[:, 2] < 1e-9) & sim.model.movable)[:3]
    sim.state.contact[bottom] = 1
    system = system_of(sim)
    system.contact.slides.sliding[bottom[0]] = True
    cache = cache_of()
    cache.begin_step(system)
    cache.set_rows(system)
    cons, g = cache.constraints, sim.control.grasp
    held = bottom[1:]
    np.testing.assert_array_equal(cons.node, np.concatenate([np.repeat(g.nodes, 3), np.repeat(held, 3), bottom[:1]]))
    np.testing.assert_array_equal(cons.e, np.vstack([np.tile(np.eye(3), (g.nodes.size + held.size, 1)), fl.normal]))
    comp = np.zeros(cons.node.size)
    if mode == "spring":
        comp[:3 * g.nodes.size] = 1 / 50.0
    np.testing.assert_array_equal(cons.comp, comp)
    # the preconditioner keeps the hard rows: held nodes do not move, the sliding one only along the plane
    z = cons.apply(np.random.default_rng(1).normal(size=3 * sim.model.n_nodes)).reshape(-1, 3)
    assert np.abs(z[held]).max() < 1e-12 * np.abs(z).max()
    assert abs(z[bottom[0], 2]) < 1e-12 * np.abs(z).max() and np.abs(z[bottom[0], :2]).max() > 0


@pytest.mark.parametrize("solo, expected", [(0.5 * TICK, 1), (2 * TICK, 2), (math.nan, 2)])
def test_two_threads_fall_back_to_one_at_a_renewal_where_their_solves_got_slower(solo, expected):
    """The median of the last factor's solves on two threads against a solve on one in the run's trial
    (here the solves' times are set: a tick each); NaN: no trial, never."""
    th = Threads(solve=2, solo_solve_s=solo)
    sim = slab()
    cache = cache_of(threads=th)
    cache.begin_step(system_of(sim, th))
    assert th.solve == 2 and cache.factor.ldl.threads == 2         # no solve yet: nothing to weigh
    cache.constraints.apply_s[:] = [10 * TICK, TICK, TICK]        # a slow first one: the median is one tick
    cache.stale = True
    cache.begin_step(system_of(sim, th))
    assert th.solve == expected and cache.factor.ldl.threads == expected
    assert cache.stats.thread_fallbacks == (expected == 1)
