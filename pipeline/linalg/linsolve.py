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
  :math:`W = P^{-1}J^T`, maps any residual into it).

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
    """Constraint rows on top of a :class:`SparseFactor` ``P`` (the capacitance method).

    Each row m acts on node ``node[m]`` along the unit vector ``e[m]`` (3,):
    a hard constraint (compliance 0: the dof does not move in the Newton
    update) or a coupling spring (compliance ``1/k``). ``W = P^-1 J^T`` is
    cached per row (node and direction: one solve each) until the factor
    changes.

    Parameters
    ----------
    factor : SparseFactor
    n : int
        Nodes.
    """

    factor: SparseFactor
    n: int
    _cols: dict = field(default_factory=dict, repr=False)
    node: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    e: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    comp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    W: np.ndarray | None = None
    cap_inv: np.ndarray | None = None
    _hard: tuple | None = field(default=None, repr=False)   #: hard rows' nodes, directions, orthonormal
    solves: int = 0
    solve_s: float = 0.0        #: seconds spent in the preconditioner's solves
    apply_s: list = field(default_factory=list, repr=False)   #: each of the preconditioner's solves [s]
    columns_s: float = 0.0      #: seconds spent computing the columns of W

    def columns(self, node: np.ndarray, e: np.ndarray) -> None:
        """Compute (once per factor) the column ``P^-1 J_m^T`` of every row (*node* (c,), unit *e* (c, 3)):
        one solve per row (a slip contact's normal row: one, not three)."""
        new, seen = [], set()
        for a, d in zip(np.asarray(node, dtype=np.int64), np.asarray(e, dtype=np.float64).reshape(-1, 3)):
            key = (int(a), d.tobytes())
            if key not in self._cols and key not in seen:
                seen.add(key)
                new.append((key, int(a), d))
        if not new:
            return
        E = np.zeros((3 * self.n, len(new)))
        for q, (_, a, d) in enumerate(new):
            E[3 * a:3 * a + 3, q] = d
        t = time.perf_counter()
        X = self.factor.solve(E)
        self.columns_s += time.perf_counter() - t
        self.solves += len(new)
        for q, (key, _, _) in enumerate(new):
            self._cols[key] = np.ascontiguousarray(X[:, q])

    def set_rows(self, node: np.ndarray, e: np.ndarray, comp: np.ndarray) -> None:
        """Use rows (*node* (c,), unit *e* (c, 3), compliance *comp* (c,)); builds W and the capacitance inverse
        (kept where the rows are the ones in use: a step whose grasp and contacts did not change, where
        rebuilding them, W's copy of 3n x c entries, would be most of the call)."""
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
            self.W, self.cap_inv = None, None
            return
        self.columns(self.node, self.e)
        W = np.empty((3 * self.n, c))
        for m in range(c):
            W[:, m] = self._cols[(int(self.node[m]), self.e[m].tobytes())]
        self.W = W
        cap = self.gather(W) + np.diag(self.comp)
        cap = 0.5 * (cap + cap.T)
        try:
            self.cap_inv = np.linalg.inv(cap)
        except np.linalg.LinAlgError:
            raise SimulationError("the implicit step's constraints are dependent (a node held twice?)") from None

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
        """The constrained preconditioner ``(P^-1 - W C^-1 W^T) r`` (zero on *fixed* dofs)."""
        if fixed is not None:
            r = np.where(fixed, 0.0, r)
        t = time.perf_counter()
        z = self.factor.solve(r)
        dt = time.perf_counter() - t
        self.solve_s += dt
        self.solves += 1
        self.apply_s.append(dt)
        if self.W is not None:
            z = z - self.W @ (self.cap_inv @ self.gather(z))
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
