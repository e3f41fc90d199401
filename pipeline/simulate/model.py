"""What a simulation is made of: a constant Model, a mutable State, a Control from outside.

* :class:`Model`: everything that stays the same during a run: the force terms
  (the springs, with their tables and material effects' parameters), the rest
  shape, the inertial masses, the external forces (gravity on the true
  masses), the fixed nodes, the mass damping and the rigid floor;
* :class:`State`: what a step changes: positions, velocities, the clock, the
  springs' effect state and the floor's contact flags (a copy is a snapshot);
* :class:`Control`: what the scene prescribes from outside: the grasper, and
  what it implies for the nodes (which are integrated, which the floor acts on).

A :class:`ForceTerm` is one contribution to the nodal forces: the springs
(:class:`~.springterm.SpringTerm`) and, when the asset has one and the scene
keeps it, the volume term (:class:`~.volumeterm.VolumeTerm`), both in
:attr:`Model.terms`. A stepper (:mod:`.stepper`) advances a State under a
Model and a Control.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import ConfigError, InputError
from .effects import EffectState
from .kernels import GRASP_NONE, GRASP_PRESCRIBED, GRASP_SPRING, FloorKernel, GraspKernel, tip_state
from .springterm import SpringTerm
from .volumeterm import VolumeTerm


class ForceTerm(Protocol):
    """One contribution to the nodal forces f(x, v) (the springs; the volume term).

    What the steppers need from a term:

    * ``forces(x, v, ...)``: its nodal forces (n, 3) [N] (the compiled step
      loop calls the term's kernel tuple directly: :mod:`.kernels`);
    * ``stiffness_rows(x=None, window=None)``: per node, a bound of the row
      sums of its tangent stiffness |K| [N/m] (Gershgorin), over every
      configuration or over a window around *x*: the explicit step's bound;
    * ``damping_rows()``: the same for its damping matrix [N s/m];
    * ``state_rows(state, x, delta)``: rows added by its state (None if none);
    * ``tangent(x, v=None, *, definite=False)``: its tangent stiffness
      ``K = -df/dx`` at *x*, a ``scipy.sparse.csr_matrix`` (3n, 3n), dof order
      ``x.ravel()``; *definite*: a positive semi-definite part of it (the
      implicit stepper, :mod:`.implicit`, sums it over the terms for Newton's matrix);
    * optionally ``tangent_operator(x, *, definite=False)``: the product
      ``p -> K p`` without forming K (the implicit stepper's conjugate gradients
      use it when a term has it: the volume term, whose K is dense two tets wide).
    """

    n_nodes: int

    def forces(self, x: np.ndarray, v: np.ndarray | None = None, **options) -> np.ndarray: ...

    def stiffness_rows(self, *, x: np.ndarray | None = None, window: float | None = None) -> np.ndarray: ...

    def damping_rows(self) -> np.ndarray: ...

    def state_rows(self, state, x: np.ndarray, delta: float) -> np.ndarray | None: ...

    def tangent(self, x: np.ndarray, v: np.ndarray | None = None, *, definite: bool = False): ...


@dataclass(eq=False)
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


@dataclass(eq=False)
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
        pos, _ = tip_state(float(t), self.wp_t, self.wp_x)
        return pos

    def tip_velocity(self, t: float) -> np.ndarray:
        _, vel = tip_state(float(t), self.wp_t, self.wp_x)
        return vel

    def checked(self, movable: np.ndarray) -> Grasp:
        """This grasp validated against the nodes that may move (*movable* (n,) bool), arrays normalised.

        Raises
        ------
        ConfigError
            No node, a fixed node, an unknown mode or a non-positive stiffness.
        """
        nodes = np.asarray(self.nodes, dtype=np.int64).ravel()
        if nodes.size == 0:
            raise ConfigError("grasper: no node to grasp")
        if np.any(~movable[nodes]):
            raise ConfigError("grasper: a grasped node is fixed; grasp elsewhere or change the fixed region")
        if self.mode not in ("prescribed", "spring"):
            raise ConfigError(f"grasper.mode: unknown {self.mode!r}; use \"prescribed\" or \"spring\"")
        if self.mode == "spring":
            k = np.asarray(self.stiffness, dtype=np.float64).reshape(nodes.size)
            if np.any(~np.isfinite(k)) or np.any(k <= 0):
                raise ConfigError("grasper.stiffness: must be positive (N/m)")
        else:
            k = np.zeros(nodes.size)
        return Grasp(nodes=nodes,
                     offsets=np.ascontiguousarray(np.asarray(self.offsets, dtype=np.float64).reshape(nodes.size, 3)),
                     wp_t=np.ascontiguousarray(np.asarray(self.wp_t, dtype=np.float64).ravel()),
                     wp_x=np.ascontiguousarray(np.asarray(self.wp_x, dtype=np.float64).reshape(-1, 3)),
                     mode=self.mode, stiffness=k)


@dataclass(frozen=True, eq=False)
class Model:
    """The constant part of a simulation (see the module doc).

    Attributes
    ----------
    springs : SpringTerm
    rest : ndarray, shape (n, 3)
        Rest positions [m].
    mass : ndarray, shape (n,)
        Inertial node masses [kg] (raised by mass scaling).
    fext : ndarray, shape (n, 3)
        External force per node [N]: gravity on the true masses.
    fixed : ndarray, shape (f,), int64
        Nodes held in place.
    gravity : ndarray, shape (3,)
        [m/s2].
    mass_damping : float
        Rayleigh mass-proportional coefficient alpha [1/s] (0: none).
    floor : Floor or None
    volume : VolumeTerm or None
        The volume term (nearly incompressible behaviour), when the asset has one
        and the scene keeps it.
    """

    springs: SpringTerm
    rest: np.ndarray
    mass: np.ndarray
    fext: np.ndarray
    fixed: np.ndarray
    gravity: np.ndarray
    mass_damping: float = 0.0
    floor: Floor | None = None
    volume: VolumeTerm | None = None

    @classmethod
    def build(cls, springs: SpringTerm, points: np.ndarray, mass: np.ndarray, *, fixed=(),
              gravity=(0.0, 0.0, 0.0), gravity_mass: np.ndarray | None = None, mass_damping: float = 0.0,
              floor: Floor | None = None, volume: VolumeTerm | None = None) -> Model:
        """Validate and assemble a model (*gravity_mass*: the masses gravity acts on, default *mass*).

        Raises
        ------
        InputError
            Masses not positive and finite, fixed nodes out of range.
        ConfigError
            Gravity not finite, negative mass damping, a floor that is not a :class:`Floor`.
        """
        n = springs.n_nodes
        rest = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(n, 3)).copy()
        m = np.asarray(mass, dtype=np.float64).reshape(n).copy()
        if np.any(~np.isfinite(m)) or np.any(m <= 0):
            raise InputError("network has nodes of zero, negative or non-finite mass; rebuild the asset")
        fixed = np.unique(np.asarray(fixed, dtype=np.int64).ravel())
        if fixed.size and (fixed[0] < 0 or fixed[-1] >= n):
            raise InputError(f"fixed nodes outside 0..{n - 1}")
        g = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(g)):
            raise ConfigError("gravity: must be three finite numbers (m/s2)", parameter="gravity")
        if not (np.isfinite(mass_damping) and mass_damping >= 0):
            raise ConfigError(f"mass_damping: must be >= 0 1/s, got {mass_damping}", parameter="mass_damping")
        if floor is not None and not isinstance(floor, Floor):
            raise ConfigError("floor: expected a Floor or None", parameter="floor")
        if volume is not None and volume.n_nodes != n:
            raise InputError(f"volume term: {volume.n_nodes} nodes, the springs have {n}")
        gm = m if gravity_mass is None else np.asarray(gravity_mass, dtype=np.float64).reshape(n)
        return cls(springs=springs, rest=rest, mass=m, fext=np.ascontiguousarray(gm[:, None] * g[None, :]),
                   fixed=fixed, gravity=g, mass_damping=float(mass_damping), floor=floor, volume=volume)

    @property
    def n_nodes(self) -> int:
        return int(self.rest.shape[0])

    @property
    def terms(self) -> tuple:
        """The force terms (:class:`ForceTerm`), in the order the step sums them."""
        return (self.springs,) if self.volume is None else (self.springs, self.volume)

    def volume_kernel(self):
        """The kernels' tuple of the volume term, or None without one."""
        return None if self.volume is None else self.volume.kernel()

    @property
    def movable(self) -> np.ndarray:
        """Nodes that are not fixed, shape (n,) bool."""
        out = np.ones(self.n_nodes, bool)
        out[self.fixed] = False
        return out


@dataclass(eq=False)
class State:
    """What a step changes (see the module doc); :meth:`copy` is a snapshot.

    Attributes
    ----------
    x, v : ndarray, shape (n, 3)
        Positions [m] and velocities [m/s].
    t0 : float
        Time of step count 0 [s]; the current time is ``t0 + steps * dt``.
    steps : int
    dt : float
        The current step [s].
    effects : EffectState or None
        The springs' material effect state.
    contact : ndarray, shape (n,), uint8
        1 for the nodes the floor held at the last step (or relaxation iteration).
    """

    x: np.ndarray
    v: np.ndarray
    t0: float = 0.0
    steps: int = 0
    dt: float = 0.0
    effects: EffectState | None = None
    contact: np.ndarray | None = None

    @classmethod
    def at_rest(cls, model: Model) -> State:
        """The model's rest shape, at rest, at t = 0, with virgin effect state."""
        n = model.n_nodes
        return cls(x=model.rest.copy(), v=np.zeros((n, 3)), effects=model.springs.new_state(),
                   contact=np.zeros(n, np.uint8))

    @property
    def t(self) -> float:
        """Current time [s]."""
        return self.t0 + self.steps * self.dt

    def copy(self) -> State:
        return State(self.x.copy(), self.v.copy(), self.t0, self.steps, self.dt,
                     None if self.effects is None else self.effects.copy(), self.contact.copy())

    def assign(self, other: State) -> None:
        """Overwrite this state in place with *other* (arrays keep their identity)."""
        self.x[:] = other.x
        self.v[:] = other.v
        self.t0, self.steps, self.dt = other.t0, other.steps, other.dt
        if other.effects is not None and self.effects is not None:
            self.effects.assign(other.effects)
        self.contact[:] = other.contact

    def restart_clock(self, dt: float, t0: float | None = None) -> None:
        """Take steps of *dt* from now on (or from time *t0*), counting from 0."""
        self.t0 = self.t if t0 is None else float(t0)
        self.steps = 0
        self.dt = float(dt)


@dataclass(frozen=True, eq=False)
class Control:
    """What the scene prescribes: the grasper, and which nodes are integrated and meet the floor.

    Attributes
    ----------
    grasp : Grasp or None
    inv_mass : ndarray, shape (n,)
        1/m of the integrated nodes; 0 for fixed nodes and nodes held by a prescribed grasp.
    floor_mask : ndarray, shape (n,), uint8
        Nodes under the floor's rule: integrated and not grasped (in either mode).
    """

    grasp: Grasp | None
    inv_mass: np.ndarray
    floor_mask: np.ndarray

    @classmethod
    def of(cls, model: Model, grasp: Grasp | None = None) -> Control:
        """The control of *model* with *grasp* (validated) or nothing grasped."""
        if grasp is not None:
            grasp = grasp.checked(model.movable)
        inv = np.where(model.movable, 1.0 / model.mass, 0.0)
        if grasp is not None and grasp.mode == "prescribed":
            inv[grasp.nodes] = 0.0
        mask = inv > 0
        if grasp is not None:
            mask[grasp.nodes] = False
        return cls(grasp=grasp, inv_mass=np.ascontiguousarray(inv),
                   floor_mask=np.ascontiguousarray(mask.astype(np.uint8)))

    @property
    def free(self) -> np.ndarray:
        """Nodes integrated in time (not fixed, not held by a prescribed grasp), shape (n,)."""
        return self.inv_mass > 0

    def coupling_rows(self) -> np.ndarray | None:
        """Per node, the stiffness of the grasper's coupling springs [N/m] (None unless mode "spring")."""
        g = self.grasp
        if g is None or g.mode != "spring":
            return None
        out = np.zeros(self.inv_mass.size)
        np.add.at(out, g.nodes, g.stiffness)
        return out

    def grasp_kernel(self) -> GraspKernel:
        """The kernels' tuple of the grasper (mode none: empty arrays)."""
        g = self.grasp
        if g is None:
            return GraspKernel(GRASP_NONE, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(1),
                               np.zeros((1, 3)))
        mode = GRASP_PRESCRIBED if g.mode == "prescribed" else GRASP_SPRING
        return GraspKernel(mode, g.nodes, g.offsets, g.stiffness, g.wp_t, g.wp_x)

    def floor_kernel(self, model: Model, state: State) -> FloorKernel:
        """The kernels' tuple of the floor (off: placeholders), writing ``state.contact``."""
        fl = model.floor
        if fl is None:
            return FloorKernel(False, np.zeros(3), 0.0, False, self.floor_mask, state.contact)
        return FloorKernel(True, fl.normal, fl.height, fl.friction == "stick", self.floor_mask, state.contact)
