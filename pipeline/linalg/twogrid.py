r"""A two-grid preconditioner on a split mesh's own hierarchy: the parents as the coarse level.

A split mesh (docs/design/model.md, "The network on the quadratic tetrahedra's nodes (`--split`)")
carries two levels: every node is a parent vertex or the middle of a parent edge, so a field
linear on each parent (the parents' P1 space) is carried to the split nodes exactly by
:func:`prolongation` (vertices copied, middles the mean of their edge's ends). The two-grid
operator :math:`B \approx A^{-1}` of the split network's matrix A (:class:`TwoGrid`) is, for a
right-hand side b,

.. math::

    x \leftarrow \omega D^{-1} b,\qquad
    x \leftarrow x + P A_c^{-1} P^{\mathsf T}(b - Ax),\qquad
    x \leftarrow x + \omega D^{-1}(b - Ax),\qquad A_c = P^{\mathsf T} A P,

with D the node blocks of A (block Jacobi, damped by :math:`\omega = 1/\lambda_{max}(D^{-1}A)`:
the smoother converges and B is symmetric positive definite) and :math:`A_c` the Galerkin product
(:class:`Galerkin`), factored by the supernodal :math:`LDL^T` (:mod:`.supernodal`). The coarse
factor has the parents' node count and fill, a small part of the split matrix's factor to take;
an application costs two products with A, the coarse solve and the block products.

Constraint rows (the grasp, the floor's contacts; :class:`TwoGridConstraints`) enter both levels.
In the smoother a held direction of a node is projected out of the residual, the products and
the correction (its operator is :math:`QAQ + (I - Q)`, Q the projection off the held directions)
and a coupling spring joins its node's block; on the coarse level the rows pass through the
prolongation, :math:`G = JP`, into the coarse factor's capacitance matrix (:class:`CoarseRows`),
so the coarse correction meets them too. The coarse factor, taken with the operator, does not
change with the rows. docs/design/twogrid.md has the method's measurements against the split
matrix's own factor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np
import scipy.sparse as sps

from .linsolve import Constraints, SparseFactor
from .newton import node_ordering
from .supernodal import Analysis, canonical

#: Power iterations estimating the largest eigenvalue of ``D^-1 A`` (the smoother's damping is its
#: inverse: the smoother then converges, and the two-grid operator is positive definite).
POWER_ITERATIONS = 8
#: Block-Jacobi sweeps before and after the coarse correction (one each: more cost a product with A
#: each and did not pay in the implicit step; docs/design/twogrid.md).
SWEEPS = 1
#: Eigenvalues of the coarse capacitance matrix below this fraction of its largest are dependent rows'.
RANK_TOL = 1e-6
#: The vertex pairs of a 10-node tetrahedron's middle nodes 4..9 (:mod:`esmm.pipeline.mesh.refine`'s
#: ``TET10_EDGES``; repeated here: the linear algebra does not import the mesh package).
TET10_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))


def prolongation(cells: np.ndarray, n: int, free: np.ndarray | None = None) -> tuple[sps.csr_matrix, np.ndarray]:
    """The split nodes' dofs from the parents' vertex dofs, linear on each parent.

    Parameters
    ----------
    cells : ndarray of int, shape (p, 10)
        The parents as 10-node tetrahedra on the split nodes (vertices, then the middles of
        :data:`TET10_EDGES`).
    n : int
        Split nodes.
    free : ndarray of bool, shape (n,), optional
        Nodes not fixed; a fixed node's rows of P are zero (its dofs do not move).

    Returns
    -------
    P : scipy.sparse.csr_matrix, shape (3n, 3m)
        Row ``3a + d`` of node a and axis d: 1 at its vertex's column ``3v + d``, or 1/2 at each of
        its edge's ends.
    vertices : ndarray of int, shape (m,)
        The split node of each coarse node (the parents' vertices, sorted).
    """
    cells = np.asarray(cells, dtype=np.int64)
    vertices = np.unique(cells[:, :4])
    col = np.full(n, -1, np.int64)
    col[vertices] = np.arange(vertices.size)
    mids = cells[:, 4:].ravel()
    ends = cells[:, np.array(TET10_EDGES)].reshape(-1, 2)
    rows = np.concatenate([vertices, mids, mids])
    cols = np.concatenate([col[vertices], col[ends[:, 0]], col[ends[:, 1]]])
    vals = np.concatenate([np.ones(vertices.size), np.full(2 * mids.size, 0.5)])
    # each middle appears once per parent around its edge: keep one (its ends are the same each time)
    key = rows * (vertices.size + 1) + cols
    _, first = np.unique(key, return_index=True)
    Pn = sps.csr_matrix((vals[first], (rows[first], cols[first])), shape=(n, vertices.size))
    if free is not None:
        Pn = sps.diags(np.asarray(free, dtype=np.float64)) @ Pn
    P = sps.kron(Pn, sps.eye(3), format="csr")
    P.eliminate_zeros()
    return P, vertices


@nb.njit(cache=True)
def _diagonal_blocks(indptr, indices, data, n):      # pragma: no cover - compiled
    """A's node diagonal blocks (n, 3, 3)."""
    out = np.zeros((n, 3, 3))
    for a in range(n):
        for d in range(3):
            r = 3 * a + d
            for p in range(indptr[r], indptr[r + 1]):
                j = indices[p]
                if 3 * a <= j < 3 * a + 3:
                    out[a, d, j - 3 * a] = data[p]
    return out


def _block_product(dinv: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The node blocks *dinv* (n, 3, 3) times *x* (3n,)."""
    return np.einsum("aij,aj->ai", dinv, x.reshape(-1, 3)).ravel()


def _largest_eigenvalue(A: sps.csr_matrix, dinv: np.ndarray) -> float:
    """An estimate of the largest eigenvalue of ``D^-1 A`` (D: A's node blocks) by power iteration."""
    x = np.random.default_rng(0).standard_normal(A.shape[0])
    lam = 1.0
    for _ in range(POWER_ITERATIONS):
        y = _block_product(dinv, A @ x)
        lam = float(np.linalg.norm(y) / np.linalg.norm(x))
        x = y
    return lam


def _expand(items: np.ndarray, start: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of *items* repeated *count* times, beside ``start, start + 1, ...`` (its range)."""
    rep = np.repeat(items, count)
    first = np.repeat(np.cumsum(count) - count, count)
    return rep, np.repeat(start, count) + np.arange(rep.size) - first


@dataclass(eq=False)
class Galerkin:
    """``P^T A P`` for matrices A of one sparsity pattern: a fixed linear map of A's entries.

    Each entry of A reaches at most four entries of the product (P has one or two entries a
    row), so the product's values are ``M @ A.data`` with M sparse, built once per pattern: a
    product of a few nonzeros per entry of A instead of two general sparse products.
    """

    indptr: np.ndarray
    indices: np.ndarray
    M: sps.csr_matrix
    pattern: sps.csr_matrix

    @classmethod
    def of(cls, A: sps.csr_matrix, P: sps.csr_matrix) -> Galerkin:
        """The map for *A*'s pattern (canonical CSR (N, N)) and *P* (N, M)."""
        P = sps.csr_matrix(P)
        row = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
        # each entry k = (i, j) of A with each entry p of P's row i, then each entry q of P's row j
        k, p = _expand(np.arange(A.nnz), P.indptr[row], np.diff(P.indptr)[row])
        col = A.indices[k]
        pair, q = _expand(np.arange(k.size), P.indptr[col], np.diff(P.indptr)[col])
        k, p = k[pair], p[pair]
        m = P.shape[1]
        key = P.indices[p] * m + P.indices[q]
        uniq, pos = np.unique(key, return_inverse=True)
        M = sps.csr_matrix((P.data[p] * P.data[q], (pos, k)), shape=(uniq.size, A.nnz))
        pattern = canonical(sps.csr_matrix((np.ones(uniq.size), (uniq // m, uniq % m)), shape=(m, m)))
        return cls(indptr=A.indptr.copy(), indices=A.indices.copy(), M=M, pattern=pattern)

    def matches(self, A: sps.csr_matrix) -> bool:
        return np.array_equal(A.indptr, self.indptr) and np.array_equal(A.indices, self.indices)

    def product(self, A: sps.csr_matrix) -> sps.csr_matrix:
        """``P^T A P`` (canonical CSR (M, M)) for *A* of this map's pattern."""
        out = self.pattern.copy()
        out.data = self.M @ A.data
        return out


@dataclass(eq=False)
class CoarseRows:
    r"""Constraint rows on the coarse level, :math:`G = JP` (a row of a held or coupled split node's
    direction, through the prolongation: one or two coarse nodes), joined to the coarse factor by
    the capacitance matrix as :class:`~.linsolve.Constraints` joins rows to the split factor
    (the forward halves of the solves of G's columns, on their paths in the supernode tree).

    Rows of G may depend on each other (a parent vertex's whole support held), so the capacitance
    matrix is inverted on its range (a pseudo-inverse): the coarse correction then meets every row
    it can.
    """

    factor: SparseFactor
    R: np.ndarray
    Y: np.ndarray
    dY: np.ndarray
    cap_pinv: np.ndarray

    @classmethod
    def of(cls, factor: SparseFactor, G: sps.csr_matrix, comp: np.ndarray) -> CoarseRows:
        """Rows *G* (c, M) with compliances *comp* (c,) on the coarse *factor*."""
        G = sps.csr_matrix(G)
        dofs = np.unique(G.indices)
        R, Yu = factor.columns(dofs)                                     # (r, d) of the unit vectors
        coef = sps.csr_matrix(G[:, dofs].T)                              # (d, c)
        Y = np.asarray((coef.T @ Yu.T).T)                                # (r, c)
        dY = factor.dinv[R].astype(np.float64)[:, None] * Y
        cap = Y.T @ dY + np.diag(comp)
        cap = 0.5 * (cap + cap.T)
        w, V = np.linalg.eigh(cap)
        keep = w > RANK_TOL * max(float(w.max()), 0.0)
        cap_pinv = (V[:, keep] / w[keep]) @ V[:, keep].T
        return cls(factor=factor, R=R, Y=Y, dY=dY, cap_pinv=cap_pinv)

    def solve(self, r: np.ndarray) -> np.ndarray:
        """The coarse solve of *r* (M,) in the rows' null space (for the held rows; the coupled
        rows' springs added)."""
        fac = self.factor
        y = fac.forward(r)
        y *= fac.dinv
        yR = y[self.R].astype(np.float64)
        y[self.R] = (yR - self.dY @ (self.cap_pinv @ (self.Y.T @ yR))).astype(y.dtype)
        return fac.backward(y)


@dataclass(frozen=True)
class Rows:
    """Constraint rows as the smoother sees them (:meth:`TwoGrid.rows`).

    Attributes
    ----------
    hard : ndarray of int, shape (h,)
        Nodes with held directions.
    H : ndarray, shape (h, 3, 3)
        The projection onto each one's held directions.
    soft : ndarray of int, shape (s,)
        Nodes with coupling springs.
    K : ndarray, shape (s, 3, 3)
        Their springs' stiffness, ``sum k e e^T``.
    dinv : ndarray, shape (n, 3, 3)
        The smoother's block inverses with the rows: of ``Q (D + K) Q + (I - Q)`` at each node.
    coarse : CoarseRows or None
        The rows on the coarse level (None: none).
    """

    hard: np.ndarray
    H: np.ndarray
    soft: np.ndarray
    K: np.ndarray
    dinv: np.ndarray
    coarse: CoarseRows | None = None


@dataclass(eq=False)
class TwoGrid:
    """The two-grid operator B of a split network's matrix (module doc), taken once per matrix.

    Attributes
    ----------
    A : scipy.sparse.csr_matrix, shape (N, N)
        The split level's matrix (float64).
    P : scipy.sparse.csr_matrix, shape (N, M)
        The prolongation (:func:`prolongation`).
    coarse : SparseFactor
        The Galerkin product ``P^T A P`` (:class:`Galerkin`) factored.
    blocks : ndarray, shape (N / 3, 3, 3)
        A's node diagonal blocks.
    galerkin : Galerkin
        The coarse product's map (kept for the next operator of the same pattern).
    omega : float
        The smoother's damping, ``1 / lambda_max(D^-1 A)`` (estimated for a run's first operator).
    sweeps : int
        Smoothing sweeps before and after the coarse correction.
    seconds : float
        Time taking it took (the coarse product, its factorization, the smoother's blocks).
    analysis_s : float
        Of it, the coarse factor's symbolic analysis, where it needed a new one (else 0).
    """

    A: sps.csr_matrix
    P: sps.csr_matrix
    coarse: SparseFactor
    blocks: np.ndarray = field(repr=False)
    galerkin: Galerkin = field(repr=False)
    omega: float = 1.0
    sweeps: int = SWEEPS
    seconds: float = 0.0
    analysis_s: float = 0.0
    applications: int = 0
    free: Rows = field(init=False, repr=False)          #: the rows of no constraint

    def __post_init__(self):
        empty = np.zeros(0, np.int64)
        self.free = Rows(empty, np.zeros((0, 3, 3)), empty, np.zeros((0, 3, 3)), np.linalg.inv(self.blocks))

    @classmethod
    def of(cls, A, P, *, sweeps: int = SWEEPS, single: bool = True, previous: TwoGrid | None = None,
           threads: int = 1) -> TwoGrid:
        """Take the operator of *A* (N, N), symmetric positive definite, on the prolongation *P*
        (N, M), with *previous*'s Galerkin map, coarse analysis and damping where *A* has its
        pattern (it does over a run)."""
        t = time.perf_counter()
        A = canonical(A).astype(np.float64)
        same = previous is not None and previous.galerkin.matches(A)
        galerkin = previous.galerkin if same else Galerkin.of(A, P)
        Ac = galerkin.product(A)
        empty = ~(np.abs(Ac.diagonal()) > 0.0)      # a coarse node whose whole basis function is fixed
        if np.any(empty):
            Ac = canonical(Ac + sps.diags(empty.astype(np.float64)))
        analysis = previous.analysis if same else None
        perm = None if analysis is not None and analysis.matches(Ac) else node_ordering(Ac)
        coarse = SparseFactor.of(Ac, perm, single=single, analysis=analysis, threads=threads)
        blocks = _diagonal_blocks(A.indptr, A.indices, A.data, A.shape[0] // 3)
        omega = previous.omega if same else 1.0 / _largest_eigenvalue(A, np.linalg.inv(blocks))
        return cls(A=A, P=sps.csr_matrix(P), coarse=coarse, blocks=blocks, galerkin=galerkin, omega=omega,
                   sweeps=int(sweeps), seconds=time.perf_counter() - t, analysis_s=coarse.analysis_s)

    @property
    def nnz(self) -> int:
        """Nonzeros of the coarse factor."""
        return self.coarse.nnz

    @property
    def analysis(self) -> Analysis:
        """The coarse factor's symbolic analysis (for the next operator of the same pattern)."""
        return self.coarse.analysis

    @property
    def ldl(self):
        """The coarse factor's :class:`~.supernodal.LDLT` (its solves' threads)."""
        return self.coarse.ldl

    def rows(self, node: np.ndarray, e: np.ndarray, comp: np.ndarray) -> Rows:
        """The smoother's view of constraint rows: *node* (c,), unit *e* (c, 3), compliance *comp* (c,),
        0 for a held direction (the held directions of a node need not be orthogonal)."""
        node = np.asarray(node, dtype=np.int64)
        hard = comp == 0.0
        hn = np.unique(node[hard])
        H = np.zeros((hn.size, 3, 3))
        for q, a in enumerate(hn):
            E = e[hard & (node == a)]
            u, sv, _ = np.linalg.svd(E.T, full_matrices=False)
            U = u[:, sv > 1e-12 * sv.max()]
            H[q] = U @ U.T
        sn = np.unique(node[~hard])
        K = np.zeros((sn.size, 3, 3))
        k = 1.0 / comp[~hard]
        np.add.at(K, np.searchsorted(sn, node[~hard]), k[:, None, None] * e[~hard, :, None] * e[~hard, None, :])
        dinv = self.free.dinv.copy()
        if sn.size:
            dinv[sn] = np.linalg.inv(self.blocks[sn] + K)
        if hn.size:
            D = self.blocks[hn].copy()
            _, ks, kh = np.intersect1d(sn, hn, return_indices=True)
            D[kh] += K[ks]
            Q = np.eye(3) - H
            dinv[hn] = np.linalg.inv(Q @ D @ Q + H)
        J = sps.csr_matrix((e.ravel(), ((np.arange(node.size)[:, None] + np.zeros(3, np.int64)).ravel(),
                                        (3 * node[:, None] + np.arange(3)).ravel())), shape=(node.size, self.A.shape[0]))
        coarse = CoarseRows.of(self.coarse, J @ self.P, comp) if node.size else None
        return Rows(hn, H, sn, K, dinv, coarse)

    def _project(self, x: np.ndarray, rows: Rows) -> np.ndarray:
        """*x* (3n,) without its held components, in place."""
        if rows.hard.size:
            x3 = x.reshape(-1, 3)
            x3[rows.hard] -= np.einsum("aij,aj->ai", rows.H, x3[rows.hard])
        return x

    def _residual(self, b: np.ndarray, x: np.ndarray, rows: Rows) -> np.ndarray:
        """``b - Q(A + K)x`` for x in the range of Q (Q b = b)."""
        y = self.A @ x
        if rows.soft.size:
            y3, x3 = y.reshape(-1, 3), x.reshape(-1, 3)
            y3[rows.soft] += np.einsum("aij,aj->ai", rows.K, x3[rows.soft])
        return b - self._project(y, rows)

    def solve(self, b: np.ndarray, rows: Rows | None = None) -> np.ndarray:
        """``B b`` for *b* (N,) (float64); with *rows*, B of the constrained matrix, zero on the held
        directions (module doc)."""
        rows = self.free if rows is None else rows
        b = self._project(np.array(b, dtype=np.float64), rows)
        w = self.omega
        x = w * _block_product(rows.dinv, b)
        for _ in range(self.sweeps - 1):
            x += w * _block_product(rows.dinv, self._residual(b, x, rows))
        rc = self.P.T @ self._residual(b, x, rows)
        x += self._project(self.P @ (self.coarse.solve(rc) if rows.coarse is None else rows.coarse.solve(rc)), rows)
        for _ in range(self.sweeps):
            x += w * _block_product(rows.dinv, self._residual(b, x, rows))
        self.applications += 1
        return x


@dataclass(eq=False)
class TwoGridConstraints(Constraints):
    r"""Constraint rows on a :class:`TwoGrid`: in its smoother (module doc), not by a capacitance matrix.

    The projection the stepper needs, a preconditioner zero on the held directions, is the two-grid
    operator of the matrix with those directions eliminated (:meth:`TwoGrid.rows`); coupling springs
    join the matrix. The grasped patch's stiffness (:meth:`block_stiffness`) is read from the coarse
    level's capacitance matrix.

    Parameters
    ----------
    factor : TwoGrid
    n : int
        Nodes.
    """

    _rows: Rows | None = field(default=None, repr=False)

    @property
    def has_rows(self) -> bool:
        return self.node.size > 0

    def set_rows(self, node: np.ndarray, e: np.ndarray, comp: np.ndarray) -> None:
        """Use rows (*node* (c,), unit *e* (c, 3), compliance *comp* (c,)); kept where they are the ones
        in use."""
        node = np.asarray(node, dtype=np.int64)
        e = np.asarray(e, dtype=np.float64).reshape(-1, 3)
        comp = np.asarray(comp, dtype=np.float64)
        if (self._rows is not None and np.array_equal(node, self.node) and np.array_equal(e, self.e)
                and np.array_equal(comp, self.comp)):
            return
        t = time.perf_counter()
        self.node, self.e, self.comp = node, e, comp
        self._rows = self.factor.rows(node, e, comp)
        self.columns_s += time.perf_counter() - t

    def apply(self, r: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
        """The constrained two-grid operator applied to *r* (zero on *fixed* dofs and held directions)."""
        if fixed is not None:
            r = np.where(fixed, 0.0, r)
        t = time.perf_counter()
        z = self.factor.solve(r, self._rows)
        dt = time.perf_counter() - t
        self.solve_s += dt
        self.solves += 1
        self.apply_s.append(dt)
        if fixed is not None:
            z[fixed] = 0.0
        return z

    def block_stiffness(self, rows: np.ndarray) -> np.ndarray:
        """``sum over rows a, b of [C_c^+]_ab e_a e_b^T`` (3, 3): the stiffness of moving those rows together
        on the coarse level (:class:`CoarseRows`' capacitance matrix; the parents' P1 fields, so stiffer
        than the split matrix's own Schur complement, which the operator has no cheap way to read)."""
        rows = np.asarray(rows, dtype=np.int64)
        if self._rows is None or self._rows.coarse is None or rows.size == 0:
            return np.zeros((3, 3))
        E = self.e[rows]
        return E.T @ self._rows.coarse.cap_pinv[np.ix_(rows, rows)] @ E
