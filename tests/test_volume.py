"""The volume term (pipeline/network/volume.py) against finite differences and analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from esmm.pipeline.errors import ConfigError, InputError
from esmm.pipeline.network.springs import tet_volumes
from esmm.pipeline.network.volume import (
    VolumeSpec,
    bulk_modulus,
    bulk_ratio,
    inverted_tets,
    nodal_volumes,
    tangent_shear_modulus,
    volume_elements,
)
from simkit import jittered_box_network


@pytest.fixture(scope="module")
def block():
    """A jittered structured block (4 x 3 x 3 cells, 6 Kuhn tets each), 30 x 20 x 20 mm."""
    return jittered_box_network((4, 3, 3), (0.03, 0.02, 0.02), jitter=0.8e-3, seed=3)


def deformed(net, scale=0.04, seed=1):
    rng = np.random.default_rng(seed)
    return net.points + scale * 1e-2 * rng.standard_normal(net.points.shape)


@pytest.mark.parametrize("form", ["nodal", "tet"])
def test_forces_are_minus_energy_gradient(block, form):
    el = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, form))
    x = deformed(block)
    f = el.forces(x)
    h = 1e-7
    rng = np.random.default_rng(0)
    for _ in range(12):                      # random directional derivatives
        d = rng.standard_normal(x.shape)
        num = -(el.energy(x + h * d) - el.energy(x - h * d)) / (2 * h)
        assert num == pytest.approx(float(np.sum(f * d)), rel=1e-6)


@pytest.mark.parametrize("form", ["nodal", "tet"])
def test_tangent_is_minus_force_jacobian(block, form):
    el = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, form))
    x = deformed(block)
    K = el.tangent(x)
    assert abs(K - K.T).max() <= 1e-12 * abs(K).max()
    h = 1e-8
    rng = np.random.default_rng(2)
    for _ in range(6):
        d = rng.standard_normal(x.shape)
        num = -(el.forces(x + h * d) - el.forces(x - h * d)).ravel() / (2 * h)
        np.testing.assert_allclose(K @ d.ravel(), num, rtol=0, atol=2e-6 * np.abs(num).max())


@pytest.mark.parametrize("form", ["nodal", "tet"])
@pytest.mark.parametrize("definite", [False, True])
def test_matrix_free_product_is_the_tangent(block, form, definite):
    el = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, form))
    x = deformed(block)
    K = el.tangent(x, definite=definite)
    product = el.tangent_operator(x, definite=definite)
    rng = np.random.default_rng(5)
    for _ in range(4):
        p = rng.standard_normal(x.size)
        y = K @ p
        np.testing.assert_allclose(product(p), y, rtol=0, atol=1e-12 * np.abs(y).max())
    # the definite part differs from the full tangent by the pressures' geometric part
    assert abs(el.tangent(x, definite=not definite) - K).max() > 1e-6 * abs(K).max()


def test_tangent_bound_is_above_the_nodal_tangent_with_the_tets_sparsity(block):
    """The per-tet Gauss-Newton matrix the implicit stepper factors (docs/design/simulator.md,
    "What is factored, and when it is renewed"): above the nodal term's definite tangent
    (Cauchy-Schwarz: the difference is positive semi-definite, and strictly larger somewhere),
    equal to it for the per-tet formulation, and coupling only nodes of a common tet."""
    x = deformed(block)
    nodal = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, "nodal"))
    tet = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, "tet"))
    K, B = nodal.tangent(x, definite=True), nodal.tangent_bound(x)
    np.testing.assert_allclose(B.toarray(), tet.tangent(x, definite=True).toarray(), rtol=0, atol=1e-12 * abs(B).max())
    ev = np.linalg.eigvalsh((B - K).toarray())
    assert ev.min() > -1e-10 * ev.max() and ev.max() > 0.1 * np.linalg.eigvalsh(B.toarray()).max()
    n = block.points.shape[0]
    pairs = set(map(tuple, np.concatenate([block.tets[:, [i, j]] for i in range(4) for j in range(4)])))
    Bc = B.tocoo()
    assert {(int(r) // 3, int(c) // 3) for r, c in zip(Bc.row, Bc.col)} <= pairs
    Kc = K.tocoo()
    assert len({(int(r) // 3, int(c) // 3) for r, c in zip(Kc.row, Kc.col)} - pairs) > n     # K reaches further


def test_bound_pattern_is_the_sorted_dof_pairs(block):
    """The bound's CSR pattern, found on node pairs and widened to 3 x 3 blocks, is the one that sorting
    every tet's 144 dof pairs gives (the plain definition), on a mesh with its tets and their nodes
    shuffled; and each tet's 12 x 12 entries land on their own (row, column)."""
    from esmm.pipeline.network.volume import _tet_block_pattern

    rng = np.random.default_rng(5)
    tets = block.tets[rng.permutation(len(block.tets))][:, rng.permutation(4)]
    n, m = block.points.shape[0], 3 * block.points.shape[0]
    indptr, indices, pos = _tet_block_pattern(tets, n)
    dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(-1, 12).astype(np.int64)
    key = (np.repeat(dofs, 12, axis=1) * m + np.tile(dofs, (1, 12))).ravel()
    uniq = np.unique(key)
    np.testing.assert_array_equal(indptr, np.searchsorted(uniq // m, np.arange(m + 1)))
    np.testing.assert_array_equal(indices, uniq % m)
    rows = np.repeat(np.arange(m), np.diff(indptr))
    np.testing.assert_array_equal(rows[pos.ravel()] * m + indices[pos.ravel()], key)


@pytest.mark.parametrize("form", ["nodal", "tet"])
def test_no_net_force_or_torque_and_rigid_motions_free(block, form):
    el = volume_elements(block.points, block.tets, VolumeSpec(2.0e5, form))
    x = deformed(block)
    f = el.forces(x)
    scale = np.abs(f).sum()
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * scale
    assert np.abs(np.cross(x - x.mean(axis=0), f).sum(axis=0)).max() < 1e-12 * scale * 0.03
    # a rigid rotation + translation of the rest shape: no volume changes, no force
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    xr = block.points @ R.T + [0.1, -0.2, 0.05]
    assert el.energy(xr) < 1e-20
    assert np.abs(el.forces(xr)).max() < 1e-9 * scale / x.shape[0]


def test_uniform_dilation_pressure_is_analytic(block):
    el = volume_elements(block.points, block.tets, VolumeSpec(3.0e5, "nodal"))
    s = 1.01
    x = block.points * s
    np.testing.assert_allclose(el.jacobians(x), s**3, rtol=1e-12)
    np.testing.assert_allclose(el.pressures(x), 3.0e5 * (s**3 - 1), rtol=1e-10)
    V0 = tet_volumes(block.points, block.tets).sum()
    assert el.energy(x) == pytest.approx(0.5 * 3.0e5 * V0 * (s**3 - 1) ** 2, rel=1e-10)


def test_nodal_volumes_partition_the_mesh(block):
    v = nodal_volumes(block.points, block.tets)
    assert v.sum() == pytest.approx(tet_volumes(block.points, block.tets).sum(), rel=1e-13)
    assert np.all(v > 0)


@pytest.mark.parametrize("form", ["nodal", "tet"])
def test_row_bound_covers_the_largest_eigenvalue(block, form):
    el = volume_elements(block.points, block.tets, VolumeSpec(1.0e6, form))
    m = block.mass
    for x in (block.points, deformed(block, 0.02)):
        K = el.tangent(x)
        Mi = sp.diags(1.0 / np.sqrt(np.repeat(m, 3)))
        w = spl.eigsh(Mi @ K @ Mi, k=1, which="LA")[0][0]
        r = el.stiffness_rows(x if x is not block.points else None, j_bound=0.0) if x is block.points \
            else el.stiffness_rows(x)
        bound = (r / m).max()
        assert bound >= w
        assert bound < 6 * w            # the weighted Cauchy-Schwarz rows are not loose


def test_whole_run_rows_grow_with_the_stretch_bound(block):
    el = volume_elements(block.points, block.tets, VolumeSpec(1.0e6, "nodal"))
    r1 = el.stiffness_rows(growth=1.0, j_bound=0.0)
    r2 = el.stiffness_rows(growth=1.2, j_bound=0.0)
    np.testing.assert_allclose(r2, r1 * 1.2**4, rtol=1e-12)
    assert np.all(el.stiffness_rows(growth=1.0) > r1)          # the pressures' geometric part adds


def test_inverted_tets_counted(block):
    x = block.points.copy()
    assert inverted_tets(x, block.tets) == 0
    t0 = block.tets[0]
    x[t0[0]] = x[t0[1:]].mean(axis=0) * 2 - x[t0[0]]       # reflect one node through its opposite face
    assert inverted_tets(x, block.tets) >= 1


def test_bulk_modulus_rule(tables):
    spec = bulk_modulus(tables, poisson=0.49, calibration_range=(0.9, 1.3))
    mu_t, at = tangent_shear_modulus(tables, 0.9, 1.3)
    assert spec.bulk_modulus == pytest.approx(bulk_ratio(0.49) * mu_t)
    assert bulk_ratio(0.49) == pytest.approx(2 * 1.49 / (3 * 0.02))
    assert 1.29 <= at <= 1.3                     # the liver stiffens: the largest tangent is at the tension end
    # independent: the material's uniaxial tangent dP/dlam at 1.3 by central differences
    from esmm.pipeline.materials.loading import nominal_stress
    from esmm.pipeline.materials.material import load_material

    liver = load_material("porcine_liver_paper")
    h = 1e-5
    dP = (nominal_stress(liver.model_obj, liver.params, "uniaxial", at + h)
          - nominal_stress(liver.model_obj, liver.params, "uniaxial", at - h)) / (2 * h)
    assert mu_t == pytest.approx(float(dP) / 3, rel=2e-3)
    # small-strain tangent: E/3 with E = mu_e(1) = 0.0149231 MPa (docs/design/model.md)
    mu0, _ = tangent_shear_modulus(tables, 0.999, 1.001)
    assert mu0 == pytest.approx(0.0149231e6 / 3, rel=5e-3)    # (the largest over the window: stiffening)
    assert mu_t / mu0 > 30


def test_spec_and_elements_refuse_bad_input(block):
    with pytest.raises(ConfigError, match="bulk_modulus"):
        VolumeSpec(-1.0)
    with pytest.raises(ConfigError, match="formulation"):
        VolumeSpec(1.0, "hex")
    with pytest.raises(ConfigError, match="poisson_ratio"):
        bulk_modulus(None, poisson=0.5)
    with pytest.raises(InputError, match="no tetrahedra"):
        volume_elements(block.points, np.zeros((0, 4), int), VolumeSpec(1.0))
    bad = block.tets.copy()
    bad[0] = bad[0][[1, 0, 2, 3]]
    with pytest.raises(InputError, match="positively oriented"):
        volume_elements(block.points, bad, VolumeSpec(1.0))
