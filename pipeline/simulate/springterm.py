r"""The spring force term: a network and its tables as the kernels read them.

:func:`build_spring_term` turns a
:class:`~esmm.pipeline.network.springs.SpringNetwork` and
:class:`~esmm.pipeline.network.tables.StiffnessTables` into a
:class:`SpringTerm`: the springs sorted for the kernels, their weights, the
law's table, and the bounds of their tangent stiffness that the explicit step
needs (docs/design/simulator.md, "The explicit stepper (the accuracy reference)"):

.. math::  \kappa_{ij} = \max(k^t_{ij}, F_{ij}/L_{ij}, 0) \le \sum_d a_{ij,d} G_d

with :math:`G_d = \sup_\lambda \max(f_d'(\lambda), f_d(\lambda)/\lambda)` over
the grid and its extrapolation (:func:`tangent_bound`), per grid cell
(:func:`cell_tangent_bound`) or over a stretch window (:func:`windowed_bound`).
The term is constant during a run; its per-spring state (the material
effects') lives in the :class:`~.model.State`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sps
from scipy.ndimage import maximum_filter1d

from ..errors import ConfigError, InputError
from ..network.tables import spring_factors
from . import kernels as K
from .effects import EffectModel, EffectState, build_effect_model

PRECISIONS = ("float64", "float32")
LAW_CODES = {"secant": K.LAW_SECANT, "energy": K.LAW_ENERGY}


@dataclass(eq=False)
class SpringTerm:
    """The compiled kernels' view of a network and its tables (a :class:`~.model.ForceTerm`).

    Attributes
    ----------
    n_nodes : int
    ij : ndarray, shape (2, s), uint32
        Springs (rows i and j), ``i < j``, sorted by ``(i, j)``.
    order : ndarray, shape (s,), int64
        Spring p of the term is ``network.springs[order[p]]``.
    sd : ndarray, shape (4, s) or (5, s); isotropic tables: (2, s) or (3, s)
        Rows ``1/L0, w_x, w_y, w_z(, c_ij)`` with ``w_d = c V_ij cos2_d / L0``
        [m2] and the dashpot ``c_ij`` [N s/m]; isotropic: ``1/L0, w(, c_ij)``
        with ``w = sum_d w_d``.
    tab : ndarray, shape (n_grid - 1, 6)
        Per cell ``[f_x, f_y, f_z, df_x, df_y, df_z]`` [Pa] of the law's table.
    lam_min, inv_h : float
        Grid start and inverse step.
    law : str
        ``"secant"`` or ``"energy"``.
    kappa : ndarray, shape (s,)
        Upper bound of each spring's tangent stiffness over all stretches [N/m].
    rest_tangent : ndarray, shape (s,)
        Axial tangent stiffness at rest [N/m].
    dashpot : float
        Stiffness-proportional dashpot time beta [s]; ``c_ij = beta * rest_tangent``.
    lam_max : float
        Grid end.
    cell_bound : ndarray, shape (n_grid - 1, 3)
        Tangent bound per grid cell and direction [Pa] (effects included).
    effects : EffectModel or None
        Material effects (QLV, Mullins, damage; :mod:`.effects`): the springs then
        carry state and the kernels' effects variant is used. ``kappa`` and
        ``cell_bound`` include their added tangent bounds.
    """

    n_nodes: int
    ij: np.ndarray
    order: np.ndarray
    sd: np.ndarray
    tab: np.ndarray
    lam_min: float
    inv_h: float
    law: str
    kappa: np.ndarray
    rest_tangent: np.ndarray
    dashpot: float = 0.0
    lam_max: float = math.inf
    cell_bound: np.ndarray | None = None
    effects: EffectModel | None = None
    _layouts: dict = field(default_factory=dict, repr=False)
    _windows: dict = field(default_factory=dict, repr=False)
    _pattern: BlockPattern | None = field(default=None, repr=False)

    @property
    def n_springs(self) -> int:
        return int(self.ij.shape[1])

    @property
    def law_code(self) -> int:
        return LAW_CODES[self.law]

    @property
    def damped(self) -> bool:
        return self.dashpot > 0.0

    @property
    def n_directions(self) -> int:
        """3, or 1 when the tables are isotropic (one weight and one lookup per spring)."""
        return int(self.sd.shape[0] - 1 - (1 if self.damped else 0))

    @property
    def last_cell(self) -> int:
        return int(self.tab.shape[0] - 1)

    def kernel(self, *, damped: bool | None = None) -> K.SpringKernel:
        """The kernels' tuple (dashpots as the term has them, or off with ``damped=False``)."""
        use = self.damped if damped is None else (bool(damped) and self.damped)
        return K.SpringKernel(self.ij, self.sd, self.tab, self.lam_min, self.inv_h, self.last_cell,
                              self.law_code, use)

    def bytes_per_spring(self) -> int:
        """Bytes of spring data streamed per spring per step (indices + data rows)."""
        return int(self.ij.itemsize * 2 + self.sd.itemsize * self.sd.shape[0])

    def new_state(self, *, t: float = 0.0) -> EffectState | None:
        """The springs' virgin state (None without effects)."""
        return None if self.effects is None else self.effects.new_state(self.n_springs, t=t)

    # -- evaluation ------------------------------------------------------
    def forces(self, x: np.ndarray, v: np.ndarray | None = None, *, fext: np.ndarray | None = None,
               damped: bool | None = None, state: EffectState | None = None, mode: int = K.FX_PEEK,
               dt: float = 0.0, beside: K.VolumeKernel | None = None) -> np.ndarray:
        """Nodal forces (n, 3) [N] at positions *x* (and velocities *v* for the dashpots).

        With material effects, *state* is the springs' state (default: the
        virgin state, so the force is the instantaneous response from rest) and
        *mode* one of ``kernels.FX_PEEK`` (the force a step of *dt* from the
        state would give; state unchanged), ``FX_STEP`` (the same, committing
        the state), ``FX_RELAXED`` (long-term force) or ``FX_SETTLE``.
        *beside*: a volume term's kernel whose forces are computed on a second
        thread meanwhile and added (:func:`~.kernels.forces_beside_volume`).
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise InputError(f"x: expected shape ({self.n_nodes}, 3), got {x.shape}")
        v = np.zeros_like(x) if v is None else np.ascontiguousarray(v, dtype=np.float64)
        fe = np.zeros_like(x) if fext is None else np.ascontiguousarray(fext, dtype=np.float64)
        f = np.empty_like(x)
        fx = None
        if self.effects is not None:
            st = self.new_state() if state is None else state
            fx = self.effects.kernel(st, mode=int(mode), dt=dt)
        if beside is None:
            K.forces_serial(x, v, f, fe, self.kernel(damped=damped), fx, self.layout(1))
        else:
            K.forces_beside_volume(x, v, f, np.empty_like(x), fe, self.kernel(damped=damped), fx, self.layout(1),
                                   beside)
        return f

    def stretches(self, x: np.ndarray) -> np.ndarray:
        """Stretch of every spring at positions *x*, shape (s,) (term spring order)."""
        x = np.asarray(x, dtype=np.float64)
        d = x[self.ij[1]] - x[self.ij[0]]
        return np.sqrt(np.einsum("ij,ij->i", d, d)) * self.sd[0].astype(np.float64)

    def stretch_range(self, x: np.ndarray) -> tuple[float, float]:
        """(min, max) stretch over the springs at positions *x*."""
        lo, hi = K.stretch_range(np.ascontiguousarray(x, dtype=np.float64), self.ij, self.sd)
        return float(lo), float(hi)

    def stretch_change(self, x: np.ndarray, x0: np.ndarray) -> float:
        """Largest change of a spring's stretch between positions *x0* and *x*."""
        return float(K.stretch_change(x, x0, self.ij, self.sd))

    # -- tangent stiffness (the implicit step) ---------------------------------
    @property
    def pattern(self) -> BlockPattern:
        """The sparsity pattern of :meth:`tangent` (built once)."""
        if self._pattern is None:
            self._pattern = BlockPattern.of(self.ij, self.n_nodes)
        return self._pattern

    def tangent(self, x: np.ndarray, v: np.ndarray | None = None, *, state: EffectState | None = None,
                dt: float = 0.0, mode: int = K.FX_PEEK, definite: bool = False):
        """Tangent stiffness ``K = -df/dx`` at positions *x*, a symmetric CSR matrix (3n, 3n) [N/m].

        Dof order ``x.ravel()`` (node-major, xyz). Per spring ``k_t u u^T + (F/L)(I - u u^T)``
        with ``k_t = dF/dL`` of the law's table (both laws, every fibre direction); with
        material effects, the force and its derivative of a step of *dt* from *state* (the
        same arguments as :meth:`forces`; default the virgin state): the QLV instantaneous
        factor times the derivative of the damaged and Mullins-softened force. The
        dashpots are not in it (:meth:`damping_matrix`); *v* is accepted for the
        :class:`~.model.ForceTerm` interface. *definite*: negative ``k_t`` and ``F/L`` are
        dropped (every spring block positive semi-definite).
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise InputError(f"x: expected shape ({self.n_nodes}, 3), got {x.shape}")
        s = self.n_springs
        kt, fl, u = np.empty(s), np.empty(s), np.empty((s, 3))
        fx = None
        if self.effects is not None:
            st = self.new_state() if state is None else state
            fx = self.effects.kernel(st, mode=int(mode), dt=dt)
        K.tangent_coefficients(x, self.kernel(damped=False), fx, kt, fl, u)
        return self.pattern.matrix(self.ij, kt, fl, u, definite=definite)

    def damping_matrix(self, x: np.ndarray):
        """The dashpots' damping matrix ``C = sum c_ij u u^T`` (graph-Laplacian signs) at *x*, CSR (3n, 3n) [N s/m].

        The dashpots' force is ``-C v`` (their change with the direction u is left
        out); zeros without dashpots.
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        d = x[self.ij[1]] - x[self.ij[0]]
        L = np.sqrt(np.einsum("ij,ij->i", d, d))
        u = np.divide(d, L[:, None], out=np.zeros_like(d), where=L[:, None] > 0)
        c = self.sd[-1].astype(np.float64) if self.damped else np.zeros(self.n_springs)
        return self.pattern.matrix(self.ij, c, np.zeros(self.n_springs), u, definite=False)

    # -- stiffness bounds (the explicit step) --------------------------------
    def window(self, delta: float) -> np.ndarray:
        """Tangent bound per cell over a stretch window of +-*delta* (cached), shape (n_cells, 3)."""
        cells = int(math.ceil(delta * self.inv_h - 1e-9))
        if cells not in self._windows:
            self._windows[cells] = windowed_bound(self.cell_bound, cells)
        return self._windows[cells]

    def stiffness_rows(self, *, x: np.ndarray | None = None, window: float | None = None) -> np.ndarray:
        """Per node, ``2 sum_j kappa_ij`` [N/m]: the Gershgorin row of the tangent bound, shape (n,).

        Over every stretch by default; with positions *x* and a stretch
        *window* delta, over ``[lam - delta, lam + delta]`` around each
        spring's stretch in *x*.
        """
        n = self.n_nodes
        if x is None or window is None:
            i, j = self.ij[0], self.ij[1]
            ksum = np.bincount(i, weights=self.kappa, minlength=n) + np.bincount(j, weights=self.kappa, minlength=n)
        else:
            ksum = np.empty(n)
            K.node_tangent_sums(np.ascontiguousarray(x, dtype=np.float64), self.ij, self.sd, self.window(window),
                                self.lam_min, self.inv_h, self.last_cell, self.n_directions == 3, ksum)
        return 2.0 * ksum

    def damping_rows(self) -> np.ndarray:
        """Per node, ``2 sum_j c_ij`` [N s/m] of the dashpots (zeros without), shape (n,)."""
        n = self.n_nodes
        if not self.damped:
            return np.zeros(n)
        c = self.sd[-1].astype(np.float64)
        return 2.0 * (np.bincount(self.ij[0], weights=c, minlength=n) + np.bincount(self.ij[1], weights=c, minlength=n))

    def state_rows(self, state: EffectState | None, x: np.ndarray, delta: float) -> np.ndarray | None:
        """Per-node Gershgorin row added by the viscoelastic history forces [N/m], or None.

        See :meth:`EffectModel.history_stiffness` (valid while no stretch moves
        by more than *delta*); None without viscoelasticity.
        """
        fx = self.effects
        if fx is None or fx.n_terms == 0:
            return None
        lam = self.stretches(x)
        k = fx.history_stiffness(state, lam, 1.0 / self.sd[0].astype(np.float64), float(delta))
        n = self.n_nodes
        return 2.0 * (np.bincount(self.ij[0], weights=k, minlength=n) + np.bincount(self.ij[1], weights=k, minlength=n))

    # -- threading ---------------------------------------------------------
    def layout(self, chunks: int) -> K.Layout:
        """Owner/halo layout for *chunks* threads (cached; one chunk: the serial pass): see :mod:`.kernels`."""
        chunks = max(1, int(chunks))
        if chunks not in self._layouts:
            self._layouts[chunks] = thread_layout(self.ij, self.n_nodes, chunks)
        return self._layouts[chunks]


