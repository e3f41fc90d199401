r"""Compiled (numba) hot loops of the simulator.

Everything here works on plain arrays in SI units; :mod:`.integrator` builds
them from a :class:`~esmm.pipeline.network.springs.SpringNetwork` and
:class:`~esmm.pipeline.network.tables.StiffnessTables`.

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
weight (contiguous: LLVM vectorises it, sqrt included), (3) table fetch, (4)
force coefficient ``F/L`` (vectorised, the division included), (5) scatter.
This is ~20 % faster than the one-loop form on AVX-512 hardware and gives
bitwise the same numbers.

Race-free threading
-------------------
Springs are sorted by their lower node ``i``. The nodes are cut into ``T``
contiguous ranges with about equal spring counts; chunk ``t`` owns the
springs whose ``i`` lies in its range. It writes ``f[i]`` (owned) and
``f[j]`` when ``j`` is also owned; a spring whose ``j`` lies in a later
chunk's range (a *halo* spring: few after a bandwidth-reducing node order)
writes its force into a private slot ``hbuf[h]`` instead. A second parallel
pass over the node ranges adds the halo slots of each range (precomputed per
owner) and integrates its nodes. No two threads ever write the same address:
no atomics and no reduction buffers.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

LAW_SECANT = 0
LAW_ENERGY = 1

GRASP_NONE = 0
GRASP_PRESCRIBED = 1
GRASP_SPRING = 2

#: Springs per block (buffers of 10 x BLOCK doubles stay in L1).
BLOCK = 64

_OPTS = dict(cache=True, error_model="numpy")


# ---------------------------------------------------------------------------
# one block of springs
# ---------------------------------------------------------------------------

@njit(inline="always", **_OPTS)
def _block(p0, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, buf, kk):
    """Force coefficients of springs p0..p0+nb-1 into buf[5] (F/L + dashpot), d into buf[0:3].

    buf rows: 0-2 dx dy dz, 3 L, 4 lam, 5 coefficient, 6 t, 7 d.dv. The law is
    applied without branches: secant clips t to [0, 1] and multiplies by
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
    if damped:
        cd = sd.shape[0] - 1
        for b in range(nb):
            rinv = buf[3, b]
            buf[5, b] = (buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0)
                         + sd[cd, p0 + b] * buf[7, b] * rinv) * rinv
    else:
        for b in range(nb):
            buf[5, b] = buf[5, b] * (a1 * (buf[4, b] - 1.0) + a0) * buf[3, b]


@njit(inline="always", **_OPTS)
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


@njit(inline="always", **_OPTS)
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


@njit(inline="always", **_OPTS)
def _range_forces(p0, p1, hi, h, x, v, f, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                  hbuf, owned):
    buf = np.empty((8, BLOCK))
    kk = np.empty(BLOCK, np.int64)
    for q in range(p0, p1, BLOCK):
        nb = min(BLOCK, p1 - q)
        _block(q, nb, x, v, ij, sd, tab, lam_min, inv_h, last_cell, law, damped, buf, kk)
        if owned:
            h = _scatter_owned(nb, q, hi, h, ij, f, buf, hbuf)
        else:
            _scatter_all(nb, q, ij, f, buf)


# ---------------------------------------------------------------------------
# force passes
# ---------------------------------------------------------------------------

@njit(**_OPTS)
def forces_serial(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped):
    """f = fext + spring forces (+ dashpots), one thread, scatter over the springs."""
    n = x.shape[0]
    for a in range(n):
        f[a, 0] = fext[a, 0]
        f[a, 1] = fext[a, 1]
        f[a, 2] = fext[a, 2]
    hbuf = np.empty((0, 3))
    _range_forces(0, ij.shape[1], n, 0, x, v, f, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                  hbuf, False)


