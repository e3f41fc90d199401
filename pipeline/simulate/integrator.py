r"""Time integration of a spring network: symplectic Euler, stability bound, FIRE.

:class:`ForceModel` turns a :class:`~esmm.pipeline.network.springs.SpringNetwork`
and :class:`~esmm.pipeline.network.tables.StiffnessTables` into the compiled
kernels' arrays; :class:`Simulator` holds the state (positions, velocities,
time) and advances it.

Integrator (per step, time :math:`t_n = n\,\Delta t`)

.. math::

    \mathbf f_n = \mathbf f(\mathbf x_n, \mathbf v_n) + m\mathbf g, \quad
    \mathbf v_{n+1} = \frac{\mathbf v_n + \Delta t\,\mathbf f_n/m}{1 + \alpha\Delta t}, \quad
    \mathbf x_{n+1} = \mathbf x_n + \Delta t\,\mathbf v_{n+1}

(semi-implicit Euler; :math:`\alpha = 1/\tau` is the optional mass-proportional
Rayleigh damping, treated implicitly so that it never limits the step).
Fixed nodes have :math:`1/m = 0`.

Stability bound. For a network whose spring ``ij`` has axial tangent
:math:`k^t_{ij}` and force :math:`F_{ij}`, the tangent stiffness
:math:`K = \sum_{ij} [k^t u u^T + (F/L)(I - u u^T)]` (assembled with the usual
signs) satisfies, for any :math:`y = M^{1/2}x`,
:math:`x^TKx \le 2\sum_i |y_i|^2 \sum_j \kappa_{ij}/m_i` with
:math:`\kappa_{ij} = \max(k^t_{ij}, F_{ij}/L_{ij}, 0)`. Hence

.. math::  \omega_{max}^2 \le \Omega^2 = 2\max_i \frac{1}{m_i}\sum_j \kappa_{ij}

and :math:`\kappa_{ij}` is bounded over *every* stretch by the tables:
:math:`\kappa_{ij} \le \sum_d a_{ij,d} G_d`, :math:`G_d = \sup_\lambda
\max(f_d'(\lambda), f_d(\lambda)/\lambda)` over the grid and its extrapolation
(both laws keep a bounded tangent off the grid). With spring dashpots
:math:`c_{ij}` (damping bound :math:`\Gamma = 2\max_i \sum_j c_{ij}/m_i`), the
semi-implicit Euler step of a mode :math:`\ddot q + \gamma\dot q + \omega^2 q
= 0` is stable iff :math:`\omega^2\Delta t^2 + 2\gamma\Delta t < 4`, so

.. math::  \Delta t = s\,\frac{4}{\Gamma + \sqrt{\Gamma^2 + 4\Omega^2}}

with a safety factor :math:`s` (default 0.9). The bound holds whatever the
deformation (locking included), because it uses the largest tangent of the
table; it is exact for Rayleigh damping of a linear network and conservative
(Gershgorin) otherwise.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, InputError, SimulationError
from . import kernels as K
from .effects import EffectModel, EffectState, build_effect_model

PRECISIONS = ("float64", "float32")
LAW_CODES = {"secant": K.LAW_SECANT, "energy": K.LAW_ENERGY}
DEFAULT_SAFETY = 0.9


# ---------------------------------------------------------------------------
# force model
# ---------------------------------------------------------------------------

@dataclass
class ForceModel:
    """The compiled kernels' view of a network and its tables.

    Attributes
    ----------
    n_nodes : int
    ij : ndarray, shape (2, s), uint32
        Springs (rows i and j), ``i < j``, sorted by ``(i, j)``.
    order : ndarray, shape (s,), int64
        Spring p of the model is ``network.springs[order[p]]``.
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
    effects : EffectModel or None
        Material effects (QLV, Mullins, damage; :mod:`.effects`): the springs then
        carry state and the effects kernels are used. ``kappa`` and
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

    def kernel_args(self) -> tuple:
        """(ij, sd, tab, lam_min, inv_h, last_cell, law, damped) for the kernels."""
        return (self.ij, self.sd, self.tab, self.lam_min, self.inv_h, self.last_cell,
                self.law_code, self.damped)

    def bytes_per_spring(self) -> int:
        """Bytes of spring data streamed per spring per step (indices + data rows)."""
        return int(self.ij.itemsize * 2 + self.sd.itemsize * self.sd.shape[0])

    # -- evaluation ------------------------------------------------------
    def forces(self, x: np.ndarray, v: np.ndarray | None = None, *, fext: np.ndarray | None = None,
               damped: bool | None = None, state: EffectState | None = None, mode: int = K.FX_PEEK,
               dt: float = 0.0) -> np.ndarray:
        """Nodal forces (n, 3) [N] at positions *x* (and velocities *v* for the dashpots).

        With material effects, *state* is the springs' state (default: the
        virgin state, so the force is the instantaneous response from rest) and
        *mode* one of ``kernels.FX_PEEK`` (the force a step of *dt* from the
        state would give; state unchanged), ``FX_STEP`` (the same, committing
        the state), ``FX_RELAXED`` (long-term force) or ``FX_SETTLE``.
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise InputError(f"x: expected shape ({self.n_nodes}, 3), got {x.shape}")
        use_damp = self.damped if damped is None else (bool(damped) and self.damped)
        v = np.zeros_like(x) if v is None else np.ascontiguousarray(v, dtype=np.float64)
        fe = np.zeros_like(x) if fext is None else np.ascontiguousarray(fext, dtype=np.float64)
        f = np.empty_like(x)
        if self.effects is None:
            K.forces_serial(x, v, f, fe, self.ij, self.sd, self.tab, self.lam_min, self.inv_h,
                            self.last_cell, self.law_code, use_damp)
            return f
        st = self.effects.new_state(self.n_springs) if state is None else state
        K.forces_serial_fx(x, v, f, fe, self.ij, self.sd, self.tab, self.lam_min, self.inv_h,
                           self.last_cell, self.law_code, use_damp, *self.effects.kernel_args(),
                           self.effects.ab(dt), *st.arrays(), int(mode))
        return f

    def stretches(self, x: np.ndarray) -> np.ndarray:
        """Stretch of every spring at positions *x*, shape (s,) (model spring order)."""
        x = np.asarray(x, dtype=np.float64)
        d = x[self.ij[1]] - x[self.ij[0]]
        return np.sqrt(np.einsum("ij,ij->i", d, d)) * self.sd[0].astype(np.float64)

    def stretch_range(self, x: np.ndarray) -> tuple[float, float]:
        """(min, max) stretch over the springs at positions *x*."""
        lo, hi = K.stretch_range(np.ascontiguousarray(x, dtype=np.float64), self.ij, self.sd)
        return float(lo), float(hi)

    def window(self, delta: float) -> np.ndarray:
        """Tangent bound per cell over a stretch window of +-*delta* (cached), shape (n_cells, 3)."""
        cells = int(math.ceil(delta * self.inv_h - 1e-9))
        if cells not in self._windows:
            self._windows[cells] = windowed_bound(self.cell_bound, cells)
        return self._windows[cells]

    # -- threading ---------------------------------------------------------
    def layout(self, chunks: int) -> tuple:
        """Owner/halo layout for *chunks* threads (cached): see :mod:`.kernels`."""
        chunks = max(1, int(chunks))
        if chunks not in self._layouts:
            self._layouts[chunks] = thread_layout(self.ij, self.n_nodes, chunks)
        return self._layouts[chunks]


def _tables_arrays(tables, law: str) -> np.ndarray:
    return np.asarray(tables.values if law == "secant" else tables.stress, dtype=np.float64)


def tangent_bound(tables, law: str) -> np.ndarray:
    """G_d = sup over all stretches of max(f_d', f_d/lam, 0) [Pa], shape (3,).

    Follows the tables' interpolation and extrapolation exactly (linear cells;
    secant: mu_e held off the grid; energy: stress continued linearly).
    """
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    vals = _tables_arrays(tables, law)
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
    vals = _tables_arrays(tables, law)
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
    from scipy.ndimage import maximum_filter1d

    size = 2 * int(cells) + 1
    return np.ascontiguousarray(maximum_filter1d(cell_bound, size=size, axis=0, mode="nearest"))


def build_force_model(network, tables, *, law: str | None = None, dashpot: float = 0.0,
                      precision: str = "float64", isotropic_fast: bool = True,
                      effects=None) -> ForceModel:
    """Build the :class:`ForceModel` of *network* with *tables*.

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
        :mod:`.effects`); None or empty: the plain elastic kernels.
    """
    from ..network.tables import spring_factors

    law = tables.check_law(law)
    if precision not in PRECISIONS:
        raise ConfigError(f"precision: unknown {precision!r}; use one of {', '.join(PRECISIONS)}")
    if not (np.isfinite(dashpot) and dashpot >= 0):
        raise ConfigError(f"dashpot: must be a time >= 0 s, got {dashpot!r}")
    springs = np.asarray(network.springs, dtype=np.int64).reshape(-1, 2)
    n = int(np.asarray(network.points).shape[0])
    s = springs.shape[0]
    if s == 0:
        raise InputError("network has no springs; rebuild the asset")
    if springs.min() < 0 or springs.max() >= n:
        raise InputError(f"network springs reference nodes outside 0..{n - 1}; rebuild the asset")
    if n >= 2**32 - 1:
        raise InputError(f"network has {n} nodes; the simulator supports fewer than 2**32")
    L0 = np.asarray(network.rest_length, dtype=np.float64)
    if np.any(~np.isfinite(L0)) or np.any(L0 <= 0):
        raise InputError("network has springs of zero or non-finite rest length; rebuild the asset")
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
    vals = _tables_arrays(tables, law)
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
    vals = _tables_arrays(tables, law)
    tab = np.ascontiguousarray(np.concatenate([vals[:, :-1].T, np.diff(vals, axis=1).T], axis=1))
    cell_bound = cell_tangent_bound(tables, law)
    fx = build_effect_model(effects, tables, law)
    if fx is not None:
        extra = fx.history_table.copy()
        if fx.mullins_cell is not None:
            cell_bound = np.ascontiguousarray(cell_bound + fx.mullins_cell)
            extra += fx.mullins_cell.max(axis=0)
        kappa = kappa + a @ extra
    return ForceModel(n_nodes=n, ij=ij, order=order, sd=np.ascontiguousarray(sd), tab=tab,
                      lam_min=float(tables.lam_min), inv_h=1.0 / float(tables.dlam), law=law,
                      kappa=kappa, rest_tangent=rest_tangent, dashpot=float(dashpot),
                      lam_max=float(tables.lam_max), cell_bound=cell_bound, effects=fx)


def thread_layout(ij: np.ndarray, n_nodes: int, chunks: int) -> tuple:
    """Owner/halo arrays for the race-free parallel force pass.

    Returns
    -------
    (node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node)
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
    return (node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node)