@dataclass(frozen=True, eq=False)
class BlockPattern:
    """CSR pattern (3n, 3n) of a node graph with 3x3 blocks: every node with itself and its springs' nodes.

    Attributes
    ----------
    indptr, indices : ndarray, int32
        The scalar CSR arrays (each node row ``a`` has the 3 columns of every block of
        its node row, in node order).
    blk : ndarray, shape (4, s), int64
        Per spring ``(i, j)``: data offsets of the blocks (i, i), (j, j), (i, j), (j, i) at
        their first row.
    stride : ndarray, shape (n,), int64
        Entries per scalar row of node a's rows (3 x its block count).
    diag : ndarray, shape (3n,), int64
        Data offset of each diagonal entry.
    """

    indptr: np.ndarray
    indices: np.ndarray
    blk: np.ndarray
    stride: np.ndarray
    diag: np.ndarray

    @classmethod
    def of(cls, ij: np.ndarray, n: int) -> BlockPattern:
        """The pattern of springs *ij* (2, s) on *n* nodes."""
        i = ij[0].astype(np.int64)
        j = ij[1].astype(np.int64)
        nodes = np.arange(n, dtype=np.int64)
        rows = np.concatenate([i, j, nodes])
        cols = np.concatenate([j, i, nodes])
        key = np.unique(rows * n + cols)                       # node-CSR, sorted by (row, col)
        brow, bcol = key // n, key % n
        deg = np.bincount(brow, minlength=n)
        bstart = np.concatenate([[0], np.cumsum(deg)])          # block-row starts
        stride = 3 * deg
        rstart = np.concatenate([[0], np.cumsum(np.repeat(stride, 3))]).astype(np.int64)   # scalar rows
        indices = np.empty(int(rstart[-1]), np.int32)
        q = np.arange(key.size) - bstart[brow]                  # position of each block in its row
        for r in range(3):
            base = rstart[3 * brow + r] + 3 * q
            for c in range(3):
                indices[base + c] = 3 * bcol + c

        def offset(a, b):
            pos = np.searchsorted(key, a * n + b) - bstart[a]
            return rstart[3 * a] + 3 * pos

        blk = np.ascontiguousarray(np.stack([offset(i, i), offset(j, j), offset(i, j), offset(j, i)]))
        d0 = offset(nodes, nodes)
        diag = (np.repeat(d0, 3) + np.tile(np.arange(3), n) * (np.repeat(stride, 3) + 1)).astype(np.int64)
        return cls(indptr=rstart.astype(np.int32), indices=indices, blk=blk, stride=stride.astype(np.int64),
                   diag=diag)

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    def matrix(self, ij, kt, fl, u, *, definite: bool = False):
        """The CSR matrix of the spring blocks ``kt u u^T + fl (I - u u^T)`` (:func:`.kernels.fill_blocks`)."""
        data = np.zeros(self.nnz)
        K.fill_blocks(ij, kt, fl, u, self.blk, self.stride, data, bool(definite))
        n3 = self.indptr.size - 1
        return sps.csr_matrix((data, self.indices, self.indptr), shape=(n3, n3), copy=False)


