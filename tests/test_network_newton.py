"""The sparse linear algebra shared by the network's static solvers (pipeline/linalg/newton.py)."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from esmm.pipeline.linalg.newton import (
    OrderedFactor,
    at_round_off,
    descent_direction,
    free_order,
    ldlt,
    node_ordering,
    restricted_order,
)


def _laplacian_3d(n: int) -> sp.csc_matrix:
    """A 3-D grid Laplacian plus a small diagonal (SPD), shape (n^3, n^3)."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    L = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    return (L + 1e-3 * sp.identity(n ** 3)).tocsc()


def _elastic_3d(n: int) -> sp.csc_matrix:
    """The grid Laplacian on 3x3 blocks (a node's three dofs coupled), shape (3 n^3, 3 n^3), SPD."""
    block = np.array([[2.0, 0.5, 0.2], [0.5, 2.0, 0.3], [0.2, 0.3, 2.0]])
    return sp.kron(_laplacian_3d(n), block).tocsc()


@pytest.mark.parametrize("ordered", [False, True])
def test_direction_solves_the_newton_system_with_either_factorization(ordered):
    K = _elastic_3d(5)
    free = np.ones(K.shape[0], bool)
    free[:9] = False                                   # three nodes held, as a case's prescribed nodes are
    Kf = K[free][:, free].tocsc()
    g = np.random.default_rng(1).standard_normal(Kf.shape[0])
    d, fac = descent_direction(Kf, g, order=free_order(K, free) if ordered else None)
    assert fac is not None
    np.testing.assert_allclose(Kf @ d, -g, atol=1e-9 * np.abs(g).max())
    assert float(g @ d) < 0
    np.testing.assert_allclose(fac.solve(g), -d, rtol=1e-12, atol=1e-14)   # the factor a caller keeps


def test_node_order_fills_less_than_colamd():
    K = _elastic_3d(9)
    p = node_ordering(K)
    assert sorted(p.tolist()) == list(range(K.shape[0]))
    assert np.array_equal(p.reshape(-1, 3) % 3, np.tile(np.arange(3), (K.shape[0] // 3, 1)))   # nodes kept whole
    nested = ldlt(K, p)
    colamd = spl.splu(K, permc_spec="COLAMD", options={"SymmetricMode": True})
    assert nested.nnz < 0.8 * colamd.nnz


def test_restricted_order_is_the_kept_dofs_in_the_whole_order():
    perm = np.array([4, 0, 3, 1, 2, 5])
    keep = np.array([True, False, True, True, True, False])     # dofs 0, 2, 3, 4 -> 0, 1, 2, 3
    assert restricted_order(perm, keep).tolist() == [3, 0, 2, 1]


def test_indefinite_tangent_is_shifted_to_a_descent_direction():
    K = _laplacian_3d(4) - 2.0 * sp.identity(64, format="csc")      # some negative eigenvalues
    assert np.linalg.eigvalsh(K.toarray()).min() < 0
    rng = np.random.default_rng(2)
    for order in (None, np.arange(64)):
        for _ in range(5):
            g = rng.standard_normal(64)
            d, _ = descent_direction(K, g, order=order)
            assert d is not None and float(g @ d) < 0


def test_tiny_pivot_in_the_order_falls_back_to_the_pivoting_lu():
    K = sp.csc_matrix(np.array([[1e-14, 1.0, 0.0], [1.0, 1e-14, 0.0], [0.0, 0.0, 2.0]]))   # indefinite
    g = np.array([1.0, -1.0, 3.0])                       # g K^-1 g = 2.5 > 0: -K^-1 g is a descent direction
    x = OrderedFactor(np.arange(3), ldlt(K, np.arange(3))).solve(g)
    assert not at_round_off(K, x, g)                     # the LDLᵀ in this order loses the answer
    d, fac = descent_direction(K, g, order=np.arange(3))
    assert not isinstance(fac, OrderedFactor)            # the LU with COLAMD solved it, unshifted
    np.testing.assert_allclose(K @ d, -g, atol=1e-12)
    d, fac = descent_direction(K + 3.0 * sp.identity(3, format="csc"), g, order=np.arange(3))
    assert isinstance(fac, OrderedFactor)                # positive definite: the ordered LDLᵀ is kept
