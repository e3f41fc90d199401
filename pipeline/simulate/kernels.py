r"""Compiled (numba) kernels of the simulator: the force pass, the step loop, FIRE.

Everything here works on plain arrays in SI units, grouped in a few tuples
that :class:`~.springterm.SpringTerm`, :mod:`.effects`, :class:`~.model.Control`
and the steppers build:

* :class:`SpringKernel` ``(ij, sd, tab, lam_min, inv_h, last_cell, law, damped)``:
  the springs and their table (constant during a run);
* :class:`EffectKernel` ``(etab, fxp, ab, h, pold, wmax, ximax, mode)``: the
  material effects' parameters and tables, the Prony factors of the step, the
  per-spring state and what to do with it; **None** for an elastic run;
* :class:`Layout` ``(node_start, spring_start, halo_start, hbuf, own_start,
  own_slot, own_node)``: the race-free threading layout (one chunk: serial);
* :class:`Clock` ``(n, dt, t0, step0, dt_first, vfac)``: how many steps, the
  step, the time origin and the step count from it (step ``k`` is at
  ``t0 + (step0 + k) dt``), the time the effects' state must first advance
  by, and the implicit mass-damping factor ``1 / (1 + alpha dt)``;
* :class:`Nodes` ``(x, v, f, fext, inv_mass)``;
* :class:`GraspKernel` ``(mode, nodes, offsets, stiffness, wp_t, wp_x)``;
* :class:`FloorKernel` ``(on, normal, height, stick, mask, contact)``;
* :class:`VolumeKernel` ``(tets, s24, kq, dsum, q, tv, node_ptr, node_tet,
  node_loc)``: the volume term's elements and scratch (None: no volume term).

The entry points take these tuples; they unpack them once and hand plain arrays
to the inlined helpers of the loops (an array taken out of a tuple is
reference-counted: an atomic increment and decrement each time, measurable
when done per block of springs). Every kernel lives in this one file on
purpose: numba's on-disk cache of a function is invalidated only when *its*
file changes, not when a function it calls from another file does.

Symplectic Euler with implicit mass damping (docs/design/simulator.md, "The explicit
stepper (the accuracy reference)")::

    f_n = f(x_n, v_n) + f_ext
    v_{n+1} = (v_n + dt f_n / m) / (1 + alpha dt),   x_{n+1} = x_n + dt v_{n+1}

Spring force (the tables module's convention, paper Eq. 8-9)::

    lam = L / L0
    F   = sum_d w_d * f_d(lam)          w_d = c * V_ij / L0 * cos2_d   [m^2]
    f_d = mu_e,d(lam) * (lam - 1)       secant law (mu_e held constant off the grid)
    f_d = W_T,d'(lam)                   energy law (stress continued linearly off the grid)
    F_i = +F (P_j - P_i) / L,  F_j = -F_i

plus an optional dashpot along the spring, ``c_ij ((v_j - v_i) . u) u``. A
spring of zero current length carries no force.

Data layout
-----------
* node arrays ``x``, ``v``, ``f``: (n, 3) float64, C order - the three
  components of a node sit in one cache line, which is what the gather of a
  spring's two end nodes reads;
* spring indices ``ij``: (2, s) uint32 (rows ``i`` and ``j``; ``i < j``,
  sorted by ``i`` then ``j``; unsigned so that no negative-index wraparound
  code is generated);
* spring data ``sd``: (4, s) or (5, s) float64 or float32, rows ``1/L0, w_x,
  w_y, w_z(, c_ij)`` (structure of arrays: each row is one sequential stream);
  for isotropic tables (three equal rows) (2, s) or (3, s): ``1/L0, w(, c_ij)``
  with ``w = sum_d w_d``, and one lookup per spring;
* table ``tab``: (n_cells, 6) float64, per cell ``[f_x, f_y, f_z, df_x, df_y,
  df_z]`` (value at the cell's left node and increment to the right node), so
  a lookup reads one 48-byte row.

Blocking
--------
Springs are processed in blocks of :data:`BLOCK`: (1) gather the end-node
differences into block buffers (scalar), (2) length, stretch, table cell and
weight (contiguous: LLVM vectorises it, sqrt included), (3) table fetch and
law factor, (4) the material effects when there are any, (5) force
coefficient ``F/L`` (vectorised, the division included), (6) scatter. This is
faster than the one-loop form on vector hardware (AVX-512) and gives bitwise the
same numbers.

Written once, compiled as needed
--------------------------------
The effects are one optional argument: ``fx is None`` is decided when numba
compiles (dead-branch pruning on the argument's type), so the elastic variant
contains no effect code and no branch for it, and the effects variant shares
every other line. The force pass (:func:`_forces`) and the step loop
(:func:`_steps`) are written once with ``prange`` and compiled twice, on one
thread (``prange`` is ``range``; one chunk) and on numba's threads
(:func:`twin`). The volume term joins the same way: its own tuple
(:class:`VolumeKernel`, None when absent: the spring-only variant contains no
volume code), its passes called after :func:`chunk_forces` in the force pass,
the step loop and FIRE (:func:`_volume_forces`: one chunk scatters over the
tets; several chunks gather per node range, race-free, in four passes).

Race-free threading
-------------------
Springs are sorted by their lower node ``i``. The nodes are cut into ``T``
contiguous ranges with about equal spring counts; chunk ``t`` owns the
springs whose ``i`` lies in its range. It writes ``f[i]`` (owned) and
``f[j]`` when ``j`` is also owned; a spring whose ``j`` lies in a later
chunk's range (a *halo* spring: few after a bandwidth-reducing node order)
writes its force into a private slot ``hbuf[h]`` instead. A second parallel
pass over the node ranges adds the halo slots of each range (precomputed per
owner). No two threads ever write the same address: no atomics and no
reduction buffers. With one chunk there is no halo and the scatter is the
plain one.

Material effects
----------------
With effects (viscoelastic QLV, Mullins, damage), each spring carries state
(model spring order, structure of arrays):

    h     (nt, s)  Prony internal variables h_i [N]
    pold  (s,)     the spring's softened elastic force P at the last committed evaluation [N]
    wmax  (s,)     largest energy density W reached so far [Pa]            (Mullins)
    ximax (s,)     largest uniaxial-equivalent stretch reached so far      (damage)

and its force is (docs/design/model.md, "Material effects")

    F_e = sum_d w_d f_d(lam)                      the elastic (instantaneous) force
    P   = (1 - D(ximax)) * eta(W, wmax) * F_e     damage and Mullins softening
    h_i <- a_i h_i + b_i (P - pold),  a_i = exp(-dt/tau_i), b_i = tau_i/dt (1 - a_i)
    F   = g_inf P + sum_i g_i h_i                 QLV, G(0) = 1

``etab`` (n_cells, 8): per cell ``[W_x, W_y, W_z, dW_x, dW_y, dW_z, xi, dxi]``: the
material's uniaxial energy density [Pa] and the uniaxial-equivalent stretch of a
spring at the cell's left node, with their increments (xi is exact for lam >= 1
and below the grid). Parameters ``fxp`` (float64): [g_inf, nt, mullins_on, 1/r, m,
beta, damage_on, onset, scale, shape, floor, g_1..g_nt, tau_1..tau_nt]; ``ab`` (2, nt):
a_i and b_i of the current step (from :func:`prony_ab`); ``mode`` one of
:data:`FX_STEP`, :data:`FX_PEEK`, :data:`FX_RELAXED`, :data:`FX_SETTLE`.
"""

from __future__ import annotations

import math
import types
from typing import NamedTuple

import numpy as np
from numba import njit, prange

LAW_SECANT = 0
LAW_ENERGY = 1

FX_STEP = 0       #: advance the state by the step in ``ab`` and commit it
FX_PEEK = 1       #: the force the step in ``ab`` would give, state unchanged
FX_RELAXED = 2    #: long-term force g_inf * P (maxima including the current stretch), state unchanged
FX_SETTLE = 3     #: commit the maxima and a fully relaxed history at the current stretch (h = 0)

#: Number of leading scalars in ``fxp`` before the Prony weights.
FXP_HEAD = 11