def _law_values(tables, law: str) -> np.ndarray:
    """The law's table rows f_d (secant: mu_e; energy: the stress), shape (3, n) [Pa]."""
    return np.asarray(tables.values if law == "secant" else tables.stress, dtype=np.float64)


def tangent_bound(tables, law: str) -> np.ndarray:
    """G_d = sup over all stretches of max(f_d', f_d/lam, 0) [Pa], shape (3,).

    Follows the tables' interpolation and extrapolation exactly (linear cells;
    secant: mu_e held off the grid; energy: stress continued linearly).
    """
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    vals = _law_values(tables, law)
    h = lam[1] - lam[0]
    slope = np.diff(vals, axis=1) / h                        # (3, n-1)
    if law == "secant":
        # f = mu (lam-1): f' = mu + (lam-1) mu' is linear in each cell -> max at its ends;
        # f/lam <= mu for lam >= 1 (and negative below 1); off the grid f' = mu_end.
        fa = vals[:, :-1] + (lam[:-1] - 1.0) * slope
        fb = vals[:, 1:] + (lam[1:] - 1.0) * slope
        g = np.maximum(np.maximum(fa.max(axis=1), fb.max(axis=1)), vals.max(axis=1))
    else:
        # f' is the cell slope (the end slopes continue off the grid); f/lam is bounded by
        # its grid values and, beyond lam_max, by max(f_end/lam_max, end slope).
        g = np.maximum(slope.max(axis=1), (vals / lam).max(axis=1))
    return np.maximum(g, 0.0)


