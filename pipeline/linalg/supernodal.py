r"""A supernodal multifrontal :math:`LDL^T` factorization without pivoting, compiled with numba.

For a symmetric matrix :math:`A` (N, N) that is positive definite, or
quasi-definite (Vanderbei 1995: the saddle-point matrix of
:class:`esmm.pipeline.linalg.linsolve.MixedFactor`), in a fill-reducing
order :math:`P`,

.. math::

    P A P^T = L D L^T, \qquad L \text{ unit lower triangular},\; D \text{ diagonal},

and ``A^-1 b = P^T L^-T D^-1 L^-1 P b``. Two phases:

* :class:`Analysis` (once per sparsity pattern): the elimination tree (Liu's
  algorithm), its postorder (composed with the caller's order: the same
  fill), the row structure of every column of L, the maximal supernodes
  (consecutive columns ``j-1, j`` with ``parent(j-1) = j`` and the same rows
  below ``j``: Ng & Peyton 1993) relaxed as CHOLMOD relaxes them (a few
  explicit zeros for fewer, wider blocks: :data:`RELAX`), the tree of fronts,
  its two halves for two threads and where each entry of A goes;
* :class:`LDLT` (each matrix of that pattern): the multifrontal method (Duff
  & Reid 1983; Liu 1992), front by front in postorder: assemble the front's
  columns of A and its children's update matrices (extend-add), factor its
  pivot columns (a Crout :math:`LDL^T` of the dense front), and pass the
  Schur complement :math:`F_{22} - L_{21} D L_{21}^T` (one matrix product,
  BLAS) to the parent on a stack. Each supernode's columns of L are kept as
  one dense block (column by column, below the unit diagonal), so that a solve
  reads L once, block by block (vectorised loops, the row indices read once
  per block, not per entry), and only L (not the :math:`U = DL^T` a general
  LU keeps beside it). The factorization and the solve each run on one
  thread or on two (``threads``): the two halves of the tree's subtrees
  (:func:`_two_parts`) at once, then their few ancestors (the top separators)
  on one thread. Factoring, each part keeps its update matrices on a stack of
  its own, and the ancestors read the part roots' where the parts left them
  (:func:`_numeric_two`); every front's arithmetic is the same on one thread
  or two, and so is the factor, bit for bit while OpenBLAS runs on one thread
  (as the implicit stepper runs it). Solving, see :func:`_solve_two`.

Why here and not SuperLU (scipy's ``splu`` in symmetric mode without
pivoting, which :func:`~esmm.pipeline.linalg.newton.ldlt` uses): the
implicit stepper's preconditioner is factored tens of times a run and solved
hundreds of times. SuperLU keeps :math:`U = DL^T` beside L and its solves read
both (exporting its L for a faster solve alone would cost a large part of
its factorization again); this factorization is several times faster to factor and
to solve on the organs' matrices (docs/design/simulator.md, "What is factored,
and when it is renewed"). On two threads the ancestors, which run on one thread,
bound the gain. With another process busy on the second core the two threads
still factor about as fast, but their solves slow down many times: which to use
is the caller's to time.

No pivoting: exact for positive definite and quasi-definite matrices in any
symmetric order; a zero or non-finite pivot raises :class:`ZeroPivot` (a
``RuntimeError``, as SuperLU's).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from ..blas import single_threaded_blas

__all__ = ["LDLT", "Analysis", "ZeroPivot", "canonical", "warm_up"]

_JIT = dict(cache=True, error_model="numpy")


class ZeroPivot(RuntimeError):
    """A zero or non-finite pivot: the matrix is singular or not (quasi-)definite in this order."""


# -- symbolic phase ------------------------------------------------------------------------
@nb.njit(**_JIT)
def _etree(n, up_ptr, up_idx):
    """Elimination tree (Liu's algorithm with path compression) from the upper triangle in CSC
    (column i: the rows k < i); ``parent[j] = -1`` at a root."""
    parent = np.full(n, -1, np.int64)
    anc = np.full(n, -1, np.int64)
    for i in range(n):
        for p in range(up_ptr[i], up_ptr[i + 1]):
            k = up_idx[p]
            while k != -1 and k < i:
                nxt = anc[k]
                anc[k] = i
                if nxt == -1:
                    parent[k] = i
                k = nxt
    return parent


@nb.njit(**_JIT)
def _children(parent):
    """Linked lists of children: ``head[p]`` the first child of p, ``nxt[c]`` the next sibling."""
    n = parent.size
    head = np.full(n, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    for j in range(n - 1, -1, -1):
        p = parent[j]
        if p != -1:
            nxt[j] = head[p]
            head[p] = j
    return head, nxt


@nb.njit(**_JIT)
def _postorder(parent):
    """A postorder of the forest: ``post[k]`` is the k-th node visited (children before parents)."""
    n = parent.size
    head, nxt = _children(parent)
    post = np.empty(n, np.int64)
    stack = np.empty(n, np.int64)
    k = 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top = 0
        stack[0] = root
        while top >= 0:
            p = stack[top]
            c = head[p]
            if c == -1:
                top -= 1
                post[k] = p
                k += 1
            else:
                head[p] = nxt[c]
                top += 1
                stack[top] = c
    return post


@nb.njit(**_JIT)
def _column_rows(n, lo_ptr, lo_idx, parent):
    """The rows of every column of L, sorted, the diagonal first: ``struct(j) = {j} U rows of A's
    column j below it U (struct(c) minus c for each child c)`` (a postordered tree: children first)."""
    head, nxt = _children(parent)
    mark = np.full(n, -1, np.int64)
    rows = np.empty(max(4 * lo_ptr[n] + n, 16), np.int32)
    ptr = np.zeros(n + 1, np.int64)
    buf = np.empty(n, np.int64)
    for j in range(n):
        cnt = 1
        mark[j] = j
        buf[0] = j
        for p in range(lo_ptr[j], lo_ptr[j + 1]):
            i = lo_idx[p]
            if i > j and mark[i] != j:
                mark[i] = j
                buf[cnt] = i
                cnt += 1
        c = head[j]
        while c != -1:
            for p in range(ptr[c] + 1, ptr[c + 1]):
                i = rows[p]
                if mark[i] != j:
                    mark[i] = j
                    buf[cnt] = i
                    cnt += 1
            c = nxt[c]
        if ptr[j] + cnt > rows.size:
            grown = np.empty(max(2 * rows.size, ptr[j] + cnt), np.int32)
            grown[:ptr[j]] = rows[:ptr[j]]
            rows = grown
        rows[ptr[j]:ptr[j] + cnt] = np.sort(buf[:cnt])
        ptr[j + 1] = ptr[j] + cnt
    return ptr, rows[:ptr[n]].copy()


@nb.njit(**_JIT)
def _supernodes(parent, ptr):
    """First column of each maximal supernode (and n at the end): j joins j-1's supernode when
    ``parent[j-1] == j`` and column j-1's rows are column j's and j-1 itself."""
    n = parent.size
    start = np.empty(n + 1, np.int64)
    start[0] = 0
    ns = 1
    for j in range(1, n):
        if not (parent[j - 1] == j and ptr[j] - ptr[j - 1] == ptr[j + 1] - ptr[j] + 1):
            start[ns] = j
            ns += 1
    start[ns] = n
    return start[:ns + 1].copy()


@nb.njit(**_JIT)
def _stack_size(nchild, m):
    """Largest total size of the update matrices on the stack at once (postorder)."""
    ns = m.size
    sizes = np.empty(ns + 1, np.int64)
    top = 0
    cur = 0
    peak = 0
    for s in range(ns):
        for _ in range(nchild[s]):
            top -= 1
            cur -= sizes[top]
        sizes[top] = m[s] * m[s]
        top += 1
        cur += m[s] * m[s]
        peak = max(peak, cur)
    return peak


@dataclass(eq=False)
class Analysis:
    """The symbolic factorization of a sparsity pattern in an order (module doc).

    Attributes
    ----------
    n : int
    perm : ndarray, shape (n,)
        The order factored: the caller's, postordered (row i of ``P A P^T`` is row ``perm[i]`` of A).
    start : ndarray, shape (ns + 1,)
        First column of each supernode.
    rows, row_ptr : ndarray
        Supernode s's rows of L (its columns first): ``rows[row_ptr[s]:row_ptr[s + 1]]``.
    block_ptr : ndarray, shape (ns + 1,)
        Offsets of the supernodes' blocks: column by column, each column's rows below its diagonal
        (a dense trapezoid, packed: ``nc (nr - 1) - nc (nc - 1) / 2`` entries).
    nnz : int
        Entries of L (the diagonal included).
    """

    n: int
    perm: np.ndarray
    start: np.ndarray
    rows: np.ndarray
    row_ptr: np.ndarray
    block_ptr: np.ndarray
    nchild: np.ndarray
    kids: np.ndarray            #: the supernodes' children, each one's last first: ``kids[kid_ptr[s]:kid_ptr[s + 1]]``
    kid_ptr: np.ndarray
    part: np.ndarray            #: (ns,) the supernode's part for two threads (0, 1), or -1: their ancestors
    by_part: np.ndarray         #: the supernodes of part 0, of part 1, then the ancestors (each in postorder) ...
    part_ptr: np.ndarray        #: ... from ``by_part[part_ptr[g]]`` (g = 0, 1, 2), and each one's stack size:
    part_stack: np.ndarray      #: (3,) the two-thread factorization's three stacks (:func:`_numeric_two`)
    lo_ptr: np.ndarray          #: the lower triangle of P A P^T, CSC: column pointers ...
    lo_idx: np.ndarray          #: ... row indices ...
    lo_src: np.ndarray          #: ... and each entry's position in A's CSR data
    a_indptr: np.ndarray        #: A's pattern (CSR), to recognise a matrix of the same pattern
    a_indices: np.ndarray
    stack_size: int
    max_rows: int
    nnz: int
    seconds: float = 0.0        #: how long the analysis took (a run's first factor does it; its renewals not)

    @classmethod
    def of(cls, A, perm: np.ndarray) -> Analysis:
        """Analyse the pattern of *A* (N, N; symmetric pattern, CSR or anything scipy converts) in order *perm*."""
        t = time.perf_counter()
        A = canonical(A)
        n = A.shape[0]
        perm, lo, parent = _postordered(A, perm)
        lo_ptr, lo_idx = lo.indptr.astype(np.int64), lo.indices.astype(np.int64)
        ptr, col_rows = _column_rows(n, lo_ptr, lo_idx, parent)
        start = _amalgamate(_supernodes(parent, ptr), parent, ptr)
        rows, row_ptr, sparent = _front_rows(start, parent, ptr, col_rows)
        nr, nc = np.diff(row_ptr), np.diff(start)
        block_ptr = np.concatenate([[0], np.cumsum(nc * (nr - 1) - nc * (nc - 1) // 2)]).astype(np.int64)
        nchild = np.bincount(sparent[sparent >= 0], minlength=nc.size).astype(np.int64)
        kids = np.flatnonzero(sparent >= 0)
        kids = kids[np.lexsort((-kids, sparent[kids]))]
        part = _two_parts(sparent, np.diff(block_ptr) + nr)
        by_part, part_ptr, part_stack = _part_stacks(part, sparent, nr - nc)
        return cls(n=n, perm=perm, start=start, rows=rows, row_ptr=row_ptr, block_ptr=block_ptr, nchild=nchild,
                   kids=kids.astype(np.int64), kid_ptr=np.concatenate([[0], np.cumsum(nchild)]).astype(np.int64),
                   part=part, by_part=by_part, part_ptr=part_ptr, part_stack=part_stack, lo_ptr=lo_ptr,
                   lo_idx=lo_idx, lo_src=lo.data.astype(np.int64), a_indptr=A.indptr.copy(),
                   a_indices=A.indices.copy(), stack_size=int(_stack_size(nchild, nr - nc)),
                   max_rows=int(nr.max()) if n else 0, nnz=int(ptr[n]), seconds=time.perf_counter() - t)

    def snode_parent(self) -> np.ndarray:
        """The supernode tree: each supernode's parent, -1 at a root (from ``kids``)."""
        ns = self.start.size - 1
        parent = np.full(ns, -1, np.int64)
        owner = np.repeat(np.arange(ns), np.diff(self.kid_ptr))
        parent[self.kids] = owner
        return parent

    def matches(self, A) -> bool:
        """Whether the canonical CSR *A* has the pattern analysed."""
        return (A.shape[0] == self.n and np.array_equal(A.indptr, self.a_indptr)
                and np.array_equal(A.indices, self.a_indices))


def _postordered(A, perm):
    """The order *perm* followed by a postorder of its elimination tree (the same fill), the lower
    triangle of ``P A P^T`` in CSC with each entry's position in A's data, and the tree."""
    n = A.shape[0]
    up = sp.triu(A[perm][:, perm]).tocsc()
    parent = _etree(n, up.indptr.astype(np.int64), up.indices.astype(np.int64))
    perm = np.asarray(perm, dtype=np.int64)[_postorder(parent)]
    pos = A.copy()
    pos.data = np.arange(A.nnz, dtype=np.float64)          # exact positions (< 2**53)
    B = pos[perm][:, perm]
    lo = sp.tril(B).tocsc()
    lo.sort_indices()
    up = sp.triu(B).tocsc()
    return perm, lo, _etree(n, up.indptr.astype(np.int64), up.indices.astype(np.int64))


#: Relaxed supernodes: (most columns, largest share of explicit zeros) a merged supernode may have
#: (CHOLMOD's defaults, ``cholmod_super``'s nrelax and zrelax; Ashcraft & Grimes 1989).
RELAX = ((4, 1.0), (16, 0.8), (48, 0.1), (np.inf, 0.05))


def _amalgamate(start: np.ndarray, parent: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    """Merge each supernode into its parent supernode when that one follows it directly (their columns
    are contiguous) and the merged one stays within :data:`RELAX`, storing a few zeros for fewer, larger
    blocks: where new rows enter a chain of columns one by one (a structured grid's separators) the
    supernodes are one or two columns wide otherwise (the 100 k Kuhn box: 19 708 of them, the widest
    2 columns of 2 906 rows). Returns the new first columns (and n)."""
    ns = start.size - 1
    nc = np.diff(start).astype(np.int64)
    nr = (ptr[start[:-1] + 1] - ptr[start[:-1]]).astype(np.int64)
    sparent = _supernode_parents(start, parent)
    g_nc, g_nr, g_zeros = nc.copy(), nr.copy(), np.zeros(ns)
    top = np.ones(ns, bool)                        # s ends its group (not merged into s + 1)
    for s in range(ns - 1):
        p = s + 1
        if sparent[s] != p:
            continue
        cols, rows = g_nc[s] + nc[p], g_nc[s] + nr[p]
        zeros = g_zeros[s] + g_nc[s] * (rows - g_nr[s])
        share = zeros / (cols * rows - cols * (cols - 1) // 2)
        if any(cols <= most and share < (limit if most > 4 else np.inf) for most, limit in RELAX):
            g_nc[p], g_nr[p], g_zeros[p] = cols, rows, zeros
            top[s] = False
    tops = np.flatnonzero(top)
    return np.concatenate([[0], start[tops + 1]]).astype(np.int64)


def _supernode_parents(start: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Each supernode's parent in the supernodal tree (the one holding its last column's parent), or -1."""
    nc = np.diff(start)
    col2sn = np.repeat(np.arange(nc.size), nc)
    last_parent = parent[start[1:] - 1]
    return np.where(last_parent >= 0, col2sn[np.maximum(last_parent, 0)], -1)


def _front_rows(start, parent, ptr, col_rows):
    """Each supernode's rows (its columns, then the rows of L below its last column: they hold every
    other column's rows below the supernode), their pointers and the supernodal tree's parents."""
    ns = start.size - 1
    nc = np.diff(start)
    parts, counts = [], np.empty(ns, np.int64)
    for s in range(ns):
        f, last = start[s], start[s + 1] - 1
        below = col_rows[ptr[last] + 1:ptr[last + 1]]            # the last column's rows below it
        parts.append(np.arange(f, last + 1, dtype=np.int32))
        parts.append(below.astype(np.int32))
        counts[s] = nc[s] + below.size
    rows = np.concatenate(parts) if parts else np.zeros(0, np.int32)
    return rows, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), _supernode_parents(start, parent)


def _two_parts(sparent: np.ndarray, work: np.ndarray) -> np.ndarray:
    """Split the supernodal forest for two threads: whole subtrees in two parts of about equal work,
    the rest (their ancestors: the top separators of the nested dissection) in neither.

    From the roots down, the heaviest subtree is replaced by its children while it alone weighs more
    than half of all the subtrees in play; the subtrees are then dealt largest first to the lighter
    part. Returns each supernode's part: 0, 1, or -1 for the ancestors.
    """
    ns = sparent.size
    sub = np.asarray(work, dtype=np.float64).copy()
    for c in range(ns):                               # postorder: children before parents
        if sparent[c] >= 0:
            sub[sparent[c]] += sub[c]
    children = [[] for _ in range(ns)]
    for c in range(ns):
        if sparent[c] >= 0:
            children[sparent[c]].append(c)
    part = np.full(ns, -1, np.int64)
    cand = [r for r in range(ns) if sparent[r] < 0]
    while cand:
        big = max(cand, key=lambda r: sub[r])
        if not children[big] or sub[big] <= 0.5 * sum(sub[r] for r in cand):
            break
        cand.remove(big)
        cand.extend(children[big])
    load = [0.0, 0.0]
    first = np.zeros(ns + 1, np.int64)                # a subtree is the postorder range [first, root]
    for c in range(ns):
        first[c] = min([c] + [first[k] for k in children[c]])
    for r in sorted(cand, key=lambda r: -sub[r]):
        g = int(load[1] < load[0])
        load[g] += sub[r]
        part[first[r]:r + 1] = g
    return part


def _part_stacks(part: np.ndarray, sparent: np.ndarray, m: np.ndarray):
    """The supernodes by part (0, 1, then the ancestors: -1), each in postorder, where each part's
    begin, and the peak of each part's stack of update matrices (m: each one's order) when it pops
    only its own children (a part root's stays on its part's stack for the ancestors to read)."""
    key = np.where(part < 0, 2, part)
    by_part = np.argsort(key, kind="stable").astype(np.int64)
    part_ptr = np.searchsorted(key[by_part], np.arange(4)).astype(np.int64)
    kid = np.flatnonzero(sparent >= 0)
    own = kid[part[kid] == part[sparent[kid]]]
    nown = np.bincount(sparent[own], minlength=part.size).astype(np.int64)
    sizes = [int(_stack_size(nown[sel], m[sel].astype(np.int64))) for sel in np.split(by_part, part_ptr[1:3])]
    return by_part, part_ptr, np.array(sizes, np.int64)


def canonical(A) -> sp.csr_matrix:
    """*A* as CSR with sorted indices and no duplicates (a copy only when needed)."""
    A = sp.csr_matrix(A)
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    return A


# -- numeric phase ---------------------------------------------------------------------------
@nb.njit(fastmath=True, **_JIT)
def _crout(F, nc, nr, d, w):
    """Crout LDL^T of the first *nc* columns of the dense front F (nr, nr; its lower part): L's
    columns overwrite F[:, :nc], D goes to d. Returns -1, or the local index of a bad pivot."""
    for j in range(nc):
        rowj = F[j]
        for p in range(j):
            w[p] = rowj[p] * d[p]
        acc = rowj[j]
        for p in range(j):
            acc -= rowj[p] * w[p]
        if not (acc != 0.0 and np.isfinite(acc)):
            return j
        d[j] = acc
        inv = 1.0 / acc
        for i in range(j + 1, nr):
            rowi = F[i]
            a = rowi[j]
            for p in range(j):
                a -= rowi[p] * w[p]
            rowi[j] = a * inv
    return -1


@nb.njit(**_JIT)
def _assemble(F, s, start, rows, row_ptr, lo_ptr, lo_idx, vals, relpos, kids, kid_ptr, stack, uoff):
    """Front s: A's columns, then its children's update matrices (extend-add; child c's at
    ``stack[uoff[c]:]``), the last child first (the order a single stack pops them in)."""
    f = start[s]
    nc = start[s + 1] - f
    r0 = row_ptr[s]
    nr = row_ptr[s + 1] - r0
    for k in range(nr):
        relpos[rows[r0 + k]] = k
    for a in range(nr):
        F[a, :a + 1] = 0.0
    for jj in range(nc):
        j = f + jj
        for p in range(lo_ptr[j], lo_ptr[j + 1]):
            F[relpos[lo_idx[p]], jj] += vals[p]
    for q in range(kid_ptr[s], kid_ptr[s + 1]):
        c = kids[q]
        rc0 = row_ptr[c] + start[c + 1] - start[c]
        mc = row_ptr[c + 1] - rc0
        U = stack[uoff[c]:uoff[c] + mc * mc].reshape((mc, mc))
        for a in range(mc):
            rowF = F[relpos[rows[rc0 + a]]]
            rowU = U[a]
            for b in range(a + 1):
                rowF[relpos[rows[rc0 + b]]] += rowU[b]


@nb.njit(**_JIT)
def _schur(F, nc, m, d, U):
    """The update matrix ``U = F22 - L21 D L21^T`` (m, m; its lower part) of a factored front F."""
    L21 = np.empty((m, nc), F.dtype)
    W = np.empty((m, nc), F.dtype)
    for i in range(m):
        for k in range(nc):
            v = F[nc + i, k]
            L21[i, k] = v
            W[i, k] = v * d[k]
    G = np.dot(W, L21.T)
    for a in range(m):
        for b in range(a + 1):
            U[a, b] = F[nc + a, nc + b] - G[a, b]


@nb.njit(**_JIT)
def _numeric(seq, region, top, start, rows, row_ptr, block_ptr, kids, kid_ptr, lo_ptr, lo_idx, vals, blk, dout,
             stack, uoff, front, relpos, dbuf, wbuf):
    """The multifrontal factorization (module doc) of the supernodes *seq* (in postorder) into *blk*
    and *dout*; -1, or the column of a bad pivot. Update matrices go on the stack of their
    ``region`` (a stretch of *stack*, this one's from *top*; ``uoff[s]``: where s's is): a child in
    the front's own region is popped from its top, one of another region (done before) only read."""
    for s in seq:
        f = start[s]
        nc = start[s + 1] - f
        nr = row_ptr[s + 1] - row_ptr[s]
        m = nr - nc
        F = front[:nr * nr].reshape((nr, nr))
        _assemble(F, s, start, rows, row_ptr, lo_ptr, lo_idx, vals, relpos, kids, kid_ptr, stack, uoff)
        for q in range(kid_ptr[s], kid_ptr[s + 1]):         # the own children: the stack's top
            if region[kids[q]] == region[s]:
                top = uoff[kids[q]]
        bad = _crout(F, nc, nr, dbuf, wbuf)
        if bad >= 0:
            return f + bad
        b0 = block_ptr[s]
        for k in range(nc):
            dout[f + k] = dbuf[k]
            c = _column(b0, nr, k)
            for i in range(k + 1, nr):
                blk[c + i - k - 1] = F[i, k]
        if m > 0:
            _schur(F, nc, m, dbuf, stack[top:top + m * m].reshape((m, m)))
            uoff[s] = top
            top += m * m
    return -1


@nb.njit(parallel=True, **_JIT)
def _numeric_two(seq, seq_ptr, region, base, start, rows, row_ptr, block_ptr, kids, kid_ptr, lo_ptr, lo_idx,
                 vals, blk, dout, stack, uoff, front2, relpos2, dbuf2, wbuf2):
    """:func:`_numeric` on two threads (:func:`_two_parts`): each part's subtrees (``seq[seq_ptr[g]:
    seq_ptr[g + 1]]``) at once, on its own stack (from ``base[g]``), front and scratch (``front2[g]``
    ...); then the ancestors on one, reading the part roots' update matrices from the parts' stacks.
    A bad pivot: the first one of either part, else the ancestors'."""
    bad = np.full(2, -1, np.int64)
    for g in nb.prange(2):
        bad[g] = _numeric(seq[seq_ptr[g]:seq_ptr[g + 1]], region, base[g], start, rows, row_ptr, block_ptr,
                          kids, kid_ptr, lo_ptr, lo_idx, vals, blk, dout, stack, uoff, front2[g], relpos2[g],
                          dbuf2[g], wbuf2[g])
    if bad[0] >= 0 or bad[1] >= 0:
        return bad[0] if bad[1] < 0 or (0 <= bad[0] < bad[1]) else bad[1]
    return _numeric(seq[seq_ptr[2]:seq_ptr[3]], region, base[2], start, rows, row_ptr, block_ptr, kids, kid_ptr,
                    lo_ptr, lo_idx, vals, blk, dout, stack, uoff, front2[0], relpos2[0], dbuf2[0], wbuf2[0])


# -- solves ------------------------------------------------------------------------------------
@nb.njit(inline="always", **_JIT)
def _column(b0, nr, k):
    """Where column k of a supernode with *nr* rows and block offset *b0* starts: its rows below the
    diagonal, ``k + 1 .. nr - 1``, packed (columns of ``nr - 1``, ``nr - 2``, ... entries)."""
    return b0 + k * (nr - 1) - (k * (k - 1)) // 2


@nb.njit(inline="always", **_JIT)
def _below(blk, b0, nr, nc, k):
    """Column k's entries in the rows below the supernode (``nc .. nr - 1``)."""
    c = _column(b0, nr, k) + nc - k - 1
    return blk[c:c + nr - nc]


@nb.njit(fastmath=True, inline="always", **_JIT)
def _forward_block(s, start, rows, row_ptr, blk, block_ptr, x, tmp):
    """Supernode s's part of ``x <- L^-1 x``: its triangle, then its rows below (into tmp, scattered once)."""
    f = start[s]
    nc = start[s + 1] - f
    r0 = row_ptr[s]
    nr = row_ptr[s + 1] - r0
    b0 = block_ptr[s]
    for k in range(nc):
        xk = x[f + k]
        c = _column(b0, nr, k)
        col = blk[c:c + nc - k - 1]
        xs = x[f + k + 1:f + nc]
        for i in range(nc - k - 1):
            xs[i] -= col[i] * xk
    no = nr - nc
    if no == 0:
        return
    t = tmp[:no]
    t[:] = 0.0
    k = 0
    while k + 4 <= nc:                          # four columns per pass over t
        p0 = _below(blk, b0, nr, nc, k)
        p1 = _below(blk, b0, nr, nc, k + 1)
        p2 = _below(blk, b0, nr, nc, k + 2)
        p3 = _below(blk, b0, nr, nc, k + 3)
        x0, x1, x2, x3 = x[f + k], x[f + k + 1], x[f + k + 2], x[f + k + 3]
        for i in range(no):
            t[i] += p0[i] * x0 + p1[i] * x1 + p2[i] * x2 + p3[i] * x3
        k += 4
    while k < nc:
        p0 = _below(blk, b0, nr, nc, k)
        x0 = x[f + k]
        for i in range(no):
            t[i] += p0[i] * x0
        k += 1
    rr = rows[r0 + nc:r0 + nr]
    for i in range(no):
        x[rr[i]] -= t[i]


@nb.njit(fastmath=True, inline="always", **_JIT)
def _backward_block(s, start, rows, row_ptr, blk, block_ptr, x, tmp):
    """Supernode s's part of ``x <- L^-T x``: its rows below (gathered once into tmp), then its triangle."""
    zero = x.dtype.type(0.0)
    f = start[s]
    nc = start[s + 1] - f
    r0 = row_ptr[s]
    nr = row_ptr[s + 1] - r0
    b0 = block_ptr[s]
    no = nr - nc
    if no > 0:
        t = tmp[:no]
        rr = rows[r0 + nc:r0 + nr]
        for i in range(no):
            t[i] = x[rr[i]]
        k = 0
        while k + 4 <= nc:
            p0 = _below(blk, b0, nr, nc, k)
            p1 = _below(blk, b0, nr, nc, k + 1)
            p2 = _below(blk, b0, nr, nc, k + 2)
            p3 = _below(blk, b0, nr, nc, k + 3)
            a0 = zero
            a1 = zero
            a2 = zero
            a3 = zero
            for i in range(no):
                ti = t[i]
                a0 += p0[i] * ti
                a1 += p1[i] * ti
                a2 += p2[i] * ti
                a3 += p3[i] * ti
            x[f + k] -= a0
            x[f + k + 1] -= a1
            x[f + k + 2] -= a2
            x[f + k + 3] -= a3
            k += 4
        while k < nc:
            p0 = _below(blk, b0, nr, nc, k)
            a0 = zero
            for i in range(no):
                a0 += p0[i] * t[i]
            x[f + k] -= a0
            k += 1
    for k in range(nc - 1, -1, -1):
        c = _column(b0, nr, k)
        col = blk[c:c + nc - k - 1]
        xs = x[f + k + 1:f + nc]
        acc = zero
        for i in range(nc - k - 1):
            acc += col[i] * xs[i]
        x[f + k] -= acc


@nb.njit(fastmath=True, **_JIT)
def _solve(start, rows, row_ptr, blk, block_ptr, dinv, X, tmp):
    """``X[q] <- L^-T D^-1 L^-1 X[q]`` for each right-hand side (row) q of X (k, n): supernode by
    supernode, every right-hand side in turn, so that a block is read from memory once for all."""
    ns = start.size - 1
    for s in range(ns):
        for q in range(X.shape[0]):
            _forward_block(s, start, rows, row_ptr, blk, block_ptr, X[q], tmp)
    for q in range(X.shape[0]):
        x = X[q]
        for j in range(x.size):
            x[j] *= dinv[j]
    for s in range(ns - 1, -1, -1):
        for q in range(X.shape[0]):
            _backward_block(s, start, rows, row_ptr, blk, block_ptr, X[q], tmp)


@nb.njit(fastmath=True, **_JIT)
def _forward_many(seq, start, rows, row_ptr, blk, block_ptr, X, T):
    """``X <- L^-1 X`` over the supernodes *seq* (ascending: a postorder's), for X (n, k) with the k
    right-hand sides in the inner (contiguous) dimension: each entry of L read once for all of them and
    applied to k values in one vectorised loop. T (max_rows, k): scratch. Where X is zero outside the
    columns of *seq* and *seq* holds every ancestor of its supernodes (a unit vector's path to the
    root, :meth:`LDLT.columns`), the other supernodes would change nothing."""
    k = X.shape[1]
    for s in seq:
        f = start[s]
        nc = start[s + 1] - f
        r0 = row_ptr[s]
        nr = row_ptr[s + 1] - r0
        b0 = block_ptr[s]
        no = nr - nc
        for c in range(nc):
            base = _column(b0, nr, c)
            for i in range(nc - c - 1):
                lv = blk[base + i]
                for q in range(k):
                    X[f + c + 1 + i, q] -= lv * X[f + c, q]
        if no == 0:
            continue
        T[:no, :] = 0.0
        for c in range(nc):
            pc = _column(b0, nr, c) + nc - c - 1
            for i in range(no):
                lv = blk[pc + i]
                for q in range(k):
                    T[i, q] += lv * X[f + c, q]
        for i in range(no):
            r = rows[r0 + nc + i]
            for q in range(k):
                X[r, q] -= T[i, q]


@nb.njit(fastmath=True, **_JIT)
def _forward_one(start, rows, row_ptr, blk, block_ptr, x, tmp):
    """``x <- L^-1 x`` (one right-hand side, :func:`_forward_block` supernode by supernode)."""
    for s in range(start.size - 1):
        _forward_block(s, start, rows, row_ptr, blk, block_ptr, x, tmp)


@nb.njit(fastmath=True, **_JIT)
def _backward_one(start, rows, row_ptr, blk, block_ptr, x, tmp):
    """``x <- L^-T x`` (one right-hand side)."""
    for s in range(start.size - 2, -1, -1):
        _backward_block(s, start, rows, row_ptr, blk, block_ptr, x, tmp)


@nb.njit(fastmath=True, **_JIT)
def _forward_part(g, part, start, rows, row_ptr, blk, block_ptr, X, tmp):
    """The forward sweep over the supernodes of part g (:func:`_two_parts`), in order."""
    for s in range(start.size - 1):
        if part[s] == g:
            for q in range(X.shape[0]):
                _forward_block(s, start, rows, row_ptr, blk, block_ptr, X[q], tmp)


@nb.njit(fastmath=True, **_JIT)
def _backward_part(g, part, start, rows, row_ptr, blk, block_ptr, X, tmp):
    """The backward sweep over the supernodes of part g, in reverse order."""
    for s in range(start.size - 2, -1, -1):
        if part[s] == g:
            for q in range(X.shape[0]):
                _backward_block(s, start, rows, row_ptr, blk, block_ptr, X[q], tmp)


@nb.njit(fastmath=True, **_JIT)
def _merge_parts(part, start, X, XX):
    """X after both parts' forward sweeps on their copies XX[0], XX[1] of it: each part's own rows
    from its copy, the shared ancestors' rows with both copies' updates."""
    for s in range(start.size - 1):
        g = part[s]
        for q in range(X.shape[0]):
            if g >= 0:
                X[q, start[s]:start[s + 1]] = XX[g, q, start[s]:start[s + 1]]
            else:
                for j in range(start[s], start[s + 1]):
                    X[q, j] = XX[0, q, j] + XX[1, q, j] - X[q, j]


@nb.njit(parallel=True, **_JIT)
def _solve_two(start, rows, row_ptr, blk, block_ptr, dinv, part, X, XX, tmp2):
    """:func:`_solve` on two threads (:func:`_two_parts`): forward, each part's subtrees on its own
    copy of X (XX[g]; they update their ancestors' rows, which the parts share), then the copies
    merged and the ancestors solved; backward, the ancestors first, then both parts in place (each
    writes its own rows only). tmp2 (2, m): the threads' scratch."""
    for g in nb.prange(2):
        XX[g] = X
        _forward_part(g, part, start, rows, row_ptr, blk, block_ptr, XX[g], tmp2[g])
    _merge_parts(part, start, X, XX)
    _forward_part(-1, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[0])
    for q in range(X.shape[0]):
        for j in range(X.shape[1]):
            X[q, j] *= dinv[j]
    _backward_part(-1, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[0])
    for g in nb.prange(2):
        _backward_part(g, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[g])


@nb.njit(parallel=True, **_JIT)
def _forward_two(start, rows, row_ptr, blk, block_ptr, part, X, XX, tmp2):
    """The forward half of :func:`_solve_two`: ``X <- L^-1 X``."""
    for g in nb.prange(2):
        XX[g] = X
        _forward_part(g, part, start, rows, row_ptr, blk, block_ptr, XX[g], tmp2[g])
    _merge_parts(part, start, X, XX)
    _forward_part(-1, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[0])


@nb.njit(parallel=True, **_JIT)
def _backward_two(start, rows, row_ptr, blk, block_ptr, part, X, tmp2):
    """The backward half of :func:`_solve_two`: ``X <- L^-T X``."""
    _backward_part(-1, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[0])
    for g in nb.prange(2):
        _backward_part(g, part, start, rows, row_ptr, blk, block_ptr, X, tmp2[g])


@dataclass(eq=False)
class LDLT:
    """A matrix factored (:meth:`of`) for solves (:meth:`solve`).

    Attributes
    ----------
    analysis : Analysis
    blk : ndarray
        The supernodes' blocks of L: column by column, the rows below the (unit) diagonal.
    dinv : ndarray, shape (n,)
        1 / D, in the factor's order.
    """

    analysis: Analysis
    blk: np.ndarray
    dinv: np.ndarray
    threads: int = 1            #: 2: :meth:`solve` on two threads (:func:`_solve_two`)

    @property
    def dtype(self):
        return self.blk.dtype

    @property
    def nnz(self) -> int:
        """Entries of L."""
        return self.analysis.nnz

    @classmethod
    def of(cls, A, analysis: Analysis | None = None, *, perm: np.ndarray | None = None,
           dtype=np.float64, threads: int = 1) -> LDLT:
        """Factor *A*, with *analysis* if it matches *A*'s pattern, else a new one in order *perm*
        (default: *analysis*'s order, or the natural one), on one thread or (*threads* 2) two
        (:func:`_numeric_two`); the factor solves on as many. Raises :class:`ZeroPivot`."""
        A = canonical(A)
        if analysis is None or not analysis.matches(A):
            order = perm if perm is not None else (analysis.perm if analysis is not None else np.arange(A.shape[0]))
            analysis = Analysis.of(A, order)
        an = analysis
        vals = A.data[an.lo_src].astype(dtype)
        blk = np.empty(int(an.block_ptr[-1]), dtype)
        d = np.empty(an.n, dtype)
        bad = (_factor_two if threads > 1 else _factor_one)(an, vals, blk, d)
        if bad >= 0:
            raise ZeroPivot(f"zero or non-finite pivot in column {int(an.perm[bad])}")
        return cls(analysis=an, blk=blk, dinv=(1.0 / d).astype(dtype), threads=threads)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for *b* of shape (N,) or (N, k), in float64 (computed in the factor's precision)."""
        an = self.analysis
        X = np.ascontiguousarray(np.asarray(b)[an.perm].reshape(an.n, -1).T, dtype=self.dtype)
        if self.threads > 1:
            _solve_two(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, self.dinv, an.part, X,
                       np.empty((2,) + X.shape, self.dtype), np.empty((2, max(an.max_rows, 1)), self.dtype))
        else:
            _solve(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, self.dinv, X,
                   np.empty(max(an.max_rows, 1), self.dtype))
        out = np.empty((an.n, X.shape[0]))
        out[an.perm] = X.T
        return out.reshape(np.shape(b))

    # -- the two halves of a solve, for corrections between them (the constraints' capacitance) ----
    def forward(self, b: np.ndarray) -> np.ndarray:
        """``y = L^-1 P b`` for *b* (N,): the forward half of :meth:`solve`, in the factor's order and
        precision (``solve(b) = backward(dinv * y)``)."""
        an = self.analysis
        x = np.ascontiguousarray(np.asarray(b)[an.perm], dtype=self.dtype)
        if self.threads > 1:
            X = x.reshape(1, -1)
            _forward_two(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, an.part, X,
                         np.empty((2,) + X.shape, self.dtype), np.empty((2, max(an.max_rows, 1)), self.dtype))
        else:
            _forward_one(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, x,
                         np.empty(max(an.max_rows, 1), self.dtype))
        return x

    def backward(self, y: np.ndarray) -> np.ndarray:
        """``P^T L^-T y`` for *y* (N,) in the factor's order (overwritten), in float64 in the matrix's order."""
        an = self.analysis
        x = np.ascontiguousarray(y, dtype=self.dtype)
        if self.threads > 1:
            _backward_two(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, an.part, x.reshape(1, -1),
                          np.empty((2, max(an.max_rows, 1)), self.dtype))
        else:
            _backward_one(an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, x,
                          np.empty(max(an.max_rows, 1), self.dtype))
        out = np.empty(an.n)
        out[an.perm] = x
        return out

    def columns(self, dofs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Y = L^-1 P E`` for the unit vectors E at *dofs* (k,) of the matrix, as ``(R, Y_R)``: the
        rows R (factor order, sorted) where any column can be nonzero, and Y there (len(R), k; float64).

        ``L^-1 e_j`` is zero outside the supernodes on the path from j's supernode to the root of
        the supernode tree, so only those are swept (:func:`_forward_many`): each column costs its
        path, not the whole factor."""
        an = self.analysis
        ns = an.start.size - 1
        pos = np.empty(an.n, np.int64)
        pos[an.perm] = np.arange(an.n)
        cols = pos[np.asarray(dofs, dtype=np.int64)]
        snode = np.searchsorted(an.start, cols, side="right") - 1
        parent = an.snode_parent()
        on = np.zeros(ns, bool)
        for s0 in np.unique(snode):
            s_ = int(s0)
            while s_ >= 0 and not on[s_]:
                on[s_] = True
                s_ = int(parent[s_])
        seq = np.flatnonzero(on)
        R = np.concatenate([np.arange(an.start[s_], an.start[s_ + 1]) for s_ in seq]) if seq.size else \
            np.zeros(0, np.int64)
        X = np.zeros((an.n, cols.size), self.dtype)
        X[cols, np.arange(cols.size)] = 1.0
        _forward_many(seq.astype(np.int64), an.start, an.rows, an.row_ptr, self.blk, an.block_ptr, X,
                      np.empty((max(an.max_rows, 1), max(cols.size, 1)), self.dtype))
        return R, X[R].astype(np.float64)


def _factor_one(an: Analysis, vals, blk, d) -> int:
    """:func:`_numeric` over all supernodes, on one stack."""
    ns, dtype = an.start.size - 1, blk.dtype
    nc_max = int(np.diff(an.start).max()) if an.n else 0
    return _numeric(np.arange(ns), np.zeros(ns, np.int64), 0, an.start, an.rows, an.row_ptr, an.block_ptr,
                    an.kids, an.kid_ptr, an.lo_ptr, an.lo_idx, vals, blk, d, np.empty(max(an.stack_size, 1), dtype),
                    np.empty(ns, np.int64), np.empty(an.max_rows ** 2, dtype), np.empty(an.n, np.int64),
                    np.empty(nc_max, dtype), np.empty(nc_max, dtype))


def _factor_two(an: Analysis, vals, blk, d) -> int:
    """:func:`_numeric_two`: each thread with its own stack, front and scratch; OpenBLAS on one thread
    meanwhile (the two threads' matrix products would otherwise each start its threads, on cores
    that are busy)."""
    ns, dtype = an.start.size - 1, blk.dtype
    nc_max = int(np.diff(an.start).max()) if an.n else 0
    base = np.concatenate([[0], np.cumsum(an.part_stack)[:2]]).astype(np.int64)
    with single_threaded_blas():
        return _numeric_two(an.by_part, an.part_ptr, an.part, base, an.start, an.rows, an.row_ptr, an.block_ptr,
                            an.kids, an.kid_ptr, an.lo_ptr, an.lo_idx, vals, blk, d,
                            np.empty(max(int(an.part_stack.sum()), 1), dtype), np.empty(ns, np.int64),
                            np.empty((2, an.max_rows ** 2), dtype), np.empty((2, an.n), np.int64),
                            np.empty((2, nc_max), dtype), np.empty((2, nc_max), dtype))


def warm_up(*, dtypes=(np.float32,)) -> None:
    """Compile (or load from numba's cache) the kernels for *dtypes* on a 3 x 3 matrix, on one thread
    and, where numba has two, on two (the factorization and the solve).

    Compiling on a fresh machine takes tens of seconds for one dtype on one and two threads (most of
    it the two-thread solve), a fraction of a second from the cache; the implicit stepper factors in
    float32.
    """
    A = sp.csr_matrix(np.array([[4.0, 1.0, 0.0], [1.0, 4.0, 1.0], [0.0, 1.0, 4.0]]))
    an = Analysis.of(A, np.array([2, 0, 1]))
    for dtype in dtypes:
        for n in (1, 2) if nb.config.NUMBA_NUM_THREADS > 1 else (1,):
            LDLT.of(A, an, dtype=dtype, threads=n).solve(np.ones((3, 2)))