#: Springs per block (buffers of 8 x BLOCK doubles stay in L1).
BLOCK = 64

#: Options of every compiled function: cached on disk, numpy semantics for division (inf, NaN).
JIT_OPTIONS = dict(cache=True, error_model="numpy")


class SpringKernel(NamedTuple):
    """The springs and their table, as the kernels read them (see the module doc)."""

    ij: np.ndarray          #: (2, s) uint32
    sd: np.ndarray          #: (2..5, s) float64 or float32
    tab: np.ndarray         #: (n_cells, 6) float64
    lam_min: float
    inv_h: float
    last_cell: int
    law: int                #: :data:`LAW_SECANT` or :data:`LAW_ENERGY`
    damped: bool            #: the last row of ``sd`` is the dashpot c_ij


class EffectKernel(NamedTuple):
    """The material effects' tables, step factors, per-spring state and mode."""

    etab: np.ndarray        #: (n_cells, 8)
    fxp: np.ndarray         #: (10 + 2 nt,)
    ab: np.ndarray          #: (2, nt)
    h: np.ndarray           #: (nt, s)
    pold: np.ndarray        #: (s,)
    wmax: np.ndarray        #: (s,)
    ximax: np.ndarray       #: (s,)
    mode: int


class Layout(NamedTuple):
    """Owner/halo threading layout (:func:`~.springterm.thread_layout`)."""

    node_start: np.ndarray   #: (T+1,) node ranges
    spring_start: np.ndarray  #: (T+1,) their spring ranges
    halo_start: np.ndarray   #: (T+1,) their halo slot ranges
    hbuf: np.ndarray         #: (H, 3) halo slots
    own_start: np.ndarray    #: (T+1,) per chunk, the range of the slots landing in its nodes
    own_slot: np.ndarray     #: the slots
    own_node: np.ndarray     #: the node each lands on


class VolumeKernel(NamedTuple):
    """The volume term (nodal-averaged volume penalty, docs/design/model.md, "The volume term (nearly
    incompressible network)") as the kernels read it.

    ``None`` in place of it: no volume term (the spring-only variant, which
    contains no volume code). Per node ``a``: ``J_a = s24[a] * sum_{t ni a} 6 V_t``
    and ``q_a = kq (J_a - 1)`` (the pressure over 24); per tet the force on
    node ``b`` is ``-(sum of its four q) d(6 V_t)/dx_b``.
    """

    tets: np.ndarray        #: (4, t) uint32, positively oriented
    s24: np.ndarray         #: (n,) 1 / (24 V_a0)
    kq: float               #: kappa / 24 [Pa]
    dsum: np.ndarray        #: (n,) scratch: sum of 6 V_t over the node's tets
    q: np.ndarray           #: (n,) scratch: kappa (J_a - 1) / 24
    tv: np.ndarray          #: (t,) scratch of the threaded pass (6 V_t, then the tet's sum of q)
    node_ptr: np.ndarray    #: (n + 1,) int64: the tets of node a are node_tet[node_ptr[a]:node_ptr[a+1]]
    node_tet: np.ndarray    #: (4 t,) int64
    node_loc: np.ndarray    #: (4 t,) int64: the node's place (0-3) in that tet


def twin(fn, name: str):
    """A copy of the Python function *fn* named *name* (its own numba dispatcher and cache file).

    A loop written once with ``prange`` is compiled twice, serial (``prange``
    is ``range``) and parallel; numba's cache tells its entries apart by the
    function's qualified name, not by the ``parallel`` flag, so each variant
    gets its own name.
    """
    g = types.FunctionType(fn.__code__.replace(co_name=name, co_qualname=name), fn.__globals__, name,
                           fn.__defaults__, fn.__closure__)
    g.__qualname__ = name
    g.__doc__ = fn.__doc__
    g.__module__ = fn.__module__
    return g


# ---------------------------------------------------------------------------
# one block of springs
# ---------------------------------------------------------------------------

@njit(inline="always", **JIT_OPTIONS)
def _elastic_block(p0, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, buf, kk):
    """Elastic forces F_e of springs p0..p0+nb-1 into buf[5], d into buf[0:3], 1/L into buf[3].

    buf rows: 0-2 dx dy dz, 3 1/L, 4 lam, 5 force, 6 t, 7 d.dv; kk the table cells.
    The law is applied without branches: secant clips t to [0, 1] and multiplies by
    (lam - 1); energy leaves t unclipped and multiplies by 1. The damping
    branch is outside the loops, so that both versions vectorise.
    """
    last = float(last_cell)
    secant = law == LAW_SECANT
    t_lo = 0.0 if secant else -np.inf
    t_hi = 1.0 if secant else np.inf
    if damped:
        for b in range(nb):
            i = ij[0, p0 + b]
            j = ij[1, p0 + b]
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            buf[0, b] = dx
            buf[1, b] = dy
            buf[2, b] = dz
            buf[7, b] = (v[j, 0] - v[i, 0]) * dx + (v[j, 1] - v[i, 1]) * dy + (v[j, 2] - v[i, 2]) * dz
    else:
        for b in range(nb):
            i = ij[0, p0 + b]
            j = ij[1, p0 + b]
            buf[0, b] = x[j, 0] - x[i, 0]
            buf[1, b] = x[j, 1] - x[i, 1]
            buf[2, b] = x[j, 2] - x[i, 2]
    for b in range(nb):
        L = np.sqrt(buf[0, b] * buf[0, b] + buf[1, b] * buf[1, b] + buf[2, b] * buf[2, b])
        buf[3, b] = 1.0 / L if L > 0.0 else 0.0
        lam = L * sd[0, p0 + b]
        buf[4, b] = lam
        s = (lam - lam_min) * inv_h
        # max/min with the constant first: a NaN stretch gives cell 0, and the NaN
        # still propagates through lam into the force.
        sc = min(max(s, 0.0), last + 1.0)
        k = min(np.int64(sc), last_cell)
        kk[b] = k
        buf[6, b] = min(max(s - k, t_lo), t_hi)
    if sd.shape[0] - damped >= 4:          # three fibre directions
        for b in range(nb):
            k = kk[b]
            t = buf[6, b]
            p = p0 + b
            buf[5, b] = (sd[1, p] * (tab[k, 0] + t * tab[k, 3]) + sd[2, p] * (tab[k, 1] + t * tab[k, 4])
                         + sd[3, p] * (tab[k, 2] + t * tab[k, 5]))
    else:                                   # isotropic: one row, weight sum_d w_d
        for b in range(nb):
            k = kk[b]
            buf[5, b] = sd[1, p0 + b] * (tab[k, 0] + buf[6, b] * tab[k, 3])


@njit(inline="always", **JIT_OPTIONS)
def _coefficients(p0, nb, sd, damped, a1, a0, buf):
    """buf[5] <- buf[5] (a1 (lam - 1) + a0) / L (+ the dashpot's c (d.dv) / L^2): the factor of d on node i."""
    if damped:
        cd = sd.shape[0] - 1
        for b in range(nb):
            rinv = buf[3, b]
            buf[5, b] = (buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0) + sd[cd, p0 + b] * buf[7, b] * rinv) * rinv
    else:
        for b in range(nb):
            buf[5, b] = buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0) * buf[3, b]


@njit(inline="always", **JIT_OPTIONS)
def _equivalent_stretch(lam):
    """Uniaxial-equivalent stretch xi >= 1 of a spring at stretch lam (lam itself in tension)."""
    if lam >= 1.0:
        return lam
    if lam <= 1e-6:
        return np.inf
    i1 = lam * lam + 2.0 / lam
    c = -((3.0 / i1) ** 1.5)
    c = min(max(c, -1.0), 1.0)
    return 2.0 * np.sqrt(i1 / 3.0) * np.cos(np.arccos(c) / 3.0)