def cell_tangent_bound(tables, law: str) -> np.ndarray:
    """Per grid cell, the sup of max(f_d', f_d/lam, 0) over the cell [Pa], shape (n - 1, 3).

    The first and last cells also cover the extrapolation beyond the grid (a
    stretch off the grid is looked up in the end cell).
    """
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    vals = _law_values(tables, law)
    h = lam[1] - lam[0]
    slope = np.diff(vals, axis=1) / h
    if law == "secant":
        fa = vals[:, :-1] + (lam[:-1] - 1.0) * slope
        fb = vals[:, 1:] + (lam[1:] - 1.0) * slope
        g = np.maximum(np.maximum(fa, fb), np.maximum(vals[:, :-1], vals[:, 1:]))
        g[:, 0] = np.maximum(g[:, 0], vals[:, 0])          # mu held below the grid
        g[:, -1] = np.maximum(g[:, -1], vals[:, -1])       # ... and above it
    else:
        fl = vals / lam
        g = np.maximum(slope, np.maximum(fl[:, :-1], fl[:, 1:]))
    return np.ascontiguousarray(np.maximum(g, 0.0).T)


def windowed_bound(cell_bound: np.ndarray, cells: int) -> np.ndarray:
    """Running max of *cell_bound* (n_cells, 3) over +-*cells* cells, same shape."""
    size = 2 * int(cells) + 1
    return np.ascontiguousarray(maximum_filter1d(cell_bound, size=size, axis=0, mode="nearest"))


