"""The sparse Newton direction shared by the virtual tensile test and validate's network solve."""

import numpy as np
import pytest
import scipy.sparse as sp
from esmm.pipeline.network.newton import descent_direction, lu_ordering


def _laplacian_3d(n: int) -> sp.csc_matrix:
    """A 3-D grid Laplacian plus a small diagonal (SPD), shape (n^3, n^3)."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    L = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    return (L + 1e-3 * sp.identity(n ** 3)).tocsc()


@pytest.mark.parametrize("volume_term", [False, True])
def test_direction_solves_the_newton_system_with_either_ordering(volume_term):
    K = _laplacian_3d(6)
    g = np.random.default_rng(1).standard_normal(K.shape[0])
    d, lu = descent_direction(K, g, ordering=lu_ordering(volume_term))
    assert lu is not None
    np.testing.assert_allclose(K @ d, -g, atol=1e-9 * np.abs(g).max())
    assert float(g @ d) < 0


def test_indefinite_tangent_is_shifted_to_a_descent_direction():
    K = _laplacian_3d(4) - 2.0 * sp.identity(64, format="csc")      # some negative eigenvalues
    assert np.linalg.eigvalsh(K.toarray()).min() < 0
    rng = np.random.default_rng(2)
    for _ in range(5):
        g = rng.standard_normal(64)
        d, _ = descent_direction(K, g, ordering="COLAMD")
        assert d is not None and float(g @ d) < 0
