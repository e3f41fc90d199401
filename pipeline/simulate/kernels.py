r"""Compiled (numba) force pass of the spring term, with the material effects.

Everything here works on plain arrays in SI units, grouped in a few tuples that
:class:`~.springterm.SpringTerm` and :mod:`.effects` build:

* :class:`SpringKernel` ``(ij, sd, tab, lam_min, inv_h, last_cell, law, damped)``:
  the springs and their table (constant during a run);
* :class:`EffectKernel` ``(etab, fxp, ab, h, pold, wmax, ximax, mode)``: the
  material effects' parameters and tables, the Prony factors of the step, the
  per-spring state and what to do with it; **None** for an elastic run;
* :class:`Layout` ``(node_start, spring_start, halo_start, hbuf, own_start,
  own_slot, own_node)``: the race-free threading layout (one chunk: serial).

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
~20 % faster than the one-loop form on AVX-512 hardware and gives bitwise the
same numbers.

One pass, two compiled variants
-------------------------------
The effects are one optional argument: ``fx is None`` is decided when numba
compiles (dead-branch pruning on the argument's type), so the elastic variant
contains no effect code and no branch for it, and the effects variant shares
every other line. A force term that joins later (a per-tetrahedron volume term)
joins the same way: its own tuple, its own chunk function adding its forces to
the owned nodes and halo slots of a chunk, called next to
:func:`chunk_forces` when its tuple is not None.

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

and its force is (docs/simulate.md, "Material effects")

    F_e = sum_d w_d f_d(lam)                      the elastic (instantaneous) force
    P   = (1 - D(ximax)) * eta(W, wmax) * F_e     damage and Mullins softening
    h_i <- a_i h_i + b_i (P - pold),  a_i = exp(-dt/tau_i), b_i = tau_i/dt (1 - a_i)
    F   = g_inf P + sum_i g_i h_i                 QLV, G(0) = 1

``etab`` (n_cells, 8): per cell ``[W_x, W_y, W_z, dW_x, dW_y, dW_z, xi, dxi]``: the
material's uniaxial energy density [Pa] and the uniaxial-equivalent stretch of a
spring at the cell's left node, with their increments (xi is exact for lam >= 1
and below the grid). Parameters ``fxp`` (float64): [g_inf, nt, mullins_on, 1/r, m,
beta, damage_on, onset, scale, shape, g_1..g_nt, tau_1..tau_nt]; ``ab`` (2, nt):
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
FXP_HEAD = 10

#: Springs per block (buffers of 9 x BLOCK doubles stay in L1).
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
def _block(p0, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, fx, buf, kk):
    """Force coefficients of springs p0..p0+nb-1 into buf[5] (F/L + dashpot), d into buf[0:3].

    buf rows: 0-2 dx dy dz, 3 1/L, 4 lam, 5 coefficient, 6 t, 7 d.dv, 8 unclipped t
    (effects only). The law
    is applied without branches: secant clips t to [0, 1] and multiplies by
    (lam - 1); energy leaves t unclipped and multiplies by 1. The damping
    branch is outside the loops, so that both versions vectorise.
    """
    last = float(last_cell)
    secant = law == LAW_SECANT
    t_lo = 0.0 if secant else -np.inf
    t_hi = 1.0 if secant else np.inf
    a1 = 1.0 if secant else 0.0          # factor = a1 * (lam - 1) + a0
    a0 = 0.0 if secant else 1.0
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
        if fx is not None:
            buf[8, b] = s - k                  # unclipped: the effects' energy continues off the grid
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
    if fx is not None:
        for b in range(nb):
            buf[5, b] = buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0)
        _effects_block(p0, nb, sd, lam_min, damped, fx, buf, kk)
        a1 = 0.0
        a0 = 1.0
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
def _effects_block(p0, nb, sd, lam_min, damped, fx, buf, kk):
    """Replace the elastic forces F_e in buf[5] by the effects' forces F, updating the state per ``fx.mode``."""
    etab = fx.etab
    fxp = fx.fxp
    ab = fx.ab
    h = fx.h
    pold = fx.pold
    wmax = fx.wmax
    ximax = fx.ximax
    mode = fx.mode
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
    commit_max = mode == FX_STEP or mode == FX_SETTLE
    for b in range(nb):
        p = p0 + b
        lam = buf[4, b]
        k = kk[b]
        tr = buf[8, b]
        fac = 1.0
        if damage:
            if lam >= 1.0:
                xi = lam
            elif lam >= lam_min:           # tabulated on the grid (exact at its nodes)
                xi = etab[k, 6] + tr * etab[k, 7]
            else:
                xi = _equivalent_stretch(lam)
            xi = max(ximax[p], xi)
            if commit_max:
                ximax[p] = xi
            e = max(xi - onset, 0.0) / dscale
            if e > 0.0:
                fac = np.exp(-(e ** dshape))
        if mullins:
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
        if mode == FX_RELAXED:
            f_tot = g_inf * pe
        elif mode == FX_SETTLE:
            f_tot = g_inf * pe
            pold[p] = pe
            for q in range(nt):
                h[q, p] = 0.0
        else:
            dp = pe - pold[p]
            f_tot = g_inf * pe
            for q in range(nt):
                hq = ab[0, q] * h[q, p] + ab[1, q] * dp
                f_tot += fxp[FXP_HEAD + q] * hq
                if mode == FX_STEP:
                    h[q, p] = hq
            if mode == FX_STEP:
                pold[p] = pe
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
    # The tuple is unpacked once here: the inlined block then sees plain arrays and
    # scalars (reading them from the tuple inside the loops costs ~10 %).
    ij, sd, tab, lam_min, inv_h, last_cell, law, damped = sp
    buf = np.empty((9, BLOCK))
    kk = np.empty(BLOCK, np.int64)
    for q in range(p0, p1, BLOCK):
        nb = min(BLOCK, p1 - q)
        _block(q, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, fx, buf, kk)
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
    # the loop's constants in registers (~5 % faster than the chunked form).
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


def _forces(x, v, f, fext, sp, fx, lay):
    """f = fext + spring forces (+ dashpots, + effects unless *fx* is None), chunked as *lay*."""
    nchunk = lay.node_start.shape[0] - 1
    for c in prange(nchunk):
        chunk_forces(c, x, v, f, fext, sp, fx, lay)
    for c in prange(nchunk):
        apply_halo(c, f, lay)


#: The force pass on one thread (``prange`` is ``range``): any layout, one chunk is the plain pass.
forces_serial = njit(**JIT_OPTIONS)(twin(_forces, "forces_serial"))
#: The same pass with the chunks on numba's threads.
forces_parallel = njit(parallel=True, **JIT_OPTIONS)(twin(_forces, "forces_parallel"))


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
