"""The continuum reference's linear solves: one per Newton iteration, nearly all of a validation's time.

* P2 (:class:`NodeDissection`): the system of the displacements alone (the
  P0 pressure and volume ratio are condensed element by element, so it is
  symmetric, and positive definite at a stable equilibrium) is factored by
  esmm's supernodal multifrontal LDLᵀ without pivoting
  (:mod:`esmm.pipeline.linalg.supernodal`) in the nested-dissection order of
  the mesh's node graph (METIS). The order depends on the mesh only and its
  symbolic analysis on the free degrees of freedom only, so both are kept
  (:class:`_Memo`) and shared by every Newton iteration, load step, floor
  round and case of the same mesh: each iteration only factors numerically.
  A solution whose residual is not at round-off (a tangent the line search
  took through an unstable state) is solved again by SuperLU's LU with
  COLAMD, which pivots.
* MINI (:class:`CondensedMini`): the bubbles condensed element by element,
  the vertex system by SuperLU's LU.

Why not SuperLU for P2 (docs/design/validation.md, "The continuum reference"):
SuperLU in symmetric mode without pivoting in the same order keeps
``U = D Lᵀ`` beside L and factors supernode by supernode with its own
kernels; the multifrontal LDLᵀ factors the same fill with one dense matrix
product per front, in less than half the time on an organ's P2 system.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

from ..blas import single_threaded_blas
from ..linalg.newton import at_round_off, node_ordering, restricted_order
from ..linalg.supernodal import LDLT, Analysis, ZeroPivot, canonical

__all__ = ["CondensedMini", "NodeDissection", "lu_solve", "mesh_order"]


def lu_solve(A, b):
    """SuperLU with COLAMD: faster on these systems than scipy's spsolve default, and far faster than MMD."""
    import scipy.sparse.linalg as spl

    return spl.splu(A.tocsc(), permc_spec="COLAMD").solve(np.asarray(b, dtype=np.float64).ravel())


class _Memo:
    """A few results kept by key, the oldest dropped first (the orders and analyses of the meshes in use)."""

    def __init__(self, size: int):
        self.size, self.items = size, OrderedDict()

    def get(self, key, make):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = self.items[key] = make()
        while len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


_ORDERS = _Memo(4)        #: mesh digest -> dof order of the whole mesh
_ANALYSES = _Memo(4)      #: (mesh digest, free dofs digest) -> Analysis


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def mesh_order(cells: np.ndarray, n_nodes: int) -> np.ndarray:
    """Fill-reducing order of the dofs (3 per node, node-major) of a mesh's *cells* (c, k): METIS nested
    dissection of the node graph (nodes sharing a cell are neighbours), shape (3 n,).

    The same order :func:`~esmm.pipeline.linalg.newton.node_ordering` gives the mesh's stiffness matrix."""
    return _ORDERS.get(_digest(cells, np.int64(n_nodes)), lambda: _node_graph_order(cells, n_nodes)).copy()


def _node_graph_order(cells: np.ndarray, n_nodes: int) -> np.ndarray:
    import scipy.sparse as sp

    cells = np.asarray(cells, dtype=np.int64)
    k = cells.shape[1]
    a = np.repeat(cells, k, axis=1).ravel()
    b = np.tile(cells, (1, k)).ravel()
    # node_ordering reads each node's first dof row: the graph's edges are put there
    P = sp.csr_matrix((np.ones(a.size), (3 * a, 3 * b)), shape=(3 * n_nodes, 3 * n_nodes))
    return node_ordering(P)