# ---------------------------------------------------------------------------
# stability
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class StepBound:
    """The stable time step and what it is made of."""

    dt: float            #: step used [s] (safety included)
    dt_critical: float   #: bound without the safety factor [s]
    omega_max: float     #: Gershgorin bound of the highest angular frequency [rad/s]
    gamma_max: float     #: bound of the dashpots' damping rate [1/s]
    safety: float
    node: int            #: the node that sets the bound


def stable_step(model: ForceModel, mass: np.ndarray, *, free: np.ndarray | None = None,
                extra_stiffness: np.ndarray | None = None, safety: float = DEFAULT_SAFETY,
                x: np.ndarray | None = None, window: float | None = None) -> StepBound:
    """Largest stable semi-implicit Euler step of *model* with node masses *mass*.

    By default the springs' tangents are bounded over every stretch (the whole
    table and its extrapolation): the step is then safe whatever happens. With
    positions *x* and a stretch *window* delta, each spring's tangent is
    bounded only over ``[lam - delta, lam + delta]`` around its stretch in *x*:
    a larger step that is safe as long as no stretch moves by more than delta
    (the caller checks that and redoes the interval otherwise).

    Parameters
    ----------
    model : ForceModel
    mass : ndarray, shape (n,)
        Node masses [kg].
    free : ndarray of bool, shape (n,), optional
        Nodes that move (default: all). Fixed nodes do not limit the step.
    extra_stiffness : ndarray, shape (n,), optional
        Stiffness to the ground per node [N/m] (grasper coupling springs).
    safety : float
        Factor in (0, 1] applied to the critical step.
    """
    if not (0 < safety <= 1):
        raise ConfigError(f"safety: must be in (0, 1], got {safety}")
    m = np.asarray(mass, dtype=np.float64)
    n = model.n_nodes
    i, j = model.ij[0], model.ij[1]
    if x is None or window is None:
        ksum = np.bincount(i, weights=model.kappa, minlength=n) + np.bincount(j, weights=model.kappa, minlength=n)
    else:
        ksum = np.empty(n)
        K.node_tangent_sums(np.ascontiguousarray(x, dtype=np.float64), model.ij, model.sd, model.window(window),
                            model.lam_min, model.inv_h, model.last_cell, model.n_directions == 3, ksum)
    row = 2.0 * ksum
    if extra_stiffness is not None:
        row = row + np.asarray(extra_stiffness, dtype=np.float64)
    if model.damped:
        c = model.sd[-1].astype(np.float64)
        csum = np.bincount(i, weights=c, minlength=n) + np.bincount(j, weights=c, minlength=n)
        crow = 2.0 * csum
    else:
        crow = np.zeros(n)
    mask = np.ones(n, bool) if free is None else np.asarray(free, bool)
    if not mask.any():
        return StepBound(math.inf, math.inf, 0.0, 0.0, safety, -1)
    w2 = np.where(mask, row / m, 0.0)
    g = np.where(mask, crow / m, 0.0)
    node = int(np.argmax(w2))
    omega2 = float(w2.max())
    gamma = float(g.max())
    if omega2 <= 0:
        return StepBound(math.inf, math.inf, 0.0, gamma, safety, node)
    dtc = 4.0 / (gamma + math.sqrt(gamma * gamma + 4.0 * omega2))
    return StepBound(safety * dtc, dtc, math.sqrt(omega2), gamma, safety, node)


