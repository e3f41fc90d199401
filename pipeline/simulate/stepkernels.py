r"""Compiled (numba) time stepping: the step loop, the grasper, the floor and FIRE.

The step loop is written once (:func:`_steps`) and compiled twice: on one
thread (``steps_serial``: ``prange`` is ``range``, one chunk) and on numba's
threads (``steps_parallel``, the owner/halo layout of :mod:`.kernels`). Both
variants exist with and without material effects (``fx`` None or an
:class:`~.kernels.EffectKernel`, decided at compile time). Arguments come in
a few tuples:

* :class:`Clock` ``(n, dt, t0, step0, dt_first, vfac)``: how many steps, the
  step, the time origin and the step count from it (step ``k`` is at
  ``t0 + (step0 + k) dt``), the time the effects' state must first advance
  by, and the implicit mass-damping factor ``1 / (1 + alpha dt)``;
* :class:`Nodes` ``(x, v, f, fext, inv_mass)``;
* :class:`~.kernels.SpringKernel`, the effects (None or
  :class:`~.kernels.EffectKernel`) and the :class:`~.kernels.Layout`;
* :class:`GraspKernel` ``(mode, nodes, offsets, stiffness, wp_t, wp_x)``;
* :class:`FloorKernel` ``(on, normal, height, stick, mask, contact)``.

Symplectic Euler with implicit mass damping (docs/simulate.md §2)::

    f_n = f(x_n, v_n) + f_ext
    v_{n+1} = (v_n + dt f_n / m) / (1 + alpha dt),   x_{n+1} = x_n + dt v_{n+1}
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .kernels import JIT_OPTIONS, apply_halo, chunk_forces, forces_serial, prony_ab, twin

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

def _steps(clock, nodes, sp, fx, grasp, floor, lay, rec):
    """Advance ``clock.n`` semi-implicit Euler steps.

    Step k (time ``t = t0 + (step0 + k) dt``): forces at (x, v); the force on
    the grasper goes to ``rec[k]``; ``v <- (v + dt f / m) * vfac``, ``x <- x +
    dt v``. Nodes with ``inv_mass = 0`` keep ``v = 0`` (fixed) unless grasped in
    prescribed mode: those are put on the path at ``t + dt``. With effects, the
    springs' state advances by ``dt_first`` at the first step, then by dt.
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
#: The step loop on numba's threads (same arithmetic; the owner/halo layout of :mod:`.kernels`).
steps_parallel = njit(parallel=True, **JIT_OPTIONS)(twin(_steps, "steps_parallel"))


# ---------------------------------------------------------------------------
# quasi-static relaxation (FIRE)
# ---------------------------------------------------------------------------

@njit(**JIT_OPTIONS)
def fire_relax(nodes, free, sp, fx, lay, grasp, tip, floor, dt0, dt_max, ftol, max_iter):
    """FIRE minimisation (Bitzek et al. 2006) of the network energy under fext.

    Uses the dynamics' force pass (*sp* without dashpots; one-chunk *lay*) and a
    mass-weighted semi-implicit Euler MD step; grasper coupling springs (mode
    SPRING) pull the held nodes to ``tip + offsets``. Converged when the
    largest residual force on a free node is below *ftol* [N]. Returns
    (iterations, final max residual); iterations = -1 when the forces became
    non-finite. With effects (*fx* not None) their long-term force (mode
    ``FX_RELAXED``, state unchanged) is used.

    With ``floor.on`` the rigid floor of :func:`_integrate_range_floor` constrains
    the nodes with ``floor.mask``: each MD update puts the nodes that end below
    the plane back on it (same rule as the dynamics, "stick" or "slip"), and
    for a node in contact (``floor.contact[a]``, set by the last update) whose force
    presses into the floor the floor's reaction is taken off the force used
    by FIRE and by the convergence test (the normal part with "slip", all of it
    with "stick": sticking friction carries any tangential load).
    """
    x, v, f, fext, inv_mass = nodes
    g_mode, g_nodes, g_off, g_k, wp_t, wp_x = grasp
    fl_on, fl_n, fl_h, fl_stick, fl_mask, contact = floor
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
        forces_serial(x, v, f, fext, sp, fx, lay)
        if g_mode == GRASP_SPRING:
            _grasp_forces(f, x, g_mode, g_nodes, g_off, g_k, tip, out)
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
    return max_iter, resid
