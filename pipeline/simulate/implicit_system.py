r"""One implicit step's nonlinear system: its constants, its residual and its matrices.

A step of :math:`h` from :math:`(\mathbf x_n, \mathbf v_n)` solves for
:math:`\mathbf x = \mathbf x_{n+1}` (docs/design/simulator.md, "Scheme")

.. math::

    \mathbf g(\mathbf x) = M\frac{\mathbf x - \mathbf x_n - h\mathbf v_n}{h^2}
        + \alpha M\frac{\mathbf x - \mathbf x_n}{h}
        - \mathbf f\Bigl(\mathbf x, \frac{\mathbf x - \mathbf x_n}{h}\Bigr) - \mathbf f_{ext} = 0

subject to the fixed nodes, the prescribed grasp and the floor's contacts (:mod:`.contact`).
Newton's matrix is :math:`A = M/h^2 + (\alpha M + C)/h + K(\mathbf x)`, :math:`K` the sum of the
terms' tangents and :math:`C` the dashpots' damping matrix.

:class:`StepSystem` is that problem, apart from how it is solved (:mod:`.implicit_iteration`)
and from the factor that preconditions it (:mod:`.factorcache`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps

from . import kernels as K
from .contact import FloorContact
from .implicit_stats import Threads
from .model import Control, Model, State
from .volumeterm import VolumeTerm


def effects_dt(state: State, h: float) -> float:
    """How far the springs' effect state must advance to reach the end of a step of *h* [s]."""
    fxs = state.effects
    return h if fxs is None else max(0.0, state.t + h - fxs.t)


def forces(model: Model, state: State, x: np.ndarray, v: np.ndarray, dt_fx: float,
           mode: int = K.FX_PEEK, *, threads: int = 1) -> np.ndarray:
    """Every term's force at (x, v) plus the external forces (n, 3) [N]; effects over *dt_fx*.

    On two *threads*, where the only other term is a volume term, the springs on one and the volume
    term on the other (:func:`~.kernels.forces_beside_volume`, the same sum bit for bit). The explicit
    stepper's chunked two-thread pass does not pay here: its chunks share nodes and need a halo pass.
    """
    sp = model.springs
    others = [term for term in model.terms if term is not sp]
    beside = None
    if threads > 1 and len(others) == 1 and isinstance(others[0], VolumeTerm):
        beside, others = others[0].kernel(), []
    if state.effects is None:
        f = sp.forces(x, v, fext=model.fext, beside=beside)
    else:
        f = sp.forces(x, v, fext=model.fext, state=state.effects, mode=mode, dt=dt_fx, beside=beside)
    for term in others:
        f += term.forces(x, v)
    return f


def force_scale(model: Model) -> float:
    """The largest nodal weight on a moving node [N] (the residual's scale); a spring force scale without gravity."""
    mov = model.movable
    w = float(np.linalg.norm(model.fext[mov], axis=1).max()) if mov.any() else 0.0
    if w > 0.0:
        return w
    sp = model.springs
    return 1e-3 * float(np.median(sp.rest_tangent / sp.sd[0].astype(np.float64)))


def tangent(model: Model, state: State, x: np.ndarray, dt_fx: float, *, definite: bool,
            bound: bool = False, skip: tuple = ()):
    """Sum of the terms' tangent stiffness at x (CSR (3n, 3n)); the springs' with their effect state.
    *bound*: each term's ``tangent_bound`` instead where it has one (a sparser matrix above it);
    the terms in *skip* left out."""
    sp = model.springs
    Kt = sp.tangent(x, state=state.effects, dt=dt_fx, definite=definite)
    for term in model.terms:
        if term is not sp and not any(term is k for k in skip):
            upper = getattr(term, "tangent_bound", None) if bound else None
            Kt = Kt + (upper(x) if upper is not None else term.tangent(x, definite=definite))
    return Kt


def _product(term, x: np.ndarray, definite: bool):
    """``p -> K p`` of a term's tangent at x: its matrix-free product when it has one (the volume
    term: its matrix couples nodes two tets apart), else its sparse matrix's."""
    op = getattr(term, "tangent_operator", None)
    if op is not None:
        return op(x, definite=definite)
    return term.tangent(x, definite=definite).__matmul__