@njit(inline="always", **JIT_OPTIONS)
def _effects_block(p0, nb, sd, lam_min, inv_h, damped, a1, a0, etab, fxp, ab, h, pold, wmax, ximax, mode, buf,
                   kk):
    """Replace the elastic forces F_e in buf[5] by the effects' forces F, updating the state per *mode*.

    buf[5] holds the table's weighted f_d before the law's factor ``a1 (lam - 1) + a0``.
    One function on purpose: helpers taking arrays, called per spring, cost an atomic
    reference count per array and call (several times slower with damage, Mullins and
    QLV split out).
    """
    for b in range(nb):
        buf[5, b] = buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0)
    aniso = sd.shape[0] - damped >= 4
    g_inf = fxp[0]
    nt = int(fxp[1])
    mullins = fxp[2] != 0.0
    inv_r = fxp[3]
    m_w = fxp[4]
    beta = fxp[5]
    damage = fxp[6] != 0.0
    onset = fxp[7]
    dscale = fxp[8]
    dshape = fxp[9]
    dfloor = fxp[10]
    commit_max = mode == FX_STEP or mode == FX_SETTLE
    for b in range(nb):
        p = p0 + b
        fac = 1.0
        if damage:
            lam = buf[4, b]
            if lam >= 1.0:
                xi = lam
            elif lam >= lam_min:           # tabulated on the grid (exact at its nodes)
                k = kk[b]
                xi = etab[k, 6] + ((lam - lam_min) * inv_h - k) * etab[k, 7]
            else:
                xi = _equivalent_stretch(lam)
            xi = max(ximax[p], xi)
            if commit_max:
                ximax[p] = xi
            e = max(xi - onset, 0.0) / dscale
            if e > 0.0:
                fac = dfloor + (1.0 - dfloor) * np.exp(-(e ** dshape))
        if mullins:
            k = kk[b]
            tr = (buf[4, b] - lam_min) * inv_h - k     # unclipped: the energy continues linearly off the grid
            if aniso:
                ws = sd[1, p] + sd[2, p] + sd[3, p]
                w = (sd[1, p] * (etab[k, 0] + tr * etab[k, 3]) + sd[2, p] * (etab[k, 1] + tr * etab[k, 4])
                     + sd[3, p] * (etab[k, 2] + tr * etab[k, 5]))
                w = w / ws if ws > 0.0 else 0.0
            else:
                w = etab[k, 0] + tr * etab[k, 3]
            wm = max(wmax[p], w)
            if commit_max:
                wmax[p] = wm
            z = (wm - w) / (m_w + beta * wm)
            if z > 0.0:                           # erf(0) = 0 on the primary path; erf(z > 6) = 1 - 2e-17
                fac *= 1.0 - inv_r * (math.erf(z) if z < 6.0 else 1.0)
        pe = fac * buf[5, b]
        f_tot = g_inf * pe
        if mode == FX_STEP:                       # (the mode decided once per spring, outside the Prony loop)
            dp = pe - pold[p]
            for q in range(nt):
                hq = ab[0, q] * h[q, p] + ab[1, q] * dp
                f_tot += fxp[FXP_HEAD + q] * hq
                h[q, p] = hq
            pold[p] = pe
        elif mode == FX_PEEK:
            dp = pe - pold[p]
            for q in range(nt):
                f_tot += fxp[FXP_HEAD + q] * (ab[0, q] * h[q, p] + ab[1, q] * dp)
        elif mode == FX_SETTLE:
            pold[p] = pe
            for q in range(nt):
                h[q, p] = 0.0
        buf[5, b] = f_tot


@njit(**JIT_OPTIONS)
def prony_ab(fxp, dd, ab):
    """a_i = exp(-dd/tau_i), b_i = tau_i/dd (1 - a_i) (1 at dd = 0) into ab (2, nt)."""
    nt = int(fxp[1])
    for q in range(nt):
        x = dd / fxp[FXP_HEAD + nt + q]
        ab[0, q] = np.exp(-x)
        ab[1, q] = -np.expm1(-x) / x if x > 1e-12 else 1.0 - 0.5 * x


# ---------------------------------------------------------------------------
# scatter and the force pass of a range of springs
# ---------------------------------------------------------------------------

@njit(inline="always", **JIT_OPTIONS)
def _scatter_all(nb, p0, ij, f, buf):
    for b in range(nb):
        i = ij[0, p0 + b]
        j = ij[1, p0 + b]
        c = buf[5, b]
        fx = c * buf[0, b]
        fy = c * buf[1, b]
        fz = c * buf[2, b]
        f[i, 0] += fx
        f[i, 1] += fy
        f[i, 2] += fz
        f[j, 0] -= fx
        f[j, 1] -= fy
        f[j, 2] -= fz


@njit(inline="always", **JIT_OPTIONS)
def _scatter_owned(nb, p0, hi, h, ij, f, buf, hbuf):
    for b in range(nb):
        i = ij[0, p0 + b]
        j = ij[1, p0 + b]
        c = buf[5, b]
        fx = c * buf[0, b]
        fy = c * buf[1, b]
        fz = c * buf[2, b]
        f[i, 0] += fx
        f[i, 1] += fy
        f[i, 2] += fz
        if j < hi:
            f[j, 0] -= fx
            f[j, 1] -= fy
            f[j, 2] -= fz
        else:
            hbuf[h, 0] = fx
            hbuf[h, 1] = fy
            hbuf[h, 2] = fz
            h += 1
    return h


@njit(inline="always", **JIT_OPTIONS)
def _range_forces(p0, p1, hi, h, x, v, f, sp, fx, hbuf, owned):
    # The tuples are unpacked once, here, and the inlined block functions get plain
    # arrays: an array taken out of a tuple is reference-counted (an atomic increment
    # and decrement), which done per block of springs costs a noticeable part of the pass.
    ij, sd, tab, lam_min, inv_h, last_cell, law, damped = sp
    if fx is not None:
        etab, fxp, ab, hp, pold, wmax, ximax, mode = fx
    buf = np.empty((8, BLOCK))
    kk = np.empty(BLOCK, np.int64)
    secant = law == LAW_SECANT
    a1 = 1.0 if secant else 0.0          # the law's factor a1 (lam - 1) + a0
    a0 = 0.0 if secant else 1.0
    for q in range(p0, p1, BLOCK):
        nb = min(BLOCK, p1 - q)
        _elastic_block(q, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, buf, kk)
        if fx is not None:
            _effects_block(q, nb, sd, lam_min, inv_h, damped, a1, a0, etab, fxp, ab, hp, pold, wmax, ximax, mode,
                           buf, kk)
            _coefficients(q, nb, sd, damped, 0.0, 1.0, buf)      # the factor is in the effects' force
        else:
            _coefficients(q, nb, sd, damped, a1, a0, buf)
        if owned:
            h = _scatter_owned(nb, q, hi, h, ij, f, buf, hbuf)
        else:
            _scatter_all(nb, q, ij, f, buf)


@njit(inline="always", **JIT_OPTIONS)
def _start_forces(lo, hi, f, fext):
    for a in range(lo, hi):
        f[a, 0] = fext[a, 0]
        f[a, 1] = fext[a, 1]
        f[a, 2] = fext[a, 2]


@njit(**JIT_OPTIONS)
def chunk_forces(c, x, v, f, fext, sp, fx, lay):
    """f = fext + spring forces on the nodes of chunk *c*, halo springs into their slots.

    Not inlined: the parallel loops only call it, which keeps their (slow)
    parfor compilation small. A spring's effect state is written only by the
    chunk that owns the spring.
    """
    if lay.node_start.shape[0] == 2:
        _all_forces(x, v, f, fext, sp, fx)
    else:
        _owned_forces(c, x, v, f, fext, sp, fx, lay)


@njit(**JIT_OPTIONS)
def _all_forces(x, v, f, fext, sp, fx):
    # One chunk: every node and spring, scattered plainly. Its own compiled function
    # with literal bounds: LLVM then keeps the block buffers' row offsets constant and
    # the loop's constants in registers (faster than the chunked form).
    _start_forces(0, x.shape[0], f, fext)
    _range_forces(0, sp.ij.shape[1], x.shape[0], 0, x, v, f, sp, fx, np.empty((0, 3)), False)


