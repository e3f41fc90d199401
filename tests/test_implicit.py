"""The implicit stepper: the tangent stiffness, the linear algebra, and the comparison with the explicit reference.

The explicit stepper (symplectic Euler under its stability bound) is the
accuracy reference; the implicit one (backward Euler, docs/design/simulator.md) is
compared with it on the same network, start and damping.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numba
import numpy as np
import pytest
import scipy.sparse as sps
from esmm.pipeline.linalg import supernodal
from esmm.pipeline.linalg.linsolve import Constraints, SparseFactor, pcg
from esmm.pipeline.materials.effects import (
    DamageEffect,
    MaterialEffects,
    MullinsEffect,
    ViscoelasticEffect,
)
from esmm.pipeline.mesh.refine import split_in_eight
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.forcelaw import tangent_stiffness
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.tables import StiffnessTables
from esmm.pipeline.progress import ListReporter
from esmm.pipeline.simulate import implicit_iteration, runsetup
from esmm.pipeline.simulate import kernels as K
from esmm.pipeline.simulate.factorcache import FactorCache
from esmm.pipeline.simulate.history import History
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_iteration import QuasiNewton, StepSolver
from esmm.pipeline.simulate.model import Floor, Grasp
from esmm.pipeline.simulate.run import simulate_network
from esmm.pipeline.simulate.scene import ITERATIONS, scene_from_dict
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.stepper import SymplecticEuler, stable_step
from scipy.linalg import eigh
from simkit import make_tables as simkit_tables


def make_tables(mu0=2.0e4, aniso=True):
    """Stiffening tables, different per fibre direction (or the same: *aniso* False)."""
    return simkit_tables("nonlinear" if aniso else "stiffening", mu0=mu0)


@pytest.fixture(scope="module")
def box():
    return network_from_tets(box_tets(4, 3, 3, (0.04, 0.03, 0.03)))


@pytest.fixture(scope="module")
def slab():
    """A 60 x 20 x 15 mm slab, fixed at x = 0."""
    net = network_from_tets(box_tets(8, 3, 2, (0.06, 0.02, 0.015)))
    return net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))


def deformed(net, scale=0.08, seed=0):
    rng = np.random.default_rng(seed)
    size = np.ptp(net.points, axis=0).max()
    return net.points + rng.normal(scale=scale * size / 10, size=net.points.shape)


# ---------------------------------------------------------------------------
# the tangent stiffness
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("law", ["secant", "energy"])
@pytest.mark.parametrize("aniso", [True, False])
def test_tangent_matches_the_reference_hessian(box, law, aniso):
    tables = make_tables(aniso=aniso)
    term = build_spring_term(box, tables, law=law)
    x = deformed(box)
    Kt = term.tangent(x)
    ref = tangent_stiffness(x, box, tables, law=law)
    assert Kt.shape == (3 * box.n_nodes,) * 2
    assert abs(Kt - ref).max() <= 1e-9 * abs(ref).max()
    assert abs(Kt - Kt.T).max() == 0.0


def fd_check(term, x, **forces_kw):
    """Largest relative difference between K dx and the central difference of the compiled forces."""
    rng = np.random.default_rng(3)
    Kt = term.tangent(x, **{k: v for k, v in forces_kw.items() if k in ("state", "dt", "mode")})
    worst = 0.0
    for _ in range(3):
        d = rng.normal(size=x.shape)
        d /= np.abs(d).max()
        eps = 1e-8 * np.ptp(x)
        fd = -(term.forces(x + eps * d, **forces_kw) - term.forces(x - eps * d, **forces_kw)).ravel() / (2 * eps)
        kd = Kt @ d.ravel()
        worst = max(worst, np.abs(fd - kd).max() / np.abs(kd).max())
    return worst


@pytest.mark.parametrize("law", ["secant", "energy"])
def test_tangent_is_the_derivative_of_the_compiled_forces(box, law):
    term = build_spring_term(box, make_tables(), law=law)
    # Off the cell boundaries (where the tables' slope jumps) the difference is rounding only.
    assert fd_check(term, deformed(box, scale=0.03)) < 2e-3


@pytest.mark.parametrize("floor", [0.0, 0.6])
def test_tangent_with_effects_follows_their_factors(box, floor):
    """QLV's instantaneous factor, Mullins reloading and damage on its primary path (with and without a
    floor), against finite differences."""
    tables = make_tables()
    fx = MaterialEffects(ViscoelasticEffect((0.3, 0.2), (0.05, 0.5)), MullinsEffect(2.0, 2.0, 0.1),
                         DamageEffect(1.02, 0.05, 2.0, floor))
    term = build_spring_term(box, tables, effects=fx)
    x = deformed(box, scale=0.03)
    state = term.new_state()
    # Load beyond x first (maxima above the current stretches: Mullins reloads), then come back.
    far = box.points + 1.6 * (x - box.points)
    term.forces(far, state=state, mode=K.FX_STEP, dt=1e-3)
    err = fd_check(term, x, state=state, dt=2e-3, mode=K.FX_PEEK)
    assert err < 2e-3
    # The factors matter: the elastic tangent alone is off by far more.
    plain = build_spring_term(box, tables)
    d = np.random.default_rng(1).normal(size=x.shape).ravel()
    a, b = term.tangent(x, state=state, dt=2e-3) @ d, plain.tangent(x) @ d
    assert np.abs(a - b).max() > 0.05 * np.abs(b).max()


def test_definite_tangent_is_positive_semidefinite(box):
    term = build_spring_term(box, make_tables())
    x = box.points * np.array([1.0, 1.0, 0.7])          # squeezed: compressed springs, negative F/L
    true = term.tangent(x).toarray()
    fixed = term.tangent(x, definite=True).toarray()
    assert np.linalg.eigvalsh(true).min() < -1e-6 * np.abs(true).max()
    assert np.linalg.eigvalsh(fixed).min() > -1e-9 * np.abs(fixed).max()


def test_damping_matrix_gives_the_dashpot_forces(box):
    term = build_spring_term(box, make_tables(), dashpot=1e-3)
    x = deformed(box, scale=0.02)
    v = np.random.default_rng(2).normal(size=x.shape) * 0.01
    f_d = term.forces(x, v) - term.forces(x)
    np.testing.assert_allclose(-(term.damping_matrix(x) @ v.ravel()), f_d.ravel(), atol=1e-12 * np.abs(f_d).max())


# ---------------------------------------------------------------------------
# the linear algebra
# ---------------------------------------------------------------------------

def spd_system(box):
    term = build_spring_term(box, make_tables())
    A = term.tangent(deformed(box, scale=0.02), definite=True) + sps.diags(np.repeat(box.mass, 3) * 900.0)
    return A.tocsr()


@pytest.mark.parametrize("single", [False, True])
def test_factor_solves(box, single):
    A = spd_system(box)
    fac = SparseFactor.of(A, single=single)
    b = np.random.default_rng(0).normal(size=(A.shape[0], 5))
    y = fac.solve(b)
    assert np.linalg.norm(A @ y - b) <= (1e-4 if single else 1e-10) * np.linalg.norm(b)
    assert fac.nnz < A.shape[0] ** 2 / 2


def test_constraints_hold_and_pcg_converges(box):
    A = spd_system(box)
    cons = Constraints(SparseFactor.of(A), box.n_nodes)
    n = np.array([0.0, 0.6, 0.8])
    cons.set_rows(np.array([0, 0, 0, 5]), np.vstack([np.eye(3), n]), np.zeros(4))
    z = cons.apply(np.random.default_rng(1).normal(size=A.shape[0]))
    np.testing.assert_allclose(z[:3], 0.0, atol=1e-12)
    assert abs(z[15:18] @ n) < 1e-12 * np.abs(z).max()
    # PCG in the constraints' null space solves the constrained problem exactly (direct preconditioner)
    b = np.random.default_rng(2).normal(size=A.shape[0])
    y, its, ok = pcg(lambda p: A @ p, cons.apply, b, rtol=1e-10, max_iter=20)
    assert ok and its <= 3
    r = (A @ y - b).reshape(-1, 3)
    r[0] = 0.0
    r[5] -= (r[5] @ n) * n
    assert np.abs(r).max() < 1e-8 * np.abs(b).max()


def test_constraints_keep_their_matrices_for_the_same_rows_and_rebuild_for_others(box):
    """Rows set again as they are (a step whose grasp and contacts did not change) keep Y and the
    capacitance inverse; other rows (or a compliance changed) rebuild them, as a fresh object would
    (Y exactly; the capacitance from the entries of the rows kept and those of the new rows, to
    rounding)."""
    A = spd_system(box)
    fac = SparseFactor.of(A)
    cons = Constraints(fac, box.n_nodes)
    rows = (np.array([0, 0, 0, 5]), np.vstack([np.eye(3), [0.0, 0.6, 0.8]]), np.zeros(4))
    cons.set_rows(*rows)
    Y, cap = cons.Y, cons.cap_inv
    cons.set_rows(*(np.copy(a) for a in rows))
    assert cons.Y is Y and cons.cap_inv is cap
    for node, e, comp in [(rows[0][:3], rows[1][:3], rows[2][:3]), (rows[0], rows[1], np.array([0, 0, 0, 1e-3]))]:
        cons.set_rows(node, e, comp)
        fresh = Constraints(fac, box.n_nodes)
        fresh.set_rows(node, e, comp)
        assert cons.Y is not Y
        np.testing.assert_array_equal(cons.R, fresh.R)
        np.testing.assert_array_equal(cons.Y, fresh.Y)
        np.testing.assert_allclose(cons.cap_inv, fresh.cap_inv, rtol=0, atol=1e-12 * np.abs(fresh.cap_inv).max())
        Y = cons.Y
    # rows coming and going in any order: the capacitance is the one of the rows in use
    n = np.array([0.0, 0.6, 0.8])
    for node in ([3, 5, 7], [7, 3, 9, 11], [11, 2, 5], [2]):
        node = np.array(node)
        e = np.tile(n, (node.size, 1))
        cons.set_rows(node, e, np.zeros(node.size))
        fresh = Constraints(fac, box.n_nodes)
        fresh.set_rows(node, e, np.zeros(node.size))
        np.testing.assert_allclose(cons.cap_inv, fresh.cap_inv, rtol=0, atol=1e-12 * np.abs(fresh.cap_inv).max())


def test_constraints_project_into_their_hard_rows_null_space(box):
    """``project`` removes a vector's components along the hard rows (a node held in place, another
    along a normal) and leaves the coupling springs' rows (compliance > 0) and the other nodes alone."""
    cons = Constraints(SparseFactor.of(spd_system(box)), box.n_nodes)
    nrm = np.array([0.0, 0.6, 0.8])
    cons.set_rows(np.array([0, 0, 0, 5, 7]), np.vstack([np.eye(3), nrm, [1.0, 0.0, 0.0]]),
                  np.array([0.0, 0.0, 0.0, 0.0, 1e-3]))
    z = np.random.default_rng(4).normal(size=3 * box.n_nodes)
    p = cons.project(z).reshape(-1, 3)
    zz = z.reshape(-1, 3)
    assert not p[0].any()
    assert p[5] @ nrm == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(p[5], zz[5] - (zz[5] @ nrm) * nrm, rtol=1e-14)
    keep = np.ones(box.n_nodes, bool)
    keep[[0, 5]] = False
    np.testing.assert_array_equal(p[keep], zz[keep])


