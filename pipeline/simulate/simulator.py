"""A simulation session: one Model, its State, the Control and a Stepper, held together.

:class:`Simulator` is the convenient face of :mod:`.model`, :mod:`.stepper`
and :mod:`.relax` for scripts, tests and the run (:mod:`.run`): it builds the
model from a force term, keeps the state and the grasper's control, and
forwards ``advance``, ``relax``, ``attach``/``release`` and the evaluations to
the pieces that own them.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from ..blas import single_threaded_blas
from ..errors import ConfigError, SimulationError
from ..linalg import supernodal
from ..progress import Reporter
from . import kernels as K
from .model import Control, Floor, Grasp, Model, State
from .relax import relax, settle_effects
from .springterm import SpringTerm
from .stepper import DEFAULT_SAFETY, StepBound, Stepper, SymplecticEuler
from .volumeterm import VolumeTerm, build_volume_term


class Simulator:
    """State and time stepping of a spring network.

    Parameters
    ----------
    springs : SpringTerm
    points : ndarray, shape (n, 3)
        Rest positions [m] (the initial state).
    mass : ndarray, shape (n,)
        Node masses [kg] (inertia).
    fixed : ndarray of int, shape (f,)
        Nodes held in place.
    gravity : array-like, shape (3,)
        Acceleration of gravity [m/s2].
    gravity_mass : ndarray, shape (n,), optional
        Masses that gravity acts on (default *mass*; differs under mass scaling).
    mass_damping : float
        Rayleigh mass-proportional coefficient alpha [1/s] (0: none).
    dt : float, optional
        Time step [s]; default: the stability bound with *safety*. A larger one
        than the bound raises :class:`SimulationError`.
    safety : float
    threads : int
        1: the serial step loop; more: the owner/halo parallel loop.
    floor : Floor, optional
        Rigid floor acting on the free nodes (not the fixed or grasped ones)
        after every position update, in the dynamics and in :meth:`relax`.
    stepper : Stepper, optional
        What advances the state (default: :class:`~.stepper.SymplecticEuler`
        with *safety* and *threads*).
    volume : VolumeTerm, optional
        The volume term (nearly incompressible behaviour), beside the springs.

    Attributes
    ----------
    model : Model
    state : State
    control : Control
    stepper : Stepper
    bound : StepBound
        The whole-table stability bound with the current control.
    """

    def __init__(self, springs: SpringTerm, points: np.ndarray, mass: np.ndarray, *, fixed=(),
                 gravity=(0.0, 0.0, 0.0), mass_damping: float = 0.0, dt: float | None = None,
                 safety: float = DEFAULT_SAFETY, threads: int = 1, gravity_mass: np.ndarray | None = None,
                 floor: Floor | None = None, stepper: Stepper | None = None, volume: VolumeTerm | None = None):
        self.model = Model.build(springs, points, mass, fixed=fixed, gravity=gravity, gravity_mass=gravity_mass,
                                 mass_damping=mass_damping, floor=floor, volume=volume)
        self.state = State.at_rest(self.model)
        self.stepper = SymplecticEuler(safety=float(safety), threads=max(1, int(threads))) if stepper is None \
            else stepper
        self._set_control(Control.of(self.model))
        if dt is None:
            self.state.dt = self.bound.dt
        else:
            if not (np.isfinite(dt) and dt > 0):
                raise ConfigError(f"dt: must be a positive time step, got {dt}", parameter="dt")
            if dt > self.bound.dt_critical:
                raise SimulationError(
                    f"dt: {dt:.3g} s exceeds the stability bound {self.bound.dt_critical:.3g} s of "
                    f"this network; use a smaller step or none (automatic)")
            self.state.dt = float(dt)

    # -- the pieces' fields, for reading (and x, v, dt, threads for setting) --------
    x = property(lambda self: self.state.x, doc="Positions (n, 3) [m] (the state's array).")
    v = property(lambda self: self.state.v, doc="Velocities (n, 3) [m/s] (the state's array).")
    t = property(lambda self: self.state.t, doc="Current time [s].")
    fx_state = property(lambda self: self.state.effects, doc="The springs' effect state (None without effects).")
    contact = property(lambda self: self.state.contact, doc="Nodes the floor held at the last step, (n,) uint8.")
    mass = property(lambda self: self.model.mass, doc="Inertial masses (n,) [kg].")
    fext = property(lambda self: self.model.fext, doc="External forces (n, 3) [N].")
    rest = property(lambda self: self.model.rest, doc="Rest positions (n, 3) [m].")
    floor = property(lambda self: self.model.floor)
    grasp = property(lambda self: self.control.grasp, doc="The current grasp (None when open).")
    inv_mass = property(lambda self: self.control.inv_mass, doc="1/m of the integrated nodes (0: not integrated).")
    free = property(lambda self: self.control.free, doc="Nodes integrated in time, (n,) bool.")

    @property
    def dt(self) -> float:
        """The current step [s] (setting it bypasses the stability guard: see :meth:`set_time_step`)."""
        return self.state.dt

    @dt.setter
    def dt(self, value: float) -> None:
        self.state.dt = float(value)

    @property
    def threads(self) -> int:
        return self.stepper.threads

    @threads.setter
    def threads(self, value: int) -> None:
        self.stepper.threads = max(1, int(value))

    @property
    def n_contact(self) -> int:
        """Nodes the floor held at the last step."""
        return int(np.count_nonzero(self.state.contact))

    def displacement(self) -> np.ndarray:
        return self.state.x - self.model.rest

    def _set_control(self, control: Control) -> None:
        self.control = control
        self.state.contact[control.floor_mask == 0] = 0
        self.bound = self.stepper.bound(self.model, control)

    def set_time_step(self, dt: float, *, bound: StepBound | None = None, t0: float | None = None) -> None:
        """Change the step, keeping the current time (or restarting the count at *t0*).

        Refuses a step above *bound* (default: the whole-table bound of the
        current configuration of fixed and held nodes).
        """
        if not (np.isfinite(dt) and dt > 0):
            raise ConfigError(f"dt: must be a positive time step, got {dt}", parameter="dt")
        limit = (self.bound if bound is None else bound).dt_critical
        if dt > limit * (1 + 1e-12):
            raise SimulationError(f"dt: {dt:.3g} s exceeds the stability bound {limit:.3g} s")
        self.state.restart_clock(dt, t0)

    def snapshot(self) -> tuple:
        """The state and the control, for :meth:`restore`."""
        return (self.state.copy(), self.control)

    def restore(self, snapshot: tuple) -> None:
        state, control = snapshot
        self.state.assign(state)
        if control is not self.control:
            self._set_control(control)

    # -- grasper -------------------------------------------------------------
    def attach(self, grasp: Grasp, *, check_step: bool = True) -> None:
        """Start holding ``grasp.nodes`` (at the current time).

        With *check_step*, a step above the whole-table bound with the coupling
        springs is refused (callers that bound the step themselves, per frame,
        pass False).
        """
        self._set_control(Control.of(self.model, grasp))
        g = self.control.grasp
        if check_step and self.state.dt > self.bound.dt_critical:
            raise SimulationError(
                f"grasper.stiffness: the coupling springs need a step below {self.bound.dt_critical:.3g} s "
                f"(current {self.state.dt:.3g} s); lower the stiffness or use mode = \"prescribed\"")
        if g.mode == "prescribed":
            t = self.state.t
            self.state.x[g.nodes] = g.tip(t) + g.offsets
            self.state.v[g.nodes] = g.tip_velocity(t)

    def release(self) -> None:
        """Let go: the grasped nodes become free again (keeping their velocity)."""
        self._set_control(Control.of(self.model))

    # -- stepping and equilibrium ----------------------------------------------
    def advance(self, nsteps: int, *, record: np.ndarray | None = None) -> np.ndarray:
        """Run *nsteps* steps; return the force on the grasper at each step, shape (nsteps, 3) [N].

        The force is the one the tissue (with its weight) exerts on the grasper
        (what a haptic device renders); zeros when nothing is grasped. OpenBLAS
        runs on one thread meanwhile: the implicit stepper's vector and
        triangular-solve operations are too small to share (docs/design/simulator.md, "What is factored, and
        when it is renewed").
        """
        with single_threaded_blas():
            return self.stepper.advance(self.model, self.state, self.control, nsteps, record=record)

    def relax(self, *, ftol: float | None = None, rtol: float = 1e-8, max_iter: int = 200_000,
              inertia: np.ndarray | None = None, reporter: Reporter | None = None, cache: Path | None = None) -> dict:
        """Static equilibrium under gravity (and a held grasp) with FIRE: :func:`.relax.relax`.

        FIRE's molecular-dynamics step is the explicit stability bound (also
        when the stepper is implicit and has none). *inertia*: FIRE's node
        masses instead of the model's (its path, and so the equilibrium it finds
        on a sticking floor, depends on them). *reporter*: shown FIRE's progress;
        *cache*: a folder of equilibria found before (:func:`.relax.relax`).
        """
        model, control, dtc = self.model, self.control, self.bound.dt_critical
        if inertia is not None:
            model = dataclasses.replace(model, mass=np.ascontiguousarray(inertia, dtype=np.float64))
            control = Control.of(model, control.grasp)
        if inertia is not None or not np.isfinite(dtc):
            dtc = SymplecticEuler().bound(model, control).dt_critical
        return relax(model, self.state, control, dt_critical=dtc, ftol=ftol, rtol=rtol, max_iter=max_iter,
                     reporter=reporter, cache=cache)

    def settle_effects(self) -> None:
        """Take the current configuration as long held (:func:`.relax.settle_effects`)."""
        settle_effects(self.model, self.state)

    def history_stiffness(self, delta: float) -> np.ndarray | None:
        """Per-node Gershgorin row added by the viscoelastic history forces [N/m], or None.

        For :func:`~.stepper.stable_step`'s ``extra_stiffness`` (valid while no
        stretch moves by more than *delta*): :meth:`.SpringTerm.state_rows`.
        """
        return self.model.springs.state_rows(self.state.effects, self.state.x, delta)

    # -- evaluations -------------------------------------------------------------
    def forces(self) -> np.ndarray:
        """Total nodal forces (springs, dashpots, volume term, gravity) at the current state, shape (n, 3) [N].

        With material effects: the force the next step would use (the state
        advanced to the current time, not committed).
        """
        st = self.state
        springs = self.model.springs
        if st.effects is None:
            f = springs.forces(st.x, st.v, fext=self.model.fext)
        else:
            f = springs.forces(st.x, st.v, fext=self.model.fext, state=st.effects, mode=K.FX_PEEK,
                               dt=max(0.0, st.t - st.effects.t))
        return f if self.model.volume is None else f + self.model.volume.forces(st.x)

    def grasper_force(self) -> np.ndarray:
        """Force of the tissue on the grasper at the current state, shape (3,) [N] (zeros if open)."""
        g = self.control.grasp
        if g is None:
            return np.zeros(3)
        f = self.forces()
        if g.mode == "spring":
            tip = g.tip(self.t)
            return -(g.stiffness[:, None] * (tip + g.offsets - self.x[g.nodes])).sum(axis=0)
        return f[g.nodes].sum(axis=0)

    def kinetic_energy(self) -> float:
        return 0.5 * float(np.sum(self.model.mass[:, None] * self.state.v**2))

    def gravity_energy(self) -> float:
        return -float(np.sum(self.model.fext * self.state.x))


def warm_up(springs: SpringTerm, *, threads: int = 1, volume: VolumeTerm | None = None,
            implicit: bool = False) -> float:
    """Compile (or load from cache) the step loop on a small problem; return the seconds spent.

    With *volume*: the variants of the step loop and of FIRE with a volume term,
    on one tetrahedron. *implicit*: also the tangent kernels of the implicit stepper.
    """
    t = time.perf_counter()
    if volume is None:
        x = np.array([[0.0, 0, 0], [1.0, 0, 0]])
        sub = _tiny_springs(springs, [[0], [1]])
        sim = Simulator(sub, x, np.ones(2), fixed=[0], threads=threads)
        sim.dt = min(1e-3, sim.bound.dt)
    else:
        x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        sub = _tiny_springs(springs, [[0, 0, 0, 1, 1, 2], [1, 2, 3, 2, 3, 3]])
        vol = build_volume_term(x, np.array([[0, 1, 2, 3]]), volume.spec, lam_max=volume.lam_max)
        # The step within this tiny problem's own bound: a stiff material's volume term (a foam's bulk
        # modulus of 47 MPa on this 1 m tet of 1 kg nodes: bound 0.28 us) refuses a fixed 1 us.
        sim = Simulator(sub, x, np.ones(4), fixed=[0], threads=threads, volume=vol, gravity=(0, 0, -1.0))
        sim.dt = min(1e-6, sim.bound.dt)
        try:
            sim.relax(rtol=1e30, max_iter=1)
        except SimulationError:       # only the compilation matters here
            pass
    sim.advance(1)
    sim.attach(Grasp(nodes=np.array([1]), offsets=np.zeros((1, 3)), wp_t=np.array([0.0, 1.0]),
                     wp_x=np.array([[1.0, 0, 0], [1.0, 0, 0]])))
    sim.advance(1)
    if implicit:
        sub.tangent(sim.x, state=sim.state.effects, dt=1e-3)
        if volume is not None:
            vol.tangent(sim.x)
            vol.tangent_bound(sim.x)
            sub.forces(sim.x, state=sim.state.effects, dt=1e-3, beside=vol.kernel())
        supernodal.warm_up()
    return time.perf_counter() - t


def _tiny_springs(springs: SpringTerm, ij) -> SpringTerm:
    """Springs *ij* (2, s) of zero weight with the kernel variant of *springs* (layout, law, dashpots, effects)."""
    ij = np.asarray(ij, np.uint32)
    s = ij.shape[1]
    sub = SpringTerm(n_nodes=int(ij.max()) + 1, ij=ij, order=np.arange(s, dtype=np.int64),
                     sd=np.zeros((springs.sd.shape[0], s), springs.sd.dtype), tab=springs.tab[:2].copy(),
                     lam_min=springs.lam_min, inv_h=springs.inv_h, law=springs.law, kappa=np.zeros(s),
                     rest_tangent=np.zeros(s), dashpot=springs.dashpot, effects=springs.effects)
    sub.sd[0] = 1.0
    return sub