def mass_scaling(model: ForceModel, mass: np.ndarray, *, free: np.ndarray | None = None,
                 budget: float = 1e-3) -> tuple[np.ndarray, dict]:
    """Selective mass scaling: inertial masses that allow a larger stable step.

    The step is limited by the nodes whose stiffness-to-mass ratio is largest
    (typically a few light nodes in slivers of the mesh). For a target step
    ``dt`` a node needs ``m_i >= r_i dt^2 / 4`` with ``r_i = 2 sum_j kappa_ij``
    (the whole-table Gershgorin row, so the gain holds for every stretch).
    This finds the largest ``dt`` whose added mass ``sum max(0, r_i dt^2/4 -
    m_i)`` over the free nodes is at most ``budget`` times the total mass, and
    returns the raised masses. They are used for inertia only; gravity keeps
    the true masses.

    Parameters
    ----------
    model : ForceModel
    mass : ndarray, shape (n,)
        True node masses [kg].
    free : ndarray of bool, shape (n,), optional
    budget : float
        Largest added mass as a fraction of the total (0: no scaling).

    Returns
    -------
    (scaled_mass (n,), info dict with ``added_fraction``, ``nodes``, ``gain``)
    """
    m = np.asarray(mass, dtype=np.float64)
    n = model.n_nodes
    mask = np.ones(n, bool) if free is None else np.asarray(free, bool)
    if budget <= 0 or not mask.any():
        return m.copy(), {"added_fraction": 0.0, "nodes": 0, "gain": 1.0}
    i, j = model.ij[0], model.ij[1]
    r = 2.0 * (np.bincount(i, weights=model.kappa, minlength=n) + np.bincount(j, weights=model.kappa, minlength=n))
    r = np.where(mask, r, 0.0)
    with np.errstate(divide="ignore"):
        dt_node = np.where(r > 0, 2.0 * np.sqrt(m / np.where(r > 0, r, 1.0)), np.inf)
    dt0 = float(dt_node[mask].min())
    if not np.isfinite(dt0):
        return m.copy(), {"added_fraction": 0.0, "nodes": 0, "gain": 1.0}
    total = float(m.sum())

    def added(dt):
        return float(np.maximum(r * dt * dt / 4.0 - m, 0.0)[mask].sum())

    lo, hi = dt0, dt0
    while added(hi * 2) <= budget * total and hi < 1e3 * dt0:
        hi *= 2
    hi *= 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if added(mid) <= budget * total:
            lo = mid
        else:
            hi = mid
    scaled = np.where(mask, np.maximum(m, r * lo * lo / 4.0), m)
    nodes = int(np.count_nonzero(scaled > m))
    return scaled, {"added_fraction": float((scaled - m).sum() / total), "nodes": nodes, "gain": lo / dt0}