@pytest.mark.parametrize("kind", ["sparse", "mixed", "two-threads", "float32"])
def test_constraints_apply_the_capacitance_formula(box, kind):
    """The correction between the two halves of a solve is ``(P^-1 - W C^-1 W^T) r`` with
    ``W = P^-1 J^T`` and ``C = J W + D_c``, computed here with dense matrices (hard rows, a normal
    row and a coupling spring's compliance); the grasped patch's stiffness is C^-1's block. A float32
    factor (the stepper's) makes the correction in float32: a preconditioner to its precision."""
    from esmm.pipeline.linalg.linsolve import MixedFactor

    A = spd_system(box)
    N = A.shape[0]
    if kind == "mixed":                        # a saddle point: A + B^T diag(w) B, B one row per node
        rng = np.random.default_rng(4)
        B = sps.random(box.n_nodes, N, density=0.01, random_state=5, format="csr")
        w = rng.uniform(1.0, 2.0, box.n_nodes)
        fac = MixedFactor.of_parts(A, B, w)
        P = (A + B.T @ sps.diags(w) @ B).toarray()
    else:
        fac = SparseFactor.of(A, threads=2 if kind == "two-threads" else 1, single=kind == "float32")
        P = A.toarray()
    node = np.array([0, 0, 0, 5, 9])
    e = np.vstack([np.eye(3), [0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    comp = np.array([0.0, 0.0, 0.0, 0.0, 1e-4])
    cons = Constraints(fac, box.n_nodes)
    cons.set_rows(node, e, comp)
    J = np.zeros((node.size, N))
    for m, (a, d) in enumerate(zip(node, e)):
        J[m, 3 * a:3 * a + 3] = d
    W = np.linalg.solve(P, J.T)
    C = J @ W + np.diag(comp)
    tol = 1e-4 if kind == "float32" else 1e-9
    np.testing.assert_allclose(cons.cap_inv, np.linalg.inv(C), rtol=10 * tol)
    r = np.random.default_rng(6).normal(size=N)
    ref = np.linalg.solve(P, r) - W @ np.linalg.solve(C, W.T @ r)
    z = cons.apply(r)
    assert np.abs(z - ref).max() <= tol * np.abs(ref).max()
    assert cons.solves == 1
    np.testing.assert_allclose(cons.block_stiffness(np.arange(3)), np.linalg.inv(C)[:3, :3], rtol=10 * tol)


def test_hard_rows_are_projected_out_at_once_as_one_after_the_other(box):
    """The preconditioner's last projection removes each hard row's component: all at once when each
    node's rows are orthonormal (the same as in turn), in turn otherwise."""
    A = spd_system(box)
    rng = np.random.default_rng(3)
    n = np.array([0.0, 0.6, 0.8])
    skew = np.array([[1.0, 0.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]])
    for rows, e in (([0, 0, 0, 5, 7], np.vstack([np.eye(3), n, n])), ([2, 2], skew)):
        cons = Constraints(SparseFactor.of(A), box.n_nodes)
        cons.set_rows(np.array(rows), e, np.zeros(len(rows)))
        zz = rng.normal(size=(box.n_nodes, 3))
        ref = zz.copy()
        for a, d in zip(rows, e):
            ref[a] -= (ref[a] @ d) * d
        cons._project_hard(zz)
        np.testing.assert_allclose(zz, ref, rtol=0, atol=1e-14)
        assert cons._hard[2] == (rows[0] == 0)


# ---------------------------------------------------------------------------
# steps: stability and the explicit reference
# ---------------------------------------------------------------------------

DECAY = 30.0        # 1/s: mass-proportional damping of the comparison (both steppers)
LIFT = 0.6          # s: the lift's duration: slow against the slab's first mode (~60 rad/s), as an
                    # organ's (~5 rad/s, docs/design/simulator.md, "Numerical damping and stability") is against
                    # the frame step


def lift(slab, tables, stepper, *, frames=24, dt=None, floor=None, rise=0.002):
    """Settle under gravity, grasp the free end's top and lift it *rise* (2 mm) in LIFT s; (times, forces,
    frames of x, sim)."""
    term = build_spring_term(slab, tables, dashpot=2e-4)
    sim = Simulator(term, slab.points, slab.mass, fixed=slab.fixed, gravity=(0, 0, -9.81), mass_damping=DECAY,
                    stepper=stepper, floor=floor)
    sim.relax(rtol=1e-9)
    p = slab.points
    nodes = np.flatnonzero((p[:, 0] > p[:, 0].max() - 1e-9) & (p[:, 2] > p[:, 2].max() - 1e-9))
    tip0 = sim.x[nodes].mean(axis=0)
    # a smooth path (as a hand moves a haptic device): 2 mm up in LIFT s, velocity zero at both ends
    s = np.linspace(0.0, 1.0, 21)
    sim.attach(Grasp(nodes=nodes, offsets=sim.x[nodes] - tip0, wp_t=LIFT * s,
                     wp_x=tip0 + np.outer(s * s * (3 - 2 * s), [0, 0, rise])), check_step=False)
    step = (1 / 30) if dt is None else dt
    spf = max(1, int(np.ceil(1 / 30 / step - 1e-9)))
    sim.set_time_step(1 / 30 / spf, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    ticks = sim.stepper.ticks_per_step(sim.dt)
    F, X = [], [sim.x.copy()]
    for _ in range(frames):
        F.append(sim.advance(spf))
        X.append(sim.x.copy())
    times = np.arange(frames * spf * ticks) * sim.dt / ticks
    return times, np.concatenate(F), np.array(X), sim


@pytest.fixture(scope="module")
def reference(slab):
    tables = make_tables(mu0=2.0e4)
    term = build_spring_term(slab, tables, dashpot=2e-4)
    dt = stable_step(term, slab.mass).dt
    return tables, lift(slab, tables, SymplecticEuler(), dt=dt)


@pytest.mark.parametrize("iteration", ITERATIONS)
def test_implicit_matches_the_explicit_reference(slab, reference, iteration):
    tables, (te, Fe, Xe, _) = reference
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler(iteration=iteration))
    st = sim.stepper.stats
    if iteration == "quasi-newton":
        assert st.quasi_newton > 0
    else:
        assert st.quasi_newton == 0 and st.newton > 0
    assert sim.stepper.ticks_per_step(sim.dt) >= 34          # the grasper force at >= 1 kHz
    assert np.diff(ti).max() <= 1e-3 + 1e-12
    Fe_i = np.stack([np.interp(ti, te, Fe[:, d]) for d in range(3)], axis=1)
    lifting = ti <= LIFT
    scale = np.linalg.norm(Fe[te <= LIFT], axis=1).max()
    err = np.linalg.norm(Fi - Fe_i, axis=1)[lifting].max()
    assert err <= 0.05 * scale
    u_e = Xe - slab.points
    u_i = Xi - slab.points
    assert np.abs(u_i - u_e).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()
    # and the motion since the start (2 mm at the tip), within 5 % of its largest value too
    m_e, m_i = Xe - Xe[0], Xi - Xi[0]
    assert np.linalg.norm(m_i - m_e, axis=2).max() <= 0.05 * np.linalg.norm(m_e, axis=2).max()


@pytest.mark.parametrize("iteration", ITERATIONS)
def test_implicit_matches_the_explicit_reference_on_a_frictionless_bed(slab, iteration):
    """The interactive scene's bed (docs/design/simulator.md, "The scenes' physics"): the clamped slab
    sags onto a frictionless floor touching its rest shape and its free end is lifted off it; both
    steppers at matched damping."""
    tables = make_tables(mu0=2.0e4)
    fl = Floor.under(slab.points, (0, 0, -9.81), friction="slip")
    dt = stable_step(build_spring_term(slab, tables, dashpot=2e-4), slab.mass).dt
    te, Fe, Xe, _ = lift(slab, tables, SymplecticEuler(), dt=dt, floor=fl)
    ti, Fi, Xi, _ = lift(slab, tables, BackwardEuler(iteration=iteration), floor=fl)
    assert (fl.distance(Xe[0]) < 1e-9).sum() >= 4          # it rests on the bed before the lift
    assert min(fl.distance(Xi.reshape(-1, 3)).min(), fl.distance(Xe.reshape(-1, 3)).min()) >= -1e-9
    Fe_i = np.stack([np.interp(ti, te, Fe[:, d]) for d in range(3)], axis=1)
    lifting = ti <= LIFT
    scale = np.linalg.norm(Fe[te <= LIFT], axis=1).max()
    assert np.linalg.norm(Fi - Fe_i, axis=1)[lifting].max() <= 0.05 * scale
    u_e, u_i = Xe - slab.points, Xi - slab.points
    # the nodes the lift peels off the bed leave it in the step they are let go (contact_rounds: 6.6 %
    # of the largest displacement when they left a step later; 0.7 % measured)
    assert np.linalg.norm(u_i - u_e, axis=2).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()


@pytest.mark.parametrize("iteration", ITERATIONS)
def test_implicit_matches_the_explicit_reference_on_a_sticking_bed(slab, iteration):
    """The default scene's bed: as above with sticking friction. Where the lift peels the slab off
    the bed the explicit stepper's contacts creep (let go, landed, held again, within microseconds);
    the implicit one lets them slide within its step and stop where the floor pushes again
    (:class:`Slides`; docs/design/simulator.md, "Floor contact, with slides"); holding them to the
    step's end instead errs by several per cent in force here. The displacement is not held to 5 %
    on this slab: the peeled corner leaves the bed a step before the explicit one's (about a tenth
    of the largest displacement at 1/30 s, less at shorter steps)."""
    tables = make_tables(mu0=2.0e4)
    fl = Floor.under(slab.points, (0, 0, -9.81), friction="stick")
    dt = stable_step(build_spring_term(slab, tables, dashpot=2e-4), slab.mass).dt
    te, Fe, Xe, _ = lift(slab, tables, SymplecticEuler(), dt=dt, floor=fl)
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler(iteration=iteration), floor=fl)
    assert sim.stepper.stats.slides > 0                     # the lift peels it: contacts slide
    assert min(fl.distance(Xi.reshape(-1, 3)).min(), fl.distance(Xe.reshape(-1, 3)).min()) >= -1e-9
    Fe_i = np.stack([np.interp(ti, te, Fe[:, d]) for d in range(3)], axis=1)
    lifting = ti <= LIFT
    scale = np.linalg.norm(Fe[te <= LIFT], axis=1).max()
    assert np.linalg.norm(Fi - Fe_i, axis=1)[lifting].max() <= 0.05 * scale


def test_a_peel_node_that_pulls_free_after_its_neighbour_leaves_in_the_same_step():
    """A split slab (mid-edge nodes on its bed, as an asset made with ``--split``) lifted 4 mm off a
    sticking bed: nodes of the peel line pull free only once a neighbour has left. With a third
    re-solve they leave in the same step, as the explicit stepper's do (docs/design/simulator.md,
    "Floor contact, with slides"); with two (the earlier rule) one leaves a step late and the
    displacement is 11 % of the largest off the explicit stepper's (5 % with three). The renewals'
    price is fixed so that the run does not depend on timing."""
    m = box_tets(6, 2, 2, (0.06, 0.02, 0.015))
    pts, tets, _ = split_in_eight(m.points, m.tets)
    net = network_from_tets(SimpleNamespace(points=pts, tets=tets))
    slab = net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))
    tables = make_tables(mu0=1.0e4)
    fl = Floor.under(slab.points, (0, 0, -9.81), friction="stick")
    dt = stable_step(build_spring_term(slab, tables, dashpot=2e-4), slab.mass).dt
    _, _, Xe, _ = lift(slab, tables, SymplecticEuler(), dt=dt, floor=fl, rise=0.004)
    u_e = Xe - slab.points
    errors = {}
    for rounds in (None, 2):
        stepper = BackwardEuler(contact_rounds=rounds)
        stepper.factors.factor_in_solves = lambda: 30.0
        _, _, Xi, sim = lift(slab, tables, stepper, floor=fl, rise=0.004)
        assert sim.stepper.stats.slides > 0
        errors[rounds] = np.linalg.norm(Xi - Xe, axis=2).max() / np.linalg.norm(u_e, axis=2).max()
    assert errors[None] <= 0.08 < errors[2]


