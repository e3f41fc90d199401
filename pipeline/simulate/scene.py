"""Scenes: what happens to the organ during ``esmm simulate``.

A scene is a TOML file (or a bundled preset, ``configs/scenes/<name>.toml``).
Every dimensional value carries its unit, as in every esmm config; the full
schema with defaults is ``configs/scenes/default.toml`` and docs/reference/configuration.md.
Tables and keys::

    [scene]       duration, frame_rate, gravity, gravity_unit, law, start, effects, volume
    [damping]     dashpot, velocity_decay
    [integrator]  method, implicit_step, haptic_rate, newton_tol, factor, iteration (implicit); safety, step, window,
                  mass_scaling (explicit); threads, precision, max_steps
    [fixed]       kind = "asset" (keep the asset's fixed nodes) or a region
                  table as in prepare configs (band / box / nearest / none);
                  a band's axis may be "up" (against gravity)
    [floor]       enabled, height ("auto" or a length along "up"), friction
                  ("stick" / "slip"); absent: no floor
    [grasper]     enabled, target, radius, mode, stiffness, direction,
                  grasp_time, release_time, waypoints
    [video]       width, height, colormap, view, zoom, show_fixed, show_edges

A scene may start from another one: a top-level ``base = "default"`` (a
bundled name or a path, relative to the file) takes that scene and overrides
it key by key, table by table (a ``[fixed]`` table that names its ``kind``
replaces the base's region whole; ``[grasper] waypoints`` are replaced whole).

Unknown tables or keys are errors (a typo must not be ignored silently).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..checks import boolean, choice, keys, number, number_text, quantity, table
from ..config import load as load_config
from ..errors import ConfigError
from ..network.regions import region_from_config

DEFAULT_SCENE = "default"
#: Half-width of a laparoscopic grasper's jaws [m] (radius "auto" grasps at least this).
JAW_RADIUS = 0.004

_TABLES = {
    "scene": {"duration", "frame_rate", "gravity", "gravity_unit", "law", "start", "effects", "volume"},
    "damping": {"dashpot", "velocity_decay"},
    "integrator": {"method", "implicit_step", "haptic_rate", "newton_tol", "factor", "preconditioner", "iteration", "safety", "threads", "precision",
                   "max_steps", "step", "window", "mass_scaling"},
    "fixed": None,  # validated by esmm.pipeline.network.regions (plus kind = "asset")
    "grasper": {"enabled", "target", "radius", "mode", "stiffness", "direction", "grasp_time",
                "release_time", "waypoints"},
    "video": {"width", "height", "colormap", "view", "zoom", "show_fixed", "show_edges"},
    "floor": {"enabled", "height", "friction"},
}
_GRAVITY_UNITS = {"m/s2": 1.0, "m/s^2": 1.0, "mm/s2": 1e-3, "mm/s^2": 1e-3, "g": 9.80665}
_STIFFNESS_UNITS = {"n/m": 1.0, "n/mm": 1e3, "kn/m": 1e3}
VIEWS = ("auto", "xy", "xz", "yz", "iso")
LAWS = ("asset", "secant", "energy")
EFFECTS = ("asset", "none")
#: Use the asset's volume term (nearly incompressible network) or not (docs/design/model.md, "The volume term
#: (nearly incompressible network)").
VOLUME = ("asset", "none")
GRASP_MODES = ("prescribed", "spring")
STARTS = ("equilibrium", "rest")
STEPS = ("adaptive", "table")
PRECISIONS = ("float64", "float32")
FRICTIONS = ("stick", "slip")
DIRECTIONS = ("away", "up")
METHODS = ("implicit", "explicit")
#: What the implicit stepper's reused factor is taken of (docs/design/simulator.md, "What is factored, and when
#: it is renewed").
FACTORS = ("bound", "exact", "mixed")
#: The implicit stepper's reused preconditioner: the matrix's factor, or the two-grid operator on a split
#: asset's parents (docs/design/twogrid.md).
PRECONDITIONERS = ("factor", "two-grid")
#: How the implicit stepper iterates each solve (docs/design/simulator.md, "The iteration: quasi-Newton on a
#: reused factor").
ITERATIONS = ("quasi-newton", "newton")


@dataclass(frozen=True)
class FloorSpec:
    """A rigid floor perpendicular to gravity (docs/design/simulator.md, "The scenes' physics").

    Attributes
    ----------
    height : "auto" or float
        "auto": the plane touching the organ's rest shape from below; else the
        plane's offset along "up" (against gravity) in the asset's frame [m].
    friction : {"stick", "slip"}
    """

    height: Any = "auto"
    friction: str = "stick"


@dataclass(frozen=True)
class Waypoint:
    """A grasper waypoint: at *time* [s] the tip is at grasp point + offset."""

    time: float
    offset: np.ndarray | None = None      #: (3,) [m], or None when *distance* is given
    distance: float | None = None         #: [m] along the grasper direction


@dataclass(frozen=True)
class GrasperSpec:
    """The scripted grasper (SI units).

    Attributes
    ----------
    target : "auto" or ndarray (3,)
        "auto": the surface node farthest from the fixed nodes; else the
        surface node nearest to this point [m].
    radius : float or "auto"
        Every surface node within this distance of the target node is held [m];
        "auto": the larger of :data:`JAW_RADIUS` and 1.05 times the median
        length of the target's springs (so that a coarse mesh is grasped by a
        patch, not by one node).
    mode : {"prescribed", "spring"}
        Held nodes follow the tip exactly, or are tied to it by springs.
    stiffness : float
        Total coupling stiffness in mode "spring" [N/m] (shared by mass).
    direction : "away", "up" or ndarray (3,)
        Unit direction of ``distance`` waypoints: away from the fixed nodes'
        centroid, against gravity, or a given vector.
    grasp_time, release_time : float
        When the grasper closes and opens [s]; release_time None: never.
    waypoints : tuple of Waypoint
        Tip path relative to the grasp point (linear in between; held after).
    """

    target: Any = "auto"
    radius: Any = "auto"
    mode: str = "prescribed"
    stiffness: float = 0.0
    direction: Any = "away"
    grasp_time: float = 0.0
    release_time: float | None = 2.0
    waypoints: tuple = ()


@dataclass(frozen=True)
class VideoSpec:
    width: int = 960
    height: int = 720
    colormap: str = "viridis"
    view: str = "auto"
    zoom: float = 1.0
    show_fixed: bool = True
    show_edges: bool = False


@dataclass(frozen=True)
class Scene:
    """A validated scene (SI units).

    Attributes
    ----------
    duration : float
        Simulated time [s].
    frame_rate : float
        History frames (and video frames) per second of simulated time.
    gravity : ndarray, shape (3,)
        [m/s2] in the asset's coordinates.
    law : {"asset", "secant", "energy"}
    start : {"equilibrium", "rest"}
        Start from the static equilibrium under gravity (found with FIRE before
        t = 0), or from the asset's rest shape (the organ then drops at t = 0).
    effects : {"asset", "none"}
        Apply the material effects stored in the asset (viscoelastic, Mullins,
        damage), or simulate the instantaneous elastic response alone.
    volume : {"asset", "none"}
        Apply the asset's volume term (nearly incompressible network, when the
        asset has one), or the springs alone (for comparisons).
    dashpot : float
        Stiffness-proportional dashpot time beta [s] (0: none).
    velocity_decay : float or None
        Time constant tau of the mass-proportional damping [s] (None: none).
    method : {"explicit", "implicit"}
        The integrator: backward Euler with Newton and a reused factorization
        (:mod:`.implicit`; stable at the frame step; the default: the faster at
        the same accuracy, docs/design/simulator.md, "What it achieves"), or the explicit
        symplectic Euler bounded by the stiffest spring (the accuracy reference).
    implicit_step : "frame" or float
        Step of the implicit solve: one frame (1 / frame_rate), or a time [s].
    haptic_rate : float
        Implicit: samples per second of the recorded grasper force (between
        solves from the grasped patch's stiffness) [Hz].
    newton_tol : float
        Implicit: the largest residual force on a node after a step, as a
        fraction of the largest nodal weight.
    factor : {"bound", "exact", "mixed"}
        Implicit: what the reused factor is taken of, Newton's matrix with the
        volume term's per-tet bound in it (a third of the fill: the fastest
        where the volume term's fill dominates), Newton's matrix itself, or
        Newton's matrix as the saddle point of the springs' matrix and the
        volume term's parts (about half the exact fill; docs/design/simulator.md,
        "What is factored, and when it is renewed").
    preconditioner : {"factor", "two-grid"}
        Implicit: the reused preconditioner, the matrix's factor (default), or on a
        split asset the two-grid operator with its parents as the coarse level:
        cheaper to renew and to apply on large splits, but more iterations and
        solves that stop earlier, so slower at the factor's accuracy
        (docs/design/twogrid.md).
    iteration : {"quasi-newton", "newton"}
        Implicit: how each step's solve iterates, L-BFGS with the reused factor
        (Newton taking over a solve it does not finish; the faster, at the same
        accuracy) or Newton with conjugate gradients (docs/design/simulator.md,
        "The iteration: quasi-Newton on a reused factor").
    safety : float
        Explicit: fraction of the critical time step used.
    step : {"adaptive", "table"}
        "table": one step for the whole run, bounded with the largest tangent
        of the whole table (safe whatever happens); "adaptive": per frame, the
        bound over a stretch window around the current stretches (checked
        along the frame; the frame is redone with a wider window if a stretch
        leaves it).
    window : float
        Half-width delta of the stretch window of "adaptive".
    mass_scaling : float
        Largest inertial mass added to the step-limiting light nodes, as a
        fraction of the organ's mass (0: none); gravity keeps the true masses.
    threads : "auto" or int
    precision : {"float64", "float32"}
    max_steps : int
        Refuse a run that needs more steps than this (a bad asset or scene).
    fixed : FixedRegion or None
        None: the asset's fixed nodes.
    floor : FloorSpec or None
        A rigid floor under the organ (None: no floor).
    grasper : GrasperSpec or None
    video : VideoSpec
    source : str
        Where the scene came from.
    """

    duration: float = 3.0
    frame_rate: float = 30.0
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.80665]))
    law: str = "asset"
    start: str = "equilibrium"
    effects: str = "asset"
    volume: str = "asset"
    dashpot: float = 0.0
    velocity_decay: float | None = 0.2
    method: str = "implicit"
    implicit_step: Any = "frame"
    haptic_rate: float = 1000.0
    newton_tol: float = 0.01
    factor: str = "bound"
    preconditioner: str = "factor"
    iteration: str = "quasi-newton"
    safety: float = 0.9
    step: str = "adaptive"
    window: float = 0.05
    mass_scaling: float = 1e-3
    threads: Any = "auto"
    precision: str = "float64"
    max_steps: int = 50_000_000
    fixed: Any = None
    floor: FloorSpec | None = None
    grasper: GrasperSpec | None = field(default_factory=GrasperSpec)
    video: VideoSpec = field(default_factory=VideoSpec)
    source: str = "built-in defaults"

    @property
    def mass_damping(self) -> float:
        """alpha = 1 / tau [1/s] (0 without velocity decay)."""
        return 0.0 if self.velocity_decay is None else 1.0 / self.velocity_decay

    @property
    def solve_step(self) -> float:
        """The implicit step [s] (one frame unless ``implicit_step`` is a time)."""
        return 1.0 / self.frame_rate if self.implicit_step == "frame" else float(self.implicit_step)

    @property
    def n_frames(self) -> int:
        """Frames after the initial one."""
        return max(1, int(math.ceil(self.duration * self.frame_rate - 1e-9)))

    def with_overrides(self, *, duration=None, threads=None, law: str | None = None,
                       effects: str | None = None, method: str | None = None,
                       volume: str | None = None) -> Scene:
        """A copy with overrides applied (validated; a message names the parameter).

        *duration* is a number of seconds or a time with its unit (``"500 ms"``;
        text with a bare number is seconds); *threads* ``"auto"`` or a whole number.
        """
        out = self
        if method is not None:
            out = replace(out, method=choice(method, METHODS, "method"))
        if effects is not None:
            out = replace(out, effects=choice(effects, EFFECTS, "effects"))
        if volume is not None:
            out = replace(out, volume=choice(volume, VOLUME, "volume"))
        if duration is not None:
            out = replace(out, duration=_seconds(duration, "duration"))
            _check_whole_frame(out, "duration", parameter="duration")
        if threads is not None:
            out = replace(out, threads=_threads(threads, "threads"))
        if law is not None:
            out = replace(out, law=choice(law, LAWS, "law"))
        if out.grasper is not None:
            _check_grasper_times(out.grasper, out.duration, "[grasper]")
        return out

    def describe(self) -> str:
        g = self.grasper
        grasp = "no grasper" if g is None else (
            f"grasper {g.mode}, {len(g.waypoints)} waypoints, release "
            + ("never" if g.release_time is None else f"{g.release_time:g} s"))
        integ = (f"implicit, step {self.solve_step * 1e3:.4g} ms, grasper force at {self.haptic_rate:g} Hz"
                 if self.method == "implicit" else f"explicit ({self.step} step)")
        return (f"{self.duration:g} s at {self.frame_rate:g} frames/s, {integ}, gravity "
                f"{np.round(self.gravity, 3).tolist()} m/s2, law {self.law}, dashpot {self.dashpot * 1e3:g} ms, "
                f"velocity decay {'none' if self.velocity_decay is None else f'{self.velocity_decay:g} s'}, {grasp}, "
                f"material effects {'from the asset' if self.effects == 'asset' else 'off'}, "
                f"volume term {'from the asset' if self.volume == 'asset' else 'off'}, "
                + ("no floor" if self.floor is None else
                   f"floor at {self.floor.height if isinstance(self.floor.height, str) else f'{self.floor.height * 1e3:g} mm'}"
                   f" ({self.floor.friction})"))


# ---------------------------------------------------------------------------
# value helpers (on top of esmm.pipeline.checks)
# ---------------------------------------------------------------------------

def _seconds(value, name: str) -> float:
    """A positive time: a number of seconds (also as text, "2") or a time with its unit ("500 ms")."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return quantity(value, "time", name, lo=0.0, lo_open=True)
    return number_text(value, name, lo=0.0, lo_open=True)