@njit(**_OPTS)
def _chunk_forces(c, x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                  node_start, spring_start, halo_start, hbuf):
    # Not inlined: the parallel loops only call it, which keeps their (slow) parfor
    # compilation small; it is compiled and cached once like forces_serial.
    lo = node_start[c]
    hi = node_start[c + 1]
    for a in range(lo, hi):
        f[a, 0] = fext[a, 0]
        f[a, 1] = fext[a, 1]
        f[a, 2] = fext[a, 2]
    _range_forces(spring_start[c], spring_start[c + 1], hi, halo_start[c], x, v, f, ij, sd, tab, lam_min,
                  inv_h, last_cell, law, damped, hbuf, True)


@njit(**_OPTS)
def _apply_halo(c, f, own_start, own_slot, own_node, hbuf):
    for q in range(own_start[c], own_start[c + 1]):
        h = own_slot[q]
        a = own_node[q]
        f[a, 0] -= hbuf[h, 0]
        f[a, 1] -= hbuf[h, 1]
        f[a, 2] -= hbuf[h, 2]


@njit(parallel=True, **_OPTS)
def forces_parallel(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                    node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node):
    """:func:`forces_serial` with the owner/halo threading (see the module doc)."""
    nchunk = node_start.shape[0] - 1
    for c in prange(nchunk):
        _chunk_forces(c, x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                      node_start, spring_start, halo_start, hbuf)
    for c in prange(nchunk):
        _apply_halo(c, f, own_start, own_slot, own_node, hbuf)


# ---------------------------------------------------------------------------
# material effects (viscoelastic QLV, Mullins, damage): a separate kernel family
# ---------------------------------------------------------------------------
#
# The plain kernels above stay exactly as they are (no branch, no state) so that an
# elastic run pays nothing for the effects. With effects, each spring carries state
# (model order, structure of arrays):
#
#   h     (nt, s)  Prony internal variables h_i [N]
#   pold  (s,)     the spring's softened elastic force P at the last committed evaluation [N]
#   wmax  (s,)     largest energy density W reached so far [Pa]            (Mullins)
#   ximax (s,)     largest uniaxial-equivalent stretch reached so far      (damage)
#
# and its force is (docs/simulate.md, "Material effects")
#
#   F_e = sum_d w_d f_d(lam)                      the elastic (instantaneous) force
#   P   = (1 - D(ximax)) * eta(W, wmax) * F_e     damage and Mullins softening
#   h_i <- a_i h_i + b_i (P - pold),  a_i = exp(-dt/tau_i), b_i = tau_i/dt (1 - a_i)
#   F   = g_inf P + sum_i g_i h_i                 QLV, G(0) = 1
#
# ``etab`` (n_cells, 8): per cell ``[W_x, W_y, W_z, dW_x, dW_y, dW_z, xi, dxi]``: the material's
# uniaxial energy density [Pa] and the uniaxial-equivalent stretch of a spring at the cell's left
# node, with their increments (xi is exact for lam >= 1 and below the grid).
# Parameters ``fxp`` (float64): [g_inf, nt, mullins_on, 1/r, m, beta, damage_on, onset,
# scale, shape, g_1..g_nt, tau_1..tau_nt]; ``ab`` (2, nt): a_i and b_i of the current
# step (from :func:`prony_ab`). Modes:

FX_STEP = 0       #: advance the state by the step in ``ab`` and commit it
FX_PEEK = 1       #: the force the step in ``ab`` would give, state unchanged
FX_RELAXED = 2    #: long-term force g_inf * P (maxima including the current stretch), state unchanged
FX_SETTLE = 3     #: commit the maxima and a fully relaxed history at the current stretch (h = 0)

#: Number of leading scalars in ``fxp`` before the Prony weights.
FXP_HEAD = 10


