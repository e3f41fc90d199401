"""The sparse linear algebra shared by the network's static solvers, the continuum reference and the simulator.

* :func:`node_ordering`: a fill-reducing order of a 3x3-block matrix (METIS
  nested dissection of its node graph), expanded to the dofs;
  :func:`restricted_order` carries it to a submatrix, :func:`free_order` to
  the free dofs' tangent.
* :func:`ldlt`: an :math:`LDL^T`-type factorization of a symmetric matrix in
  that order (SuperLU without pivoting, symmetric mode); :class:`OrderedFactor`
  solves with it in the original numbering; :func:`at_round_off` tells
  whether a solution without pivoting is one.
* :func:`descent_direction`: the Newton direction of ``esmm prepare``'s
  virtual tensile test (:mod:`~esmm.pipeline.compensation.virtual_tensile`) and ``esmm validate``'s network
  solve (:mod:`esmm.pipeline.fidelity.network_solve`), with the exact sparse
  tangent.

Why nested dissection and no pivoting: on the networks' tangents it fills
less and factors several times faster than SuperLU's own orders with pivoting
(COLAMD; docs/design/validation.md, "The continuum reference"); no
pivoting is exact for a positive definite matrix, and a solution that is not
at round-off (an indefinite tangent's small pivot) is solved again by the LU
with COLAMD, which pivots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

__all__ = ["OrderedFactor", "at_round_off", "descent_direction", "free_order", "ldlt", "node_ordering",
           "ordered_solve", "restricted_order"]


def node_ordering(A) -> np.ndarray:
    """Fill-reducing dof permutation of *A* (3n, 3n) with 3x3 blocks: METIS nested dissection of its node graph.

    Returns
    -------
    ndarray, shape (3n,), int64
        ``perm`` such that ``A[perm][:, perm]`` is factored with little fill.
    """
    import pymetis

    A = sp.csr_matrix(A)
    n = A.shape[0] // 3
    rows = A[0::3].tocsr()                          # node a's first row holds every block column
    nodes = rows.indices // 3
    rid = np.repeat(np.arange(n), np.diff(rows.indptr))
    key = np.unique(rid.astype(np.int64) * n + nodes)
    r, c = key // n, key % n
    keep = r != c
    r, c = r[keep], c[keep]
    xadj = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))]).astype(np.int64)
    if c.size == 0:
        order = np.arange(n)
    else:
        graph = pymetis.CSRAdjacency(xadj, c.astype(np.int64))
        perm, _ = pymetis.nested_dissection(adjacency=graph)      # row i of A' is row perm[i] of A
        order = np.asarray(perm, dtype=np.int64)
    return (3 * order[:, None] + np.arange(3)).ravel()


def restricted_order(perm: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The order *perm* of the whole matrix carried to its rows and columns *keep* (a boolean mask).

    Returns a permutation of ``range(keep.sum())``: the kept dofs in the
    order *perm* visits them.
    """
    keep = np.asarray(keep, dtype=bool)
    pos = np.full(keep.size, -1, dtype=np.int64)
    pos[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
    p = pos[np.asarray(perm)]
    return p[p >= 0]


def free_order(K, free: np.ndarray) -> np.ndarray:
    """The order of the free dofs' tangent ``K[free][:, free]``: :func:`node_ordering` of the whole *K*, restricted."""
    return restricted_order(node_ordering(K), free)


def ldlt(A, perm: np.ndarray, *, dtype=np.float64):
    """SuperLU of ``A[perm][:, perm]`` without pivoting, in symmetric mode (an LDLᵀ for a symmetric *A*).

    Raises RuntimeError (SuperLU's) on an exactly zero pivot.
    """
    B = sp.csr_matrix(A)[perm][:, perm].tocsc().astype(dtype)
    return spl.splu(B, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


@dataclass(eq=False)
class OrderedFactor:
    """:func:`ldlt`'s factor, solved in the original numbering.

    SuperLU's solves with many right-hand sides at once slow down steeply
    beyond a few columns, so :meth:`solve` takes at most three at a time.
    """

    perm: np.ndarray
    lu: object
    dtype: type = np.float64       #: the factor's (float32: a preconditioner, not a solver)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for *b* of shape (N,) or (N, k)."""
        out = np.empty_like(b, dtype=np.float64)
        if b.ndim == 1:
            out[self.perm] = self.lu.solve(np.ascontiguousarray(b[self.perm], dtype=self.dtype))
            return out
        for c in range(0, b.shape[1], 3):
            out[self.perm, c:c + 3] = self.lu.solve(np.ascontiguousarray(b[self.perm, c:c + 3], dtype=self.dtype))
        return out


def at_round_off(A, x: np.ndarray, b: np.ndarray) -> bool:
    """Whether *x* solves ``A x = b`` to round-off (the check of a solve without pivoting)."""
    if not np.all(np.isfinite(x)):
        return False
    return float(np.abs(A @ x - b).max()) <= 1e-9 * float(np.abs(b).max() + abs(A).max() * np.abs(x).max())


def ordered_solve(A, b, order):
    """``(x, factor)`` of ``A x = b``: the LDLᵀ in *order* (an :class:`OrderedFactor`) if at round-off,
    else the LU with COLAMD (SuperLU's object); ``(None, None)`` when *A* is exactly singular."""
    if order is not None:
        try:
            fac = OrderedFactor(order, ldlt(A, order))
            x = fac.solve(b)
            if at_round_off(A, x, b):
                return x, fac
        except RuntimeError:                  # a zero pivot
            pass
    try:
        lu = spl.splu(A.tocsc(), permc_spec="COLAMD", options={"SymmetricMode": True})
    except RuntimeError:                      # exactly singular
        return None, None
    return lu.solve(b), lu


def descent_direction(K, g, *, order: np.ndarray | None = None):
    """Newton direction ``-K^-1 g`` and its factorization; K shifted towards positive definite when needed.

    Parameters
    ----------
    K : sparse matrix, shape (m, m)
        The tangent on the free degrees of freedom (symmetric).
    g : ndarray, shape (m,)
        The gradient of the potential (minus the free residual forces).
    order : ndarray, shape (m,), optional
        A fill-reducing order of K (:func:`free_order`): K is factored
        without pivoting in that order, and by the LU with COLAMD when that
        solution is not at round-off. None: the LU with COLAMD.

    Returns
    -------
    (d, factor) : (ndarray of shape (m,), object with ``solve``) or (None, None)
        *d* a descent direction (``g @ d < 0``) and the factorization of the
        (possibly shifted) tangent that gave it; None when eight shifts
        (1e-4 times the mean |diagonal|, then tenfold) gave none.
    """
    K = K.tocsc()
    scale = float(np.mean(np.abs(K.diagonal()))) or 1.0
    shift = 0.0
    for _ in range(8):
        A = K if shift == 0.0 else (K + shift * sp.identity(K.shape[0], format="csc")).tocsc()
        x, fac = ordered_solve(A, g, order)
        if x is not None and np.all(np.isfinite(x)) and float(g @ x) > 0:
            return -x, fac
        shift = 1e-4 * scale if shift == 0.0 else shift * 10.0
    return None, None