def locking_hang(box, load=300):
    """(term, fixed, gravity): *box* hung by its top face under *load* g, its tables locking above
    1.15 (tangent x 40 at 1.25): a unique equilibrium in the stiff range.

    Not the box on its base: a network without a volume term folds through its fixed base under
    such loads, into one of several hanging equilibria, and the path decides which (runs far apart
    where the factor's renewals, which follow measured times, differed)."""
    lam = np.linspace(0.6, 1.6, 201)
    mu = np.vstack([2e4 * (1 + 40 * np.clip((lam - 1.15) / 0.1, 0, None) ** 2)] * 3)
    tables = StiffnessTables(lam_min=0.6, lam_max=1.6, n=201, values=mu, stress=mu * (lam - 1),
                             energy=np.zeros((3, 201)))
    fixed = np.flatnonzero(box.points[:, 2] > box.points[:, 2].max() - 1e-9)
    return build_spring_term(box, tables), fixed, (0, 0, -9.81 * load)


def test_stable_at_frame_and_haptic_steps_and_near_locking(box):
    """Tables that lock above 1.15, loaded by 300 g: steps of 1/30 s and 1 ms settle on the equilibrium,
    whenever the factor is renewed (here at random: the renewals follow measured times)."""
    term, fixed, g = locking_hang(box)
    ref = Simulator(term, box.points, box.mass, fixed=fixed, gravity=g)
    ref.relax(rtol=1e-9)
    _, hi = term.stretch_range(ref.x)
    assert hi > 1.25                                   # the equilibrium is in the stiff (locking) range
    u = ref.x - box.points
    rng = np.random.default_rng(1)
    for timed in (True, False):
        for dt in (1 / 30, 1e-3):
            stepper = BackwardEuler(step=dt)
            if not timed:
                stepper.factors.factor_in_solves = lambda: float(rng.uniform(0.0, 60.0))
            sim = Simulator(term, box.points, box.mass, fixed=fixed, gravity=g, mass_damping=20.0, stepper=stepper)
            assert dt > 10 * stable_step(term, box.mass).dt
            sim.advance(int(round(0.6 / dt)))
            assert np.all(np.isfinite(sim.x))
            assert np.abs(sim.x - ref.x).max() < 0.02 * np.abs(u).max()


