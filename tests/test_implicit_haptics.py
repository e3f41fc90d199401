r"""The grasper force at the haptic rate between implicit solves (pipeline/simulate/haptics.py).

Between two solves the force is :math:`\mathbf F_n - S\,(\mathbf p(t) - \mathbf p(t_n)) +
\tfrac{\tau}{h}\mathbf D_n`; :math:`S` is checked against the Schur complement of the factored
matrix on the grasped patch's translation, computed densely here, and the stepper's samples against
that formula with it.
"""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.linalg.linsolve import Constraints, SparseFactor
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.simulate.contact import FloorContact
from esmm.pipeline.simulate.haptics import Haptics, LastForce, patch_stiffness
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_stats import ImplicitStats, Threads
from esmm.pipeline.simulate.implicit_system import StepSystem
from esmm.pipeline.simulate.model import Grasp
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from simkit import make_tables

H = 1 / 30
DAMPING = 30.0


def grasped_slab(stepper=None, *, lift=0.0002, duration=0.3):
    """A 40 x 20 x 10 mm slab fixed at x = 0, its free end's top grasped and lifted by *lift* in *duration*
    along a smooth path; (sim, grasp)."""
    net = network_from_tets(box_tets(4, 2, 2, (0.04, 0.02, 0.01)))
    p = net.points
    term = build_spring_term(net, make_tables("constant", mu0=2.0e4))
    stepper = BackwardEuler() if stepper is None else stepper
    sim = Simulator(term, p, net.mass, fixed=np.flatnonzero(p[:, 0] < 1e-9), gravity=(0, 0, -9.81),
                    mass_damping=DAMPING, stepper=stepper)
    nodes = np.flatnonzero((p[:, 0] > p[:, 0].max() - 1e-9) & (p[:, 2] > p[:, 2].max() - 1e-9))
    tip0 = p[nodes].mean(axis=0)
    s = np.linspace(0.0, 1.0, 11)
    grasp = Grasp(nodes=nodes, offsets=p[nodes] - tip0, wp_t=duration * s,
                  wp_x=tip0 + np.outer(s * s * (3 - 2 * s), [0, 0, lift]))
    sim.attach(grasp, check_step=False)
    sim.set_time_step(H, bound=stepper.bound(sim.model, sim.control), t0=0.0)
    return sim, sim.control.grasp