def _threads(value, name: str):
    """``"auto"`` or a whole number >= 1 (also as text)."""
    if value == "auto":
        return "auto"
    try:
        return number_text(value, name, lo=1, integer=True)
    except ConfigError:
        raise ConfigError(f"{name}: expected \"auto\" or a whole number >= 1, got {value!r}",
                          parameter=name) from None


def _vec3(value, name: str, *, lengths: bool) -> np.ndarray:
    """Three numbers, or three lengths with their units (SI)."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        ex = '["10 mm", "0 mm", "5 mm"]' if lengths else "[0, 0, 1]"
        raise ConfigError(f"{name}: expected a list of 3 {'lengths with units' if lengths else 'numbers'}, e.g. {ex}",
                          parameter=name)
    if lengths:
        return np.array([quantity(v, "length", f"{name}[{k}]") for k, v in enumerate(value)])
    return np.array([number(v, f"{name}[{k}]") for k, v in enumerate(value)])


_STIFF = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S+)\s*$")


def _stiffness(value, name: str) -> float:
    """A positive stiffness with its unit (N/m, N/mm, kN/m), in N/m."""
    m = _STIFF.match(value) if isinstance(value, str) else None
    if not m or m.group(2).lower() not in _STIFFNESS_UNITS:
        raise ConfigError(f"{name}: expected a stiffness with its unit ({', '.join(['N/m', 'N/mm', 'kN/m'])}), "
                          f"e.g. \"200 N/m\", got {value!r}", parameter=name)
    v = float(m.group(1)) * _STIFFNESS_UNITS[m.group(2).lower()]
    if not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{name}: must be positive, got {value!r}", parameter=name)
    return v


def _section(data: dict, name: str) -> dict:
    """The table ``[name]`` of a scene (empty when absent), its keys checked."""
    t = table(data.get(name, {}), f"[{name}]")
    if _TABLES[name] is not None:
        keys(t, sorted(_TABLES[name]), f"[{name}]")
    return t


def _check_grasper_times(g: GrasperSpec, duration: float, where: str) -> None:
    if g.grasp_time >= duration:
        raise ConfigError(f"{where} grasp_time: {g.grasp_time:g} s is not before the end of the scene "
                          f"({duration:g} s); shorten it or lengthen the duration")


def _default_gravity(kw: dict) -> np.ndarray:
    return np.asarray(kw.get("gravity", Scene.__dataclass_fields__["gravity"].default_factory()))


# ---------------------------------------------------------------------------
# the parser
# ---------------------------------------------------------------------------

def scene_from_dict(data: dict, *, source: str = "<dict>") -> Scene:
    """Validate a scene table (as read from TOML) into a :class:`Scene`.

    Raises
    ------
    ConfigError
        Unknown table or key, a value without unit, out of range or inconsistent.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a scene must be a TOML table")
    unknown = sorted(set(data) - set(_TABLES))
    if unknown:
        raise ConfigError(f"{source}: unknown table(s) {', '.join('[' + u + ']' for u in unknown)}; "
                          f"allowed: {', '.join('[' + t + ']' for t in _TABLES)}")
    kw: dict[str, Any] = {"source": source}
    kw.update(_scene_table(_section(data, "scene")))
    kw.update(_damping(_section(data, "damping")))
    kw.update(_integrator(_section(data, "integrator")))
    if "fixed" in data:
        kw["fixed"] = _fixed(_section(data, "fixed"), _default_gravity(kw))
    kw["floor"] = _floor(_section(data, "floor"), _default_gravity(kw), present="floor" in data)
    gr = _section(data, "grasper")
    if "enabled" in gr:
        boolean(gr["enabled"], "[grasper] enabled")
    kw["grasper"] = None if gr.get("enabled", True) is False else _grasper(gr)
    kw["video"] = _video(_section(data, "video"))
    scene = Scene(**kw)
    _check_whole_frame(scene, "[scene] frame_rate")
    if scene.grasper is not None:
        _check_grasper_times(scene.grasper, scene.duration, "[grasper]")
    return scene