@pytest.mark.parametrize("dt", [1 / 30, 1e-3])
def test_a_force_below_the_tolerance_still_moves_a_state_at_rest(box, dt):
    """At rest on one load's equilibrium, the weight raised by half the tolerance: the steps reach the
    new equilibrium (each step iterates once at least; accepted as predicted, the state never moved)."""
    term, fixed, g = locking_hang(box, load=30)
    g1 = np.multiply(g, 1.005)
    eq = []
    for load in (g, g1):
        ref = Simulator(term, box.points, box.mass, fixed=fixed, gravity=load)
        ref.relax(rtol=1e-10)
        eq.append(ref.x.copy())
    stepper = BackwardEuler(step=dt)
    sim = Simulator(term, box.points, box.mass, fixed=fixed, gravity=g1, mass_damping=20.0, stepper=stepper)
    sim.state.x[:] = eq[0]
    free = np.setdiff1d(np.arange(box.n_nodes), fixed)
    weight = np.abs(g1[2]) * box.mass[free].max()
    assert np.abs(term.forces(eq[0])[free] + box.mass[free, None] * g1).max() < stepper.rtol * weight
    sim.advance(int(round(0.6 / dt)))
    shift = np.abs(eq[1] - eq[0]).max()
    assert shift > 1e-6
    assert np.abs(sim.x - eq[1]).max() < 0.05 * shift