@njit(**_OPTS)
def prony_ab(fxp, dd, ab):
    """a_i = exp(-dd/tau_i), b_i = tau_i/dd (1 - a_i) (1 at dd = 0) into ab (2, nt)."""
    nt = int(fxp[1])
    for q in range(nt):
        x = dd / fxp[FXP_HEAD + nt + q]
        ab[0, q] = np.exp(-x)
        ab[1, q] = -np.expm1(-x) / x if x > 1e-12 else 1.0 - 0.5 * x


@njit(inline="always", **_OPTS)
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


@njit(inline="always", **_OPTS)
def _block_fx(p0, nb, x, v, ij, sd, tab, etab, lam_min, inv_h, last_cell, law, damped, buf, kk,
              fxp, ab, h, pold, wmax, ximax, mode):
    """:func:`_block` with the material effects and their per-spring state (see above)."""
    last = float(last_cell)
    secant = law == LAW_SECANT
    t_lo = 0.0 if secant else -np.inf
    t_hi = 1.0 if secant else np.inf
    a1 = 1.0 if secant else 0.0
    a0 = 0.0 if secant else 1.0
    for b in range(nb):
        i = ij[0, p0 + b]
        j = ij[1, p0 + b]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        buf[0, b] = dx
        buf[1, b] = dy
        buf[2, b] = dz
        if damped:
            buf[7, b] = (v[j, 0] - v[i, 0]) * dx + (v[j, 1] - v[i, 1]) * dy + (v[j, 2] - v[i, 2]) * dz
    for b in range(nb):
        L = np.sqrt(buf[0, b] * buf[0, b] + buf[1, b] * buf[1, b] + buf[2, b] * buf[2, b])
        buf[3, b] = 1.0 / L if L > 0.0 else 0.0
        lam = L * sd[0, p0 + b]
        buf[4, b] = lam
        s = (lam - lam_min) * inv_h
        sc = min(max(s, 0.0), last + 1.0)
        k = min(np.int64(sc), last_cell)
        kk[b] = k
        buf[8, b] = s - k                      # unclipped: the energy continues linearly off the grid
        buf[6, b] = min(max(s - k, t_lo), t_hi)
    aniso = sd.shape[0] - damped >= 4
    for b in range(nb):
        k = kk[b]
        t = buf[6, b]
        p = p0 + b
        if aniso:
            fe = (sd[1, p] * (tab[k, 0] + t * tab[k, 3]) + sd[2, p] * (tab[k, 1] + t * tab[k, 4])
                  + sd[3, p] * (tab[k, 2] + t * tab[k, 5]))
        else:
            fe = sd[1, p] * (tab[k, 0] + t * tab[k, 3])
        buf[5, b] = fe * (a1 * (buf[4, b] - 1.0) + a0)
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
        fac = 1.0
        if damage:
            lam = buf[4, b]
            if lam >= 1.0:
                xi = lam
            elif lam >= lam_min:              # tabulated on the grid (exact at its nodes)
                xi = etab[kk[b], 6] + buf[8, b] * etab[kk[b], 7]
            else:
                xi = _equivalent_stretch(lam)
            xi = max(ximax[p], xi)
            if commit_max:
                ximax[p] = xi
            e = max(xi - onset, 0.0) / dscale
            if e > 0.0:
                fac = np.exp(-(e ** dshape))
        if mullins:
            k = kk[b]
            tr = buf[8, b]
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
    if damped:
        cd = sd.shape[0] - 1
        for b in range(nb):
            rinv = buf[3, b]
            buf[5, b] = (buf[5, b] + sd[cd, p0 + b] * buf[7, b] * rinv) * rinv
    else:
        for b in range(nb):
            buf[5, b] = buf[5, b] * buf[3, b]