def _check_whole_frame(scene: Scene, name: str, parameter: str | None = None) -> None:
    """Refuse a duration shorter than one frame: one frame (1 / frame_rate) would be run instead of it."""
    if scene.duration * scene.frame_rate < 1.0 - 1e-9:
        raise ConfigError(f"{name}: {scene.frame_rate:g} frames/s leaves no whole frame in the duration "
                          f"({scene.duration:g} s; a frame is {1.0 / scene.frame_rate:g} s); give at least "
                          f"{1.0 / scene.duration:g} frames/s or a longer duration", parameter=parameter)


def _scene_table(sc: dict) -> dict:
    kw: dict[str, Any] = {}
    if "duration" in sc:
        kw["duration"] = quantity(sc["duration"], "time", "[scene] duration", lo=0.0, lo_open=True)
    if "frame_rate" in sc:
        kw["frame_rate"] = number(sc["frame_rate"], "[scene] frame_rate", lo=0.0, hi=10_000.0, lo_open=True)
    unit = sc.get("gravity_unit", "m/s2")
    unit = choice(unit.lower().replace(" ", "") if isinstance(unit, str) else unit, _GRAVITY_UNITS,
                  "[scene] gravity_unit")
    if "gravity" in sc:
        kw["gravity"] = _vec3(sc["gravity"], "[scene] gravity", lengths=False) * _GRAVITY_UNITS[unit]
    if "start" in sc:
        kw["start"] = choice(sc["start"], STARTS, "[scene] start")
    if "law" in sc:
        kw["law"] = choice(sc["law"], LAWS, "[scene] law")
    if "effects" in sc:
        kw["effects"] = choice(sc["effects"], EFFECTS, "[scene] effects")
    if "volume" in sc:
        kw["volume"] = choice(sc["volume"], VOLUME, "[scene] volume")
    return kw