@njit(**JIT_OPTIONS)
def _owned_forces(c, x, v, f, fext, sp, fx, lay):
    hi = lay.node_start[c + 1]
    _start_forces(lay.node_start[c], hi, f, fext)
    _range_forces(lay.spring_start[c], lay.spring_start[c + 1], hi, lay.halo_start[c], x, v, f, sp, fx,
                  lay.hbuf, True)


@njit(**JIT_OPTIONS)
def apply_halo(c, f, lay):
    """Add to the nodes of chunk *c* the halo slots that land there (see the module doc)."""
    for q in range(lay.own_start[c], lay.own_start[c + 1]):
        h = lay.own_slot[q]
        a = lay.own_node[q]
        f[a, 0] -= lay.hbuf[h, 0]
        f[a, 1] -= lay.hbuf[h, 1]
        f[a, 2] -= lay.hbuf[h, 2]


# ---------------------------------------------------------------------------
# the volume term (nodal-averaged volume penalty)
# ---------------------------------------------------------------------------

@njit(inline="always", **JIT_OPTIONS)
def _tet_edges(x, tets, t):
    """(i0, i1, i2, i3) of tet t and its edge vectors e1, e2, e3 from node i0 (nine floats)."""
    i0 = tets[0, t]
    i1 = tets[1, t]
    i2 = tets[2, t]
    i3 = tets[3, t]
    ax = x[i1, 0] - x[i0, 0]
    ay = x[i1, 1] - x[i0, 1]
    az = x[i1, 2] - x[i0, 2]
    bx = x[i2, 0] - x[i0, 0]
    by = x[i2, 1] - x[i0, 1]
    bz = x[i2, 2] - x[i0, 2]
    cx = x[i3, 0] - x[i0, 0]
    cy = x[i3, 1] - x[i0, 1]
    cz = x[i3, 2] - x[i0, 2]
    return i0, i1, i2, i3, ax, ay, az, bx, by, bz, cx, cy, cz


@njit(**JIT_OPTIONS)
def volume_forces_serial(x, f, vt):
    """Add the volume term's forces to *f* (n, 3), one thread: scatter over the tets.

    Three passes: the nodes' summed tet volumes (scatter), their pressures, the
    forces (gather the four pressures, scatter the four gradients).
    """
    tets = vt.tets
    s24 = vt.s24
    kq = vt.kq
    dsum = vt.dsum
    q = vt.q
    n = x.shape[0]
    nt = tets.shape[1]
    for a in range(n):
        dsum[a] = 0.0
    for t in range(nt):
        i0, i1, i2, i3, ax, ay, az, bx, by, bz, cx, cy, cz = _tet_edges(x, tets, t)
        d = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        dsum[i0] += d
        dsum[i1] += d
        dsum[i2] += d
        dsum[i3] += d
    for a in range(n):
        q[a] = kq * (dsum[a] * s24[a] - 1.0)
    for t in range(nt):
        i0, i1, i2, i3, ax, ay, az, bx, by, bz, cx, cy, cz = _tet_edges(x, tets, t)
        qs = q[i0] + q[i1] + q[i2] + q[i3]
        g1x = (by * cz - bz * cy) * qs       # d(6V)/dx1 = e2 x e3
        g1y = (bz * cx - bx * cz) * qs
        g1z = (bx * cy - by * cx) * qs
        g2x = (cy * az - cz * ay) * qs       # d(6V)/dx2 = e3 x e1
        g2y = (cz * ax - cx * az) * qs
        g2z = (cx * ay - cy * ax) * qs
        g3x = (ay * bz - az * by) * qs       # d(6V)/dx3 = e1 x e2
        g3y = (az * bx - ax * bz) * qs
        g3z = (ax * by - ay * bx) * qs
        f[i1, 0] -= g1x
        f[i1, 1] -= g1y
        f[i1, 2] -= g1z
        f[i2, 0] -= g2x
        f[i2, 1] -= g2y
        f[i2, 2] -= g2z
        f[i3, 0] -= g3x
        f[i3, 1] -= g3y
        f[i3, 2] -= g3z
        f[i0, 0] += g1x + g2x + g3x
        f[i0, 1] += g1y + g2y + g3y
        f[i0, 2] += g1z + g2z + g3z


@njit(**JIT_OPTIONS)
def volume_tet_pass(c, nchunk, x, vt, second):
    """Threaded pass over the tets of chunk *c*: tv = 6 V_t (first) or the tet's sum of q (*second*)."""
    tets = vt.tets
    tv = vt.tv
    q = vt.q
    nt = tets.shape[1]
    lo = c * nt // nchunk
    hi = (c + 1) * nt // nchunk
    if second:
        for t in range(lo, hi):
            tv[t] = q[tets[0, t]] + q[tets[1, t]] + q[tets[2, t]] + q[tets[3, t]]
    else:
        for t in range(lo, hi):
            i0, i1, i2, i3, ax, ay, az, bx, by, bz, cx, cy, cz = _tet_edges(x, tets, t)
            tv[t] = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


@njit(**JIT_OPTIONS)
def volume_node_pass(c, x, f, vt, lay, second):
    """Threaded pass over the nodes of chunk *c* (the layout's node range), gathering from their tets.

    First: the node's pressure q from its tets' 6 V_t; *second*: its force,
    ``-sum over its tets of (their sum of q) d(6 V_t)/dx_a``.
    """
    tets = vt.tets
    tv = vt.tv
    ptr = vt.node_ptr
    ntet = vt.node_tet
    loc = vt.node_loc
    for a in range(lay.node_start[c], lay.node_start[c + 1]):
        if not second:
            d = 0.0
            for k in range(ptr[a], ptr[a + 1]):
                d += tv[ntet[k]]
            vt.q[a] = vt.kq * (d * vt.s24[a] - 1.0)
            continue
        fx0 = 0.0
        fy0 = 0.0
        fz0 = 0.0
        for k in range(ptr[a], ptr[a + 1]):
            t = ntet[k]
            i0, i1, i2, i3, ax, ay, az, bx, by, bz, cx, cy, cz = _tet_edges(x, tets, t)
            g1x = by * cz - bz * cy
            g1y = bz * cx - bx * cz
            g1z = bx * cy - by * cx
            g2x = cy * az - cz * ay
            g2y = cz * ax - cx * az
            g2z = cx * ay - cy * ax
            g3x = ay * bz - az * by
            g3y = az * bx - ax * bz
            g3z = ax * by - ay * bx
            m = loc[k]
            if m == 1:
                gx, gy, gz = g1x, g1y, g1z
            elif m == 2:
                gx, gy, gz = g2x, g2y, g2z
            elif m == 3:
                gx, gy, gz = g3x, g3y, g3z
            else:
                gx, gy, gz = -(g1x + g2x + g3x), -(g1y + g2y + g3y), -(g1z + g2z + g3z)
            qs = tv[t]
            fx0 -= qs * gx
            fy0 -= qs * gy
            fz0 -= qs * gz
        f[a, 0] += fx0
        f[a, 1] += fy0
        f[a, 2] += fz0


@njit(inline="always", **JIT_OPTIONS)
def _volume_forces(x, f, vt, lay):
    """Add the volume term's forces to *f*: scattered on one chunk, else four gathering passes on the chunks.

    Inlined into the force pass and the step loop, whose parallel variant runs
    the passes' ``prange`` on numba's threads (a cached function calling a
    separately compiled parallel one crashes numba when loaded from its cache,
    so the passes live in the caller).
    """
    nchunk = lay.node_start.shape[0] - 1
    if nchunk == 1:
        volume_forces_serial(x, f, vt)
    else:
        for c in prange(nchunk):
            volume_tet_pass(c, nchunk, x, vt, False)
        for c in prange(nchunk):
            volume_node_pass(c, x, f, vt, lay, False)
        for c in prange(nchunk):
            volume_tet_pass(c, nchunk, x, vt, True)
        for c in prange(nchunk):
            volume_node_pass(c, x, f, vt, lay, True)


