r"""The grasper force at the haptic rate, between the implicit stepper's solves.

A haptic device's loop reads the force at about 1 kHz, whatever the solve's step
(docs/design/simulator.md, "The grasper force at 1 kHz"). At a step's start the force is the one
at the solved state, :math:`\mathbf F_n`; until the next solve it is that force moved by the
grasped patch's stiffness in the step's linear model,

.. math::

    \mathbf F(t_n + \tau) = \mathbf F_n - S\,(\mathbf p(t_n + \tau) - \mathbf p(t_n))
        + \tfrac{\tau}{h}\mathbf D_n,

with :math:`\mathbf p` the tip's path, :math:`S` the Schur complement of the factored matrix on
the patch's translation (from the capacitance matrix of the constraint rows,
:meth:`~esmm.pipeline.linalg.linsolve.Constraints.block_stiffness`: no extra solve; with the volume
term's bound in the factor, a little stiffer than Newton's matrix) and :math:`\mathbf D_n` the
part of the last step's change that the tip's motion did not explain (the drift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..linalg.linsolve import Constraints
from .implicit_system import StepSystem, forces
from .model import Control, Grasp, Model

#: Default rate of the grasper force [Hz] (a haptic device's loop).
HAPTIC_RATE = 1000.0


def grasp_force(control: Control, f: np.ndarray, x: np.ndarray, t: float) -> np.ndarray:
    """Force (3,) of the tissue on the grasper at time *t* from the nodal forces *f* (n, 3) (springs,
    weight) at positions *x* (n, 3) [N]; zero with nothing grasped."""
    g_ = control.grasp
    if g_ is None:
        return np.zeros(3)
    if g_.mode == "spring":
        return -(g_.stiffness[:, None] * (g_.tip(t) + g_.offsets - x[g_.nodes])).sum(axis=0)
    return f[g_.nodes].sum(axis=0)


def patch_stiffness(model: Model, control: Control, cons: Constraints | None, h: float) -> np.ndarray:
    """S (3, 3): minus the change of the grasper force per tip displacement in the step's linear model.

    The grasp's rows come first in *cons* (:meth:`.factorcache.FactorCache.set_rows`); their block of
    the capacitance inverse is the patch's stiffness against the factored matrix, inertia included;
    with a prescribed grasp the patch's own inertia is taken out (the grasper moves it, it does not
    push on the grasper). Zero without a grasp or constraint rows. With the two-grid operator, the
    Schur complement of its coarse level (:class:`~esmm.pipeline.linalg.twogrid.TwoGridConstraints`).
    """
    g_ = control.grasp
    if g_ is None or cons is None or not cons.has_rows:
        return np.zeros((3, 3))
    rows = np.arange(3 * g_.nodes.size)
    S = cons.block_stiffness(rows)
    if g_.mode == "prescribed":
        mg = float(model.mass[g_.nodes].sum())
        S = S - mg * (1.0 / (h * h) + model.mass_damping / h) * np.eye(3)
    return S


@dataclass(frozen=True)
class LastForce:
    """The grasper force at the end of the last step: its grasp, time [s], force (3,) [N] and drift (3,) [N]."""

    grasp: Grasp
    t: float
    force: np.ndarray
    drift: np.ndarray


@dataclass(eq=False)
class Haptics:
    """The grasper force at *rate* samples per second of simulated time (module doc).

    Parameters
    ----------
    rate : float
        Grasper force samples per second [Hz].
    drift : bool
        Extrapolate the last step's unexplained change between solves (:math:`\\mathbf D_n`).
    """

    rate: float = HAPTIC_RATE
    drift: bool = True
    last: LastForce | None = None

    def ticks_per_step(self, dt: float) -> int:
        """Samples per step of *dt*: ``ceil(dt * rate)`` (spacing <= 1/rate)."""
        return max(1, int(math.ceil(dt * self.rate * (1 - 1e-9))))

    def start_force(self, system: StepSystem) -> np.ndarray:
        """The grasper force at the step's start: the last step's, or computed now (first step, new grasp)."""
        control, state, t = system.control, system.state, system.t
        g_ = control.grasp
        if g_ is None:
            return np.zeros(3)
        last = self.last
        if last is not None and last.grasp is g_ and abs(last.t - t) <= 1e-9 * max(1.0, abs(t)):
            return last.force
        fxs = state.effects
        f = forces(system.model, state, state.x, state.v, 0.0 if fxs is None else max(0.0, t - fxs.t))
        return grasp_force(control, f, state.x, t)

    def fill(self, rec: np.ndarray, F0: np.ndarray, S: np.ndarray, grasp: Grasp | None, t: float,
             h: float) -> None:
        """The force at a step's ticks, into *rec* (T, 3): *F0* moved by the patch stiffness *S* along
        the tip's path from *t* (+ the drift) at ``t + q h / T``."""
        rec[0] = F0
        T = rec.shape[0]
        if grasp is None or T == 1:
            rec[1:] = F0
            return
        last = self.last
        drift = last.drift if (self.drift and last is not None and last.grasp is grasp) else np.zeros(3)
        p0 = grasp.tip(t)
        for q in range(1, T):
            tau = q * h / T
            rec[q] = F0 - S @ (grasp.tip(t + tau) - p0) + (tau / h) * drift

    def remember(self, control: Control, f: np.ndarray, x: np.ndarray, t1: float, h: float,
                 F0: np.ndarray, S: np.ndarray) -> None:
        """The step's end: the force from the nodal forces *f* at the solved *x*, and the drift: its change
        since *F0* less what the patch stiffness *S* explains of the tip's motion."""
        g_ = control.grasp
        if g_ is None:
            self.last = None
            return
        F1 = grasp_force(control, f, x, t1)
        drift = F1 - F0 + S @ (g_.tip(t1) - g_.tip(t1 - h))
        self.last = LastForce(g_, t1, F1, drift)
