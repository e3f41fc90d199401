r"""The floor's contacts within one implicit step: the active set and its slides.

The implicit stepper (:mod:`.implicit`) holds the floor's contacts as constraints of the step's
system (docs/design/simulator.md, "Floor contact, with slides"): a node that crosses the plane during a step is
put back on it and held from the next step on; one the floor would have to pull (its reaction
:math:`\lambda = \mathbf g\cdot\mathbf n < 0`, :math:`\mathbf g` the step's residual) is let go and
the step solved again. On a frictionless floor ("slip") a held node is held along the normal only;
on a sticking one ("stick") in place, and a pulled node first slides on the floor within the step
(:class:`Slides`).

:class:`FloorContact` is one step's active set; :class:`Slides` the sticking floor's slides.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .implicit_stats import ImplicitStats
from .model import Control, Floor, Model, State

#: Points of a stopping slide at which :meth:`Slides.slip` evaluates the floor's reaction (a force pass
#: each; the first point ends it where the node's springs press it into the floor at once, as most do).
SLIP_SAMPLES = 8


@dataclass
class Slides:
    """A sticking floor's contacts within one implicit step (docs/design/simulator.md, "Floor contact, with slides").

    The explicit stepper lets go of a held node the moment the floor would pull it and holds it
    again where it is back on the plane: where a lift peels the organ off its bed, such nodes
    creep along the floor at no normal force. Backward Euler's step is too long to follow that
    creep, and holding them until the step's end makes the peel line chatter (a node let go,
    landed a step later, pulled again). So within a step, after each solve (``lam`` the floor's
    reaction, > 0 where it pushes):

    * a held node the floor pulls slides on it (held along the normal only; once per step);
    * a sliding node it pushes again sticks at the farther of two points of its slide (a fraction
      ``s`` of the way from where it was held): where it *slips* to, the first point where the
      floor's reaction with every other node where the held solve left them is zero (:meth:`slip`;
      1, the slide's end, where it stays negative), and where it *creeps* to, the zero of its
      reaction taken as linear along the slide (``lam0 / (lam0 - lam)``); where ``s < 1`` the
      iteration restarts from the whole field taken back by the mean ``s`` (its linear response),
      the nodes there;
    * a sliding node it still pulls leaves the floor.

    The final check of a step (no solve follows) lets pulled sliding nodes go and moves no node;
    a held node pulled then stays held (it slides in the next step).
    """

    sliding: np.ndarray                 #: (n,) held along the normal only
    slid: np.ndarray                    #: (n,) has slid this step
    lam0: np.ndarray                    #: (n,) the reaction when its slide began (< 0) [N]
    x0: np.ndarray                      #: (n, 3) where it was held then [m]
    field0: np.ndarray | None = None    #: (n, 3) every node then [m]
    moved: bool = False                 #: the last update moved nodes (slides stopped)

    @classmethod
    def none(cls, n: int) -> Slides:
        return cls(np.zeros(n, bool), np.zeros(n, bool), np.zeros(n), np.zeros((n, 3)))

    def update(self, lam: np.ndarray, x: np.ndarray, contact: np.ndarray, *, final: bool,
               reaction: Callable[[np.ndarray], np.ndarray] | None = None):
        """The rule above after a solve (*x* moved in place where slides stop; *reaction* ``y -> lam``
        the floor's reaction on every node at positions *y*, for :meth:`slip`; None: slides stop where
        they creep to): (contacts to let go, whether anything changed, slides begun)."""
        pulled = contact & (lam < 0.0)
        leave = pulled & self.sliding
        stop = contact & self.sliding & ~pulled
        start = pulled & ~self.slid
        self.sliding &= ~leave
        self.moved = False
        if final:
            return leave, bool(leave.any()), 0
        if stop.any():
            s = self.lam0[stop] / (self.lam0[stop] - lam[stop])
            if reaction is not None:
                s = np.maximum(s, self.slip(stop, x, reaction))
            self.sliding &= ~stop
            if (s < 1.0).any():
                x_stop = self.x0[stop] + s[:, None] * (x[stop] - self.x0[stop])
                x[:] = self.field0 + float(np.mean(s)) * (x - self.field0)
                x[stop] = x_stop
                self.moved = True
            else:                           # stuck where the slide ended: the solution stands
                stop = np.zeros_like(stop)
        if start.any():
            self.lam0[start] = lam[start]
            self.x0[start] = x[start]
            self.field0 = x.copy()
            self.sliding |= start
            self.slid |= start
        return leave, bool(leave.any() or stop.any() or start.any()), int(start.sum())

    def slip(self, stop: np.ndarray, x: np.ndarray, reaction: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The fraction of its slide (from ``x0`` to *x*) each node of *stop* slips before its neighbours
        follow: the first zero of the floor's reaction on it along the slide with every other node where
        the held solve left them (``field0``), sampled at :data:`SLIP_SAMPLES` points and linear between
        them; 1 where the reaction stays negative along the whole slide.

        Why: the explicit stepper lets a pulled node go and it slides within milliseconds, a node's own
        time scale, before the body around it moves; it lands where its own springs press it into the
        floor. Where they press it at once (most nodes of a peel line) it creeps instead, as fast as the
        body relaxes, and :meth:`update`'s linear zero is where it stops; where they do not, it slips
        the whole way to where the slide solve put it (docs/design/simulator.md, "Floor contact, with
        slides")."""
        idx = np.flatnonzero(stop)
        s = np.ones(idx.size)
        prev = self.lam0[idx]
        landed = np.zeros(idx.size, bool)
        y = self.field0.copy()
        for k in range(1, SLIP_SAMPLES + 1):
            y[idx] = self.x0[idx] + (k / SLIP_SAMPLES) * (x[idx] - self.x0[idx])
            lam = reaction(y)[idx]
            new = ~landed & (lam >= 0.0)
            s[new] = (k - 1 + prev[new] / (prev[new] - lam[new])) / SLIP_SAMPLES
            landed |= new
            if landed.all():
                break
            prev = lam
        return s


