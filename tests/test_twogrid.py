"""The two-grid preconditioner on a split mesh's parents (pipeline/linalg/twogrid.py).

Checked against exact identities (the prolongation reproduces linear fields; the Galerkin map is
the sparse triple product), a direct solve (conjugate gradients preconditioned by the operator
reach scipy's solution, constrained or not), and the implicit stepper with the split matrix's own
factor (a lift on a split slab ends in the same state).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sps
import scipy.sparse.linalg as spla
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.linalg.linsolve import pcg
from esmm.pipeline.linalg.twogrid import Galerkin, TwoGrid, TwoGridConstraints, prolongation
from esmm.pipeline.mesh.refine import split_in_eight
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.simulate import runsetup
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.model import Grasp
from esmm.pipeline.simulate.scene import scene_from_dict
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from simkit import make_tables


def split_network(nx, ny, nz, size):
    """The spring network of a Kuhn box with every tet split in eight (its parents kept)."""
    box = box_tets(nx, ny, nz, size)
    p, t, q = split_in_eight(box.points, box.tets)
    return network_from_tets(SimpleNamespace(points=p, tets=t, quadratic_cells=q))


@pytest.fixture(scope="module")
def split_box():
    return split_network(3, 2, 2, (0.03, 0.02, 0.02))


def system(net, h=1 / 30):
    """Newton's matrix of a step of *h* at a perturbed state (springs and inertia), fixed nodes as identity."""
    term = build_spring_term(net, make_tables("nonlinear", mu0=2.0e4))
    rng = np.random.default_rng(0)
    x = net.points + rng.normal(scale=2e-4, size=net.points.shape)
    return (term.tangent(x, definite=True) + sps.diags(np.repeat(net.mass, 3) / h ** 2)).tocsr()


def test_prolongation_is_exact_on_linear_fields(split_box):
    net = split_box
    P, vertices = prolongation(net.quadratic_cells, net.n_nodes)
    G = np.array([[0.3, -1.2, 2.0], [0.7, 0.1, -0.4], [1.5, 0.2, 0.9]])
    c = np.array([0.01, -0.02, 0.03])
    u = net.points @ G.T + c                          # a linear field (n, 3)
    np.testing.assert_allclose((P @ u[vertices].ravel()).reshape(-1, 3), u, rtol=0, atol=1e-14)
    assert P.shape == (3 * net.n_nodes, 3 * vertices.size)
    # a fixed node's rows are zero
    free = np.ones(net.n_nodes, bool)
    free[[0, 7]] = False
    Pf, _ = prolongation(net.quadratic_cells, net.n_nodes, free)
    rows = np.diff(Pf.indptr).reshape(-1, 3)
    assert np.all(rows[[0, 7]] == 0) and np.all(rows[free] > 0)