def first_mode_decay(term, box, fixed, stepper, h, duration=0.5):
    """(omega, zeta): the lowest mode's angular frequency and its measured damping ratio, kicked alone."""
    free = np.ones(box.n_nodes, bool)
    free[fixed] = False
    fd = np.repeat(free, 3)
    w2, V = eigh(term.tangent(box.points).toarray()[np.ix_(fd, fd)], np.diag(np.repeat(box.mass, 3)[fd]))
    phi = np.zeros(3 * box.n_nodes)
    phi[fd] = V[:, 0]
    omega = float(np.sqrt(w2[0]))
    sim = Simulator(term, box.points, box.mass, fixed=fixed, stepper=stepper, dt=h)
    sim.state.v[:] = (1e-3 * omega * phi).reshape(-1, 3)
    mphi = np.repeat(box.mass, 3) * phi
    q = []
    for _ in range(int(duration / h)):
        sim.advance(1)
        q.append(mphi @ (sim.x - box.points).ravel())
    q = np.array(q)
    peaks = [k for k in range(1, len(q) - 1) if q[k] > q[k - 1] and q[k] >= q[k + 1]]
    return omega, float(np.log(q[peaks[0]] / q[peaks[-1]]) / (2 * np.pi * (len(peaks) - 1)))


def test_numerical_damping_of_backward_euler(box):
    """The lowest mode without physical damping: backward Euler damps it by ln(1 + (wh)^2) / (2 wh) more
    than the (energy-conserving) explicit reference."""
    term = build_spring_term(box, make_tables(aniso=False))
    fixed = np.flatnonzero(box.points[:, 2] < 1e-9)
    omega, z_ref = first_mode_decay(term, box, fixed, SymplecticEuler(), stable_step(term, box.mass).dt)
    for h in (1e-3, 3e-3):
        _, z = first_mode_decay(term, box, fixed, BackwardEuler(step=h, rtol=1e-9, xtol=1e-12, max_newton=20), h)
        expected = np.log1p((omega * h) ** 2) / (2 * omega * h)
        assert z - z_ref == pytest.approx(expected, rel=0.15)