# ---------------------------------------------------------------------------
# the simulator
# ---------------------------------------------------------------------------

@dataclass
class Grasp:
    """Nodes held by the grasper.

    Attributes
    ----------
    nodes : ndarray, shape (g,), int64
    offsets : ndarray, shape (g, 3)
        Node position minus tip position when grasped [m].
    wp_t : ndarray, shape (p,)
        Path times [s] (increasing).
    wp_x : ndarray, shape (p, 3)
        Tip positions at those times [m].
    mode : {"prescribed", "spring"}
    stiffness : ndarray, shape (g,)
        Coupling stiffness per node [N/m] (mode "spring").
    """

    nodes: np.ndarray
    offsets: np.ndarray
    wp_t: np.ndarray
    wp_x: np.ndarray
    mode: str = "prescribed"
    stiffness: np.ndarray | None = None

    def tip(self, t: float) -> np.ndarray:
        pos, _ = K.tip_state(float(t), self.wp_t, self.wp_x)
        return pos


@dataclass
class Floor:
    """A rigid floor: the half-space ``normal . x >= height`` is free, the rest is solid.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal pointing out of the floor (against gravity) .
    height : float
        Offset of the plane along *normal* [m]: the plane is ``normal . x = height``.
    friction : {"stick", "slip"}
        "stick": a node in contact keeps its tangential position (sticking
        friction); "slip": frictionless, only the normal motion is stopped.
    """

    normal: np.ndarray
    height: float
    friction: str = "stick"

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not (np.all(np.isfinite(n)) and norm > 0):
            raise ConfigError("floor normal: must be a non-zero finite vector (the floor needs gravity)")
        self.normal = np.ascontiguousarray(n / norm)
        if not np.isfinite(self.height):
            raise ConfigError(f"[floor] height: must be finite, got {self.height}")
        self.height = float(self.height)
        if self.friction not in ("stick", "slip"):
            raise ConfigError(f"[floor] friction: {self.friction!r} is not \"stick\" or \"slip\"")

    @classmethod
    def under(cls, points: np.ndarray, gravity, *, height: float | str = "auto",
              friction: str = "stick") -> Floor:
        """The floor perpendicular to *gravity*; ``height="auto"``: touching *points* from below.

        Parameters
        ----------
        points : ndarray, shape (n, 3)
            The organ's nodes [m] (for "auto": its lowest point along gravity).
        gravity : array-like, shape (3,)
            [m/s2]; the floor's normal is ``-gravity / |gravity|``.
        height : "auto" or float
            Plane offset along the normal [m].
        friction : {"stick", "slip"}
        """
        g = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(g)) and np.any(g)):
            raise ConfigError("[floor]: needs a non-zero gravity (the floor is perpendicular to it); "
                              "set [scene] gravity or disable the floor")
        n = -g / np.linalg.norm(g)
        if isinstance(height, str):
            if height != "auto":
                raise ConfigError(f"[floor] height: {height!r}; use \"auto\" or a length such as \"-20 mm\"")
            h = float(np.min(np.asarray(points, dtype=np.float64).reshape(-1, 3) @ n))
        else:
            h = float(height)
        return cls(normal=n, height=h, friction=friction)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance of points *x* (shape (n, 3)) above the plane [m], shape (n,)."""
        return np.asarray(x, dtype=np.float64).reshape(-1, 3) @ self.normal - self.height


class Simulator:
    """State and time stepping of a spring network.

    Parameters
    ----------
    model : ForceModel
    points : ndarray, shape (n, 3)
        Rest positions [m] (the initial state).
    mass : ndarray, shape (n,)
        Node masses [kg] (inertia).
    fixed : ndarray of int, shape (f,)
        Nodes held in place.
    gravity : array-like, shape (3,)
        Acceleration of gravity [m/s2].
    gravity_mass : ndarray, shape (n,), optional
        Masses that gravity acts on (default *mass*; differs under mass scaling).
    mass_damping : float
        Rayleigh mass-proportional coefficient alpha [1/s] (0: none).
    dt : float, optional
        Time step [s]; default: :func:`stable_step` with *safety*. A larger one
        than the bound raises :class:`SimulationError`.
    safety : float
    threads : int
        1: the serial kernel; more: the owner/halo parallel kernel with that
        many chunks (``numba.set_num_threads``).
    floor : Floor, optional
        Rigid floor acting on the free nodes (not the fixed or grasped ones)
        after every position update, in the dynamics and in :meth:`relax`.
    """

    def __init__(self, model: ForceModel, points: np.ndarray, mass: np.ndarray, *, fixed=(),
                 gravity=(0.0, 0.0, 0.0), mass_damping: float = 0.0, dt: float | None = None,
                 safety: float = DEFAULT_SAFETY, threads: int = 1, gravity_mass: np.ndarray | None = None,
                 floor: Floor | None = None):
        n = model.n_nodes
        self.model = model
        self.rest = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(n, 3)).copy()
        self.x = self.rest.copy()
        self.v = np.zeros_like(self.x)
        self.f = np.zeros_like(self.x)
        self.mass = np.asarray(mass, dtype=np.float64).reshape(n).copy()
        if np.any(~np.isfinite(self.mass)) or np.any(self.mass <= 0):
            raise InputError("network has nodes of zero, negative or non-finite mass; rebuild the asset")
        self.fixed = np.unique(np.asarray(fixed, dtype=np.int64).ravel())
        if self.fixed.size and (self.fixed[0] < 0 or self.fixed[-1] >= n):
            raise InputError(f"fixed nodes outside 0..{n - 1}")
        g = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(g)):
            raise ConfigError("gravity: must be three finite numbers (m/s2)")
        self.gravity = g
        if not (np.isfinite(mass_damping) and mass_damping >= 0):
            raise ConfigError(f"mass_damping: must be >= 0 1/s, got {mass_damping}")
        self.alpha = float(mass_damping)
        self.safety = float(safety)
        self.threads = max(1, int(threads))
        gm = self.mass if gravity_mass is None else np.asarray(gravity_mass, dtype=np.float64).reshape(n)
        self.fext = np.ascontiguousarray(gm[:, None] * g[None, :])
        self.grasp: Grasp | None = None
        self.step_count = 0
        self.t0 = 0.0
        #: Per-spring state of the material effects (None without effects).
        self.fx_state: EffectState | None = (None if model.effects is None
                                             else model.effects.new_state(model.n_springs))
        self._free = np.ones(n, bool)
        self._free[self.fixed] = False
        if floor is not None and not isinstance(floor, Floor):
            raise ConfigError("floor: expected a Floor or None")
        self.floor = floor
        #: 1 for the nodes the floor put back at the last step (or relaxation iteration), shape (n,).
        self.contact = np.zeros(n, np.uint8)
        self._update_inv_mass()
        self.bound = self._bound()
        if dt is None:
            self.dt = self.bound.dt
        else:
            if not (np.isfinite(dt) and dt > 0):
                raise ConfigError(f"dt: must be a positive time step, got {dt}")
            if dt > self.bound.dt_critical:
                raise SimulationError(
                    f"dt: {dt:.3g} s exceeds the stability bound {self.bound.dt_critical:.3g} s of "
                    f"this network; use a smaller step or none (automatic)")
            self.dt = float(dt)

    # -- state ------------------------------------------------------------
    @property
    def t(self) -> float:
        """Current time [s]."""
        return self.t0 + self.step_count * self.dt

    @property
    def free(self) -> np.ndarray:
        """Nodes integrated in time (not fixed, not held by a prescribed grasp), shape (n,)."""
        return self.inv_mass > 0

    def displacement(self) -> np.ndarray:
        return self.x - self.rest

    def _update_inv_mass(self) -> None:
        inv = np.where(self._free, 1.0 / self.mass, 0.0)
        if self.grasp is not None and self.grasp.mode == "prescribed":
            inv[self.grasp.nodes] = 0.0
        self.inv_mass = np.ascontiguousarray(inv)
        # Nodes under the floor's rule: free, not grasped (in either mode).
        mask = inv > 0
        if self.grasp is not None:
            mask[self.grasp.nodes] = False
        self._fl_mask = np.ascontiguousarray(mask.astype(np.uint8))
        self.contact[~mask] = 0

    def _floor_args(self) -> tuple:
        fl = self.floor
        if fl is None:
            return (False, np.zeros(3), 0.0, False, self._fl_mask, self.contact)
        return (True, fl.normal, fl.height, fl.friction == "stick", self._fl_mask, self.contact)

    @property
    def n_contact(self) -> int:
        """Nodes the floor held at the last step."""
        return int(np.count_nonzero(self.contact))

    def _bound(self) -> StepBound:
        extra = None
        if self.grasp is not None and self.grasp.mode == "spring":
            extra = np.zeros(self.model.n_nodes)
            np.add.at(extra, self.grasp.nodes, self.grasp.stiffness)
        return stable_step(self.model, self.mass, free=self.free, extra_stiffness=extra,
                           safety=self.safety)

    def set_time_step(self, dt: float, *, bound: StepBound | None = None, t0: float | None = None) -> None:
        """Change the step, keeping the current time (or restarting the count at *t0*).

        Refuses a step above *bound* (default: the whole-table bound of the
        current configuration of fixed and held nodes).
        """
        if not (np.isfinite(dt) and dt > 0):
            raise ConfigError(f"dt: must be a positive time step, got {dt}")
        limit = (self.bound if bound is None else bound).dt_critical
        if dt > limit * (1 + 1e-12):
            raise SimulationError(f"dt: {dt:.3g} s exceeds the stability bound {limit:.3g} s")
        self.t0 = self.t if t0 is None else float(t0)
        self.step_count = 0
        self.dt = float(dt)

    def snapshot(self) -> tuple:
        """The state, for :meth:`restore` (positions, velocities, time, step, grasp, effects' state)."""
        fx = None if self.fx_state is None else self.fx_state.copy()
        return (self.x.copy(), self.v.copy(), self.t0, self.step_count, self.dt, self.grasp, fx)

    def restore(self, state: tuple) -> None:
        x, v, t0, steps, dt, grasp, fx = state
        self.x[:] = x
        self.v[:] = v
        self.t0, self.step_count, self.dt = t0, steps, dt
        if fx is not None and self.fx_state is not None:
            self.fx_state.assign(fx)
        if grasp is not self.grasp:
            self.grasp = grasp
            self._update_inv_mass()
            self.bound = self._bound()

    # -- grasper -------------------------------------------------------------
    def attach(self, grasp: Grasp, *, check_step: bool = True) -> None:
        """Start holding ``grasp.nodes`` (at the current time).

        With *check_step*, a step above the whole-table bound with the coupling
        springs is refused (callers that bound the step themselves, per frame,
        pass False).
        """
        nodes = np.asarray(grasp.nodes, dtype=np.int64).ravel()
        if nodes.size == 0:
            raise ConfigError("grasper: no node to grasp")
        if np.any(~self._free[nodes]):
            raise ConfigError("grasper: a grasped node is fixed; grasp elsewhere or change the fixed region")
        if grasp.mode not in ("prescribed", "spring"):
            raise ConfigError(f"grasper.mode: unknown {grasp.mode!r}; use \"prescribed\" or \"spring\"")
        if grasp.mode == "spring":
            k = np.asarray(grasp.stiffness, dtype=np.float64).reshape(nodes.size)
            if np.any(~np.isfinite(k)) or np.any(k <= 0):
                raise ConfigError("grasper.stiffness: must be positive (N/m)")
            grasp.stiffness = k
        else:
            grasp.stiffness = np.zeros(nodes.size)
        grasp.nodes = nodes
        grasp.offsets = np.ascontiguousarray(np.asarray(grasp.offsets, dtype=np.float64).reshape(nodes.size, 3))
        grasp.wp_t = np.ascontiguousarray(np.asarray(grasp.wp_t, dtype=np.float64).ravel())
        grasp.wp_x = np.ascontiguousarray(np.asarray(grasp.wp_x, dtype=np.float64).reshape(-1, 3))
        self.grasp = grasp
        self._update_inv_mass()
        self.bound = self._bound()
        if check_step and self.dt > self.bound.dt_critical:
            raise SimulationError(
                f"grasper.stiffness: the coupling springs need a step below {self.bound.dt_critical:.3g} s "
                f"(current {self.dt:.3g} s); lower the stiffness or use mode = \"prescribed\"")
        if grasp.mode == "prescribed":
            tip, tip_v = K.tip_state(self.t, grasp.wp_t, grasp.wp_x)
            self.x[nodes] = tip + grasp.offsets
            self.v[nodes] = tip_v

    def release(self) -> None:
        """Let go: the grasped nodes become free again (keeping their velocity)."""
        self.grasp = None
        self._update_inv_mass()
        self.bound = self._bound()

    # -- stepping --------------------------------------------------------------
    def advance(self, nsteps: int, *, record: np.ndarray | None = None) -> np.ndarray:
        """Run *nsteps* steps; return the force on the grasper at each step, shape (nsteps, 3) [N].

        The force is the one the tissue (with its weight) exerts on the grasper
        (what a haptic device renders); zeros when nothing is grasped.
        """
        nsteps = int(nsteps)
        rec = np.zeros((max(nsteps, 0), 3)) if record is None else record
        if nsteps <= 0:
            return rec
        vfac = 1.0 / (1.0 + self.alpha * self.dt)
        g = self.grasp
        if g is None:
            g_mode, g_nodes, g_off, g_k = K.GRASP_NONE, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
            wp_t, wp_x = np.zeros(1), np.zeros((1, 3))
        else:
            g_mode = K.GRASP_PRESCRIBED if g.mode == "prescribed" else K.GRASP_SPRING
            g_nodes, g_off, g_k, wp_t, wp_x = g.nodes, g.offsets, g.stiffness, g.wp_t, g.wp_x
        if self.threads > 1:
            import numba

            numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        fx = self.fx_state
        if fx is None:
            common = (nsteps, self.dt, self.t0, self.step_count, self.x, self.v, self.f, self.fext,
                      self.inv_mass, vfac) + self.model.kernel_args() + (
                      g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec) + self._floor_args()
            if self.threads == 1:
                K.run_serial(*common)
            else:
                K.run_parallel(*common, *self.model.layout(self.threads))
        else:
            # The first step advances the springs' state from the time it was last committed.
            dt_first = max(0.0, self.t - fx.t)
            common = (nsteps, self.dt, dt_first, self.t0, self.step_count, self.x, self.v, self.f, self.fext,
                      self.inv_mass, vfac) + self.model.kernel_args() + self.model.effects.kernel_args() + (
                      *fx.arrays(), g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec) + self._floor_args()
            if self.threads == 1:
                K.run_serial_fx(*common)
            else:
                K.run_parallel_fx(*common, *self.model.layout(self.threads))
            fx.t = self.t0 + (self.step_count + nsteps - 1) * self.dt
        self.step_count += nsteps
        return rec

    # -- material effects ----------------------------------------------------------
    def settle_effects(self) -> None:
        """Take the current configuration as long held: maxima updated, history relaxed (h = 0).

        Called after a static equilibrium (:meth:`relax`): the organ has rested in
        it long enough for every Prony term to relax. No-op without effects.
        """
        if self.fx_state is None:
            return
        self.model.forces(self.x, state=self.fx_state, mode=K.FX_SETTLE)
        self.fx_state.t = self.t

    def history_stiffness(self, delta: float) -> np.ndarray | None:
        """Per-node Gershgorin row added by the viscoelastic history forces [N/m], or None.

        For :func:`stable_step`'s ``extra_stiffness``; see
        :meth:`EffectModel.history_stiffness` (valid while no stretch moves by more
        than *delta*).
        """
        fx = self.model.effects
        if fx is None or fx.n_terms == 0:
            return None
        lam = self.model.stretches(self.x)
        k = fx.history_stiffness(self.fx_state, lam, 1.0 / self.model.sd[0].astype(np.float64), float(delta))
        n = self.model.n_nodes
        return 2.0 * (np.bincount(self.model.ij[0], weights=k, minlength=n)
                      + np.bincount(self.model.ij[1], weights=k, minlength=n))

    def effects_report(self) -> dict | None:
        """Extremes of the effects' state (JSON-ready), or None without effects."""
        fx, st = self.model.effects, self.fx_state
        if fx is None:
            return None
        out: dict = {"effects": fx.names}
        if fx.n_terms:
            q = np.abs(st.h).T @ fx.g
            out["max_history_force_N"] = float(q.max()) if q.size else 0.0
            out["max_elastic_force_N"] = float(np.abs(st.pold).max()) if st.pold.size else 0.0
        if fx.effects.mullins is not None:
            out["max_energy_density_Pa"] = float(st.wmax.max()) if st.wmax.size else 0.0
        if fx.effects.damage is not None:
            xi = float(st.ximax.max()) if st.ximax.size else 1.0
            out["max_equivalent_stretch"] = xi
            out["min_remaining_fraction"] = float(fx.effects.damage.factor(np.array([xi]))[0])
            out["damaged_springs"] = int(np.count_nonzero(st.ximax > fx.effects.damage.onset))
        return out

    def forces(self) -> np.ndarray:
        """Total nodal forces (springs, dashpots, gravity) at the current state, shape (n, 3) [N].

        With material effects: the force the next step would use (the state
        advanced to the current time, not committed).
        """
        if self.fx_state is None:
            return self.model.forces(self.x, self.v, fext=self.fext)
        return self.model.forces(self.x, self.v, fext=self.fext, state=self.fx_state, mode=K.FX_PEEK,
                                 dt=max(0.0, self.t - self.fx_state.t))

    def grasper_force(self) -> np.ndarray:
        """Force of the tissue on the grasper at the current state, shape (3,) [N] (zeros if open)."""
        g = self.grasp
        if g is None:
            return np.zeros(3)
        f = self.forces()
        if g.mode == "spring":
            tip = g.tip(self.t)
            return -(g.stiffness[:, None] * (tip + g.offsets - self.x[g.nodes])).sum(axis=0)
        return f[g.nodes].sum(axis=0)

    def check_finite(self) -> None:
        """Raise :class:`SimulationError` if the state has blown up (NaN/inf)."""
        if not np.all(np.isfinite(self.x)):
            raise SimulationError(
                f"the simulation became unstable at t = {self.t:.4g} s (non-finite positions); "
                f"lower integrator.safety or check the asset's masses and tables")

    def kinetic_energy(self) -> float:
        return 0.5 * float(np.sum(self.mass[:, None] * self.v**2))

    def gravity_energy(self) -> float:
        return -float(np.sum(self.fext * self.x))

    # -- quasi-static --------------------------------------------------------------
    def relax(self, *, ftol: float | None = None, rtol: float = 1e-8, max_iter: int = 200_000) -> dict:
        """Move to static equilibrium under gravity (and a held grasp, at its current tip) with FIRE.

        With material effects this is the *long-term* equilibrium (forces
        ``g_inf (1 - D) eta F_e`` with the maxima so far); afterwards the history
        is taken as relaxed there (:meth:`settle_effects`).

        Parameters
        ----------
        ftol : float, optional
            Largest residual force on a free node [N]; default ``rtol`` times
            the largest external force on a node (or times the largest spring
            force scale when there is no gravity).
        rtol : float
        max_iter : int

        Returns
        -------
        dict with ``iterations``, ``residual`` [N], ``ftol`` [N].
        """
        free = self.free
        if ftol is None:
            scale = float(np.abs(self.fext[free]).max()) if free.any() else 0.0
            if scale == 0.0:
                scale = float(np.median(self.model.rest_tangent / self.model.sd[0])) or 1.0
            ftol = rtol * scale
        dt0 = 0.2 * self.bound.dt_critical
        g = self.grasp
        if g is not None and g.mode == "spring":
            gargs = (K.GRASP_SPRING, g.nodes, g.offsets, g.stiffness, g.tip(self.t))
        else:
            gargs = (K.GRASP_NONE, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(3))
        fxm, st = self.model.effects, self.fx_state
        if fxm is None:
            fxa = (False, np.zeros((1, 8)), np.zeros(K.FXP_HEAD), np.zeros((2, 0)), np.zeros((0, 0)),
                   np.zeros(0), np.zeros(0), np.zeros(0))
        else:
            fxa = (True, *fxm.kernel_args(), fxm.ab(0.0), *st.arrays())
        if self.floor is not None:
            on = (self.floor.distance(self.x) <= 0.0) & (self._fl_mask > 0)
            self.contact[:] = on
        it, res = K.fire_relax(self.x, self.v, self.f, self.fext, self.inv_mass, free,
                               *self.model.kernel_args()[:-1], *gargs, dt0, 0.9 * self.bound.dt_critical,
                               float(ftol), int(max_iter), *fxa, *self._floor_args())
        self.v[:] = 0.0
        self.settle_effects()
        if it < 0 or not np.isfinite(res):
            raise SimulationError("quasi-static relaxation diverged (non-finite forces); check the asset")
        if res >= ftol:
            raise SimulationError(
                f"quasi-static relaxation did not converge in {max_iter} iterations "
                f"(residual {res:.3g} N > {ftol:.3g} N); raise max_iter or the tolerance")
        return {"iterations": int(it), "residual": float(res), "ftol": float(ftol)}


def warm_up(model: ForceModel, *, threads: int = 1) -> float:
    """Compile (or load from cache) the kernels on a 2-node problem; return the seconds spent."""
    t = time.perf_counter()
    x = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    sub = ForceModel(n_nodes=2, ij=np.array([[0], [1]], np.uint32), order=np.zeros(1, np.int64),
                     sd=np.zeros((model.sd.shape[0], 1), model.sd.dtype), tab=model.tab[:2].copy(),
                     lam_min=model.lam_min, inv_h=model.inv_h, law=model.law, kappa=np.zeros(1),
                     rest_tangent=np.zeros(1), dashpot=model.dashpot)
    sub.sd[0, 0] = 1.0
    if model.effects is not None:
        sub.effects = model.effects
    sim = Simulator(sub, x, np.ones(2), fixed=[0], dt=1e-3, threads=threads)
    sim.advance(1)
    sim.attach(Grasp(nodes=np.array([1]), offsets=np.zeros((1, 3)), wp_t=np.array([0.0, 1.0]),
                     wp_x=np.array([[1.0, 0, 0], [1.0, 0, 0]])))
    sim.advance(1)
    return time.perf_counter() - t