def test_the_galerkin_map_is_the_triple_product(split_box):
    A = system(split_box)
    P, _ = prolongation(split_box.quadratic_cells, split_box.n_nodes)
    gal = Galerkin.of(A, P)
    ref = (P.T @ A @ P).toarray()
    np.testing.assert_allclose(gal.product(A).toarray(), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert gal.matches(A) and not gal.matches(A[:, ::-1].tocsr())


def test_two_grid_is_symmetric_positive_definite_and_preconditions_to_the_direct_solve(split_box):
    A = system(split_box)
    P, _ = prolongation(split_box.quadratic_cells, split_box.n_nodes)
    B = TwoGrid.of(A, P, single=False)
    rng = np.random.default_rng(1)
    u, v = rng.normal(size=(2, A.shape[0]))
    assert abs(u @ B.solve(v) - v @ B.solve(u)) <= 1e-10 * abs(u @ B.solve(u))
    assert u @ B.solve(u) > 0 and v @ B.solve(v) > 0
    b = rng.normal(size=A.shape[0])
    y, its, ok = pcg(lambda p: A @ p, B.solve, b, rtol=1e-10, max_iter=200)
    ref = spla.spsolve(A.tocsc(), b)
    assert ok and its < 60
    assert np.linalg.norm(y - ref) <= 1e-7 * np.linalg.norm(ref)
    # the coarse level's correction matters: the smoother alone (no coarse level) needs more iterations
    smoother = TwoGrid.of(A, P, single=False)
    smoother.P = sps.csr_matrix(P.shape)
    _, its_smooth, _ = pcg(lambda p: A @ p, smoother.solve, b, rtol=1e-10, max_iter=400)
    assert its_smooth > 1.5 * its


def test_the_constrained_two_grid_holds_its_rows_and_solves_the_constrained_problem(split_box):
    A = system(split_box)
    n = split_box.n_nodes
    P, _ = prolongation(split_box.quadratic_cells, n)
    cons = TwoGridConstraints(TwoGrid.of(A, P, single=False), n)
    normal = np.array([0.0, 0.6, 0.8])
    # node 0 held, node 5 held along a normal, node 9 on a coupling spring (k = 1e3 N/m) along z
    cons.set_rows(np.array([0, 0, 0, 5, 9]), np.vstack([np.eye(3), normal, [0, 0, 1.0]]),
                  np.array([0, 0, 0, 0, 1e-3]))
    z = cons.apply(np.random.default_rng(2).normal(size=A.shape[0]))
    np.testing.assert_allclose(z[:3], 0.0, atol=1e-14)
    assert abs(z[15:18] @ normal) < 1e-12 * np.abs(z).max()
    assert cons.has_rows
    # conjugate gradients in the rows' null space reach the constrained direct solution
    K = A.tolil()
    K[29, 29] += 1e3
    K = K.tocsr()
    b = np.random.default_rng(3).normal(size=A.shape[0])
    y, its, ok = pcg(lambda p: K @ p, cons.apply, b, rtol=1e-10, max_iter=300)
    assert ok
    # the reduced system: node 0's dofs dropped, node 5's normal dropped (a basis of its plane)
    t1 = np.array([1.0, 0.0, 0.0])
    t2 = np.cross(normal, t1)
    T = sps.lil_matrix((3 * n, 3 * n - 4))
    col = 0
    for d in range(3 * n):
        if d < 3 or 15 <= d < 18:
            continue
        T[d, col] = 1.0
        col += 1
    T[15:18, col] = t1[:, None]
    T[15:18, col + 1] = t2[:, None]
    T = T.tocsr()
    ref = T @ spla.spsolve((T.T @ K @ T).tocsc(), T.T @ b)
    assert np.linalg.norm(y - ref) <= 1e-7 * np.linalg.norm(ref)
    # the held node's stiffness from the coarse level is the Schur complement over the parents' fields:
    # above the split matrix's own (a subspace's minimum energy), and positive definite
    J = np.zeros((5, 3 * n))
    J[[0, 1, 2], [0, 1, 2]] = 1.0
    J[3, 15:18] = normal
    J[4, 29] = 1.0
    C = J @ spla.spsolve(A.tocsc(), J.T) + np.diag([0, 0, 0, 0, 1e-3])
    S_fine = np.linalg.inv(C)[:3, :3]
    S_coarse = cons.block_stiffness(np.arange(3))
    np.testing.assert_allclose(S_coarse, S_coarse.T, rtol=1e-10, atol=0)
    assert np.linalg.eigvalsh(S_coarse - S_fine).min() >= -1e-8 * np.abs(S_fine).max()
    assert np.linalg.eigvalsh(S_fine).min() > 0


def lift(net, stepper, frames=12):
    """A split slab fixed at x = 0, settled, its free end's top lifted 2 mm; (the motion since the
    settled state (n, 3), the forces at the solves, the simulator)."""
    term = build_spring_term(net, make_tables("nonlinear", mu0=2.0e4), dashpot=2e-4)
    sim = Simulator(term, net.points, net.mass, fixed=net.fixed, gravity=(0, 0, -9.81), mass_damping=5.0,
                    stepper=stepper)
    sim.relax(rtol=1e-9)
    settled = sim.x.copy()
    p = net.points
    nodes = np.flatnonzero((p[:, 0] > p[:, 0].max() - 1e-9) & (p[:, 2] > p[:, 2].max() - 1e-9))
    tip0 = sim.x[nodes].mean(axis=0)
    s = np.linspace(0.0, 1.0, 11)
    sim.attach(Grasp(nodes=nodes, offsets=sim.x[nodes] - tip0, wp_t=0.3 * s,
                     wp_x=tip0 + np.outer(s * s * (3 - 2 * s), [0, 0, 0.002])), check_step=False)
    sim.set_time_step(1 / 30, bound=sim.stepper.bound(sim.model, sim.control), t0=0.0)
    ticks = sim.stepper.ticks_per_step(sim.dt)
    F = np.concatenate([sim.advance(1) for _ in range(frames)])[::ticks]
    return sim.x - settled, F, sim


@pytest.mark.slow
def test_a_lift_with_the_two_grid_ends_where_the_factor_takes_it():
    """Both at tolerances a hundred times tighter than the scenes' (the renewals are timed, so the
    two runs' iterations differ from run to run): the motion and the grasper force at the solves
    within 2 %."""
    net = split_network(6, 2, 2, (0.06, 0.02, 0.015))
    net = net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))
    tight = {"rtol": 1e-4, "xtol": 1e-7}
    x_f, F_f, sim_f = lift(net, BackwardEuler(**tight))
    x_t, F_t, sim = lift(net, BackwardEuler(coarse_cells=net.quadratic_cells, **tight))
    assert sim.stepper.stats.quasi_newton > 0 and sim.stepper.report()["preconditioner_levels"] == "two-grid"
    assert sim.stepper.stats.unconverged == 0 and sim_f.stepper.stats.unconverged == 0
    moved = np.linalg.norm(x_f, axis=1).max()
    assert moved > 1.9e-3
    assert np.linalg.norm(x_t - x_f, axis=1).max() <= 0.02 * moved
    assert np.linalg.norm(F_t - F_f, axis=1).max() <= 0.02 * np.linalg.norm(F_f, axis=1).max()