def test_floor_contact_in_the_implicit_step(slab):
    """Released onto a sticking floor 1 mm below: no node ends below it, nodes in contact stay put."""
    tables = make_tables()
    term = build_spring_term(slab, tables)
    fl = Floor.under(slab.points - [0, 0, 0.001], (0, 0, -9.81), friction="stick")
    free = slab.with_fixed(np.zeros(0, np.int64))
    sim = Simulator(term, free.points, free.mass, gravity=(0, 0, -9.81), mass_damping=10.0, floor=fl,
                    stepper=BackwardEuler())
    for _ in range(30):
        sim.advance(1)
        assert fl.distance(sim.x).min() >= -1e-12
    held = sim.contact.astype(bool)
    assert held.sum() >= 4
    x = sim.x.copy()
    sim.advance(5)
    np.testing.assert_allclose(sim.x[held & sim.contact.astype(bool)], x[held & sim.contact.astype(bool)], atol=1e-12)


def test_effects_state_advances_with_the_implicit_step(slab):
    tables = make_tables()
    fx = MaterialEffects(ViscoelasticEffect((0.4,), (0.05,)))
    term = build_spring_term(slab, tables, effects=fx)
    sim = Simulator(term, slab.points, slab.mass, fixed=slab.fixed, gravity=(0, 0, -9.81), stepper=BackwardEuler())
    sim.advance(3)
    assert sim.fx_state.t == pytest.approx(3 / 30)
    assert np.abs(sim.fx_state.h).max() > 0


# ---------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------

def test_run_records_the_grasper_force_at_1khz(tmp_path, slab):
    sc = scene_from_dict({"scene": {"duration": "0.3 s", "frame_rate": 30, "gravity": [0, 0, -9.81]},
                          "integrator": {"method": "implicit", "haptic_rate": 1000, "factor": "exact"},
                          "grasper": {"radius": "8 mm", "release_time": "0.2 s",
                                      "waypoints": [{"time": "0 s", "distance": "0 mm"},
                                                    {"time": "0.1 s", "distance": "2 mm"}]}}, source="t")
    res = simulate_network(slab, make_tables(), sc, tmp_path)
    s = res.summary
    assert s.method == "implicit" and s.steps == 9 and s.dt_max_s == pytest.approx(1 / 30)
    assert s.integrator["factorizations"] >= 1 and s.integrator["haptic_rate_hz"] == 1000
    assert s.integrator["factor_matrix"] == "exact"             # the scene's [integrator] factor reaches it
    with History(res.history) as h:
        t, f = h.forces()
    assert np.diff(t).max() <= 1e-3 + 1e-12 and t[-1] > 0.19
    assert np.linalg.norm(f, axis=1).max() > 0
    assert "implicit" in s.describe()


def test_the_start_on_a_sticking_floor_does_not_depend_on_the_stepper(tmp_path, slab):
    """FIRE's equilibrium on a sticking floor depends on its path, so on its masses: the run relaxes on
    the explicit stepper's (mass-scaled) masses whatever the stepper, and both start from the same
    state (the SOFA liver's two starts differed by 2.5 mm, its grasper force by 15 %, before)."""
    starts, scaled = {}, {}
    for method in ("explicit", "implicit"):
        sc = scene_from_dict({"scene": {"duration": "0.05 s", "frame_rate": 30, "gravity": [0, 0, -9.81]},
                              "integrator": {"method": method, "mass_scaling": 0.01},
                              "floor": {"enabled": True, "friction": "stick"}}, source="t")
        res = simulate_network(slab, make_tables(mu0=2.0e4), sc, tmp_path / method)
        scaled[method] = res.summary.mass_scaling["nodes"]
        with History(res.history) as h:
            starts[method] = h.displacement(0)
    assert scaled["explicit"] > 0 and scaled["implicit"] == 0      # the two steppers' masses differ
    assert np.abs(starts["explicit"]).max() > 1e-5                  # it sagged onto the floor
    np.testing.assert_array_equal(starts["implicit"], starts["explicit"])


def test_threads_of_the_implicit_stepper(tmp_path, slab, monkeypatch):
    """Its solves use one or two threads (the two halves of the nested dissection): two as asked, no
    more (a larger count warns), the same motion either way; "auto" records its timing trial. The
    factor's renewal, which compares timings (two-thread solves on a small slab are slower), is held
    off, so that both runs take the same iterations on the same factor."""
    monkeypatch.setattr(FactorCache, "factor_in_solves", lambda self: math.inf)
    base = {"scene": {"duration": "0.05 s", "gravity": [0, 0, -9.81]}, "integrator": {"method": "implicit"}}
    runs = {}
    for threads in (1, 2, 3, "auto"):
        rep = ListReporter()
        sc = scene_from_dict({**base, "integrator": {**base["integrator"], "threads": threads}}, source="t")
        runs[threads] = simulate_network(slab, make_tables(), sc, tmp_path / str(threads), reporter=rep)
        assert any("at most 2" in w for w in rep.warnings) == (threads == 3)
    avail = min(2, numba.config.NUMBA_NUM_THREADS)
    assert runs[1].summary.threads == 1
    assert runs[2].summary.threads == runs[3].summary.threads == avail
    assert runs["auto"].summary.threads in (1, 2)
    assert set(runs["auto"].summary.thread_trial_s_per_step) == ({"1", "2"} if avail == 2 else set())
    with History(runs[1].history) as one, History(runs[2].history) as two:
        k = one.n_frames - 1
        np.testing.assert_allclose(two.displacement(k), one.displacement(k), rtol=0,
                                   atol=1e-6 * np.abs(one.displacement(k)).max())


