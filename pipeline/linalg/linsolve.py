r"""Sparse linear algebra of the implicit stepper: a reused factorization, constraints, conjugate gradients.

* :class:`SparseFactor`: an :math:`LDL^T` factorization of a symmetric
  matrix in a nested-dissection order (:mod:`esmm.pipeline.linalg.newton`'s
  :func:`~esmm.pipeline.linalg.newton.node_ordering`; the supernodal
  factorization of :mod:`esmm.pipeline.linalg.supernodal`), used as the
  Newton iteration's preconditioner for many steps; :class:`MixedFactor`: Newton's matrix with
  the volume term held as a saddle point of its parts (less fill than the
  matrix itself);
* :class:`Constraints`: dofs held by hard constraints (prescribed grasp, floor
  contacts: a node, or its normal component) or by stiff coupling springs
  (the grasper in mode "spring"), joined to the factor by the capacitance
  (Sherman-Morrison-Woodbury) matrix :math:`C = JP^{-1}J^T + D` so that the
  factor never changes with them; its inverse gives the grasped patch's
  stiffness in the step's linear model (the 1 kHz grasper force);
* :func:`pcg`: preconditioned conjugate gradients in the constraints' null
  space (the preconditioner :math:`\Pi = P^{-1} - W C^{-1} W^T`,
  :math:`W = P^{-1}J^T`, maps any residual into it; applied as one solve whose
  two halves are joined by the correction, :class:`Constraints`).

docs/design/simulator.md ("What is factored, and when it is renewed", "Constraints by the
capacitance matrix") explains the choices.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sps

from ..errors import SimulationError
from .newton import node_ordering
from .supernodal import LDLT, Analysis, ZeroPivot, canonical


@dataclass(eq=False)
class SparseFactor:
    """A symmetric matrix factored once, in a nested-dissection order, for many solves.

    The supernodal multifrontal :math:`LDL^T` of
    :mod:`esmm.pipeline.linalg.supernodal` (no pivoting: the stepper's matrix
    is positive definite). Its symbolic analysis is taken over from the last
    factor (*analysis*) while the pattern stays the same, which it does over a
    run: a refactorization is then the numeric phase alone. Several times
    faster to factor and to solve than SuperLU in symmetric mode
    (:mod:`esmm.pipeline.linalg.supernodal`).

    Attributes
    ----------
    perm : ndarray, shape (N,)
        The order factored (the caller's, postordered).
    seconds : float
        Time the factorization took.
    analysis_s : float
        Of it, the symbolic analysis, where this factor needed a new one (else 0).
    nnz : int
        Nonzeros of L (fill).
    """

    ldl: LDLT
    seconds: float = 0.0
    analysis_s: float = 0.0

    @property
    def perm(self) -> np.ndarray:
        return self.ldl.analysis.perm

    @property
    def analysis(self) -> Analysis:
        return self.ldl.analysis

    @property
    def dtype(self):
        return self.ldl.dtype

    @property
    def nnz(self) -> int:
        return self.ldl.nnz

    @classmethod
    def of(cls, A, perm: np.ndarray | None = None, *, single: bool = False,
           analysis: Analysis | None = None, threads: int = 1) -> SparseFactor:
        """Factor *A* (N, N), in order *perm* (default: :func:`node_ordering`), with *analysis* (a
        former factor's, see :attr:`analysis`) when *A* has its pattern.

        *single*: factor and solve in float32 (faster solves, a relative residual about 1e-4:
        a preconditioner, not a solver).
        *threads*: 1, or 2 for the factorization and its solves both (one setting for the two:
        :mod:`esmm.pipeline.linalg.supernodal`).
        """
        t = time.perf_counter()
        A = canonical(A)
        if perm is None and (analysis is None or not analysis.matches(A)):
            perm = node_ordering(A)
        ldl, analysis_s = _factor(A, analysis, perm, np.float32 if single else np.float64, threads)
        return cls(ldl=ldl, seconds=time.perf_counter() - t, analysis_s=analysis_s)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for *b* of shape (N,) or (N, k) (float64)."""
        return self.ldl.solve(b)

    # -- a solve in two halves, for the constraints' correction between them ------------------
    @property
    def dinv(self) -> np.ndarray:
        """1 / D in the factor's order (its rows: A's, then a saddle point's pressures), factor precision."""
        return self.ldl.dinv

    def forward(self, b: np.ndarray) -> np.ndarray:
        """``L^-1 P b`` for *b* (N,), in the factor's order and precision: ``solve(b)`` is
        ``backward(dinv * forward(b))``, bit for bit."""
        return self.ldl.forward(b)

    def backward(self, y: np.ndarray) -> np.ndarray:
        """``P^T L^-T y`` for *y* in the factor's order (overwritten), float64 in A's order (N,)."""
        return self.ldl.backward(y)

    def columns(self, dofs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``L^-1 P e_j`` for the unit vectors at *dofs* (k,) of A, on the rows R where any is nonzero:
        ``(R, Y)``, R (r,) sorted in the factor's order, Y (r, k) float64. Each costs the path of its
        supernode to the root (:meth:`~esmm.pipeline.linalg.supernodal.LDLT.columns`), not a solve."""
        return self.ldl.columns(dofs)


def _factor(A, analysis, perm, dtype, threads) -> tuple[LDLT, float]:
    """:class:`~esmm.pipeline.linalg.supernodal.LDLT` of the stepper's matrix, factored and solved on
    *threads*, and the seconds of its symbolic analysis where *analysis* did not fit (0 otherwise);
    a zero pivot is the asset's fault (SimulationError)."""
    try:
        ldl = LDLT.of(A, analysis, perm=perm, dtype=dtype, threads=threads)
        return ldl, 0.0 if ldl.analysis is analysis else ldl.analysis.seconds
    except ZeroPivot as exc:
        raise SimulationError(f"the implicit step's matrix could not be factored ({exc}); "
                              "check the asset's masses and fixed nodes") from None


@dataclass(eq=False)
class MixedFactor(SparseFactor):
    r"""``A + B^T diag(w) B`` factored as the quasi-definite saddle-point matrix of its parts.

    With one pressure-like unknown per row of B (a node's volume),

    .. math::

        \begin{bmatrix} A & B^T C \\ C B & -C^2 W^{-1} \end{bmatrix}
        \begin{bmatrix} \mathbf u \\ \mathbf q \end{bmatrix}
        = \begin{bmatrix} \mathbf r \\ 0 \end{bmatrix}
        \;\Rightarrow\; (A + B^T W B)\,\mathbf u = \mathbf r

    (:math:`\mathbf q = C^{-1} W B \mathbf u`; :math:`C` a diagonal scaling,
    :math:`c_a = w_a |B_a|`, that puts both blocks at the springs' scale
    for the float32 factor). A symmetric quasi-definite matrix (:math:`A`
    positive definite, the lower block negative definite) has an
    :math:`LDL^T` factorization in any symmetric order (Vanderbei 1995), so it
    is factored like the others, in a nested-dissection order of the nodes,
    each node's row of B next to its dofs. It holds Newton's matrix exactly
    (not a bound) with the sparsity of B (one tet around a node) instead of
    :math:`B^T W B`'s (two): about half the fill on an organ's mesh
    (docs/design/simulator.md, "What is factored, and when it is renewed").

    Attributes
    ----------
    n_dof : int
        Rows of A (what :meth:`solve` takes and returns).
    """

    n_dof: int = 0

    @classmethod
    def of_parts(cls, A, B, w: np.ndarray, perm: np.ndarray | None = None, *,
                 single: bool = False, analysis: Analysis | None = None, threads: int = 1) -> MixedFactor:
        """Factor ``A + B^T diag(w) B`` (*A* (3n, 3n) positive definite, *B* (n, 3n): row a belongs to
        node a; or blocks of n such rows) in order *perm* of the saddle-point matrix (default:
        :func:`mixed_ordering`), with *analysis* when the saddle-point matrix has its pattern, on
        *threads* (:meth:`SparseFactor.of`)."""
        t = time.perf_counter()
        n_dof = A.shape[0]
        K = canonical(saddle_point(A, B, w))
        if perm is None and (analysis is None or not analysis.matches(K)):
            perm = mixed_ordering(A, B)
        ldl, analysis_s = _factor(K, analysis, perm, np.float32 if single else np.float64, threads)
        return cls(ldl=ldl, seconds=time.perf_counter() - t, analysis_s=analysis_s, n_dof=n_dof)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``(A + B^T W B)^-1 b`` for *b* of shape (3n,) or (3n, k)."""
        pad = np.zeros((self.perm.size - self.n_dof,) + b.shape[1:])
        return super().solve(np.concatenate([b, pad]))[:self.n_dof]

    def forward(self, b: np.ndarray) -> np.ndarray:
        """:meth:`SparseFactor.forward` of *b* (3n,) with zero pressures."""
        return super().forward(np.concatenate([b, np.zeros(self.perm.size - self.n_dof)]))

    def backward(self, y: np.ndarray) -> np.ndarray:
        """:meth:`SparseFactor.backward`, the dofs' part (3n,)."""
        return super().backward(y)[:self.n_dof]


def saddle_point(A, B, w: np.ndarray):
    """The scaled saddle-point matrix of :class:`MixedFactor` (CSR)."""
    w = np.asarray(w, dtype=np.float64)
    row = np.sqrt(np.asarray(B.multiply(B).sum(axis=1)).ravel())
    c = w * row
    c[~(c > 0.0)] = float(np.median(c[c > 0.0])) if np.any(c > 0.0) else 1.0
    CB = sps.diags(c) @ sps.csr_matrix(B)
    return sps.bmat([[A, CB.T], [CB, sps.diags(-c * c / w)]], format="csr")


def mixed_ordering(A, B) -> np.ndarray:
    """:func:`node_ordering` of the node graph of *A* and *B*, each node's dofs followed by its rows of B.

    *B* has one row per node (or several blocks of them: row ``r`` belongs to
    node ``r mod n``), reaching the nodes around it.
    """
    N = A.shape[0]
    n = N // 3
    Bn = sps.csr_matrix(B)
    if Bn.shape[0] % n:
        raise ValueError(f"B: expected a multiple of {n} rows (one per node), got {Bn.shape[0]}")
    rows = np.repeat(np.arange(Bn.shape[0]) % n, np.diff(Bn.indptr))
    nodes = sps.csr_matrix((np.ones(Bn.nnz), (rows, Bn.indices // 3)), shape=(n, n))
    nodes = (nodes + nodes.T).tocsr()
    pattern = sps.csr_matrix(A) + sps.kron(nodes, np.ones((3, 3)), format="csr")
    order = node_ordering(pattern)[0::3] // 3
    blocks = [N + j * n + order for j in range(Bn.shape[0] // n)]
    return np.stack([3 * order, 3 * order + 1, 3 * order + 2, *blocks], axis=1).ravel()


@dataclass(eq=False)
class Constraints:
    r"""Constraint rows on top of a :class:`SparseFactor` ``P = P_o^T L D L^T P_o`` (the capacitance method).

    Each row m acts on node ``node[m]`` along the unit vector ``e[m]`` (3,):
    a hard constraint (compliance 0: the dof does not move in the Newton
    update) or a coupling spring (compliance ``1/k``). With
    :math:`Y = L^{-1} P_o J^T` (the forward half of a solve of each row),

    .. math::

        C = J P^{-1} J^T + D_c = Y^T D^{-1} Y + D_c,\qquad
        \Pi r = P_o^T L^{-T}\big(D^{-1}\mathbf y - D^{-1} Y C^{-1} Y^T D^{-1}\mathbf y\big),\quad
        \mathbf y = L^{-1} P_o r,

    which is :math:`(P^{-1} - W C^{-1} W^T) r` with :math:`W = P^{-1}J^T`, with
    the correction made between the two halves of one solve. A column of Y is
    nonzero only on the path of its dof's supernode to the root of the
    supernode tree: it costs that path's sweep, where a column of W costs a
    whole solve, and the correction touches only the union R of the rows'
    paths. Y is cached per node (its three dofs; a sliding contact's normal
    uses its node's) until the factor changes.

    Parameters
    ----------
    factor : SparseFactor
    n : int
        Nodes.
    """

    factor: SparseFactor
    n: int
    _cols: dict = field(default_factory=dict, repr=False)   #: node -> (rows (r,), L^-1 P_o of its 3 dofs (r, 3))
    node: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    e: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    comp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    R: np.ndarray | None = None         #: rows (factor order) where a column of Y is nonzero, (r,)
    Y: np.ndarray | None = None         #: ``L^-1 P_o J^T`` on R, (r, c)
    cap_inv: np.ndarray | None = None
    _Yt: np.ndarray | None = field(default=None, repr=False)   #: Y^T (c, r), in the factor's precision
    _dY: np.ndarray | None = field(default=None, repr=False)   #: D^-1 Y (r, c), in the factor's precision
    _hard: tuple | None = field(default=None, repr=False)   #: hard rows' nodes, directions, orthonormal
    _G: np.ndarray | None = field(default=None, repr=False)       #: Y^T D^-1 Y of the rows in use
    _gram_of: dict = field(default_factory=dict, repr=False)       #: row (node, direction) -> its row of _G
    solves: int = 0             #: the preconditioner's applications (one solve each)
    solve_s: float = 0.0        #: seconds spent in them
    apply_s: list = field(default_factory=list, repr=False)   #: each of them [s]
    columns_s: float = 0.0      #: seconds spent computing the columns of Y

    @property
    def has_rows(self) -> bool:
        """Whether rows are in use (with them, :attr:`cap_inv` is their capacitance inverse)."""
        return self.cap_inv is not None

    def columns(self, node: np.ndarray) -> None:
        """Compute (once per factor) the forward half of a solve of each new node's three unit vectors,
        kept on the rows where it is nonzero (:meth:`SparseFactor.columns`)."""
        new = [int(a) for a in np.unique(np.asarray(node, dtype=np.int64)) if int(a) not in self._cols]
        if not new:
            return
        t = time.perf_counter()
        dofs = (3 * np.asarray(new, dtype=np.int64)[:, None] + np.arange(3)).ravel()
        R, Y = self.factor.columns(dofs)
        for q, a in enumerate(new):
            Yq = Y[:, 3 * q:3 * q + 3]
            nz = np.any(Yq != 0.0, axis=1)
            self._cols[a] = (R[nz], np.ascontiguousarray(Yq[nz]))
        self.columns_s += time.perf_counter() - t

    def set_rows(self, node: np.ndarray, e: np.ndarray, comp: np.ndarray) -> None:
        """Use rows (*node* (c,), unit *e* (c, 3), compliance *comp* (c,)); builds Y on R and the
        capacitance inverse (kept where the rows are the ones in use: a step whose grasp and contacts
        did not change)."""
        node = np.asarray(node, dtype=np.int64)
        e = np.asarray(e, dtype=np.float64).reshape(-1, 3)
        comp = np.asarray(comp, dtype=np.float64)
        if (self._hard is not None and np.array_equal(node, self.node) and np.array_equal(e, self.e)
                and np.array_equal(comp, self.comp)):
            return
        self.node, self.e, self.comp = node, e, comp
        self._hard_rows()
        c = self.node.size
        if c == 0:
            self.R, self.Y, self._Yt, self._dY, self.cap_inv = None, None, None, None, None
            return
        self.columns(self.node)
        cols = [self._cols[int(a)] for a in self.node]
        on = np.zeros(self.factor.dinv.size, bool)          # the union of the rows' paths, sorted
        for rows, _ in cols:
            on[rows] = True
        R = np.flatnonzero(on)
        pos = np.cumsum(on) - 1                              # row of R of each factor row on it
        Y = np.zeros((R.size, c))
        for m, (rows, Ya) in enumerate(cols):
            Y[pos[rows], m] = Ya @ self.e[m]
        dY = self.factor.dinv[R].astype(np.float64)[:, None] * Y
        cap = self._gram(Y, dY) + np.diag(self.comp)
        try:
            cap_inv = np.linalg.inv(cap)
        except np.linalg.LinAlgError:
            raise SimulationError("the implicit step's constraints are dependent (a node held twice?)") from None
        self.R, self.Y, self.cap_inv = R, Y, cap_inv
        dtype = self.factor.dinv.dtype                       # the correction in the factor's precision
        self._Yt, self._dY = np.ascontiguousarray(Y.T, dtype=dtype), dY.astype(dtype)

    def _gram(self, Y: np.ndarray, dY: np.ndarray) -> np.ndarray:
        """``Y^T D^-1 Y`` (c, c), symmetric, for the rows in use: an entry depends on its two rows
        alone, so the entries between rows of the last set are taken from it and only the new rows'
        are computed (a contact that comes or goes changes a few of an organ's tens or hundreds of
        rows: a product of c x k x r instead of c x c x r)."""
        keys = [(int(a), d.tobytes()) for a, d in zip(self.node, self.e)]
        old = np.array([self._gram_of.get(k, -1) for k in keys], dtype=np.int64)
        kept, new = np.flatnonzero(old >= 0), np.flatnonzero(old < 0)
        if kept.size == 0:
            G = Y.T @ dY
            G = 0.5 * (G + G.T)
        else:
            G = np.empty((len(keys), len(keys)))
            G[np.ix_(kept, kept)] = self._G[np.ix_(old[kept], old[kept])]
            if new.size:
                B = Y.T @ dY[:, new]
                G[:, new] = B
                G[new, :] = B.T
                Bnn = B[new]
                G[np.ix_(new, new)] = 0.5 * (Bnn + Bnn.T)
        self._G, self._gram_of = G, {k: m for m, k in enumerate(keys)}
        return G

    def _hard_rows(self) -> None:
        """The hard rows (node, direction) and whether each node's are orthonormal (the grasp's and the
        contacts' axes, a floor's normal), once per set of rows (:meth:`_project_hard`)."""
        hard = self.comp == 0.0
        node, e = self.node[hard], self.e[hard]
        gram = np.einsum("md,kd->mk", e, e)
        same = node[:, None] == node[None, :]
        self._hard = (node, e, bool(np.allclose(np.where(same, gram, 0.0), np.eye(node.size), atol=1e-12)))

    def _project_hard(self, zz: np.ndarray) -> None:
        """Remove from *zz* (n, 3), in place, the components along the hard rows: all at once where each
        node's hard rows are orthonormal, which equals one after the other; one after the other otherwise."""
        node, e, orthonormal = self._hard
        if node.size == 0:
            return
        if orthonormal:
            proj = np.einsum("md,md->m", zz[node], e)
            np.add.at(zz, node, -proj[:, None] * e)
            return
        for a, d in zip(node, e):
            zz[a] -= (zz[a] @ d) * d

    def project(self, z: np.ndarray) -> np.ndarray:
        """*z* (3n,) without its components along the hard rows (a copy): in their null space."""
        out = np.array(z, dtype=np.float64, copy=True)
        if self._hard is not None:
            self._project_hard(out.reshape(self.n, 3))
        return out

    def gather(self, z: np.ndarray) -> np.ndarray:
        """``J z`` for *z* of shape (3n,) or (3n, k): each row's component of its node."""
        zz = z.reshape(self.n, 3, -1)[self.node]                 # (c, 3, k)
        out = np.einsum("mdk,md->mk", zz, self.e)
        return out[:, 0] if z.ndim == 1 else out

    def scatter(self, lam: np.ndarray) -> np.ndarray:
        """``J^T lam``, shape (3n,)."""
        out = np.zeros((self.n, 3))
        np.add.at(out, self.node, lam[:, None] * self.e)
        return out.ravel()

    def apply(self, r: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
        """The constrained preconditioner ``(P^-1 - W C^-1 W^T) r`` (zero on *fixed* dofs): one solve, its
        two halves joined by the capacitance correction on the rows R (class docstring); without rows,
        the factor's solve itself."""
        if fixed is not None:
            r = np.where(fixed, 0.0, r)
        t = time.perf_counter()
        if self.Y is None:
            z = self.factor.solve(r)
        else:
            y = self.factor.forward(r)
            y *= self.factor.dinv
            yR = y[self.R]
            y[self.R] = yR - self._dY @ (self.cap_inv @ (self._Yt @ yR)).astype(y.dtype)
            z = self.factor.backward(y)
        dt = time.perf_counter() - t
        self.solve_s += dt
        self.solves += 1
        self.apply_s.append(dt)
        if self.Y is not None:
            self._project_hard(z.reshape(self.n, 3))     # exactly in the null space (the factor may be float32)
        if fixed is not None:
            z[fixed] = 0.0
        return z

    def block_stiffness(self, rows: np.ndarray) -> np.ndarray:
        """``sum over rows a, b of [C^-1]_ab e_a e_b^T`` (3, 3): the stiffness of moving those rows together."""
        if self.cap_inv is None or rows.size == 0:
            return np.zeros((3, 3))
        E = self.e[rows]
        return E.T @ self.cap_inv[np.ix_(rows, rows)] @ E


def pcg(matvec, precond, b: np.ndarray, *, rtol: float, max_iter: int) -> tuple[np.ndarray, int, bool]:
    """Preconditioned conjugate gradients for ``A y = b`` from ``y = 0``.

    *precond* maps a residual into the constraints' null space (so every
    iterate stays there). Stops when ``sqrt(r.z) <= rtol sqrt(r0.z0)``, after
    *max_iter* iterations, or on a direction of non-positive curvature (the
    iterate so far is returned; the first direction itself if there is none).

    Returns
    -------
    (y, iterations, converged)
    """
    y = np.zeros_like(b)
    r = b.copy()
    z = precond(r)
    rz = float(r @ z)
    if not rz > 0.0:
        return y, 0, True
    stop = rtol * rtol * rz
    p = z.copy()
    for it in range(1, max_iter + 1):
        Ap = matvec(p)
        pAp = float(p @ Ap)
        if not pAp > 0.0:
            return (p if it == 1 else y), it, False
        alpha = rz / pAp
        y += alpha * p
        r -= alpha * Ap
        z = precond(r)
        rz_new = float(r @ z)
        if rz_new <= stop:
            return y, it, True
        p = z + (rz_new / rz) * p
        rz = rz_new
    return y, max_iter, False
