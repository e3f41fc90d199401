"""The scripted grasper: which nodes it holds and the path of its tip.

The grasper closes at ``grasp_time`` on a patch of surface nodes (those
within ``radius`` of a target node), moves its tip along a piecewise-linear
path given relative to the grasp point, holds the last waypoint, and opens at
``release_time``. The force it feels (the pull of the tissue and its weight
on the held nodes) is recorded at every integration step: it is the force a
haptic device renders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ConfigError
from .model import Grasp
from .scene import JAW_RADIUS, GrasperSpec

#: A target point farther outside the organ's bounding box than this fraction of its largest extent is
#: refused (a point in another frame or unit), not silently moved to the nearest surface node.
TARGET_REACH = 0.25


@dataclass(frozen=True)
class GraspPlan:
    """A grasper resolved on a network.

    Attributes
    ----------
    target : int
        The node the tip is placed on.
    nodes : ndarray, shape (g,), int64
        Held nodes (surface nodes within the radius of the target, not fixed).
    direction : ndarray, shape (3,)
        Unit pull direction for ``distance`` waypoints.
    normal : ndarray, shape (3,)
        Outward surface normal at the target (the instrument's shaft axis).
    times : ndarray, shape (p,)
        Waypoint times [s], starting at the grasp time.
    offsets : ndarray, shape (p, 3)
        Tip offsets from the grasp point [m].
    spec : GrasperSpec
    radius : float
        The grasp radius used [m].
    """

    target: int
    nodes: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    times: np.ndarray
    offsets: np.ndarray
    spec: GrasperSpec
    radius: float = 0.0

    def make_grasp(self, x: np.ndarray, mass: np.ndarray) -> Grasp:
        """The :class:`~.model.Grasp` that closes on the current positions *x*."""
        tip0 = np.asarray(x[self.target], dtype=np.float64).copy()
        offsets = x[self.nodes] - tip0
        stiffness = None
        if self.spec.mode == "spring":
            m = mass[self.nodes]
            stiffness = self.spec.stiffness * m / m.sum()
        return Grasp(nodes=self.nodes.copy(), offsets=offsets, wp_t=self.times.copy(),
                     wp_x=tip0[None, :] + self.offsets, mode=self.spec.mode, stiffness=stiffness)

    def coupling_rows(self, x: np.ndarray, mass: np.ndarray) -> np.ndarray | None:
        """Per node, the coupling stiffness this grasper will add [N/m] (None unless mode "spring")."""
        if self.spec.mode != "spring":
            return None
        out = np.zeros(np.asarray(x).shape[0])
        out[self.nodes] = self.make_grasp(x, mass).stiffness
        return out

    def describe(self) -> str:
        far = np.linalg.norm(self.offsets, axis=1).max() * 1e3
        return (f"grasper on node {self.target} ({self.nodes.size} nodes held within {self.radius * 1e3:.3g} mm), path of "
                f"{self.times.size} waypoints up to {far:.3g} mm, mode {self.spec.mode}")


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted outward vertex normals of a triangle surface, shape (n, 3) (zero off the surface)."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    out = np.zeros_like(p)
    for k in range(3):
        np.add.at(out, f[:, k], fn)
    norm = np.linalg.norm(out, axis=1)
    nz = norm > 0
    out[nz] /= norm[nz, None]
    return out


def plan_grasp(spec: GrasperSpec, points: np.ndarray, surface_faces: np.ndarray, fixed: np.ndarray,
               gravity: np.ndarray, *, springs: np.ndarray | None = None) -> GraspPlan:
    """Resolve *spec* on a network.

    Parameters
    ----------
    spec : GrasperSpec
    points : ndarray, shape (n, 3)
        Rest positions [m].
    surface_faces : ndarray, shape (k, 3)
        Outward boundary triangles.
    fixed : ndarray of int
        Fixed nodes (never grasped).
    gravity : ndarray, shape (3,)
        [m/s2], for ``direction = "up"``.
    springs : ndarray, shape (s, 2), optional
        The network's springs, for ``radius = "auto"``.

    Raises
    ------
    ConfigError
        No free surface node, a target point far outside the organ (:data:`TARGET_REACH`), a radius
        that holds every free surface node, or ``direction = "up"`` without gravity.
    """
    p = np.asarray(points, dtype=np.float64)
    faces = np.asarray(surface_faces, dtype=np.int64).reshape(-1, 3)
    fixed = np.asarray(fixed, dtype=np.int64)
    surface = np.unique(faces)
    if surface.size == 0:
        raise ConfigError("[grasper]: the network has no surface triangles to grasp; disable the grasper "
                          "([grasper] enabled = false) or rebuild the asset")
    is_fixed = np.zeros(p.shape[0], bool)
    is_fixed[fixed] = True
    cand = surface[~is_fixed[surface]]
    if cand.size == 0:
        raise ConfigError("[grasper]: every surface node is fixed; shrink the fixed region")
    target = _target_node(spec, p, cand, fixed)
    radius = _grasp_radius(spec, p, target, springs)
    near = cKDTree(p[cand]).query_ball_point(p[target], r=radius)
    nodes = np.union1d(cand[np.asarray(near, dtype=np.int64)], [target]).astype(np.int64)
    _check_patch(nodes, cand, p, target, radius)
    normal = vertex_normals(p, faces)[target]
    if not np.any(normal):
        normal = p[target] - p.mean(axis=0)
        normal = normal / (np.linalg.norm(normal) or 1.0)
    direction = _pull_direction(spec, p, target, fixed, gravity, normal)

    times = [w.time for w in spec.waypoints]
    offs = [w.offset if w.offset is not None else w.distance * direction for w in spec.waypoints]
    if times[0] > spec.grasp_time:
        times.insert(0, spec.grasp_time)
        offs.insert(0, np.zeros(3))
    return GraspPlan(target=target, nodes=nodes, direction=direction, normal=normal,
                     times=np.asarray(times, dtype=np.float64), offsets=np.asarray(offs, dtype=np.float64),
                     spec=spec, radius=float(radius))


def _check_patch(nodes: np.ndarray, cand: np.ndarray, p: np.ndarray, target: int, radius: float) -> None:
    """Refuse a grasp radius that holds every free surface node: the grasper would carry the organ whole."""
    if cand.size > 1 and nodes.size == cand.size:
        far = float(np.linalg.norm(p[cand] - p[target], axis=1).max())
        raise ConfigError(f"[grasper] radius: {radius * 1e3:.4g} mm holds every free surface node of the organ "
                          f"({cand.size}; the farthest is {far * 1e3:.4g} mm from the grasp point), so the grasper "
                          f"would carry it whole; give a radius below {far * 1e3:.4g} mm (a grasper holds a patch)")


def _target_node(spec: GrasperSpec, p: np.ndarray, cand: np.ndarray, fixed: np.ndarray) -> int:
    """The candidate node the tip goes to: "auto" farthest from the fixed nodes (or the centroid), else nearest."""
    if isinstance(spec.target, str):
        if fixed.size:
            d, _ = cKDTree(p[fixed]).query(p[cand])
        else:
            d = np.linalg.norm(p[cand] - p.mean(axis=0), axis=1)
        return int(cand[np.argmax(d)])
    t = np.asarray(spec.target, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    outside = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - t, t - hi))))
    if outside > TARGET_REACH * float((hi - lo).max()):
        span = ", ".join(f"{a} {lo[k] * 1e3:.4g}..{hi[k] * 1e3:.4g}" for k, a in enumerate("xyz"))
        raise ConfigError(f"[grasper] target: {np.round(t * 1e3, 4).tolist()} mm is {outside * 1e3:.4g} mm outside "
                          f"the organ ({span} mm in the asset's coordinates); give a point on or near its "
                          "surface (with its unit, e.g. \"220 mm\"), or \"auto\"")
    d = np.linalg.norm(p[cand] - t, axis=1)
    return int(cand[np.argmin(d)])


def _grasp_radius(spec: GrasperSpec, p: np.ndarray, target: int, springs) -> float:
    """The grasp radius [m]; "auto": the jaws, or 1.05 x the median length of the target's springs."""
    radius = spec.radius
    if isinstance(radius, str):
        radius = JAW_RADIUS
        if springs is not None:
            sp = np.asarray(springs)
            inc = (sp[:, 0] == target) | (sp[:, 1] == target)
            if inc.any():
                lengths = np.linalg.norm(p[sp[inc, 1]] - p[sp[inc, 0]], axis=1)
                radius = max(radius, 1.05 * float(np.median(lengths)))
    return radius


def _pull_direction(spec: GrasperSpec, p: np.ndarray, target: int, fixed: np.ndarray, gravity,
                    normal: np.ndarray) -> np.ndarray:
    """Unit direction of ``distance`` waypoints: against gravity, away from the fixed nodes, or given."""
    if not isinstance(spec.direction, str):
        return np.asarray(spec.direction, dtype=np.float64)
    if spec.direction == "up":
        gn = float(np.linalg.norm(gravity))
        if gn == 0:
            raise ConfigError("[grasper] direction: \"up\" needs gravity; give a vector instead")
        return -np.asarray(gravity, dtype=np.float64) / gn
    ref = p[fixed].mean(axis=0) if fixed.size else p.mean(axis=0)
    direction = p[target] - ref
    norm = float(np.linalg.norm(direction))
    return direction / norm if norm > 0 else normal
