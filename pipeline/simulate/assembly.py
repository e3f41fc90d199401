r"""The reused factor's matrix assembled in one compiled pass into a pattern fixed for the run.

The implicit stepper factors :math:`A = M/h^2 + (\alpha M + C)/h + K_{springs} + K_{tet}` (the
volume term's per-tet bound, :meth:`~.volumeterm.VolumeTerm.tangent_bound`), the fixed nodes' rows
and columns the identity (:meth:`~.implicit_system.StepSystem.matrix`). Summed as sparse matrices
(the springs' tangent, the volume term's bound, the dashpots' matrix, the masks and the diagonal)
it cost over a third of a renewal on the split networks (19 ms against a numeric factorization's 34 ms
on the liver's split of 1 736 parents). :class:`BoundAssembly` writes every term into the data of
one CSR pattern found once per run, the springs' node blocks: the per-tet bound couples only the
nodes of a tet, which are the springs' on a tetrahedral network. The values are those of the
sparse sums to rounding (docs/design/realtime.md, "The split networks' step made cheaper").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps

from ..network.springs import tet_volumes
from . import kernels as K
from .springterm import BlockPattern
from .volumeterm import VolumeTerm


@dataclass(frozen=True, eq=False)
class BoundAssembly:
    """Where each term's entries go in the factor's matrix (module doc); :meth:`of` finds it.

    Attributes
    ----------
    pattern : BlockPattern
        Every spring's node blocks and every node's diagonal block (the terms are summed into its data).
    volume : VolumeTerm or None
    tets : ndarray of int64, shape (t, 4), or None
        Its tets.
    tet_pos : ndarray, shape (t, 144), or None
        Where each tet's 12 x 12 block goes in the pattern's data.
    tet_weight : ndarray, shape (t,), or None
        ``kappa / V_t0`` of each tet.
    keep : ndarray of int64
        The pattern's entries that stay (both nodes movable): the matrix's data is ``data[keep]``.
    indptr, indices : ndarray
        The matrix's CSR pattern (the kept entries).
    diag : ndarray of int64
        Each diagonal entry's position in the matrix's data.
    """

    pattern: BlockPattern
    volume: VolumeTerm | None
    tets: np.ndarray | None
    tet_pos: np.ndarray | None
    tet_weight: np.ndarray | None
    keep: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    diag: np.ndarray

    @classmethod
    def of(cls, model) -> BoundAssembly | None:
        """The assembly of *model*'s bound matrix, or None where its terms are not the springs and at
        most one volume term whose tets' node pairs are all springs (the sparse sums then)."""
        sp = model.springs
        others = [t for t in model.terms if t is not sp]
        if len(others) > 1 or (others and not isinstance(others[0], VolumeTerm)):
            return None
        pattern = sp.pattern
        n = model.n_nodes
        volume, tets, pos, weight = None, None, None, None
        if others:
            volume = others[0]
            tets = np.ascontiguousarray(volume.elements.tets, dtype=np.int64)
            pos = _tet_positions(pattern, tets, n)
            if pos is None:
                return None
            weight = np.ascontiguousarray(np.broadcast_to(
                volume.elements.bulk_modulus / tet_volumes(model.rest, tets), (tets.shape[0],)), dtype=np.float64)
        mov = np.repeat(model.movable, 3)
        rows = np.repeat(np.arange(3 * n), np.diff(pattern.indptr))
        on = mov[rows] & mov[pattern.indices] | (rows == pattern.indices)
        keep = np.flatnonzero(on)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[keep], minlength=3 * n))]).astype(np.int32)
        where = np.full(on.size, -1, np.int64)
        where[keep] = np.arange(keep.size)
        return cls(pattern=pattern, volume=volume, tets=tets, tet_pos=pos, tet_weight=weight, keep=keep, indptr=indptr,
                   indices=np.ascontiguousarray(pattern.indices[keep]), diag=where[pattern.diag])

    def matrix(self, system, x: np.ndarray):
        """The factor's matrix of *system* (a :class:`~.implicit_system.StepSystem`) at *x*: what
        ``system.matrix(x, bound=True)`` sums (equal to rounding: the terms are added entry by entry
        in another order)."""
        model, h = system.model, system.h
        sp = model.springs
        pat = self.pattern
        x = np.ascontiguousarray(x, dtype=np.float64)
        s = sp.n_springs
        kt, fl, u = np.empty(s), np.empty(s), np.empty((s, 3))
        st = system.state.effects
        fx = None if sp.effects is None else sp.effects.kernel(sp.new_state() if st is None else st,
                                                               mode=int(K.FX_PEEK), dt=system.dt_fx)
        K.tangent_coefficients(x, sp.kernel(damped=False), fx, kt, fl, u)
        data = np.zeros(pat.nnz)
        K.fill_blocks(sp.ij, kt, fl, u, pat.blk, pat.stride, data, bool(system.definite))
        if self.volume is not None:
            K.add_tet_bound(x, self.tets, self.tet_weight, self.tet_pos, K.TET_EVEN, data)
        if sp.damped:                                      # the dashpots' c u u^T / h, along the same u
            K.fill_blocks(sp.ij, sp.sd[-1].astype(np.float64) / h, np.zeros(s), u, pat.blk, pat.stride, data, False)
        out = data[self.keep]
        mov = np.repeat(model.movable, 3)
        out[self.diag[~mov]] = 0.0                         # the fixed nodes' rows: the identity
        out[self.diag] += np.where(mov, system.mass_dof, 1.0)
        n3 = 3 * model.n_nodes
        return sps.csr_matrix((out, self.indices, self.indptr), shape=(n3, n3), copy=False)


def _tet_positions(pattern: BlockPattern, tets: np.ndarray, n: int) -> np.ndarray | None:
    """Where entry ``12 a + b`` of each tet's 12 x 12 block (its dofs ``3 tets[t] + (0, 1, 2)``) lies in
    *pattern*'s data, (t, 144); None where a pair of a tet's nodes is not one of its blocks."""
    indptr = pattern.indptr.astype(np.int64)
    first = indptr[0:-1:3]                                   # each node's first scalar row
    deg = pattern.stride // 3
    bstart = np.concatenate([[0], np.cumsum(deg)])
    brow = np.repeat(np.arange(n, dtype=np.int64), deg)
    within = np.arange(brow.size) - bstart[brow]
    keys = brow * n + pattern.indices[first[brow] + 3 * within].astype(np.int64) // 3   # sorted (row, col)
    p_, da, q_, db = (v.reshape(12, 12) for v in np.meshgrid(np.arange(4), np.arange(3), np.arange(4),
                                                            np.arange(3), indexing="ij"))
    a, b = tets[:, p_], tets[:, q_]                           # (t, 12, 12) node pairs
    want = a * n + b
    k = np.minimum(np.searchsorted(keys, want), keys.size - 1)
    if not np.array_equal(keys[k], want):
        return None
    rank = k - bstart[a]
    pos = indptr[3 * a + da] + 3 * rank + db
    return np.ascontiguousarray(pos.reshape(-1, 144), dtype=np.int64)