@pytest.mark.parametrize("avail, requested, expected", [(2, "auto", 2), (1, "auto", 1), (2, 1, 1), (2, 3, 2),
                                                      (1, 2, 1)])
def test_factorization_threads(monkeypatch, avail, requested, expected):
    """The factorizations take two threads under "auto" where there are two (untimed: long enough for the
    workers' wake-up not to count), else as asked, at most two and at most what numba has."""
    monkeypatch.setattr(runsetup, "threads_available", lambda: avail)
    assert runsetup.choose_factor_threads(requested) == expected


def test_an_implicit_step_longer_than_a_frame_warns_and_steps_once_per_frame(tmp_path, slab):
    """implicit_step = "100 ms" at 30 frames/s ran at the frame step (33 ms) without a word; it says so now."""
    rep = ListReporter()
    sc = scene_from_dict({"scene": {"duration": "0.1 s", "gravity": [0, 0, -9.81]},
                          "integrator": {"method": "implicit", "implicit_step": "100 ms"}}, source="t")
    res = simulate_network(slab, make_tables(), sc, tmp_path / "long", reporter=rep)
    assert res.summary.steps == 3 and res.summary.dt_max_s == pytest.approx(1 / 30)
    assert any(w.startswith("[integrator] implicit_step: 100 ms is longer than a frame (33.33 ms") for w in rep.warnings)
    rep1 = ListReporter()
    sc1 = scene_from_dict({"scene": {"duration": "0.1 s", "gravity": [0, 0, -9.81]},
                           "integrator": {"method": "implicit", "implicit_step": "20 ms"}},
                          source="t")
    simulate_network(slab, make_tables(), sc1, tmp_path / "short", reporter=rep1)
    assert not any("implicit_step" in w for w in rep1.warnings)


def test_quasi_newton_hands_a_solve_it_does_not_finish_to_a_fresh_factor(slab, reference, monkeypatch):
    """A solve the quasi-Newton iteration has not finished after QN_SWITCH iterations (before any hand-over
    was measured; then after the hand-overs' mean cost) goes on from its best iterate with a factor taken
    there, where that costs less than Newton's iteration may: with the first switch after one iteration
    solves are handed over, the factor is renewed for them, and the lift still follows the explicit
    reference. (On this small slab a factorization costs more solves than Newton's budget: forced.)"""
    monkeypatch.setattr(implicit_iteration, "QN_SWITCH", 1)
    monkeypatch.setattr(StepSolver, "refresh_pays", lambda self: True)
    tables, (te, Fe, Xe, _) = reference
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler())
    st = sim.stepper.stats
    assert st.fallbacks > 0 and st.quasi_newton > 0
    assert st.factorizations > st.fallbacks           # one at the start, one per hand-over (at least)
    assert st.unconverged == 0
    # after the first hand-over a solve gets as many quasi-Newton iterations as a hand-over has cost
    # (the break-even rule), a fresh factor counted in solves: more than one
    cost, count = sim.stepper.solver.handover_cost, sim.stepper.solver.handovers
    assert count == st.fallbacks and sim.stepper.solver.switch_after() == pytest.approx(cost / count)
    assert cost / count > 1
    u_e = Xe - slab.points
    assert np.abs(Xi - Xe).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()


@pytest.mark.parametrize("xtol", [1e-4, 3e-2])
def test_a_solve_converges_on_the_residual_not_on_the_secants_model_of_it(slab, reference, monkeypatch, xtol):
    """Where the secant's step is not the full one, the next residual is the secant's model of it (no
    force pass); every quasi-Newton iterate that reports convergence (|g| <= tol), and every solve's
    end, carries the residual itself, recomputed here at the same x. (With a coarse *xtol* solves
    also end on the update's length, at an iterate whose residual was modelled.)"""
    checked = {"converged": 0, "ends": 0}
    update, solve = QuasiNewton.update, StepSolver.solve

    def spy_update(self, system, x, g, norm, h0, tol):
        xt, gt, new, moved, exact = update(self, system, x, g, norm, h0, tol)
        if new <= tol:
            assert exact
            assert new == pytest.approx(system.norm(system.residual(xt)[1]), rel=1e-12)
            checked["converged"] += 1
        return xt, gt, new, moved, exact

    def spy_solve(self, system, x):
        out = solve(self, system, x)
        assert self.record.exact
        checked["ends"] += 1
        return out

    monkeypatch.setattr(QuasiNewton, "update", spy_update)
    monkeypatch.setattr(StepSolver, "solve", spy_solve)
    tables, (te, Fe, Xe, _) = reference
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler(xtol=xtol))
    st = sim.stepper.stats
    assert st.modelled > 0 and checked["ends"] == st.steps
    if xtol < 1e-3:
        assert checked["converged"] > 0 and st.unconverged == 0
        u_e = Xe - slab.points
        assert np.abs(Xi - Xe).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()