def _damping(dm: dict) -> dict:
    kw: dict[str, Any] = {}
    if "dashpot" in dm:
        v = dm["dashpot"]
        kw["dashpot"] = 0.0 if v in ("none", 0) else quantity(v, "time", "[damping] dashpot", lo=0.0)
    if "velocity_decay" in dm:
        v = dm["velocity_decay"]
        kw["velocity_decay"] = None if v in ("none", 0) else quantity(v, "time", "[damping] velocity_decay",
                                                                      lo=0.0, lo_open=True)
    return kw


def _integrator(it: dict) -> dict:
    kw: dict[str, Any] = {}
    if "method" in it:
        kw["method"] = choice(it["method"], METHODS, "[integrator] method")
    if "implicit_step" in it and it["implicit_step"] != "frame":
        kw["implicit_step"] = quantity(it["implicit_step"], "time", "[integrator] implicit_step", lo=0.0,
                                       lo_open=True)
    if "haptic_rate" in it:
        kw["haptic_rate"] = number(it["haptic_rate"], "[integrator] haptic_rate", lo=1.0, hi=100_000.0)
    if "newton_tol" in it:
        kw["newton_tol"] = number(it["newton_tol"], "[integrator] newton_tol", lo=0.0, hi=0.5, lo_open=True)
    if "factor" in it:
        kw["factor"] = choice(it["factor"], FACTORS, "[integrator] factor")
    if "preconditioner" in it:
        kw["preconditioner"] = choice(it["preconditioner"], PRECONDITIONERS, "[integrator] preconditioner")
    if "iteration" in it:
        kw["iteration"] = choice(it["iteration"], ITERATIONS, "[integrator] iteration")
    if "safety" in it:
        kw["safety"] = number(it["safety"], "[integrator] safety", lo=0.0, hi=1.0, lo_open=True)
    if "threads" in it:
        kw["threads"] = _threads(it["threads"], "[integrator] threads")
    if "step" in it:
        kw["step"] = choice(it["step"], STEPS, "[integrator] step")
    if "mass_scaling" in it:
        kw["mass_scaling"] = number(it["mass_scaling"], "[integrator] mass_scaling", lo=0.0, hi=0.1)
    if "window" in it:
        kw["window"] = number(it["window"], "[integrator] window", lo=0.0, hi=1.0, lo_open=True)
    if "precision" in it:
        kw["precision"] = choice(it["precision"], PRECISIONS, "[integrator] precision")
    if "max_steps" in it:
        kw["max_steps"] = number(it["max_steps"], "[integrator] max_steps", lo=1, integer=True)
    return kw