def _checked_springs(network) -> tuple[np.ndarray, int, np.ndarray]:
    """(springs (s, 2) int64, n nodes, rest lengths (s,)) of *network*, refused when unusable."""
    springs = np.asarray(network.springs, dtype=np.int64).reshape(-1, 2)
    n = int(np.asarray(network.points).shape[0])
    if springs.shape[0] == 0:
        raise InputError("network has no springs; rebuild the asset")
    if springs.min() < 0 or springs.max() >= n:
        raise InputError(f"network springs reference nodes outside 0..{n - 1}; rebuild the asset")
    if n >= 2**32 - 1:
        raise InputError(f"network has {n} nodes; the simulator supports fewer than 2**32")
    L0 = np.asarray(network.rest_length, dtype=np.float64)
    if np.any(~np.isfinite(L0)) or np.any(L0 <= 0):
        raise InputError("network has springs of zero or non-finite rest length; rebuild the asset")
    return springs, n, L0


def build_spring_term(network, tables, *, law: str | None = None, dashpot: float = 0.0,
                      precision: str = "float64", isotropic_fast: bool = True,
                      effects=None) -> SpringTerm:
    """Build the :class:`SpringTerm` of *network* with *tables*.

    Parameters
    ----------
    network : SpringNetwork
        ``points`` (n, 3), ``springs`` (s, 2), ``rest_length`` (s,),
        ``volume_weight`` (s,), ``cos2`` (s, 3).
    tables : StiffnessTables
    law : {"secant", "energy"}, optional
        Default: the tables' default law.
    dashpot : float
        Stiffness-proportional dashpot time beta [s] (0: none): each spring gets
        a dashpot ``c_ij = beta * k_t,ij(lam=1)`` along its axis.
    precision : {"float64", "float32"}
        Storage of the per-spring data (the arithmetic is float64 either way).
    isotropic_fast : bool
        When the three table rows are equal, store one weight per spring and do
        one lookup (the same forces up to rounding; False keeps three).
    effects : MaterialEffects, optional
        Material effects to apply (viscoelastic, Mullins, damage; see
        :mod:`.effects`); None or empty: the elastic kernels.
    """
    law = tables.check_law(law)
    if precision not in PRECISIONS:
        raise ConfigError(f"precision: unknown {precision!r}; use one of {', '.join(PRECISIONS)}",
                          parameter="precision")
    if not (np.isfinite(dashpot) and dashpot >= 0):
        raise ConfigError(f"dashpot: must be a time >= 0 s, got {dashpot!r}", parameter="dashpot")
    springs, n, L0 = _checked_springs(network)
    s = springs.shape[0]
    a = spring_factors(tables, network)                      # (s, 3) = c v cos2   [m]
    lo = springs.min(axis=1)
    hi = springs.max(axis=1)
    order = np.lexsort((hi, lo))
    ij = np.ascontiguousarray(np.stack([lo[order], hi[order]], axis=0).astype(np.uint32))
    a = a[order]
    L0 = L0[order]
    fdt = np.float64 if precision == "float64" else np.float32
    rest_tangent = a @ np.asarray(tables.tangent_function(1.0, law=law), dtype=np.float64)
    kappa = a @ tangent_bound(tables, law)
    vals = _law_values(tables, law)
    iso = bool(np.array_equal(vals[0], vals[1]) and np.array_equal(vals[0], vals[2])) and isotropic_fast
    ndir = 1 if iso else 3
    sd = np.empty((1 + ndir + (dashpot > 0), s), dtype=fdt)
    sd[0] = 1.0 / L0
    if iso:    # one lookup per spring: sum_d cos2_d f(lam) = f(lam) sum_d cos2_d
        sd[1] = (a * L0[:, None]).sum(axis=1)
    else:
        sd[1:4] = (a * L0[:, None]).T
    if dashpot > 0:
        sd[-1] = dashpot * rest_tangent
    tab = np.ascontiguousarray(np.concatenate([vals[:, :-1].T, np.diff(vals, axis=1).T], axis=1))
    cell_bound = cell_tangent_bound(tables, law)
    fx = build_effect_model(effects, tables, law)
    if fx is not None:
        extra = fx.history_table.copy()
        if fx.mullins_cell is not None:
            cell_bound = np.ascontiguousarray(cell_bound + fx.mullins_cell)
            extra += fx.mullins_cell.max(axis=0)
        kappa = kappa + a @ extra
    return SpringTerm(n_nodes=n, ij=ij, order=order, sd=np.ascontiguousarray(sd), tab=tab,
                      lam_min=float(tables.lam_min), inv_h=1.0 / float(tables.dlam), law=law,
                      kappa=kappa, rest_tangent=rest_tangent, dashpot=float(dashpot),
                      lam_max=float(tables.lam_max), cell_bound=cell_bound, effects=fx)