def contact_rounds(requested: int | None, floor: Floor | None) -> int:
    """Times a step is solved again after its contacts changed: *requested*, or by the floor: none
    without one, once on a frictionless floor (a node the lift peels off leaves in the step it is let
    go, not a step later), three times on a sticking one (a pulled node slides, then stops or leaves,
    and a node that pulls free once its neighbour has left slides and leaves in the same step)."""
    if requested is not None:
        return int(requested)
    if floor is None:
        return 0
    return 3 if floor.friction == "stick" else 1


def on_floor(floor: Floor, x0: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Nodes (*x* (k, 3), from *x0* (k, 3)) put on the plane: "stick" where their path from *x0* crossed
    it, "slip" along the normal."""
    nrm = floor.normal
    d = x @ nrm - floor.height
    if floor.friction == "stick":
        d0 = x0 @ nrm - floor.height
        r = np.where(d0 > 0.0, d0 / np.where(d0 - d > 0, d0 - d, 1.0), 0.0)
        y = x0 + np.clip(r, 0.0, 1.0)[:, None] * (x - x0)
        return y - (y @ nrm - floor.height)[:, None] * nrm
    return x - d[:, None] * nrm


@dataclass(eq=False)
class FloorContact:
    """The floor's active set within one implicit step (module doc).

    Attributes
    ----------
    floor : Floor or None
    candidates : ndarray, shape (n,), bool
        Nodes under the floor's rule: integrated and not grasped.
    active : ndarray, shape (n,), bool
        The nodes the floor holds now (changed in place over the step).
    slides : Slides
    rounds : int
        Re-solves allowed after the contacts changed (:func:`contact_rounds`).
    stats : ImplicitStats
        Where the changes are counted (``contact_changes``, ``slides``).
    left_at : ndarray, shape (n, 3), or None
        Where the nodes the floor let go of in this step were then (NaN for the others; None: none
        yet): where a sticking floor's :meth:`touchdown` starts their path.
    """

    floor: Floor | None
    candidates: np.ndarray
    active: np.ndarray
    slides: Slides
    rounds: int
    stats: ImplicitStats
    left_at: np.ndarray | None = None

    @classmethod
    def begin(cls, model: Model, state: State, control: Control, *, rounds: int | None,
              stats: ImplicitStats) -> FloorContact:
        """The step's start: the contacts the floor held at the last step (among the candidates)."""
        candidates = (control.floor_mask > 0) & model.movable
        g_ = control.grasp
        if g_ is not None:
            candidates[g_.nodes] = False
        floor = model.floor
        active = (state.contact > 0) & candidates if floor is not None else np.zeros(model.n_nodes, bool)
        return cls(floor, candidates, active, Slides.none(model.n_nodes), contact_rounds(rounds, floor), stats)

    def holds(self) -> tuple[np.ndarray, np.ndarray]:
        """(held in place, held along the normal only), each (n,) bool: the contacts by the floor's
        friction and the step's slides."""
        contact, floor = self.active, self.floor
        none = np.zeros_like(contact)
        if floor is None or not contact.any():
            return none, none
        if floor.friction == "stick":
            slide = contact & self.slides.sliding
            return contact & ~slide, slide
        return none, contact

    def place(self, x0: np.ndarray, x: np.ndarray) -> None:
        """Put the held nodes of a predicted *x* (n, 3) on the plane (in place; *x0* the step's start)."""
        contact = self.active
        if contact.any():
            x[contact] = on_floor(self.floor, x0[contact], x[contact])

    def update(self, g: np.ndarray, x: np.ndarray, *, final: bool,
               residual: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[bool, bool]:
        """The contacts after a solve whose residual is *g* (n, 3) at *x* (in place; *x* too where a slide
        stops); whether they changed, and whether *x* moved.

        ``lam = g . n`` is the floor's reaction on a node (> 0: it pushes). A contact it would have to
        pull leaves it, except on a sticking floor where the step is solved again (:class:`Slides`;
        with ``rounds`` 0 it leaves at the step's end). *final*: no solve follows. *residual*: ``y -> g``,
        the step's residual at positions *y* (:meth:`Slides.slip`; None: slides stop where they creep to).
        """
        floor, contact = self.floor, self.active
        if floor is None or not contact.any():
            return False, False
        lam = g @ floor.normal
        moved = False
        if floor.friction == "stick" and self.rounds > 0:
            nrm = floor.normal
            reaction = None if residual is None else (lambda y: residual(y) @ nrm)
            leave, changed, started = self.slides.update(lam, x, contact, final=final, reaction=reaction)
            self.stats.slides += started
            moved = self.slides.moved
        else:
            leave = contact & (lam < 0.0)
            changed = bool(leave.any())
        contact &= ~leave
        if leave.any():
            if self.left_at is None:
                self.left_at = np.full_like(x, np.nan)
            self.left_at[leave] = x[leave]
        self.stats.contact_changes += int(leave.sum())
        return changed, moved

    def touchdown(self, x0: np.ndarray, x: np.ndarray) -> None:
        """The step's end: free candidates that went below the plane are put back on it (in *x*; where
        their path from *x0* crossed it, with "stick") and held from the next step on (the explicit
        step's rule, per step). A node the floor let go of in this step starts its path where it was
        let go (``left_at``): it left the plane there, after its slide, and landing where it was held
        at the step's start would undo the slide."""
        floor = self.floor
        if floor is None:
            return
        below = self.candidates & ~self.active & (floor.distance(x) < 0.0)
        if below.any():
            start = x0[below]
            if self.left_at is not None:
                left = self.left_at[below]
                start = np.where(np.isnan(left), start, left)
            x[below] = on_floor(floor, start, x[below])
        self.active |= below
        self.stats.contact_changes += int(below.sum())