def _fixed(fx: dict, gravity: np.ndarray):
    """The ``[fixed]`` region (None: the asset's fixed nodes); a band's axis may be "up" or "down"."""
    if fx.get("kind") == "asset":
        if set(fx) - {"kind"}:
            raise ConfigError("[fixed]: kind = \"asset\" takes no other key")
        return None
    if fx.get("axis") in ("up", "down"):
        # A band across the vertical: its normal is the gravity direction of this scene.
        if not np.any(gravity):
            raise ConfigError(f"[fixed] axis: {fx['axis']!r} needs gravity; give a vector such as [0, 0, 1]")
        up = -gravity / np.linalg.norm(gravity)
        fx = {**fx, "axis": (up if fx["axis"] == "up" else -up).tolist()}
    return region_from_config(fx, where="[fixed]")


def _floor(fl: dict, gravity: np.ndarray, *, present: bool) -> FloorSpec | None:
    """The ``[floor]`` table: absent, no floor; present (even empty, ``[floor]`` alone) without ``enabled``: on."""
    if "enabled" in fl:
        boolean(fl["enabled"], "[floor] enabled")
    if fl.get("enabled", present) is not True:
        return None
    h = fl.get("height", "auto")
    if h != "auto":
        h = quantity(h, "length", "[floor] height")
    fr = choice(fl.get("friction", "stick"), FRICTIONS, "[floor] friction")
    if not np.any(gravity):
        raise ConfigError("[floor]: needs gravity (the floor is perpendicular to it); set [scene] gravity "
                          "or enabled = false")
    return FloorSpec(height=h, friction=fr)