def thread_layout(ij: np.ndarray, n_nodes: int, chunks: int) -> K.Layout:
    """Owner/halo arrays for the race-free parallel force pass (see :mod:`.kernels`).

    Returns
    -------
    Layout
        ``node_start`` (T+1,): node ranges with about equal spring counts;
        ``spring_start`` (T+1,): their spring ranges; ``halo_start`` (T+1,):
        slot ranges of the springs whose ``j`` lies beyond their chunk;
        ``hbuf`` (H, 3) the slots; ``own_*``: for each chunk, the slots that
        land in its nodes, with the node.
    """
    i = ij[0].astype(np.int64)
    j = ij[1].astype(np.int64)
    s = i.size
    chunks = max(1, min(int(chunks), max(1, n_nodes)))
    targets = np.linspace(0, s, chunks + 1)[1:-1]
    cuts = i[np.minimum(targets.astype(np.int64), s - 1)] if s else np.zeros(0, np.int64)
    node_start = np.concatenate([[0], np.maximum.accumulate(cuts), [n_nodes]]).astype(np.int64)
    node_start = np.maximum.accumulate(node_start)
    spring_start = np.searchsorted(i, node_start).astype(np.int64)
    owner_i = np.searchsorted(node_start, i, side="right") - 1
    owner_j = np.searchsorted(node_start, j, side="right") - 1
    halo = owner_j != owner_i
    halo_idx = np.flatnonzero(halo)
    counts = np.bincount(owner_i[halo_idx], minlength=chunks)
    halo_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    slots = np.arange(halo_idx.size, dtype=np.int64)     # spring order = slot order within a chunk
    owners = owner_j[halo_idx]
    by_owner = np.argsort(owners, kind="stable")
    own_counts = np.bincount(owners, minlength=chunks)
    own_start = np.concatenate([[0], np.cumsum(own_counts)]).astype(np.int64)
    own_slot = np.ascontiguousarray(slots[by_owner])
    own_node = np.ascontiguousarray(j[halo_idx][by_owner]).astype(np.int64)
    hbuf = np.zeros((max(1, halo_idx.size), 3))
    return K.Layout(node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node)
