"""The sparse Newton direction shared by the network's static solvers.

``esmm prepare``'s virtual tensile test (:mod:`.tensile_test`) and ``esmm
validate``'s network solve (:mod:`esmm.pipeline.fidelity.network_solve`) both
take Newton steps on the network's potential with the exact sparse tangent;
this is their one linear solve.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

__all__ = ["descent_direction", "lu_ordering"]


def lu_ordering(volume_term: bool) -> str:
    """SuperLU's column ordering for a network tangent, with or without the volume term.

    The springs alone couple each node to its neighbours (35 entries a row on
    the liver): the minimum degree ordering on ``A^T + A`` factors them
    fastest (0.04 s for 4 980 unknowns, COLAMD 0.07 s). The nodal volume term
    couples every node to its second neighbours (145 entries a row): there the
    minimum degree fills the factor almost densely (19.6 M entries, 3.3 s)
    and COLAMD gives 5.3 M entries in 0.4 s (docs/validate.md, timing).
    """
    return "COLAMD" if volume_term else "MMD_AT_PLUS_A"


def descent_direction(K, g, *, ordering: str = "MMD_AT_PLUS_A"):
    """Newton direction ``-K^-1 g`` and its factorization; K shifted towards positive definite when needed.

    Parameters
    ----------
    K : sparse matrix, shape (m, m)
        The tangent on the free degrees of freedom (symmetric).
    g : ndarray, shape (m,)
        The gradient of the potential (minus the free residual forces).
    ordering : str
        SuperLU's column ordering (:func:`lu_ordering`).

    Returns
    -------
    (d, lu) : (ndarray of shape (m,), SuperLU) or (None, None)
        *d* a descent direction (``g @ d < 0``) and the factorization of the
        (possibly shifted) tangent that gave it; None when eight shifts
        (1e-4 times the mean |diagonal|, then tenfold) gave none.
    """
    K = K.tocsc()
    scale = float(np.mean(np.abs(K.diagonal()))) or 1.0
    shift = 0.0
    for _ in range(8):
        A = K if shift == 0.0 else (K + shift * sp.identity(K.shape[0], format="csc")).tocsc()
        try:
            lu = spl.splu(A, permc_spec=ordering, options={"SymmetricMode": True})
            d = -lu.solve(g)
        except RuntimeError:  # exactly singular
            d = None
        if d is not None and np.all(np.isfinite(d)) and float(g @ d) < 0:
            return d, lu
        shift = 1e-4 * scale if shift == 0.0 else shift * 10.0
    return None, None
