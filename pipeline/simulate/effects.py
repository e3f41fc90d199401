r"""Material effects in the simulator: QLV viscoelasticity, Mullins softening, damage.

The material effects kept by ``esmm calibrate --discover``
(:class:`~esmm.pipeline.materials.effects.MaterialEffects`, stored in the asset's
``/material/effects``) act on each spring's elastic force
:math:`F_e = \sum_d w_d f_d(\lambda)` exactly as they act on the nominal stress
of the tensile test they were fitted to (docs/design/discovery.md, "The extended model"; composition
:math:`P = \mathrm{QLV}[(1-D)\,\eta\,P_e]`):

.. math::

    P = (1 - D(\xi_{max}))\;\eta(W, W_{max})\;F_e, \qquad
    F = g_\infty P + \sum_i g_i h_i, \qquad
    h_i \leftarrow e^{-\Delta t/\tau_i} h_i + \frac{\tau_i}{\Delta t}\bigl(1 - e^{-\Delta t/\tau_i}\bigr)
        (P - P_{old}),

with, per spring, :math:`W` the material's uniaxial strain energy density at the
spring's stretch (:math:`W(\lambda) = \int_1^\lambda P_{uni}`, the same energy
the Mullins parameters were fitted with), :math:`\xi` the uniaxial-equivalent
stretch of the spring's stretch (:math:`\lambda` in tension; the tension
stretch with the same :math:`I_1` as uniaxial compression by :math:`\lambda`
otherwise), and :math:`W_{max}`, :math:`\xi_{max}` their largest values so far.
The tables hold the *instantaneous* response (:math:`G(0) = 1`); the long-term
response is :math:`g_\infty` times it.

:class:`EffectModel` holds the compiled kernels' parameters and tables (part of
the spring term, constant); :class:`EffectState` the per-spring state (``h``
(nt, s), ``pold``, ``wmax``, ``ximax`` (s,), in the spring term's order) and the
time it refers to (part of the simulation's state).

Stability. The instantaneous tangent of a QLV spring is
:math:`(g_\infty + \sum g_i b_i)\,P' \le P'` and damage lowers it, so the elastic
bound holds for those; two terms are added where they are not covered:

* Mullins: on reloading below :math:`W_{max}` the force rises from
  :math:`(1 - 1/r)P_e` back to :math:`P_e` over an energy range of about
  :math:`m`, a tangent up to :math:`\frac{2}{\sqrt\pi\,r\,m}|F_e|\,|W'|` above
  the elastic one. It is bounded per table cell and enters the cell (and
  window, and whole-table) bounds of :mod:`.springterm`.
* Viscoelastic history forces :math:`\sum g_i h_i` are not functions of the
  current length; their geometric stiffness :math:`F/L` is bounded per frame
  from the state (:meth:`EffectModel.history_stiffness`) and, for the
  whole-table bound, by :math:`2\sum g_i \max|f_d| / \lambda_{min}`
  (:math:`|h_i| \le 2\max|P|`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..materials.effects import MaterialEffects, equivalent_stretch
from . import kernels as K

__all__ = ["EffectModel", "EffectState", "build_effect_model", "effects_of_material"]


def effects_of_material(material) -> Any:
    """The :class:`MaterialEffects` of a ``Material`` (its ``metadata["effects"]``), or None.

    Raises
    ------
    ConfigError
        The ``[material.effects]`` table is malformed (one line naming the effect).
    """
    if material is None:
        return None
    table = (getattr(material, "metadata", None) or {}).get("effects")
    if not table:
        return None
    fx = MaterialEffects.from_toml_table(table, stress_unit=getattr(material, "stress_unit", None),
                                         where=f"{getattr(material, 'name', '') or 'material'} [material.effects]")
    return fx if fx else None


@dataclass
class EffectState:
    """Per-spring state of the material effects (spring term order).

    Attributes
    ----------
    h : ndarray, shape (nt, s)
        Prony internal variables [N].
    pold : ndarray, shape (s,)
        Softened elastic force at the last committed evaluation [N].
    wmax : ndarray, shape (s,)
        Largest energy density so far [Pa] (Mullins).
    ximax : ndarray, shape (s,)
        Largest uniaxial-equivalent stretch so far (damage).
    t : float
        Time of the last committed evaluation [s].
    """

    h: np.ndarray
    pold: np.ndarray
    wmax: np.ndarray
    ximax: np.ndarray
    t: float = 0.0

    def copy(self) -> EffectState:
        return EffectState(self.h.copy(), self.pold.copy(), self.wmax.copy(), self.ximax.copy(), self.t)

    def assign(self, other: EffectState) -> None:
        """Overwrite this state in place with *other* (arrays keep their identity)."""
        self.h[...] = other.h
        self.pold[...] = other.pold
        self.wmax[...] = other.wmax
        self.ximax[...] = other.ximax
        self.t = other.t

    def arrays(self) -> tuple:
        return (self.h, self.pold, self.wmax, self.ximax)


@dataclass
class EffectModel:
    """The effects' parameters and tables for the compiled kernels.

    Attributes
    ----------
    effects : MaterialEffects
    fxp : ndarray, shape (10 + 2 nt,)
        Kernel parameters (layout in :mod:`.kernels`).
    etab : ndarray, shape (n_cells, 8)
        Per cell: the material's uniaxial energy density per direction ``[W_x, W_y,
        W_z, dW_x, dW_y, dW_z]`` [Pa] (Mullins) and the uniaxial-equivalent stretch
        ``[xi, dxi]`` at the cell's left node with its increment (damage; linear
        in the cell, exact at the nodes, for lam >= 1 and below the grid).
    g, tau : ndarray, shape (nt,)
        Prony weights and times [s] (empty without viscoelasticity).
    mullins_cell : ndarray, shape (n_cells, 3) or None
        Added tangent bound per cell and direction [Pa] (per unit spring weight).
    history_table : ndarray, shape (3,)
        Whole-table bound of the history forces' geometric stiffness per direction [Pa].
    """

    effects: Any
    fxp: np.ndarray
    etab: np.ndarray
    g: np.ndarray
    tau: np.ndarray
    mullins_cell: np.ndarray | None = None
    history_table: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_terms(self) -> int:
        return int(self.g.size)

    @property
    def g_inf(self) -> float:
        return float(self.fxp[0])

    @property
    def names(self) -> list[str]:
        return list(self.effects.names)

    def new_state(self, n_springs: int, *, t: float = 0.0) -> EffectState:
        """The virgin state: no history, maxima at rest (W = 0, xi = 1)."""
        s = int(n_springs)
        return EffectState(np.zeros((self.n_terms, s)), np.zeros(s), np.zeros(s), np.ones(s), float(t))

    def ab(self, dt: float) -> np.ndarray:
        """(2, nt) Prony step factors a_i, b_i for a step *dt* [s]."""
        out = np.empty((2, self.n_terms))
        K.prony_ab(self.fxp, float(dt), out)
        return out

    def kernel(self, state: EffectState, *, mode: int, dt: float = 0.0) -> K.EffectKernel:
        """The kernels' tuple: tables, the Prony factors of a step *dt*, *state*'s arrays, *mode*."""
        return K.EffectKernel(self.etab, self.fxp, self.ab(dt), *state.arrays(), int(mode))

    def history_stiffness(self, state: EffectState, lam: np.ndarray, rest_length: np.ndarray,
                          delta: float) -> np.ndarray:
        """Per-spring bound of the history forces' geometric stiffness [N/m], shape (s,).

        ``sum_i g_i (|h_i| + |P_old|) / (L0 max(lam - delta, 0.05))``: with
        ``h_i' = a h_i + b (P - P_old)``, the total force exceeds the elastic
        one (covered by the elastic bound) by at most ``sum_i g_i (|h_i| +
        |P_old|)``, at any stretch within *delta* of *lam*.
        """
        if self.n_terms == 0:
            return np.zeros_like(lam)
        q = np.abs(state.h).T @ self.g + self.g.sum() * np.abs(state.pold)
        return q / (rest_length * np.maximum(lam - delta, 0.05))

    def report(self, state: EffectState) -> dict:
        """Extremes of *state* (JSON-ready): the largest history and elastic forces, energy density,
        equivalent stretch, remaining fraction and damaged springs, as the effects present have them."""
        out: dict = {"effects": self.names}
        if self.n_terms:
            q = np.abs(state.h).T @ self.g
            out["max_history_force_N"] = float(q.max()) if q.size else 0.0
            out["max_elastic_force_N"] = float(np.abs(state.pold).max()) if state.pold.size else 0.0
        if self.effects.mullins is not None:
            out["max_energy_density_Pa"] = float(state.wmax.max()) if state.wmax.size else 0.0
        if self.effects.damage is not None:
            xi = float(state.ximax.max()) if state.ximax.size else 1.0
            out["max_equivalent_stretch"] = xi
            out["min_remaining_fraction"] = float(self.effects.damage.factor(np.array([xi]))[0])
            out["damaged_springs"] = int(np.count_nonzero(state.ximax > self.effects.damage.onset))
        return out

    def explain(self) -> str:
        """One line naming the effects and their parameters (for the run's report)."""
        e = self.effects
        parts = []
        if e.viscoelastic is not None:
            v = e.viscoelastic
            parts.append("viscoelastic (QLV, " + ", ".join(f"g {g:.3g} tau {t:.3g} s" for g, t in zip(v.g, v.tau))
                         + f"; long-term {v.g_inf:.3g} of the instantaneous response)")
        if e.mullins is not None:
            parts.append(f"Mullins (r {e.mullins.r:.3g}, m {e.mullins.m:.3g} Pa, beta {e.mullins.beta:.3g})")
        if e.damage is not None:
            parts.append(f"damage (onset {e.damage.onset:.3g}, scale {e.damage.scale:.3g}, "
                         f"shape {e.damage.shape:.3g}" + (f", floor {e.damage.floor:.3g})" if e.damage.floor else ")"))
        return "; ".join(parts) + " per spring"

    def describe(self) -> dict:
        """JSON-ready description for the run's summary and history."""
        d = dict(self.effects.to_dict())
        d.pop("intervals", None)
        d["state_per_spring"] = self.effects.state_variables()
        d["g_inf"] = self.g_inf
        return d


def _material_energy(tables) -> np.ndarray:
    """W(lam) = integral from 1 of the material's uniaxial stress (uncorrected), shape (3, n) [Pa]."""
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    stress = np.asarray(tables.material_stress, dtype=np.float64)
    h = lam[1] - lam[0]
    cum = np.concatenate([np.zeros((3, 1)), np.cumsum(0.5 * (stress[:, 1:] + stress[:, :-1]) * h, axis=1)], axis=1)
    # the integral up to lam = 1 (interpolated stress within its cell: exact for linear stress)
    i = int(np.clip(np.floor((1.0 - lam[0]) / h), 0, lam.size - 2))
    t = (1.0 - lam[i]) / h
    s1 = stress[:, i] + t * (stress[:, i + 1] - stress[:, i])
    c1 = cum[:, i] + 0.5 * (stress[:, i] + s1) * (1.0 - lam[i])
    return cum - c1[:, None]


def _law_rows(tables, law: str) -> np.ndarray:
    """f_d on the grid, shape (3, n): secant mu_e (lam - 1), energy the stress [Pa]."""
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    if law == "secant":
        return np.asarray(tables.values, dtype=np.float64) * (lam - 1.0)
    return np.asarray(tables.stress, dtype=np.float64)


def build_effect_model(effects, tables, law: str) -> EffectModel | None:
    """Kernel parameters and bounds of *effects* (a MaterialEffects, None or empty: None).

    Parameters
    ----------
    effects : MaterialEffects or None
    tables : StiffnessTables
        The (instantaneous) stiffness tables the network uses.
    law : {"secant", "energy"}

    Raises
    ------
    ConfigError
        An effect the simulator cannot apply.
    """
    if effects is None or not effects:
        return None
    unknown = [n for n in effects.names if n not in ("viscoelastic", "mullins", "damage")]
    if unknown:
        raise ConfigError(f"material effects: the simulator cannot apply {unknown[0]!r}")
    v, mu, da = effects.viscoelastic, effects.mullins, effects.damage
    if v is not None and float(getattr(v, "kappa", 0.0)) != 0.0:
        # The kernels advance Fung's QLV (kappa = 0); applying it instead would drop a fitted effect silently.
        raise ConfigError(f"material effects: the simulator cannot apply stretch-dependent relaxation "
                          f"(viscoelastic kappa = {float(v.kappa):g}), only QLV (kappa = 0)")
    if v is not None and float(getattr(v, "kappa_tau", 0.0)) != 0.0:
        raise ConfigError(f"material effects: the simulator cannot apply stretch-dependent relaxation times "
                          f"(viscoelastic kappa_tau = {float(v.kappa_tau):g}), only QLV (kappa_tau = 0)")
    g = np.asarray(v.g if v is not None else (), dtype=np.float64)
    tau = np.asarray(v.tau if v is not None else (), dtype=np.float64)
    g_inf = float(v.g_inf) if v is not None else 1.0
    head = [g_inf, float(g.size),
            1.0 if mu is not None else 0.0, (1.0 / mu.r) if mu is not None else 0.0,
            mu.m if mu is not None else 1.0, mu.beta if mu is not None else 0.0,
            1.0 if da is not None else 0.0, da.onset if da is not None else 1.0,
            da.scale if da is not None else 1.0, da.shape if da is not None else 1.0,
            da.floor if da is not None else 0.0]
    assert len(head) == K.FXP_HEAD
    fxp = np.ascontiguousarray(np.concatenate([head, g, tau]), dtype=np.float64)
    W = _material_energy(tables)
    lam = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    xi = np.where(lam >= 1.0, lam, equivalent_stretch(lam**2 + 2.0 / lam))
    etab = np.ascontiguousarray(np.concatenate([W[:, :-1].T, np.diff(W, axis=1).T, xi[:-1, None],
                                                np.diff(xi)[:, None]], axis=1))
    f = _law_rows(tables, law)
    mull = None
    if mu is not None:
        a = np.maximum(np.abs(f[:, :-1]), np.abs(f[:, 1:]))                       # (3, cells) sup |f_d|
        s = np.asarray(tables.material_stress, dtype=np.float64)
        b = np.maximum(np.abs(s[:, :-1]), np.abs(s[:, 1:])).max(axis=0)            # (cells,) sup |W'|
        coef = 2.0 / (math.sqrt(math.pi) * mu.r * mu.m)
        mull = np.ascontiguousarray((coef * a * b[None, :]).T)
    hist = np.zeros(3)
    if g.size:
        hist = 2.0 * float(g.sum()) * np.abs(f).max(axis=1) / max(float(tables.lam_min), 0.05)
    return EffectModel(effects=effects, fxp=fxp, etab=etab, g=g, tau=tau, mullins_cell=mull, history_table=hist)