@dataclass(frozen=True, eq=False)
class StepSystem:
    """One step's system (module doc): its constants and what the iterations evaluate.

    Attributes
    ----------
    model, state, control : Model, State, Control
        The state is the step's start (written only when the step is committed).
    contact : FloorContact
        The floor's active set (changes within the step).
    threads : Threads
        The run's threads (the force pass on ``threads.solve``).
    definite : bool
        Newton's matrix with each spring block made positive semi-definite.
    x0, v0 : ndarray, shape (n, 3)
        Positions [m] and velocities [m/s] at the step's start.
    h : float
        The step [s].
    t : float
        The step's start [s].
    dt_fx : float
        How far the effect state advances over the step [s] (:func:`effects_dt`).
    fixed_dof : ndarray, shape (3n,), bool
        The fixed nodes' dofs.
    mass_dof : ndarray, shape (3n,)
        ``m (1/h^2 + alpha/h)`` per dof: the inertia's and mass damping's part of Newton's matrix.
    coupling : ndarray, shape (3n,), or None
        The grasper's coupling springs' stiffness per dof (mode "spring").
    """

    model: Model
    state: State
    control: Control
    contact: FloorContact
    threads: Threads
    definite: bool
    x0: np.ndarray
    v0: np.ndarray
    h: float
    t: float
    dt_fx: float
    fixed_dof: np.ndarray
    mass_dof: np.ndarray
    coupling: np.ndarray | None

    @classmethod
    def begin(cls, model: Model, state: State, control: Control, contact: FloorContact, *,
              threads: Threads, definite: bool) -> StepSystem:
        """The system of a step of ``state.dt`` from *state*."""
        h = state.dt
        k = control.coupling_rows()
        return cls(model, state, control, contact, threads, definite, state.x.copy(), state.v.copy(), h, state.t,
                   effects_dt(state, h), np.repeat(~model.movable, 3),
                   np.repeat(model.mass * (1.0 / (h * h) + model.mass_damping / h), 3),
                   None if k is None else np.repeat(k, 3))

    @property
    def t1(self) -> float:
        """The step's end [s]."""
        return self.t + self.h

    def tolerances(self, rtol: float, xtol: float) -> tuple[float, float]:
        """(largest residual force [N], largest update of a node [m]) of a converged solve: *rtol* of the
        largest nodal weight (:func:`force_scale`), *xtol* of the organ's size."""
        model = self.model
        return rtol * force_scale(model), xtol * float(np.ptp(model.rest, axis=0).max())

    def residual(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f, g): the forces at x and the residual g (n, 3) (zero on fixed nodes)."""
        model, h, x0 = self.model, self.h, self.x0
        x = np.ascontiguousarray(x, dtype=np.float64)
        v = np.empty_like(x)
        K.step_velocity(x, x0, h, v)
        f = forces(model, self.state, x, v, self.dt_fx, threads=self.threads.solve)
        fc = self.coupling_force(x)
        if fc is not None:
            f = f + fc
        g = np.empty_like(x)
        K.step_residual(x, x0, self.v0, h, model.mass, float(model.mass_damping), f, model.movable, g)
        return f, g

    def coupling_force(self, x: np.ndarray) -> np.ndarray | None:
        """The grasper's coupling springs' forces at the step's end (mode "spring"), or None."""
        g_ = self.control.grasp
        if g_ is None or g_.mode != "spring":
            return None
        out = np.zeros_like(x)
        out[g_.nodes] = g_.stiffness[:, None] * (g_.tip(self.t1) + g_.offsets - x[g_.nodes])
        return out

    def norm(self, g: np.ndarray) -> float:
        """The largest residual force on a node that no constraint holds [N]."""
        r = g.copy()
        gr = self.control.grasp
        if gr is not None and gr.mode == "prescribed":
            r[gr.nodes] = 0.0
        held, normal = self.contact.holds()
        if held.any():
            r[held] = 0.0
        if normal.any():
            nrm = self.model.floor.normal
            r[normal] -= (r[normal] @ nrm)[:, None] * nrm
        return float(np.sqrt(np.einsum("ij,ij->i", r, r)).max()) if r.size else 0.0

    def operator(self, x: np.ndarray):
        """Newton's matrix at x as a product ``p -> A p`` (zero on fixed dofs)."""
        model, h, fixed_dof = self.model, self.h, self.fixed_dof
        sp = model.springs
        Kt = sp.tangent(x, state=self.state.effects, dt=self.dt_fx, definite=self.definite)
        others = [_product(term, x, self.definite) for term in model.terms if term is not sp]
        C = sp.damping_matrix(x) if sp.damped else None
        diag = self.mass_dof if self.coupling is None else self.mass_dof + self.coupling

        def matvec(p):
            y = Kt @ p + diag * p
            for product in others:
                y += product(p)
            if C is not None:
                y += (C @ p) / h
            y[fixed_dof] = 0.0
            return y

        return matvec

    def matrix(self, x: np.ndarray, *, bound: bool, skip: tuple = ()):
        """The matrix to factor: ``M/h^2 + (alpha M + C)/h + K(x)`` (definite springs; the terms'
        bounds where *bound*; without the terms in *skip*), identity on fixed dofs (CSR (3n, 3n))."""
        model, h = self.model, self.h
        A = tangent(model, self.state, x, self.dt_fx, definite=self.definite, bound=bound, skip=skip)
        if model.springs.damped:
            A = A + model.springs.damping_matrix(x) / h
        mov = np.repeat(model.movable, 3).astype(np.float64)
        A = sps.csr_matrix(A)
        A.data *= np.repeat(mov, np.diff(A.indptr)) * mov[A.indices]     # D A D, D = diag(mov), in place
        return (A + sps.diags(self.mass_dof * mov + (1.0 - mov))).tocsr()

    def jacobi(self, x: np.ndarray):
        """``r -> z``: the diagonal of Newton's matrix at x as a preconditioner, per node (its mean over
        the node's dofs: it commutes with a normal projection), zero on held dofs."""
        model, control = self.model, self.control
        Kt = tangent(model, self.state, x, self.dt_fx, definite=False)
        d = Kt.diagonal() + self.mass_dof + (0.0 if self.coupling is None else self.coupling)
        if model.springs.damped:
            d = d + model.springs.damping_matrix(x).diagonal() / self.h
        d = np.repeat(d.reshape(-1, 3).mean(axis=1), 3)
        hold = self.fixed_dof.copy()
        g_ = control.grasp
        if g_ is not None and g_.mode == "prescribed":
            hold.reshape(-1, 3)[g_.nodes] = True
        held, normal = self.contact.holds()
        hold.reshape(-1, 3)[held] = True

        def apply(r):
            z = r / d
            z[hold] = 0.0
            if normal.any():
                zz = z.reshape(-1, 3)
                nrm = model.floor.normal
                zz[normal] -= (zz[normal] @ nrm)[:, None] * nrm
            return z

        return apply
