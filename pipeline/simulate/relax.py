"""Quasi-static equilibrium (FIRE) and the settling of the material effects' state.

:func:`relax` moves a :class:`~.model.State` to the static equilibrium of its
:class:`~.model.Model` under gravity (and a held grasp, at its current tip)
with FIRE (Bitzek et al., PRL 97, 170201, 2006) on the same force pass as the
dynamics (:func:`~.kernels.fire_relax`). With material effects this is the
*long-term* equilibrium (forces ``g_inf (1 - D) eta F_e`` with the maxima so
far), after which the history is taken as relaxed there (:func:`settle_effects`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import __version__
from ..atomicio import atomic_path
from ..cache import digest
from ..errors import SimulationError
from ..progress import Reporter, ensure
from . import kernels as K
from .kernels import Nodes, fire_relax
from .model import Control, Model, State

#: FIRE iterations per kernel call: the progress shown moves this often (about a second on an organ).
CHUNK = 2000


class RelaxNotConverged(SimulationError):
    """FIRE stopped at ``max_iter`` above the tolerance (not diverged). ``summary`` is the message without
    its advice, which names :func:`relax`'s own parameters, for a caller that offers other ways out."""

    def __init__(self, summary: str, advice: str):
        super().__init__(f"{summary}; {advice}")
        self.summary = summary


def settle_effects(model: Model, state: State) -> None:
    """Take the current configuration as long held: maxima updated, history relaxed (h = 0).

    Called after a static equilibrium: the organ has rested in it long enough
    for every Prony term to relax. No-op without effects.
    """
    if state.effects is None:
        return
    model.springs.forces(state.x, state=state.effects, mode=K.FX_SETTLE)
    state.effects.t = state.t


def relax(model: Model, state: State, control: Control, *, dt_critical: float, ftol: float | None = None,
          rtol: float = 1e-8, max_iter: int = 200_000, reporter: Reporter | None = None,
          cache: Path | None = None) -> dict:
    """Move *state* to static equilibrium under gravity (and a held grasp, at its current tip).

    Parameters
    ----------
    model, state, control
        The simulation; ``state.x`` moves, ``state.v`` ends at zero, the
        effect state is settled (:func:`settle_effects`).
    dt_critical : float
        The stability bound of the dynamics [s]: FIRE's MD step starts at 0.2
        and is capped at 0.9 times it.
    ftol : float, optional
        Largest residual force on a free node [N]; default ``rtol`` times
        the largest external force on a node (or times the largest spring
        force scale when there is no gravity).
    rtol : float
    max_iter : int
    reporter : Reporter, optional
        Shown a task whose progress is the residual's way down to *ftol*
        (log scale), advanced every :data:`CHUNK` iterations; the path is
        the same as without it.
    cache : Path, optional
        A folder of converged equilibria (:mod:`esmm.pipeline.cache`) named
        by the digest of everything FIRE is given (state, model, control,
        steps, tolerance) and of its code: the same inputs a second time
        take the stored state instead of FIRE's iterations, which is what
        FIRE would find again (it is deterministic: serial, one chunk).

    Returns
    -------
    dict with ``iterations``, ``residual`` [N], ``ftol`` [N] and ``cached``
    (taken from *cache*).

    Raises
    ------
    SimulationError
        The forces became non-finite, or no convergence within *max_iter*.
    """
    springs = model.springs
    free = control.free
    if ftol is None:
        scale = float(np.abs(model.fext[free]).max()) if free.any() else 0.0
        if scale == 0.0:
            scale = float(np.median(springs.rest_tangent / springs.sd[0])) or 1.0
        ftol = rtol * scale
    g = control.grasp
    tip = g.tip(state.t) if g is not None and g.mode == "spring" else np.zeros(3)
    fx = None if state.effects is None else springs.effects.kernel(state.effects, mode=K.FX_RELAXED)
    if model.floor is not None:
        state.contact[:] = (model.floor.distance(state.x) <= 0.0) & (control.floor_mask > 0)
    nodes = Nodes(state.x, state.v, np.zeros_like(state.x), model.fext, control.inv_mass)
    args = (nodes, free, springs.kernel(damped=False), fx, springs.layout(1), control.grasp_kernel(), tip,
            control.floor_kernel(model, state), 0.2 * dt_critical, 0.9 * dt_critical, float(ftol))
    vt = model.volume_kernel()
    key = None if cache is None else digest(_code(), args, int(max_iter), vt)
    info = None if key is None else _load(cache, key, state)
    if info is None:
        with ensure(reporter).task("equilibrium under gravity (FIRE)", total=1.0) as advance:
            it, res = _fire_chunks(args, int(max_iter), vt, float(ftol), advance)
        info = {"iterations": int(it), "residual": float(res), "ftol": float(ftol), "cached": False}
        if 0 <= it and res < ftol and key is not None:
            _store(cache, key, state, info)
    state.v[:] = 0.0
    settle_effects(model, state)
    it, res = info["iterations"], info["residual"]
    if it < 0 or not np.isfinite(res):
        raise SimulationError("quasi-static relaxation diverged (non-finite forces); check the asset")
    if res >= ftol:
        raise RelaxNotConverged(f"quasi-static relaxation did not converge in {max_iter} iterations "
                                f"(residual {res:.3g} N > {ftol:.3g} N)", "raise max_iter or the tolerance")
    return info


def _fire_chunks(args: tuple, max_iter: int, vt, ftol: float, advance) -> tuple[int, float]:
    """:func:`~.kernels.fire_relax` in calls of :data:`CHUNK` iterations (the same path as one call),
    *advance* told the residual's share of its way down to *ftol* (log scale); (iterations, residual)."""
    fs = np.zeros(4)
    done, shown, r0 = 0, 0.0, None
    while True:
        n = min(1 if r0 is None else CHUNK, max_iter - done)
        it, res = fire_relax(*args, n, fs, vt)
        if it < 0:
            return it, res
        done += it
        if it < n or done >= max_iter:
            advance(1.0 - shown)
            return done, res
        if r0 is None:
            r0 = res
        elif r0 > ftol and res < r0:
            share = min(1.0, math.log(r0 / res) / math.log(r0 / ftol))
            if share > shown:
                advance(share - shown)
                shown = share


def _code() -> tuple:
    """What of the code decides FIRE's result: its kernels' and this module's source, the versions."""
    import numba

    here = Path(__file__).resolve().parent
    return (__version__, np.__version__, numba.__version__,
            *((here / name).read_bytes() for name in ("kernels.py", "relax.py")))


def _load(cache: Path, key: str, state: State) -> dict | None:
    """The stored equilibrium *key* put into *state* (x, contacts); its record, or None (a miss: missing,
    unreadable or not of this state's shape)."""
    try:
        with np.load(cache / f"{key}.npz", allow_pickle=False) as z:
            x, contact = z["x"], z["contact"]
            info = {"iterations": int(z["iterations"]), "residual": float(z["residual"]), "ftol": float(z["ftol"])}
    except (OSError, KeyError, ValueError):
        return None
    if x.shape != state.x.shape or contact.shape != state.contact.shape:
        return None
    state.x[:] = x
    state.contact[:] = contact
    return {**info, "cached": True}


def _store(cache: Path, key: str, state: State, info: dict) -> None:
    """Keep a converged equilibrium under *key*; a cache that cannot be written only costs time."""
    try:
        with atomic_path(cache / f"{key}.npz") as tmp, open(tmp, "wb") as fh:
            np.savez(fh, x=state.x, contact=state.contact, iterations=info["iterations"],
                     residual=info["residual"], ftol=info["ftol"])
    except OSError:
        pass