def _forces(x, v, f, fext, sp, fx, lay, vt=None):
    """f = fext + spring forces (+ dashpots, + effects unless *fx* is None, + the volume term unless
    *vt* is None), chunked as *lay*."""
    nchunk = lay.node_start.shape[0] - 1
    for c in prange(nchunk):
        chunk_forces(c, x, v, f, fext, sp, fx, lay)
    if vt is not None:
        _volume_forces(x, f, vt, lay)
    for c in prange(nchunk):
        apply_halo(c, f, lay)


#: The force pass on one thread (``prange`` is ``range``): any layout, one chunk is the plain pass.
forces_serial = njit(**JIT_OPTIONS)(twin(_forces, "forces_serial"))
#: The same pass with the chunks on numba's threads.
forces_parallel = njit(parallel=True, **JIT_OPTIONS)(twin(_forces, "forces_parallel"))


@njit(parallel=True, **JIT_OPTIONS)
def forces_beside_volume(x, v, f, fv, fext, sp, fx, lay, vt):
    """The spring pass (:func:`forces_serial`) into *f* on one thread while the other computes the volume
    term's forces into *fv* (:func:`volume_forces_serial`, from zero); then ``f += fv``. The same sum, in
    the same order, as the two passes one after the other: bit for bit. No chunks and no halo: each
    thread has its own output (the implicit stepper's force pass, :func:`.implicit_system.forces`)."""
    for g in prange(2):
        if g == 0:
            forces_serial(x, v, f, fext, sp, fx, lay)
        else:
            fv[:] = 0.0
            volume_forces_serial(x, fv, vt)
    f += fv


# ---------------------------------------------------------------------------
# time stepping
# ---------------------------------------------------------------------------

GRASP_NONE = 0
GRASP_PRESCRIBED = 1
GRASP_SPRING = 2


class Clock(NamedTuple):
    """Steps to take and where they sit in time."""

    n: int
    dt: float
    t0: float
    step0: int
    dt_first: float     #: the effects' state advances by this at the first step (then by dt)
    vfac: float         #: 1 / (1 + alpha dt)


class Nodes(NamedTuple):
    """Node arrays: positions, velocities (updated), force buffer, external force, 1/m (0: not integrated)."""

    x: np.ndarray
    v: np.ndarray
    f: np.ndarray
    fext: np.ndarray
    inv_mass: np.ndarray


class GraspKernel(NamedTuple):
    """The grasper: mode, held nodes, their offsets from the tip, coupling stiffness, tip path."""

    mode: int
    nodes: np.ndarray       #: (g,) int64
    offsets: np.ndarray     #: (g, 3)
    stiffness: np.ndarray   #: (g,) [N/m] (mode SPRING)
    wp_t: np.ndarray        #: (p,) path times [s]
    wp_x: np.ndarray        #: (p, 3) tip positions [m]


class FloorKernel(NamedTuple):
    """The rigid floor ``normal . x >= height`` acting on the nodes with ``mask``; ``contact`` is written."""

    on: bool
    normal: np.ndarray
    height: float
    stick: bool
    mask: np.ndarray        #: (n,) uint8
    contact: np.ndarray     #: (n,) uint8


# ---------------------------------------------------------------------------
# grasper
# ---------------------------------------------------------------------------

@njit(**JIT_OPTIONS)
def tip_state(t, wp_t, wp_x):
    """Position (3,) and velocity (3,) of a piecewise-linear path at time t (held at the ends)."""
    pos = np.empty(3)
    vel = np.zeros(3)
    m = wp_t.shape[0]
    if m == 1 or t <= wp_t[0]:
        for d in range(3):
            pos[d] = wp_x[0, d]
        return pos, vel
    if t >= wp_t[m - 1]:
        for d in range(3):
            pos[d] = wp_x[m - 1, d]
        return pos, vel
    k = 0
    while wp_t[k + 1] < t:
        k += 1
    span = wp_t[k + 1] - wp_t[k]
    r = (t - wp_t[k]) / span
    for d in range(3):
        pos[d] = wp_x[k, d] + r * (wp_x[k + 1, d] - wp_x[k, d])
        vel[d] = (wp_x[k + 1, d] - wp_x[k, d]) / span
    return pos, vel


@njit(inline="always", **JIT_OPTIONS)
def _grasp_forces(f, x, g_mode, g_nodes, g_off, g_k, tip, out):
    """Add the coupling springs (mode SPRING); put the force on the grasper in *out*."""
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    for q in range(g_nodes.shape[0]):
        a = g_nodes[q]
        if g_mode == GRASP_SPRING:
            for d in range(3):
                fs = g_k[q] * (tip[d] + g_off[q, d] - x[a, d])
                f[a, d] += fs
                out[d] -= fs
        else:  # prescribed: the pull of the tissue (springs + weight) on the held nodes
            for d in range(3):
                out[d] += f[a, d]


@njit(inline="always", **JIT_OPTIONS)
def _place_grasped(x, v, g_nodes, g_off, tip, tip_v):
    for q in range(g_nodes.shape[0]):
        a = g_nodes[q]
        for d in range(3):
            x[a, d] = tip[d] + g_off[q, d]
            v[a, d] = tip_v[d]


# ---------------------------------------------------------------------------
# integration of a node range (and the floor)
# ---------------------------------------------------------------------------
# The helpers take plain arrays: the tuples are unpacked once by the compiled entry
# points (reading their fields inside the loops is measurably slower).

@njit(inline="always", **JIT_OPTIONS)
def _integrate_range(lo, hi, dt, x, v, f, inv_mass, vfac):
    for a in range(lo, hi):
        s = dt * inv_mass[a]
        v[a, 0] = (v[a, 0] + s * f[a, 0]) * vfac
        v[a, 1] = (v[a, 1] + s * f[a, 1]) * vfac
        v[a, 2] = (v[a, 2] + s * f[a, 2]) * vfac
        x[a, 0] += dt * v[a, 0]
        x[a, 1] += dt * v[a, 1]
        x[a, 2] += dt * v[a, 2]


@njit(inline="always", **JIT_OPTIONS)
def _integrate_range_floor(lo, hi, dt, x, v, f, inv_mass, vfac, fl_n, fl_h, fl_stick, fl_mask, contact):
    """:func:`_integrate_range`, then the rigid floor ``n.x >= h`` (unit normal *fl_n*, offset *fl_h*).

    A node with ``fl_mask`` set that ends the step below the plane is put back
    on it: "slip" (``fl_stick`` False) projects it along the normal and removes
    the normal velocity if it points into the floor; "stick" puts it where its
    path of this step crossed the plane (its tangential position where it
    touched; at its old place if it was already on the plane) and zeroes its
    velocity. ``contact[a]`` is 1 for the nodes on or below the plane after
    the position update of this step (then put back on it), else 0.
    """
    n0 = fl_n[0]
    n1 = fl_n[1]
    n2 = fl_n[2]
    for a in range(lo, hi):
        s = dt * inv_mass[a]
        x0 = x[a, 0]
        x1 = x[a, 1]
        x2 = x[a, 2]
        v[a, 0] = (v[a, 0] + s * f[a, 0]) * vfac
        v[a, 1] = (v[a, 1] + s * f[a, 1]) * vfac
        v[a, 2] = (v[a, 2] + s * f[a, 2]) * vfac
        x[a, 0] = x0 + dt * v[a, 0]
        x[a, 1] = x1 + dt * v[a, 1]
        x[a, 2] = x2 + dt * v[a, 2]
        if not fl_mask[a]:
            continue
        dn = n0 * x[a, 0] + n1 * x[a, 1] + n2 * x[a, 2] - fl_h
        if dn > 0.0:
            contact[a] = 0
            continue
        contact[a] = 1
        if fl_stick:
            d0 = n0 * x0 + n1 * x1 + n2 * x2 - fl_h
            if d0 > 0.0:
                r = d0 / (d0 - dn)
                y0 = x0 + r * (x[a, 0] - x0)
                y1 = x1 + r * (x[a, 1] - x1)
                y2 = x2 + r * (x[a, 2] - x2)
            else:
                y0 = x0
                y1 = x1
                y2 = x2
            e = n0 * y0 + n1 * y1 + n2 * y2 - fl_h
            x[a, 0] = y0 - e * n0
            x[a, 1] = y1 - e * n1
            x[a, 2] = y2 - e * n2
            v[a, 0] = 0.0
            v[a, 1] = 0.0
            v[a, 2] = 0.0
        else:
            x[a, 0] -= dn * n0
            x[a, 1] -= dn * n1
            x[a, 2] -= dn * n2
            vn = n0 * v[a, 0] + n1 * v[a, 1] + n2 * v[a, 2]
            if vn < 0.0:
                v[a, 0] -= vn * n0
                v[a, 1] -= vn * n1
                v[a, 2] -= vn * n2