def test_a_solve_that_stalls_on_the_fresh_factor_too_goes_on_with_newton(slab, reference, monkeypatch):
    monkeypatch.setattr(StepSolver, "switch_after", lambda self: 1)
    monkeypatch.setattr(StepSolver, "refresh_pays", lambda self: True)
    tables, (te, Fe, Xe, _) = reference
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler())
    st = sim.stepper.stats
    assert st.fallbacks > 0 and st.newton > 0 and st.factorizations > st.fallbacks
    assert st.unconverged == 0
    u_e = Xe - slab.points
    assert np.abs(Xi - Xe).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()


def test_where_a_factorization_costs_more_than_newton_may_newton_takes_over(slab, reference, monkeypatch):
    """Where a factorization costs more solves than Newton's iteration may spend (forced here: the slab's
    costs fewer), hand-overs go to Newton at once, whose iterations and conjugate gradients are then the
    hand-over's cost."""
    monkeypatch.setattr(implicit_iteration, "QN_SWITCH", 1)
    monkeypatch.setattr(FactorCache, "factor_in_solves", lambda self: math.inf)
    tables, (te, Fe, Xe, _) = reference
    ti, Fi, Xi, sim = lift(slab, tables, BackwardEuler())
    st = sim.stepper.stats
    assert not sim.stepper.solver.refresh_pays()
    assert st.fallbacks > 0 and st.newton > 0
    assert sim.stepper.solver.switch_after() == pytest.approx((st.cg + st.newton) / st.fallbacks)
    u_e = Xe - slab.points
    assert np.abs(Xi - Xe).max() <= 0.05 * np.linalg.norm(u_e, axis=2).max()


def test_what_a_renewal_costs_leaves_out_the_first_analysis(slab, monkeypatch):
    """The run's first factor also makes the symbolic analysis (made slow here: 0.3 s); the cost the renewal
    rules weigh (_factor_in_solves) leaves it out, and a renewal reuses the analysis. (With it the paper
    liver's runs renewed the factor in some runs and never in others.)"""
    postordered = supernodal._postordered

    def slow(A, perm):
        time.sleep(0.3)
        return postordered(A, perm)

    monkeypatch.setattr(supernodal, "_postordered", slow)
    term = build_spring_term(slab, make_tables(), dashpot=2e-4)
    sim = Simulator(term, slab.points, slab.mass, fixed=slab.fixed, gravity=(0, 0, -9.81),
                    stepper=BackwardEuler())
    sim.set_time_step(1 / 30, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    stepper = sim.stepper
    assert stepper.prepare(sim.model, sim.state, sim.control) >= 0.3
    factors = stepper.factors
    assert factors.factor.analysis_s >= 0.3
    sim.advance(2)
    cons = factors.constraints
    assert 0.0 < factors.factor_in_solves() * cons.solve_s / cons.solves < 0.3
    first = factors.factor.analysis
    stepper.prepare(sim.model, sim.state, sim.control)                # a renewal
    assert factors.factor.analysis is first and factors.factor.analysis_s == 0.0


@pytest.mark.parametrize("solo, expected", [(1e-12, 1), (math.inf, 2), (math.nan, 2)])
def test_two_threads_fall_back_to_one_where_their_solves_got_slower(slab, solo, expected):
    """Where "auto" chose two threads (solo_solve_s: a one-thread solve's time in the run's trial), a renewal
    gives them up for one when the last factor's solves took longer on two (their median); never without
    a trial (NaN)."""
    term = build_spring_term(slab, make_tables(), dashpot=2e-4)
    sim = Simulator(term, slab.points, slab.mass, fixed=slab.fixed, gravity=(0, 0, -9.81),
                    stepper=BackwardEuler(threads=2, solo_solve_s=solo))
    sim.set_time_step(1 / 30, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    stepper = sim.stepper
    stepper.prepare(sim.model, sim.state, sim.control)
    assert stepper.threads == 2 and stepper.factors.factor.ldl.threads == 2    # no solve yet: nothing to weigh
    sim.advance(3)
    stepper.prepare(sim.model, sim.state, sim.control)                # a renewal
    assert stepper.threads == expected and stepper.factors.factor.ldl.threads == expected
    assert stepper.stats.thread_fallbacks == (expected == 1)


def test_quasi_newton_needs_the_reused_factor():
    """With another preconditioner the solves iterate by Newton (the quasi-Newton's first inverse is the factor)."""
    assert BackwardEuler().quasi and not BackwardEuler(preconditioner="jacobi").quasi
    assert not BackwardEuler(iteration="newton").quasi
    assert not BackwardEuler(preconditioner="jacobi").solver.quasi
    with pytest.raises(Exception, match="iteration"):
        BackwardEuler(iteration="bfgs")


def test_scene_integrator_keys():
    assert scene_from_dict({}).method == "implicit"  # the default (docs/design/simulator.md, "What it achieves")
    sc = scene_from_dict({"integrator": {"method": "implicit", "implicit_step": "1 ms", "haptic_rate": 2000,
                                         "newton_tol": 0.01}})
    assert sc.method == "implicit" and sc.solve_step == pytest.approx(1e-3) and sc.haptic_rate == 2000
    assert scene_from_dict({}).solve_step == pytest.approx(1 / 30)
    with pytest.raises(Exception, match="method"):
        scene_from_dict({"integrator": {"method": "rk4"}})
    assert scene_from_dict({}).factor == "bound"
    assert scene_from_dict({"integrator": {"factor": "exact"}}).factor == "exact"
    with pytest.raises(Exception, match=r"\[integrator\] factor"):
        scene_from_dict({"integrator": {"factor": "cholesky"}})
    assert scene_from_dict({}).iteration == "quasi-newton"
    assert scene_from_dict({"integrator": {"iteration": "newton"}}).iteration == "newton"
    with pytest.raises(Exception, match=r"\[integrator\] iteration"):
        scene_from_dict({"integrator": {"iteration": "bfgs"}})