def _grasper(gr: dict) -> GrasperSpec:
    kw: dict[str, Any] = {}
    target = gr.get("target", "auto")
    kw["target"] = "auto" if target == "auto" else _vec3(target, "[grasper] target", lengths=True)
    if "radius" in gr and gr["radius"] != "auto":
        kw["radius"] = quantity(gr["radius"], "length", "[grasper] radius", lo=0.0)
    kw["mode"] = mode = choice(gr.get("mode", "prescribed"), GRASP_MODES, "[grasper] mode")
    if mode == "spring":
        if "stiffness" not in gr:
            raise ConfigError("[grasper] stiffness: mode \"spring\" needs a stiffness, e.g. \"500 N/m\"")
        kw["stiffness"] = _stiffness(gr["stiffness"], "[grasper] stiffness")
    elif "stiffness" in gr:
        raise ConfigError("[grasper] stiffness: only used with mode = \"spring\"; remove it or change the mode")
    direction = gr.get("direction", "away")
    if isinstance(direction, str):
        kw["direction"] = choice(direction, DIRECTIONS, "[grasper] direction")
    else:
        d = _vec3(direction, "[grasper] direction", lengths=False)
        if np.linalg.norm(d) == 0:
            raise ConfigError("[grasper] direction: the zero vector is not a direction")
        kw["direction"] = d / np.linalg.norm(d)
    grasp_time = 0.0 if gr.get("grasp_time") is None else quantity(gr["grasp_time"], "time", "[grasper] grasp_time",
                                                                    lo=0.0)
    kw["grasp_time"] = grasp_time
    rt = gr.get("release_time", "2 s")
    kw["release_time"] = None if rt == "never" else quantity(rt, "time", "[grasper] release_time")
    if kw["release_time"] is not None and kw["release_time"] <= grasp_time:
        raise ConfigError(f"[grasper] release_time: {kw['release_time']:g} s must come after grasp_time "
                          f"({grasp_time:g} s), or be \"never\"")
    kw["waypoints"] = _waypoints(gr.get("waypoints", None), grasp_time)
    return GrasperSpec(**kw)