def test_the_two_grid_needs_a_split_asset(split_box):
    scene = scene_from_dict({"integrator": {"preconditioner": "two-grid"}})
    assert scene.preconditioner == "two-grid"
    np.testing.assert_array_equal(runsetup._coarse_cells(split_box, scene), split_box.quadratic_cells)
    plain = network_from_tets(box_tets(2, 2, 2, (0.02, 0.02, 0.02)))
    with pytest.raises(ConfigError, match="needs a split asset"):
        runsetup._coarse_cells(plain, scene)
    assert runsetup._coarse_cells(plain, scene_from_dict({})) is None
    with pytest.raises(ConfigError, match="preconditioner"):
        scene_from_dict({"integrator": {"preconditioner": "multigrid"}})


def test_the_volume_bound_restricted_to_the_parents_is_the_parents_own(split_box):
    """For a field linear on a parent each child's volume changes in proportion to its rest volume, so
    P^T K_tet P of the split mesh is K_tet of the parent mesh (at rest, same bulk modulus)."""
    from esmm.pipeline.network.volume import VolumeSpec, volume_elements

    box = box_tets(3, 2, 2, (0.03, 0.02, 0.02))
    p, t, q = split_in_eight(box.points, box.tets)
    spec = VolumeSpec(bulk_modulus=1.0e6, formulation="nodal")
    K_split = volume_elements(p, t, spec).tangent_bound(p)
    P, vertices = prolongation(q, p.shape[0])
    parents = np.searchsorted(vertices, q[:, :4])
    K_parent = volume_elements(p[vertices], parents, spec).tangent_bound(p[vertices])
    ref = K_parent.toarray()
    np.testing.assert_allclose((P.T @ K_split @ P).toarray(), ref, rtol=0, atol=1e-9 * np.abs(ref).max())