@njit(inline="always", **JIT_OPTIONS)
def _integrate_nodes(lo, hi, dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    if fl_on:
        _integrate_range_floor(lo, hi, dt, x, v, f, inv_mass, vfac, fl_n, fl_h, fl_stick, fl_mask, contact)
    else:
        _integrate_range(lo, hi, dt, x, v, f, inv_mass, vfac)


@njit(**JIT_OPTIONS)
def _integrate(c, lay, dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    """Integrate the nodes of chunk *c* (one chunk: all nodes, from literal bounds)."""
    if lay.node_start.shape[0] == 2:
        _integrate_nodes(0, x.shape[0], dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
    else:
        _integrate_nodes(lay.node_start[c], lay.node_start[c + 1], dt, x, v, f, inv_mass, vfac,
                         fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)


# ---------------------------------------------------------------------------
# the step loop (symplectic Euler), written once
# ---------------------------------------------------------------------------

def _steps(clock, nodes, sp, fx, grasp, floor, lay, rec, vt=None):
    """Advance ``clock.n`` semi-implicit Euler steps.

    Step k (time ``t = t0 + (step0 + k) dt``): forces at (x, v); the force on
    the grasper goes to ``rec[k]``; ``v <- (v + dt f / m) * vfac``, ``x <- x +
    dt v``. Nodes with ``inv_mass = 0`` keep ``v = 0`` (fixed) unless grasped in
    prescribed mode: those are put on the path at ``t + dt``. With effects, the
    springs' state advances by ``dt_first`` at the first step, then by dt.
    The volume term (*vt*, None: none) adds its forces after the springs'.
    """
    nsteps, dt, t0, step0, dt_first, vfac = clock
    x, v, f, fext, inv_mass = nodes
    g_mode, g_nodes, g_off, g_k, wp_t, wp_x = grasp
    fl_on, fl_n, fl_h, fl_stick, fl_mask, contact = floor
    node_start = lay.node_start
    nchunk = node_start.shape[0] - 1
    out = np.zeros(3)
    if fx is not None:
        prony_ab(fx.fxp, dt_first, fx.ab)
    for k in range(nsteps):
        t = t0 + (step0 + k) * dt
        if fx is not None:
            if k == 1:
                prony_ab(fx.fxp, dt, fx.ab)
        for c in prange(nchunk):
            chunk_forces(c, x, v, f, fext, sp, fx, lay)
        if vt is not None:
            _volume_forces(x, f, vt, lay)
        if g_mode != GRASP_NONE:
            # The grasped nodes' halo contributions must be in before the force on the
            # grasper is read: apply all halos, read, then integrate.
            for c in prange(nchunk):
                apply_halo(c, f, lay)
            tip, tip_v = tip_state(t, wp_t, wp_x)
            _grasp_forces(f, x, g_mode, g_nodes, g_off, g_k, tip, out)
            rec[k, 0] = out[0]
            rec[k, 1] = out[1]
            rec[k, 2] = out[2]
            for c in prange(nchunk):
                _integrate(c, lay, dt, x, v, f, inv_mass, vfac,
                           fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        else:
            for c in prange(nchunk):
                apply_halo(c, f, lay)
                _integrate(c, lay, dt, x, v, f, inv_mass, vfac,
                           fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        if g_mode == GRASP_PRESCRIBED:
            tip, tip_v = tip_state(t0 + (step0 + k + 1) * dt, wp_t, wp_x)
            _place_grasped(x, v, g_nodes, g_off, tip, tip_v)


#: The step loop on one thread (a one-chunk layout).
steps_serial = njit(**JIT_OPTIONS)(twin(_steps, "steps_serial"))
#: The step loop on numba's threads (same arithmetic; the owner/halo layout above).
steps_parallel = njit(parallel=True, **JIT_OPTIONS)(twin(_steps, "steps_parallel"))


# ---------------------------------------------------------------------------
# quasi-static relaxation (FIRE)
# ---------------------------------------------------------------------------

@njit(inline="always", **JIT_OPTIONS)
def _floor_reaction(n, f, free, fl_n, fl_stick, fl_mask, contact):
    """Take off the floor's reaction from the force of the free nodes in contact that press into it."""
    for a in range(n):
        if free[a] and fl_mask[a] and contact[a]:
            fn = f[a, 0] * fl_n[0] + f[a, 1] * fl_n[1] + f[a, 2] * fl_n[2]
            if fn < 0.0:
                if fl_stick:
                    f[a, 0] = 0.0
                    f[a, 1] = 0.0
                    f[a, 2] = 0.0
                else:
                    for d in range(3):
                        f[a, d] -= fn * fl_n[d]


@njit(inline="always", **JIT_OPTIONS)
def _fire_measure(n, f, v, free):
    """(largest |f| on a free node, power f.v, |v|^2, |f|^2) over the free nodes."""
    resid = 0.0
    P = 0.0
    vn2 = 0.0
    fn2 = 0.0
    for a in range(n):
        if free[a]:
            fa2 = f[a, 0] ** 2 + f[a, 1] ** 2 + f[a, 2] ** 2
            if fa2 > resid:
                resid = fa2
            P += f[a, 0] * v[a, 0] + f[a, 1] * v[a, 1] + f[a, 2] * v[a, 2]
            vn2 += v[a, 0] ** 2 + v[a, 1] ** 2 + v[a, 2] ** 2
            fn2 += fa2
    return np.sqrt(resid), P, vn2, fn2


@njit(inline="always", **JIT_OPTIONS)
def _fire_move(n, dt, x, v, f, inv_mass, free, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    """FIRE's MD update of the free nodes (vfac = 1), the floor's nodes then put back by its rule."""
    if fl_on:
        for a in range(n):
            if free[a] and not fl_mask[a]:
                s = dt * inv_mass[a]
                for d in range(3):
                    v[a, d] += s * f[a, d]
                    x[a, d] += dt * v[a, d]
        for a in range(n):
            if free[a] and fl_mask[a]:
                _integrate_range_floor(a, a + 1, dt, x, v, f, inv_mass, 1.0, fl_n, fl_h, fl_stick, fl_mask,
                                       contact)
    else:
        for a in range(n):
            if free[a]:
                s = dt * inv_mass[a]
                for d in range(3):
                    v[a, d] += s * f[a, d]
                    x[a, d] += dt * v[a, d]


@njit(**JIT_OPTIONS)
def fire_relax(nodes, free, sp, fx, lay, grasp, tip, floor, dt0, dt_max, ftol, max_iter, fs, vt=None):
    """FIRE minimisation (Bitzek et al. 2006) of the network energy under fext.

    Uses the dynamics' force pass (*sp* without dashpots; one-chunk *lay*) and a
    mass-weighted semi-implicit Euler MD step; grasper coupling springs (mode
    SPRING) pull the held nodes to ``tip + offsets``. Converged when the
    largest residual force on a free node is below *ftol* [N]. Returns
    (iterations, final max residual); iterations = -1 when the forces became
    non-finite. With effects (*fx* not None) their long-term force (mode
    ``FX_RELAXED``, state unchanged) is used. Standard parameters: N_min 5,
    f_inc 1.1, f_dec 0.5, alpha_start 0.1, f_alpha 0.99.

    Resumable: *fs* (float64, 4) holds FIRE's own state ``[alpha, dt,
    steps since P < 0, started]``; a call with ``started == 0`` starts afresh
    (velocities zeroed), one with ``started == 1`` goes on from *fs* and the
    nodes' velocities, so that calls of *max_iter* iterations each take
    exactly the path of one long call (the caller reports progress between
    them).

    With ``floor.on`` the rigid floor of :func:`_integrate_range_floor` constrains
    the nodes with ``floor.mask``: each MD update puts the nodes that end below
    the plane back on it (same rule as the dynamics, "stick" or "slip"), and
    for a node in contact (``floor.contact[a]``, set by the last update) whose force
    presses into the floor the floor's reaction is taken off the force used
    by FIRE and by the convergence test (the normal part with "slip", all of it
    with "stick": sticking friction carries any tangential load). The volume
    term (*vt*, None: none) adds its forces to the springs'.
    """
    x, v, f, fext, inv_mass = nodes
    g_mode, g_nodes, g_off, g_k, wp_t, wp_x = grasp
    fl_on, fl_n, fl_h, fl_stick, fl_mask, contact = floor
    n = x.shape[0]
    if fs[3] == 0.0:
        fs[0], fs[1], fs[2], fs[3] = 0.1, dt0, 0.0, 1.0
        v[:, :] = 0.0
    alpha = fs[0]
    dt = fs[1]
    since_neg = int(fs[2])
    resid = np.inf
    out = np.zeros(3)
    for it in range(max_iter):
        forces_serial(x, v, f, fext, sp, fx, lay, vt)
        if g_mode == GRASP_SPRING:
            _grasp_forces(f, x, g_mode, g_nodes, g_off, g_k, tip, out)
        if fl_on:
            _floor_reaction(n, f, free, fl_n, fl_stick, fl_mask, contact)
        resid, P, vn2, fn2 = _fire_measure(n, f, v, free)
        if not np.isfinite(resid):
            return -1, resid
        if resid < ftol:
            fs[0], fs[1], fs[2] = alpha, dt, since_neg
            return it, resid
        if P > 0.0:
            vn = np.sqrt(vn2)
            fn = np.sqrt(fn2)
            if fn > 0.0:
                for a in range(n):
                    if free[a]:
                        for d in range(3):
                            v[a, d] = (1.0 - alpha) * v[a, d] + alpha * vn * f[a, d] / fn
            since_neg += 1
            if since_neg > 5:
                dt = min(dt * 1.1, dt_max)
                alpha *= 0.99
        else:
            since_neg = 0
            dt *= 0.5
            alpha = 0.1
            v[:, :] = 0.0
        _fire_move(n, dt, x, v, f, inv_mass, free, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
    fs[0], fs[1], fs[2] = alpha, dt, since_neg
    return max_iter, resid


# ---------------------------------------------------------------------------
# diagnostics
# ---------------------------------------------------------------------------

@njit(**JIT_OPTIONS)
def stretch_range(x, ij, sd):
    """(min, max) spring stretch of configuration *x* (NaN if a stretch is not finite)."""
    lo = np.inf
    hi = -np.inf
    for p in range(ij.shape[1]):
        i = ij[0, p]
        j = ij[1, p]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        lam = np.sqrt(dx * dx + dy * dy + dz * dz) * sd[0, p]
        if not np.isfinite(lam):
            return np.nan, np.nan
        if lam < lo:
            lo = lam
        if lam > hi:
            hi = lam
    return lo, hi


@njit(**JIT_OPTIONS)
def node_tangent_sums(x, ij, sd, gwin, lam_min, inv_h, last_cell, aniso, out):
    """out[a] = sum over the springs of node a of kappa_ij = sum_d (w_d / L0) gwin[cell(lam), d].

    *gwin* (n_cells, 3) bounds the tangent per fibre direction over a stretch
    window around each cell; the sums feed the Gershgorin bound of the step.
    """
    for a in range(out.shape[0]):
        out[a] = 0.0
    last = float(last_cell)
    for p in range(ij.shape[1]):
        i = ij[0, p]
        j = ij[1, p]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        lam = np.sqrt(dx * dx + dy * dy + dz * dz) * sd[0, p]
        s = min(max((lam - lam_min) * inv_h, 0.0), last + 1.0)
        k = min(np.int64(s), last_cell)
        if aniso:
            kap = sd[0, p] * (sd[1, p] * gwin[k, 0] + sd[2, p] * gwin[k, 1] + sd[3, p] * gwin[k, 2])
        else:
            kap = sd[0, p] * sd[1, p] * gwin[k, 0]
        if not np.isfinite(lam):
            kap = np.inf
        out[i] += kap
        out[j] += kap


@njit(**JIT_OPTIONS)
def stretch_change(x, x0, ij, sd):
    """Largest |lam(x) - lam(x0)| over the springs (inf if not finite)."""
    worst = 0.0
    for p in range(ij.shape[1]):
        i = ij[0, p]
        j = ij[1, p]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        ex = x0[j, 0] - x0[i, 0]
        ey = x0[j, 1] - x0[i, 1]
        ez = x0[j, 2] - x0[i, 2]
        d = abs(np.sqrt(dx * dx + dy * dy + dz * dz) - np.sqrt(ex * ex + ey * ey + ez * ez)) * sd[0, p]
        if not np.isfinite(d):
            return np.inf
        if d > worst:
            worst = d
    return worst


# ---------------------------------------------------------------------------
# tangent stiffness (the implicit stepper; docs/design/simulator.md, "Scheme")
# ---------------------------------------------------------------------------

@njit(inline="always", **JIT_OPTIONS)
def _law_and_slope(sd, p, tab, k, tr, inv_h, secant, aniso, lam):
    """(F_e, dF_e/dlam) of spring *p* at stretch *lam* in cell *k* (unclipped cell fraction *tr*).

    Secant: F_e = sum_d w_d mu_d(lam) (lam - 1) with mu held off the grid (t clipped, no slope
    there); energy: F_e = sum_d w_d f_d(lam), the end cells continued linearly.
    """
    t = min(max(tr, 0.0), 1.0) if secant else tr
    if aniso:
        val = (sd[1, p] * (tab[k, 0] + t * tab[k, 3]) + sd[2, p] * (tab[k, 1] + t * tab[k, 4])
               + sd[3, p] * (tab[k, 2] + t * tab[k, 5]))
        slope = (sd[1, p] * tab[k, 3] + sd[2, p] * tab[k, 4] + sd[3, p] * tab[k, 5]) * inv_h
    else:
        val = sd[1, p] * (tab[k, 0] + t * tab[k, 3])
        slope = sd[1, p] * tab[k, 3] * inv_h
    if not secant:
        return val, slope
    inside = 1.0 if (tr >= 0.0 and tr <= 1.0) else 0.0
    return val * (lam - 1.0), val + (lam - 1.0) * slope * inside


@njit(inline="always", **JIT_OPTIONS)
def _effect_factor(p, lam, k, tr, lam_min, inv_h, sd, aniso, etab, fxp, wmax, ximax):
    """(fac, dfac/dlam) of spring *p*: damage (1 - D) times Mullins eta, with the state's maxima (not committed).

    On the primary path (the stretch beyond its largest so far) damage grows with lam;
    below its largest energy density a Mullins spring reloads along the erf curve.
    """
    fac = 1.0
    dfac = 0.0
    if fxp[6] != 0.0:                               # damage
        onset = fxp[7]
        dscale = fxp[8]
        dshape = fxp[9]
        dfloor = fxp[10]
        if lam >= 1.0:
            xi = lam
            dxi = 1.0
        elif lam >= lam_min:
            xi = etab[k, 6] + tr * etab[k, 7]
            dxi = etab[k, 7] * inv_h
        else:
            xi = _equivalent_stretch(lam)
            e2 = 1e-7 * lam
            dxi = (_equivalent_stretch(lam + e2) - _equivalent_stretch(lam - e2)) / (2.0 * e2)
        primary = xi > ximax[p]
        xi = max(ximax[p], xi)
        e = max(xi - onset, 0.0) / dscale
        if e > 0.0:
            ef = (1.0 - dfloor) * np.exp(-(e ** dshape))
            fac = dfloor + ef
            if primary:
                dfac = -ef * dshape * e ** (dshape - 1.0) * dxi / dscale
    if fxp[2] != 0.0:                               # Mullins
        inv_r = fxp[3]
        m_w = fxp[4]
        beta = fxp[5]
        if aniso:
            ws = sd[1, p] + sd[2, p] + sd[3, p]
            w = (sd[1, p] * (etab[k, 0] + tr * etab[k, 3]) + sd[2, p] * (etab[k, 1] + tr * etab[k, 4])
                 + sd[3, p] * (etab[k, 2] + tr * etab[k, 5]))
            dw = (sd[1, p] * etab[k, 3] + sd[2, p] * etab[k, 4] + sd[3, p] * etab[k, 5]) * inv_h
            w = w / ws if ws > 0.0 else 0.0
            dw = dw / ws if ws > 0.0 else 0.0
        else:
            w = etab[k, 0] + tr * etab[k, 3]
            dw = etab[k, 3] * inv_h
        wm = max(wmax[p], w)
        den = m_w + beta * wm
        z = (wm - w) / den
        if z > 0.0:
            eta = 1.0 - inv_r * (math.erf(z) if z < 6.0 else 1.0)
            deta = inv_r * (2.0 / math.sqrt(math.pi)) * np.exp(-z * z) * dw / den if z < 6.0 else 0.0
            dfac = dfac * eta + fac * deta
            fac = fac * eta
    return fac, dfac


@njit(**JIT_OPTIONS)
def tangent_coefficients(x, sp, fx, kt, fl, u):
    """Per spring: axial tangent kt = dF/dL [N/m], geometric stiffness fl = F/L [N/m], direction u (s, 3).

    The spring's block of the tangent stiffness K = -df/dx is ``kt u u^T + fl (I - u u^T)``
    (added at (i, i), (j, j), subtracted at (i, j), (j, i)). With effects (*fx* not None) F
    is the effects' force of the step in ``fx.ab`` from the state in *fx* (not committed),
    and kt its derivative: the QLV instantaneous factor ``g_inf + sum_i g_i b_i`` (``g_inf``
    alone in mode :data:`FX_RELAXED`) times d[(1 - D) eta F_e]/dL. A spring of zero length
    gets zeros. Dashpots are not included (see :func:`fill_blocks`).
    """
    ij, sd, tab, lam_min, inv_h, last_cell, law, damped = sp
    aniso = sd.shape[0] - damped >= 4
    secant = law == LAW_SECANT
    last = float(last_cell)
    if fx is not None:
        etab, fxp, ab, hp, pold, wmax, ximax, mode = fx
    for p in range(ij.shape[1]):
        i = ij[0, p]
        j = ij[1, p]
        d0 = x[j, 0] - x[i, 0]
        d1 = x[j, 1] - x[i, 1]
        d2 = x[j, 2] - x[i, 2]
        L = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if not L > 0.0:
            kt[p] = 0.0
            fl[p] = 0.0
            u[p, 0] = 0.0
            u[p, 1] = 0.0
            u[p, 2] = 0.0
            continue
        rinv = 1.0 / L
        u[p, 0] = d0 * rinv
        u[p, 1] = d1 * rinv
        u[p, 2] = d2 * rinv
        lam = L * sd[0, p]
        s = (lam - lam_min) * inv_h
        k = min(np.int64(min(max(s, 0.0), last + 1.0)), last_cell)
        tr = s - k
        fe, dfe = _law_and_slope(sd, p, tab, k, tr, inv_h, secant, aniso, lam)
        F = fe
        dF = dfe
        if fx is not None:
            fac, dfac = _effect_factor(p, lam, k, tr, lam_min, inv_h, sd, aniso, etab, fxp, wmax, ximax)
            pe = fac * fe
            dpe = fac * dfe + fe * dfac
            g_inf = fxp[0]
            nt = int(fxp[1])
            F = g_inf * pe
            inst = g_inf
            if mode != FX_RELAXED:
                for q in range(nt):
                    F += fxp[FXP_HEAD + q] * (ab[0, q] * hp[q, p] + ab[1, q] * (pe - pold[p]))
                    inst += fxp[FXP_HEAD + q] * ab[1, q]
            dF = inst * dpe
        kt[p] = dF * sd[0, p]
        fl[p] = F * rinv


@njit(**JIT_OPTIONS)
def fill_blocks(ij, kt, fl, u, blk, stride, data, definite):
    """Add each spring's 3x3 block ``kt u u^T + fl (I - u u^T)`` into a CSR matrix's *data*.

    ``blk`` (4, s): data offsets of the blocks (i, i), (j, j), (i, j), (j, i) at their first
    row; the block's row r starts ``r * stride[node]`` further (``stride`` (n,): entries per
    scalar row of the node's rows). *definite*: negative kt and fl are taken as 0 (each block
    then positive semi-definite).
    """
    for p in range(ij.shape[1]):
        a = kt[p]
        g = fl[p]
        if definite:
            a = max(a, 0.0)
            g = max(g, 0.0)
        i = ij[0, p]
        j = ij[1, p]
        si = stride[i]
        sj = stride[j]
        for r in range(3):
            for c in range(3):
                val = (a - g) * (u[p, r] * u[p, c])
                if r == c:
                    val += g
                data[blk[0, p] + r * si + c] += val
                data[blk[1, p] + r * sj + c] += val
                data[blk[2, p] + r * si + c] -= val
                data[blk[3, p] + r * sj + c] -= val



#: Each local node k of a tet and the even ordering (a, k, b, c) of its tet: ``dV/dx_k`` is
#: ``(x_b - x_a) x (x_c - x_a) / 6`` (:mod:`esmm.pipeline.network.volume`'s ``_EVEN``).
TET_EVEN = np.array([[1, 0, 3, 2], [0, 1, 2, 3], [0, 2, 3, 1], [0, 3, 1, 2]], dtype=np.int64)


@njit(**JIT_OPTIONS)
def add_tet_bound(x, tets, w, pos, even, data):
    """``data[pos[t, 12 a + b]] += w[t] g_a g_b`` for every tet t, ``g = grad V_t`` at *x* (12,): the
    volume term's per-tet Gauss-Newton blocks (its ``tangent_bound``) summed into a CSR matrix's data,
    the gradients computed in the same pass (as ``VolumeElements._gradients``: the cross product of
    two edges over 6)."""
    g = np.empty(12)
    for t in range(tets.shape[0]):
        for k in range(4):
            a = tets[t, even[k, 0]]
            b = tets[t, even[k, 2]]
            c = tets[t, even[k, 3]]
            u0 = x[b, 0] - x[a, 0]
            u1 = x[b, 1] - x[a, 1]
            u2 = x[b, 2] - x[a, 2]
            v0 = x[c, 0] - x[a, 0]
            v1 = x[c, 1] - x[a, 1]
            v2 = x[c, 2] - x[a, 2]
            g[3 * k] = (u1 * v2 - u2 * v1) / 6.0
            g[3 * k + 1] = (u2 * v0 - u0 * v2) / 6.0
            g[3 * k + 2] = (u0 * v1 - u1 * v0) / 6.0
        for a in range(12):
            ga = w[t] * g[a]
            for b in range(12):
                data[pos[t, 12 * a + b]] += ga * g[b]


@njit(**JIT_OPTIONS)
def step_velocity(x, x0, h, v):
    """``v = (x - x0) / h`` (n, 3): the implicit step's velocities at its end positions *x*."""
    for a in range(x.shape[0]):
        for d in range(3):
            v[a, d] = (x[a, d] - x0[a, d]) / h


@njit(**JIT_OPTIONS)
def step_residual(x, x0, v0, h, mass, alpha, f, movable, g):
    """The implicit step's residual ``g = m ((x - x0 - h v0) / h^2 + alpha (x - x0) / h) - f`` (n, 3),
    zero on the nodes that are not *movable* (the numpy expression's arithmetic, element by element)."""
    hh = h * h
    for a in range(x.shape[0]):
        if not movable[a]:
            g[a, 0] = 0.0
            g[a, 1] = 0.0
            g[a, 2] = 0.0
            continue
        m = mass[a]
        for d in range(3):
            dx = x[a, d] - x0[a, d]
            g[a, d] = m * ((dx - h * v0[a, d]) / hh + alpha * dx / h) - f[a, d]