def _waypoints(wps, grasp_time: float) -> tuple:
    if wps is None:
        wps = [{"time": "0 s", "distance": "0 mm"}, {"time": "1 s", "distance": "15 mm"}]
    if not isinstance(wps, list) or not wps:
        raise ConfigError("[grasper] waypoints: expected a list of tables like {time = \"1 s\", distance = \"15 mm\"}")
    out = []
    for k, w in enumerate(wps):
        where = f"[grasper] waypoints[{k}]"
        if not isinstance(w, dict):
            raise ConfigError(f"{where}: expected a table like {{time = \"1 s\", distance = \"15 mm\"}}")
        keys(w, ("time", "distance", "offset"), where)
        if "time" not in w:
            raise ConfigError(f"{where}: needs a time, e.g. time = \"1 s\"")
        t = quantity(w["time"], "time", f"{where} time")
        if ("distance" in w) == ("offset" in w):
            raise ConfigError(f"{where}: give exactly one of distance = \"15 mm\" (along direction) "
                              f"or offset = [\"0 mm\", \"0 mm\", \"15 mm\"]")
        if "distance" in w:
            out.append(Waypoint(time=t, distance=quantity(w["distance"], "length", f"{where} distance")))
        else:
            out.append(Waypoint(time=t, offset=_vec3(w["offset"], f"{where} offset", lengths=True)))
    times = np.array([w.time for w in out])
    if np.any(np.diff(times) <= 0):
        raise ConfigError("[grasper] waypoints: times must increase strictly")
    if times[0] < grasp_time - 1e-12:
        raise ConfigError(f"[grasper] waypoints: the first waypoint ({times[0]:g} s) is before grasp_time "
                          f"({grasp_time:g} s); the path starts when the grasper closes")
    return tuple(out)