@njit(inline="always", **_OPTS)
def _range_forces_fx(p0, p1, hi, h0, x, v, f, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                     hbuf, owned, etab, fxp, ab, h, pold, wmax, ximax, mode):
    buf = np.empty((9, BLOCK))
    kk = np.empty(BLOCK, np.int64)
    hh = h0
    for q in range(p0, p1, BLOCK):
        nb = min(BLOCK, p1 - q)
        _block_fx(q, nb, x, v, ij, sd, tab, etab, lam_min, inv_h, last_cell, law, damped, buf, kk,
                  fxp, ab, h, pold, wmax, ximax, mode)
        if owned:
            hh = _scatter_owned(nb, q, hi, hh, ij, f, buf, hbuf)
        else:
            _scatter_all(nb, q, ij, f, buf)


@njit(**_OPTS)
def forces_serial_fx(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                     etab, fxp, ab, h, pold, wmax, ximax, mode):
    """:func:`forces_serial` with the material effects (state updated according to *mode*)."""
    n = x.shape[0]
    for a in range(n):
        f[a, 0] = fext[a, 0]
        f[a, 1] = fext[a, 1]
        f[a, 2] = fext[a, 2]
    hbuf = np.empty((0, 3))
    _range_forces_fx(0, ij.shape[1], n, 0, x, v, f, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                     hbuf, False, etab, fxp, ab, h, pold, wmax, ximax, mode)


@njit(**_OPTS)
def _chunk_forces_fx(c, x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                     node_start, spring_start, halo_start, hbuf, etab, fxp, ab, h, pold, wmax, ximax, mode):
    # A spring's state is written only by the chunk that owns the spring: race-free.
    lo = node_start[c]
    hi = node_start[c + 1]
    for a in range(lo, hi):
        f[a, 0] = fext[a, 0]
        f[a, 1] = fext[a, 1]
        f[a, 2] = fext[a, 2]
    _range_forces_fx(spring_start[c], spring_start[c + 1], hi, halo_start[c], x, v, f, ij, sd, tab, lam_min,
                     inv_h, last_cell, law, damped, hbuf, True, etab, fxp, ab, h, pold, wmax, ximax, mode)


@njit(**_OPTS)
def forces_any(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
               fx_on, etab, fxp, ab, h, pold, wmax, ximax, mode):
    """The plain force pass, or the effects pass when *fx_on* (used by FIRE)."""
    if fx_on:
        forces_serial_fx(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                         etab, fxp, ab, h, pold, wmax, ximax, mode)
    else:
        forces_serial(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped)


# ---------------------------------------------------------------------------
# grasper path
# ---------------------------------------------------------------------------

@njit(**_OPTS)
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


@njit(inline="always", **_OPTS)
def _grasp_forces(f, x, g_nodes, g_off, g_k, tip, mode, out):
    """Add the coupling springs (mode SPRING); put the force on the grasper in *out*."""
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    for q in range(g_nodes.shape[0]):
        a = g_nodes[q]
        if mode == GRASP_SPRING:
            for d in range(3):
                fs = g_k[q] * (tip[d] + g_off[q, d] - x[a, d])
                f[a, d] += fs
                out[d] -= fs
        else:  # prescribed: the pull of the tissue (springs + weight) on the held nodes
            for d in range(3):
                out[d] += f[a, d]


@njit(inline="always", **_OPTS)
def _place_grasped(x, v, g_nodes, g_off, tip, tip_v):
    for q in range(g_nodes.shape[0]):
        a = g_nodes[q]
        for d in range(3):
            x[a, d] = tip[d] + g_off[q, d]
            v[a, d] = tip_v[d]


@njit(inline="always", **_OPTS)
def _integrate_range(lo, hi, dt, x, v, f, inv_mass, vfac):
    for a in range(lo, hi):
        s = dt * inv_mass[a]
        v[a, 0] = (v[a, 0] + s * f[a, 0]) * vfac
        v[a, 1] = (v[a, 1] + s * f[a, 1]) * vfac
        v[a, 2] = (v[a, 2] + s * f[a, 2]) * vfac
        x[a, 0] += dt * v[a, 0]
        x[a, 1] += dt * v[a, 1]
        x[a, 2] += dt * v[a, 2]


@njit(inline="always", **_OPTS)
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