def schur_translation(A, nodes):
    """The stiffness (3, 3) of translating *nodes* together against the dense matrix *A* (3n, 3n), the
    other dofs free: ``T^T (A_pp - A_pf A_ff^-1 A_fp) T``, T the patch's translation (3p, 3)."""
    A = np.asarray(A.todense())
    p = (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()
    f = np.setdiff1d(np.arange(A.shape[0]), p)
    schur = A[np.ix_(p, p)] - A[np.ix_(p, f)] @ np.linalg.solve(A[np.ix_(f, f)], A[np.ix_(f, p)])
    T = np.tile(np.eye(3), (len(nodes), 1))
    return T.T @ schur @ T


def system_of(sim):
    contact = FloorContact.begin(sim.model, sim.state, sim.control, rounds=None, stats=ImplicitStats())
    return StepSystem.begin(sim.model, sim.state, sim.control, contact, threads=Threads(), definite=True)


def test_the_patch_stiffness_is_the_schur_complement_less_the_patchs_inertia():
    """From the capacitance matrix of the grasp's rows (no extra solve): the Schur complement of the
    factored matrix on the patch's translation, less the grasped nodes' own inertia (a prescribed
    grasp moves them; the force is the tissue's on them)."""
    sim, grasp = grasped_slab()
    A = system_of(sim).matrix(sim.x, bound=False)
    cons = Constraints(SparseFactor.of(A), sim.model.n_nodes)
    cons.set_rows(np.repeat(grasp.nodes, 3), np.tile(np.eye(3), (grasp.nodes.size, 1)), np.zeros(3 * grasp.nodes.size))
    S = patch_stiffness(sim.model, sim.control, cons, H)
    inertia = sim.model.mass[grasp.nodes].sum() * (1 / H**2 + DAMPING / H)
    expect = schur_translation(A, grasp.nodes) - inertia * np.eye(3)
    np.testing.assert_allclose(S, expect, rtol=0, atol=1e-8 * np.abs(expect).max())
    assert np.abs(S - S.T).max() <= 1e-8 * np.abs(S).max()
    assert S[2, 2] > 0                                          # lifting the patch meets resistance
    # without a grasp, or before any rows: none
    assert not patch_stiffness(sim.model, sim.control, None, H).any()


def test_between_solves_the_force_moves_by_the_patch_stiffness_along_the_path_plus_the_drift():
    """The samples of a step: F0 at its start, then F0 - S (p(t + tau) - p(t)) + tau/h D, D the last
    step's drift (for the same grasp only, and only with drift on)."""
    _, grasp = grasped_slab(lift=0.002)
    rng = np.random.default_rng(0)
    F0, D = rng.normal(size=3), rng.normal(size=3)
    S = rng.normal(size=(3, 3))
    S = S + S.T
    t, T = 0.1, 34
    for drift, last_grasp in ((True, grasp), (False, grasp), (True, None)):
        hap = Haptics(rate=1000.0, drift=drift)
        if last_grasp is not None:
            hap.last = LastForce(last_grasp, t, F0, D)
        rec = np.zeros((T, 3))
        hap.fill(rec, F0, S, grasp, t, H)
        d = D if (drift and last_grasp is not None) else np.zeros(3)
        for q in range(T):
            tau = q * H / T
            np.testing.assert_allclose(rec[q], F0 - S @ (grasp.tip(t + tau) - grasp.tip(t)) + tau / H * d,
                                       rtol=1e-12, atol=1e-15)
    # nothing grasped: the start's force held
    rec = np.zeros((T, 3))
    Haptics().fill(rec, F0, S, None, t, H)
    np.testing.assert_array_equal(rec, np.tile(F0, (T, 1)))


def test_ticks_per_step_keep_the_spacing_at_most_one_over_the_rate():
    hap = Haptics(rate=1000.0)
    assert hap.ticks_per_step(H) == 34 and hap.ticks_per_step(1e-3) == 1 and hap.ticks_per_step(1e-4) == 1
    for dt in (H, 0.0123, 2e-3):
        assert dt / hap.ticks_per_step(dt) <= 1e-3 * (1 + 1e-12)


@pytest.mark.parametrize("drift", [True, False])
def test_the_steppers_samples_follow_the_linear_model_with_the_analytic_schur_complement(drift):
    """A slow lift of a slab of linear springs, the factor kept from the start (float64, Newton's matrix
    itself): every sample between two solves equals F_n - S (p(t) - p(t_n)) + tau/h D_n with S the
    Schur complement computed densely from the matrix at the start, F_n the solved force at the step's
    start and D_n = F_n - F_(n-1) + S (p(t_n) - p(t_(n-1))) what the tip's motion did not explain."""
    stepper = BackwardEuler(single=False, factor_matrix="exact", haptic_drift=drift)
    stepper.factors.refactor_pays = lambda: False           # the factor taken at the start, kept
    sim, grasp = grasped_slab(stepper)
    A0 = system_of(sim).matrix(sim.x, bound=False)
    S = schur_translation(A0, grasp.nodes) - sim.model.mass[grasp.nodes].sum() * (1 / H**2 + DAMPING / H) * np.eye(3)
    stepper.prepare(sim.model, sim.state, sim.control)
    steps = 6
    rec = sim.advance(steps)
    assert stepper.stats.factorizations == 1 and stepper.stats.fallbacks == 0
    T = stepper.ticks_per_step(H)
    F = rec[::T]                                              # the solved force at each step's start
    scale = np.abs(rec).max()
    assert np.linalg.norm(F[-1] - F[0]) > 1e-3 * scale      # the lift changes the force
    for k in range(steps):
        t = k * H
        d = np.zeros(3)
        if drift and k > 0:
            d = F[k] - F[k - 1] + S @ (grasp.tip(t) - grasp.tip(t - H))
        for q in range(T):
            tau = q * H / T
            expect = F[k] - S @ (grasp.tip(t + tau) - grasp.tip(t)) + tau / H * d
            np.testing.assert_allclose(rec[k * T + q], expect, rtol=0, atol=1e-7 * scale)