def _video(vd: dict) -> VideoSpec:
    kw: dict[str, Any] = {}
    for key in ("width", "height"):
        if key in vd:
            v = number(vd[key], f"[video] {key}", lo=64, hi=4096, integer=True)
            kw[key] = v + (v % 2)           # H.264 with yuv420p needs even sizes
    if "colormap" in vd:
        cm = vd["colormap"]
        import matplotlib

        if not isinstance(cm, str) or cm not in matplotlib.colormaps:
            raise ConfigError(f"[video] colormap: {cm!r} is not a matplotlib colormap name (e.g. \"viridis\")")
        kw["colormap"] = cm
    if "view" in vd:
        kw["view"] = choice(vd["view"], VIEWS, "[video] view")
    if "zoom" in vd:
        kw["zoom"] = number(vd["zoom"], "[video] zoom", lo=0.1, hi=10.0)
    for key in ("show_fixed", "show_edges"):
        if key in vd:
            kw[key] = boolean(vd[key], f"[video] {key}")
    return VideoSpec(**kw)


def load_scene(name_or_path=None) -> Scene:
    """Load a scene by bundled name (default ``"default"``) or path to a TOML file (module doc: ``base``)."""
    data, source = _load_with_base(DEFAULT_SCENE if name_or_path is None else name_or_path, ())
    return scene_from_dict(data, source=source)


#: Scenes a chain of ``base`` keys may pass through.
MAX_BASES = 8


def _load_with_base(name_or_path, chain: tuple, referrer: str | None = None) -> tuple[dict, str]:
    """The scene table of *name_or_path* with its ``base`` chain merged in, and its source.

    *referrer* is ``"FILE: base = 'NAME'"`` when *name_or_path* is another scene's base (it starts the
    message of a base that cannot be read, so that the user knows which file names it).
    """
    try:
        data, source = load_config("scenes", name_or_path)
    except ConfigError as exc:
        if referrer is None:
            raise
        raise ConfigError(f"{referrer}: {exc}") from None
    if "base" not in data:
        return data, source
    base = data.pop("base")
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{source}: base: expected a scene name or a path to a .toml file, got {base!r}")
    if source in chain or len(chain) >= MAX_BASES:
        raise ConfigError(f"{source}: base: the chain of bases {' -> '.join(chain + (source,))} loops or is "
                          f"longer than {MAX_BASES}; end it with a scene that has no base")
    resolved = base
    if not source.startswith("bundled:") and (base.endswith(".toml") or "/" in base or "\\" in base):
        resolved = str(Path(source).parent / base)
    merged, _ = _load_with_base(resolved, chain + (source,), referrer=f"{source}: base = {base!r}")
    for name, keys_ in data.items():
        if isinstance(keys_, dict) and isinstance(merged.get(name), dict) and not _replaces(name, keys_):
            merged[name] = {**merged[name], **keys_}
        else:
            merged[name] = keys_
    return merged, source


def _replaces(table: str, keys_: dict) -> bool:
    """Whether an overriding table replaces the base's whole (a region of another kind)."""
    return table == "fixed" and "kind" in keys_