@njit(inline="always", **_OPTS)
def _integrate_any(lo, hi, dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    if fl_on:
        _integrate_range_floor(lo, hi, dt, x, v, f, inv_mass, vfac, fl_n, fl_h, fl_stick, fl_mask, contact)
    else:
        _integrate_range(lo, hi, dt, x, v, f, inv_mass, vfac)


# ---------------------------------------------------------------------------
# time stepping (symplectic Euler)
# ---------------------------------------------------------------------------

@njit(**_OPTS)
def run_serial(nsteps, dt, t0, step0, x, v, f, fext, inv_mass, vfac,
               ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
               g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec,
               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    """Advance *nsteps* semi-implicit Euler steps on one thread.

    Step k (time ``t = t0 + (step0 + k) * dt``): forces at (x, v); the force on
    the grasper goes to ``rec[k]``; ``v <- (v + dt f / m) * vfac`` (``vfac =
    1 / (1 + alpha dt)``: implicit mass-proportional damping), ``x <- x + dt
    v``. Nodes with ``inv_mass = 0`` keep ``v = 0`` (fixed) unless grasped in
    prescribed mode: those are put on the path at ``t + dt``.
    """
    n = x.shape[0]
    out = np.zeros(3)
    for k in range(nsteps):
        t = t0 + (step0 + k) * dt
        forces_serial(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped)
        if g_mode != GRASP_NONE:
            tip, tip_v = tip_state(t, wp_t, wp_x)
            _grasp_forces(f, x, g_nodes, g_off, g_k, tip, g_mode, out)
            rec[k, 0] = out[0]
            rec[k, 1] = out[1]
            rec[k, 2] = out[2]
        _integrate_any(0, n, dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        if g_mode == GRASP_PRESCRIBED:
            tip, tip_v = tip_state(t0 + (step0 + k + 1) * dt, wp_t, wp_x)
            _place_grasped(x, v, g_nodes, g_off, tip, tip_v)


@njit(parallel=True, **_OPTS)
def run_parallel(nsteps, dt, t0, step0, x, v, f, fext, inv_mass, vfac,
                 ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                 g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec,
                 fl_on, fl_n, fl_h, fl_stick, fl_mask, contact,
                 node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node):
    """:func:`run_serial` with the race-free owner/halo threading (same arithmetic)."""
    nchunk = node_start.shape[0] - 1
    out = np.zeros(3)
    for k in range(nsteps):
        t = t0 + (step0 + k) * dt
        for c in prange(nchunk):
            _chunk_forces(c, x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                          node_start, spring_start, halo_start, hbuf)
        if g_mode != GRASP_NONE:
            # The grasped nodes' halo contributions must be in before the force on the
            # grasper is read: apply all halos, read, then integrate.
            for c in prange(nchunk):
                _apply_halo(c, f, own_start, own_slot, own_node, hbuf)
            tip, tip_v = tip_state(t, wp_t, wp_x)
            _grasp_forces(f, x, g_nodes, g_off, g_k, tip, g_mode, out)
            rec[k, 0] = out[0]
            rec[k, 1] = out[1]
            rec[k, 2] = out[2]
            for c in prange(nchunk):
                _integrate_any(node_start[c], node_start[c + 1], dt, x, v, f, inv_mass, vfac,
                               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        else:
            for c in prange(nchunk):
                _apply_halo(c, f, own_start, own_slot, own_node, hbuf)
                _integrate_any(node_start[c], node_start[c + 1], dt, x, v, f, inv_mass, vfac,
                               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        if g_mode == GRASP_PRESCRIBED:
            tip, tip_v = tip_state(t0 + (step0 + k + 1) * dt, wp_t, wp_x)
            _place_grasped(x, v, g_nodes, g_off, tip, tip_v)


@njit(**_OPTS)
def run_serial_fx(nsteps, dt, dt_first, t0, step0, x, v, f, fext, inv_mass, vfac,
                  ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                  etab, fxp, h, pold, wmax, ximax,
                  g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec,
               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    """:func:`run_serial` with the material effects: every step advances each spring's state.

    The state is advanced by *dt_first* at the first step (the time since the
    state was last committed) and by *dt* afterwards.
    """
    n = x.shape[0]
    out = np.zeros(3)
    nt = int(fxp[1])
    ab = np.empty((2, nt))
    prony_ab(fxp, dt_first, ab)
    for k in range(nsteps):
        t = t0 + (step0 + k) * dt
        if k == 1:
            prony_ab(fxp, dt, ab)
        forces_serial_fx(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                         etab, fxp, ab, h, pold, wmax, ximax, FX_STEP)
        if g_mode != GRASP_NONE:
            tip, tip_v = tip_state(t, wp_t, wp_x)
            _grasp_forces(f, x, g_nodes, g_off, g_k, tip, g_mode, out)
            rec[k, 0] = out[0]
            rec[k, 1] = out[1]
            rec[k, 2] = out[2]
        _integrate_any(0, n, dt, x, v, f, inv_mass, vfac, fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        if g_mode == GRASP_PRESCRIBED:
            tip, tip_v = tip_state(t0 + (step0 + k + 1) * dt, wp_t, wp_x)
            _place_grasped(x, v, g_nodes, g_off, tip, tip_v)


@njit(parallel=True, **_OPTS)
def run_parallel_fx(nsteps, dt, dt_first, t0, step0, x, v, f, fext, inv_mass, vfac,
                    ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                    etab, fxp, h, pold, wmax, ximax,
                    g_mode, g_nodes, g_off, g_k, wp_t, wp_x, rec,
                    fl_on, fl_n, fl_h, fl_stick, fl_mask, contact,
                    node_start, spring_start, halo_start, hbuf, own_start, own_slot, own_node):
    """:func:`run_parallel` with the material effects (same arithmetic as :func:`run_serial_fx`)."""
    nchunk = node_start.shape[0] - 1
    out = np.zeros(3)
    nt = int(fxp[1])
    ab = np.empty((2, nt))
    prony_ab(fxp, dt_first, ab)
    for k in range(nsteps):
        t = t0 + (step0 + k) * dt
        if k == 1:
            prony_ab(fxp, dt, ab)
        for c in prange(nchunk):
            _chunk_forces_fx(c, x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, damped,
                             node_start, spring_start, halo_start, hbuf, etab, fxp, ab, h, pold, wmax, ximax,
                             FX_STEP)
        if g_mode != GRASP_NONE:
            for c in prange(nchunk):
                _apply_halo(c, f, own_start, own_slot, own_node, hbuf)
            tip, tip_v = tip_state(t, wp_t, wp_x)
            _grasp_forces(f, x, g_nodes, g_off, g_k, tip, g_mode, out)
            rec[k, 0] = out[0]
            rec[k, 1] = out[1]
            rec[k, 2] = out[2]
            for c in prange(nchunk):
                _integrate_any(node_start[c], node_start[c + 1], dt, x, v, f, inv_mass, vfac,
                               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        else:
            for c in prange(nchunk):
                _apply_halo(c, f, own_start, own_slot, own_node, hbuf)
                _integrate_any(node_start[c], node_start[c + 1], dt, x, v, f, inv_mass, vfac,
                               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact)
        if g_mode == GRASP_PRESCRIBED:
            tip, tip_v = tip_state(t0 + (step0 + k + 1) * dt, wp_t, wp_x)
            _place_grasped(x, v, g_nodes, g_off, tip, tip_v)


# ---------------------------------------------------------------------------
# quasi-static relaxation (FIRE)
# ---------------------------------------------------------------------------

@njit(**_OPTS)
def fire_relax(x, v, f, fext, inv_mass, free, ij, sd, tab, lam_min, inv_h, last_cell, law,
               g_mode, g_nodes, g_off, g_k, tip, dt0, dt_max, ftol, max_iter,
               fx_on, etab, fxp, ab, h, pold, wmax, ximax,
               fl_on, fl_n, fl_h, fl_stick, fl_mask, contact):
    """FIRE minimisation (Bitzek et al. 2006) of the network energy under fext.

    Uses the dynamics' force pass (without dashpots) and a mass-weighted
    semi-implicit Euler MD step; grasper coupling springs (mode SPRING) pull
    the held nodes to ``tip + g_off``. Converged when the largest residual force
    on a free node is below *ftol* [N]. Returns (iterations, final max residual);
    iterations = -1 when the forces became non-finite. With *fx_on* the material
    effects' long-term force (mode :data:`FX_RELAXED`, state unchanged) is used.

    With *fl_on* the rigid floor of :func:`_integrate_range_floor` constrains
    the nodes with ``fl_mask``: each MD update puts the nodes that end below
    the plane back on it (same rule as the dynamics, "stick" or "slip"), and
    for a node in contact (``contact[a]``, set by the last update) whose force
    presses into the floor the floor's reaction is taken off the force used
    by FIRE and by the convergence test (the normal part with "slip", all of it
    with "stick": sticking friction carries any tangential load).
    """
    n = x.shape[0]
    n_min = 5
    f_inc = 1.1
    f_dec = 0.5
    alpha_start = 0.1
    f_alpha = 0.99
    alpha = alpha_start
    dt = dt0
    since_neg = 0
    for a in range(n):
        for d in range(3):
            v[a, d] = 0.0
    resid = np.inf
    out = np.zeros(3)
    for it in range(max_iter):
        forces_any(x, v, f, fext, ij, sd, tab, lam_min, inv_h, last_cell, law, False,
                   fx_on, etab, fxp, ab, h, pold, wmax, ximax, FX_RELAXED)
        if g_mode == GRASP_SPRING:
            _grasp_forces(f, x, g_nodes, g_off, g_k, tip, g_mode, out)
        if fl_on:
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
        resid = np.sqrt(resid)
        if not np.isfinite(resid):
            return -1, resid
        if resid < ftol:
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
            if since_neg > n_min:
                dt = min(dt * f_inc, dt_max)
                alpha *= f_alpha
        else:
            since_neg = 0
            dt *= f_dec
            alpha = alpha_start
            for a in range(n):
                for d in range(3):
                    v[a, d] = 0.0
        if fl_on:
            for a in range(n):
                if free[a] and not fl_mask[a]:
                    s = dt * inv_mass[a]
                    for d in range(3):
                        v[a, d] += s * f[a, d]
                        x[a, d] += dt * v[a, d]
            # the floor's nodes: same update, then the contact rule (vfac = 1)
            _integrate_masked_floor(n, dt, x, v, f, inv_mass, free, fl_n, fl_h, fl_stick, fl_mask, contact)
        else:
            for a in range(n):
                if free[a]:
                    s = dt * inv_mass[a]
                    for d in range(3):
                        v[a, d] += s * f[a, d]
                        x[a, d] += dt * v[a, d]
    return max_iter, resid


@njit(**_OPTS)
def _integrate_masked_floor(n, dt, x, v, f, inv_mass, free, fl_n, fl_h, fl_stick, fl_mask, contact):
    """FIRE's MD update of the free nodes under the floor (``fl_mask``), with the contact rule."""
    for a in range(n):
        if free[a] and fl_mask[a]:
            _integrate_range_floor(a, a + 1, dt, x, v, f, inv_mass, 1.0, fl_n, fl_h, fl_stick, fl_mask, contact)


# ---------------------------------------------------------------------------
# diagnostics
# ---------------------------------------------------------------------------

@njit(**_OPTS)
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


@njit(**_OPTS)
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


@njit(**_OPTS)
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
