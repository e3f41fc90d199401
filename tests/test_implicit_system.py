r"""One implicit step's system (pipeline/simulate/implicit_system.py): its residual, norm and matrices.

The residual against backward Euler's definition from the force terms; Newton's matrix (as a product
and as the matrix to factor) against central differences of the residual.
"""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.volume import VolumeSpec
from esmm.pipeline.simulate.contact import FloorContact
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_stats import ImplicitStats, Threads
from esmm.pipeline.simulate.implicit_system import StepSystem, force_scale
from esmm.pipeline.simulate.model import Floor, Grasp
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.volumeterm import build_volume_term
from simkit import make_tables

H = 1 / 30
ALPHA = 5.0


def moving_slab(*, volume=False, definite=False, grasp_mode=None, floor=None):
    """A slab fixed at x = 0, with dashpots, mid-motion (perturbed positions and velocities); (sim, system)."""
    net = network_from_tets(box_tets(4, 2, 2, (0.04, 0.02, 0.01)))
    p = net.points
    tables = make_tables("nonlinear")
    vol = build_volume_term(p, net.tets, VolumeSpec(2e5), lam_max=tables.lam_max) if volume else None
    sim = Simulator(build_spring_term(net, tables, dashpot=2e-4), p, net.mass, fixed=np.flatnonzero(p[:, 0] < 1e-9),
                    gravity=(0, 0, -9.81), mass_damping=ALPHA, volume=vol, floor=floor, stepper=BackwardEuler())
    if grasp_mode is not None:
        nodes = np.flatnonzero((p[:, 0] > p[:, 0].max() - 1e-9) & (p[:, 2] > p[:, 2].max() - 1e-9))
        sim.attach(Grasp(nodes=nodes, offsets=np.zeros((nodes.size, 3)), wp_t=np.array([0.0, 1.0]),
                         wp_x=np.array([p[nodes].mean(axis=0), p[nodes].mean(axis=0) + [0, 0, 0.01]]),
                         mode=grasp_mode, stiffness=None if grasp_mode == "prescribed" else np.full(nodes.size, 40.0)),
                   check_step=False)
    sim.set_time_step(H, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    rng = np.random.default_rng(0)
    mov = sim.model.movable
    sim.state.x[mov] += 5e-4 * rng.standard_normal((mov.sum(), 3))
    sim.state.v[mov] = 1e-2 * rng.standard_normal((mov.sum(), 3))
    contact = FloorContact.begin(sim.model, sim.state, sim.control, rounds=None, stats=ImplicitStats())
    return sim, StepSystem.begin(sim.model, sim.state, sim.control, contact, threads=Threads(), definite=definite)


@pytest.mark.parametrize("grasp_mode", [None, "spring"])
def test_the_residual_is_backward_eulers(grasp_mode):
    """g = M (x - x0 - h v0) / h^2 + alpha M (x - x0) / h - f(x, (x - x0)/h) - f_ext (- the coupling
    springs' pull at the step's end), zero on fixed nodes."""
    sim, system = moving_slab(grasp_mode=grasp_mode)
    x = system.x0 + 1e-4 * np.random.default_rng(1).standard_normal(system.x0.shape)
    v = (x - system.x0) / H
    f = sim.model.springs.forces(x, v, fext=sim.model.fext)
    if grasp_mode == "spring":
        g_ = sim.control.grasp
        f[g_.nodes] += 40.0 * (g_.tip(H) + g_.offsets - x[g_.nodes])
    m = sim.model.mass[:, None]
    expect = m * (x - system.x0 - H * system.v0) / H**2 + ALPHA * m * (x - system.x0) / H - f
    expect[~sim.model.movable] = 0.0
    f_sys, g = system.residual(x)
    np.testing.assert_allclose(g, expect, rtol=0, atol=1e-12 * np.abs(expect).max())
    assert np.abs(g[~sim.model.movable]).max() == 0.0


@pytest.mark.parametrize("volume", [False, True])
def test_newtons_matrix_is_the_residuals_derivative(volume):
    """The product (true tangent) and the factored matrix without bound (definite off) against central
    differences of the residual, on the movable dofs; the factored matrix is the identity on fixed dofs."""
    sim, system = moving_slab(volume=volume)
    x = system.x0
    mov = np.repeat(sim.model.movable, 3)
    A = system.matrix(x, bound=False).toarray()
    op = system.operator(x)
    rng = np.random.default_rng(2)
    for _ in range(3):
        d = rng.standard_normal(x.shape)
        d[~sim.model.movable] = 0.0
        eps = 1e-7
        fd = (system.residual(x + eps * d)[1] - system.residual(x - eps * d)[1]).ravel() / (2 * eps)
        scale = np.abs(fd).max()
        np.testing.assert_allclose(op(d.ravel())[mov], fd[mov], rtol=0, atol=2e-5 * scale)
        np.testing.assert_allclose((A @ d.ravel())[mov], fd[mov], rtol=0, atol=2e-5 * scale)
    np.testing.assert_array_equal(A[np.ix_(~mov, ~mov)], np.eye(int((~mov).sum())))
    assert not A[np.ix_(~mov, mov)].any() and not A[np.ix_(mov, ~mov)].any()


def test_the_volume_terms_bound_lies_above_its_tangent():
    """The matrix with the volume term's per-tet bound: symmetric, and above Newton's matrix (A_bound - A
    positive semi-definite) with less fill."""
    _, system = moving_slab(volume=True, definite=True)
    A = system.matrix(system.x0, bound=False)
    B = system.matrix(system.x0, bound=True)
    diff = (B - A).toarray()
    assert np.abs(diff - diff.T).max() <= 1e-9 * np.abs(diff).max()
    assert np.linalg.eigvalsh(diff).min() >= -1e-9 * np.abs(diff).max()
    assert B.nnz < A.nnz


def test_the_norm_leaves_out_what_the_constraints_hold():
    """The largest residual on a node that is free: the prescribed grasp's nodes and the contacts held in
    place not at all, a sliding contact's normal component not."""
    fl = Floor(normal=np.array([0.0, 0.0, 1.0]), height=-1.0, friction="stick")
    sim, system = moving_slab(grasp_mode="prescribed", floor=fl)
    n = sim.model.n_nodes
    g = np.zeros((n, 3))
    grasped = sim.control.grasp.nodes
    free = np.flatnonzero(sim.control.floor_mask > 0)
    held, sliding, other = free[0], free[1], free[2]
    system.contact.active[[held, sliding]] = True
    system.contact.slides.sliding[sliding] = True
    g[grasped] = 100.0
    g[held] = [50.0, 50.0, 50.0]
    g[sliding] = [3.0, 4.0, 70.0]
    assert system.norm(g) == pytest.approx(5.0)
    g[other] = [0.0, 0.0, 6.0]
    assert system.norm(g) == pytest.approx(6.0)


def test_the_jacobi_preconditioner_is_the_diagonal_per_node_and_holds_what_is_held():
    sim, system = moving_slab(grasp_mode="prescribed")
    x = system.x0
    A = system.matrix(x, bound=False).toarray()          # definite off: the same diagonal as the true tangent
    apply = system.jacobi(x)
    r = np.random.default_rng(3).standard_normal(x.size)
    z = apply(r).reshape(-1, 3)
    d = np.repeat(np.diag(A).reshape(-1, 3).mean(axis=1), 3).reshape(-1, 3)
    free = sim.control.free
    np.testing.assert_allclose(z[free], (r.reshape(-1, 3) / d)[free], rtol=1e-12)
    assert not z[~free].any()


def test_the_force_scale_is_the_largest_weight():
    sim, _ = moving_slab()
    mov = sim.model.movable
    assert force_scale(sim.model) == pytest.approx(np.linalg.norm(sim.model.fext[mov], axis=1).max())