class NodeDissection:
    """The P2 system (displacements only: P0 pressure and volume ratio condensed, symmetric) by an LDLᵀ.

    Called as felupe's linear solver, ``solver(A, b)`` with *A* the system of
    the free dofs *dof1*. The order is the nested dissection of the mesh's
    node graph restricted to *dof1* (:func:`mesh_order`; without *cells*,
    that of *A*'s own node graph); the symbolic analysis of *A*'s pattern is
    kept for the next call, and for the next solver of the same mesh and free
    dofs. A zero pivot or a solution whose residual is not at round-off is
    solved again by the LU with COLAMD (counted in ``fallbacks``).

    Parameters
    ----------
    dof1 : ndarray of int, shape (m,)
        The free dofs among the field's (3 per node, node-major), sorted.
    cells : ndarray of int, shape (c, k), optional
        The mesh's cells (10-node tetrahedra).
    n_nodes : int, optional
        The mesh's nodes (with *cells*).
    """

    def __init__(self, dof1: np.ndarray, cells: np.ndarray | None = None, n_nodes: int | None = None):
        self.dof1, self.perm, self.count, self.fallbacks = np.asarray(dof1), None, 0, 0
        self.cells, self.n_nodes = cells, n_nodes
        self.analysis: Analysis | None = None
        self._key = None

    def _order(self, A) -> np.ndarray:
        import scipy.sparse as sp

        n = int(self.dof1.max()) // 3 + 1 if self.n_nodes is None else int(self.n_nodes)
        if self.cells is not None:
            full = mesh_order(self.cells, n)
            self._key = (_digest(self.cells, np.int64(n)), _digest(self.dof1))
        else:
            C = A.tocoo()        # node_ordering reads each node's first row: put every block's columns there
            P = sp.csr_matrix((np.ones(C.nnz), (3 * (self.dof1[C.row] // 3), self.dof1[C.col])),
                              shape=(3 * n, 3 * n))
            full = node_ordering(P)
        keep = np.zeros(3 * n, bool)
        keep[self.dof1] = True
        return restricted_order(full, keep)

    def _factor(self, A) -> LDLT:
        if self.analysis is None and self._key is not None:
            self.analysis = _ANALYSES.get(self._key, lambda: Analysis.of(A, self.perm))
        with single_threaded_blas():         # one dense product per front: OpenBLAS threads only contend
            fac = LDLT.of(A, self.analysis, perm=self.perm)
        self.analysis = fac.analysis
        return fac

    def __call__(self, A, b):
        self.count += 1
        A = canonical(A)
        b = np.asarray(b, dtype=np.float64).ravel()
        if self.perm is None:
            self.perm = self._order(A)
        try:
            x = self._factor(A).solve(b)
            if at_round_off(A, x, b):
                return x
        except ZeroPivot:
            pass
        self.fallbacks += 1
        import scipy.sparse.linalg as spl

        try:
            return spl.splu(A.tocsc(), permc_spec="COLAMD", options={"SymmetricMode": True}).solve(b)
        except RuntimeError as exc:
            raise RuntimeError("the P2 system is exactly singular") from exc


class CondensedMini:
    """The MINI system with its bubble unknowns condensed out, element by element.

    A bubble lives in one element, so the bubble-bubble block is block
    diagonal (3 x 3 per element) and its inverse is exact and cheap: the
    vertex system ``S = A_ss − A_sb A_bb⁻¹ A_bs`` (displacement, pressure and
    volume ratio at the vertices, a third of the unknowns) is factorised
    instead of the whole one, then the bubbles follow. The same solution, several
    times faster (docs/design/validation.md, "The continuum reference"); the
    whole LU if a block is singular.
    """

    def __init__(self, dof1: np.ndarray, n_vertices: int, n_cells: int):
        bubble = (dof1 >= 3 * n_vertices) & (dof1 < 3 * (n_vertices + n_cells))
        self.b, self.s = np.flatnonzero(bubble), np.flatnonzero(~bubble)
        nb = self.b.size // 3
        k = 3 * np.arange(nb)[:, None, None]
        self.rows = np.broadcast_to(k + np.arange(3)[None, :, None], (nb, 3, 3)).ravel()
        self.cols = np.broadcast_to(k + np.arange(3)[None, None, :], (nb, 3, 3)).ravel()
        self.count = 0

    def __call__(self, A, b):
        import scipy.sparse as sp
        import scipy.sparse.linalg as spl

        self.count += 1
        A = A.tocsr()
        b = np.asarray(b, dtype=np.float64).ravel()
        Ab = A[self.b]
        Abb, Abs = Ab[:, self.b].tocsr(), Ab[:, self.s].tocsr()
        As = A[self.s]
        Asb, Ass = As[:, self.b].tocsr(), As[:, self.s].tocsr()
        nb = self.b.size // 3
        blocks = np.asarray(Abb[self.rows, self.cols]).reshape(nb, 3, 3)
        try:
            inv = np.linalg.inv(blocks)
        except np.linalg.LinAlgError:
            return lu_solve(A, b)
        Binv = sp.bsr_matrix((inv, np.arange(nb), np.arange(nb + 1)), shape=Abb.shape).tocsr()
        S = (Ass - Asb @ (Binv @ Abs)).tocsc()
        xs = spl.splu(S, permc_spec="COLAMD").solve(b[self.s] - Asb @ (Binv @ b[self.b]))
        x = np.empty_like(b)
        x[self.s], x[self.b] = xs, Binv @ (b[self.b] - Abs @ xs)
        return x
