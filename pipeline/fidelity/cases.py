"""Load cases: one solver-neutral description of a static problem for both solvers.

A :class:`LoadCase` is the rest mesh (the asset's nodes and tetrahedra), a
body force (gravity on the tissue density) and Dirichlet constraints per node
and component (:class:`Constraint`), each reached linearly with the load factor
t in [0, 1]. The continuum (:mod:`.continuum`) and the network
(:mod:`.network_solve`) solve exactly this problem; nothing else about the
boundary is assumed by either.

Cases (docs/design/validation.md, "Load cases (the same on both sides)", states each boundary condition and why):

* ``tension``, ``compression`` -- frictionless grips on the two end faces
  along an axis (normal displacement prescribed, lateral motion free, rigid
  modes held at two nodes): on a block a homogeneous continuum is exactly in
  uniaxial stress, the analytic reference of the FE verification;
* ``shear`` -- bottom face clamped, top face clamped and moved sideways by
  γ times the height, lateral faces free;
* ``gravity`` -- the default scene: gravity, the lowest 5 % along gravity
  held (the anchor), the floor's sticking contacts as pins (:func:`with_floor_pins`);
* ``lift`` -- the same bed with the grasped patch moved by the scene's
  last waypoint (20 mm up) from its rest position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import ConfigError
from ..network.springs import tet_volumes

__all__ = ["CASES", "SPECIMEN_CASES", "ORGAN_CASES", "Constraint", "LoadCase", "Floor", "end_faces",
           "oriented", "uniaxial_case", "shear_case", "gravity_case", "lift_case", "with_floor_pins", "at_load",
           "grasp_hold", "parent_faces", "LiftStretch", "lift_stretch"]

SPECIMEN_CASES = ("tension", "compression", "shear")
ORGAN_CASES = ("gravity", "lift")
CASES = SPECIMEN_CASES + ORGAN_CASES


@dataclass(frozen=True, eq=False)
class Constraint:
    """Prescribed displacements of a group of nodes.

    Attributes
    ----------
    name : str
    nodes : ndarray of int, shape (k,)
    mask : ndarray of bool, shape (k, 3)
        The prescribed components.
    displacement : ndarray, shape (k, 3)
        Their values at full load [m] (ignored where ``mask`` is False).
    """

    name: str
    nodes: np.ndarray
    mask: np.ndarray
    displacement: np.ndarray

    @classmethod
    def clamp(cls, name: str, nodes, displacement=(0.0, 0.0, 0.0)) -> Constraint:
        """All three components of *nodes* prescribed to *displacement* ((3,) or (k, 3))."""
        nodes = np.asarray(nodes, dtype=np.int64).ravel()
        u = np.broadcast_to(np.asarray(displacement, dtype=np.float64), (nodes.size, 3)).copy()
        return cls(name, nodes, np.ones((nodes.size, 3), bool), u)


@dataclass(frozen=True)
class Floor:
    """The bed: the plane ``normal . x = height`` (normal against gravity), sticking contact."""

    normal: np.ndarray
    height: float


@dataclass(frozen=True, eq=False)
class LoadCase:
    """A static problem on a tetrahedral mesh (SI units).

    Attributes
    ----------
    name : str
        One of :data:`CASES`.
    description : str
        The boundary conditions in words (for the report).
    points : ndarray, shape (n, 3)
        Rest positions [m].
    tets : ndarray of int, shape (t, 4)
        Positively oriented tetrahedra.
    constraints : tuple of Constraint
        Disjoint node groups.
    force_group : str
        The constraint whose reaction is compared.
    gravity : ndarray, shape (3,)
        [m/s2] (zeros: none).
    density : float
        [kg/m3] (the network's masses are its own lumped masses: the same weight).
    force_scale : float or None
        Divisor of the force error [N]; None: the FE reaction's magnitude.
    floor : Floor or None
        Checked after a solve: a node below it becomes a pin (:func:`with_floor_pins`).
    load : dict
        The load's figures (stretch, gamma, lift vector) for the report.
    quadratic_cells : ndarray of int, shape (p, 10), or None
        10-node tetrahedra whose nodes are all of *points* (a network split from
        them): the second-order continuum is then solved on these, node for
        node, instead of on quadratic tetrahedra added to ``tets``.
    """

    name: str
    description: str
    points: np.ndarray
    tets: np.ndarray
    constraints: tuple
    force_group: str
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    density: float = 0.0
    force_scale: float | None = None
    floor: Floor | None = None
    load: dict = field(default_factory=dict)
    quadratic_cells: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    def constraint(self, name: str) -> Constraint:
        for c in self.constraints:
            if c.name == name:
                return c
        raise KeyError(name)

    def prescribed(self) -> tuple[np.ndarray, np.ndarray]:
        """``(mask, u)``: prescribed components (n, 3) bool and their full-load values (n, 3) [m]."""
        mask = np.zeros((self.n_nodes, 3), bool)
        u = np.zeros((self.n_nodes, 3))
        for c in self.constraints:
            mask[c.nodes] |= c.mask
            u[c.nodes] = np.where(c.mask, c.displacement, u[c.nodes])
        return mask, u

    def node_volumes(self) -> np.ndarray:
        """Lumped nodal volumes (a quarter of each tet) [m3], shape (n,): the L2 weights."""
        v = np.zeros(self.n_nodes)
        np.add.at(v, self.tets.ravel(), np.repeat(tet_volumes(self.points, self.tets) / 4.0, 4))
        return v


def oriented(points: np.ndarray, tets) -> np.ndarray:
    """*tets* (t, 4) with the negatively oriented ones turned (two vertices swapped)."""
    t = np.array(tets, dtype=np.int64).reshape(-1, 4)
    neg = tet_volumes(points, t) < 0
    t[neg, 2], t[neg, 3] = t[neg, 3], t[neg, 2].copy()
    return t


def _check_disjoint(constraints) -> tuple:
    seen = np.concatenate([c.nodes for c in constraints]) if constraints else np.zeros(0, np.int64)
    if np.unique(seen).size != seen.size:
        raise ConfigError("constraints: node groups overlap; every node may belong to one group only")
    return tuple(constraints)


def end_faces(points: np.ndarray, axis: int, *, slab: float = 0.05) -> tuple[np.ndarray, np.ndarray, float]:
    """The nodes of the two end faces along *axis* and the length between them.

    A flat end face (a block, a cylinder): the nodes within 1e-6 of the
    extent of the extreme coordinate; otherwise (an organ) the *slab*
    fraction of the extent at each end.

    Returns
    -------
    bottom, top : ndarray of int
    length : float
        Distance between the two faces' mean coordinates along *axis* [m].
    """
    s = np.asarray(points)[:, axis]
    lo, hi = float(s.min()), float(s.max())
    tol = 1e-6 * (hi - lo)
    bottom, top = np.flatnonzero(s <= lo + tol), np.flatnonzero(s >= hi - tol)
    if bottom.size < 3 or top.size < 3:
        bottom = np.flatnonzero(s <= lo + slab * (hi - lo))
        top = np.flatnonzero(s >= hi - slab * (hi - lo))
    return bottom, top, float(s[top].mean() - s[bottom].mean())


def _axis(points, axis) -> int:
    if axis is None:  # the longest extent
        return int(np.argmax(np.ptp(points, axis=0)))
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis: must be 0, 1 or 2 (x, y, z), got {axis!r}", parameter="axis")
    return int(axis)


def _rigid_pair(points, bottom, lat) -> tuple[int, int, int]:
    """Two bottom nodes c, r and the component of r to hold, so that the rigid modes are held
    without restraining a homogeneous lateral strain about c.

    Holding c laterally and r across the line c-r is compatible with any
    lateral stretch about c when that line is a coordinate direction: the two
    are taken on the row of bottom nodes with the most nodes at one lateral
    coordinate (an edge of a block's face), c nearest the row's middle, r
    farthest from c. On a face without such a row (an organ's slab) the
    bottom node nearest the centre and the farthest one are used.
    """
    p = points[bottom][:, lat]
    span = float(np.ptp(p, axis=0).max()) or 1.0
    for k in (1, 0):
        key = np.round(p[:, k] / (1e-7 * span)).astype(np.int64)
        vals, counts = np.unique(key, return_counts=True)
        row = np.flatnonzero(key == vals[np.argmax(counts)])
        if row.size >= 3:
            mid = p[row, 1 - k].mean()
            c = row[np.argmin(np.abs(p[row, 1 - k] - mid))]
            r = row[np.argmax(np.abs(p[row, 1 - k] - p[c, 1 - k]))]
            return int(bottom[c]), int(bottom[r]), lat[k]
    c = int(np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1)))
    r = int(np.argmax(np.linalg.norm(p - p[c], axis=1)))
    d = p[r] - p[c]
    return int(bottom[c]), int(bottom[r]), lat[int(np.argmin(np.abs(d)))]


def uniaxial_case(points, tets, *, stretch: float, axis: int | None = 2, density: float = 0.0) -> LoadCase:
    """Uniaxial tension (stretch > 1) or compression (< 1) between frictionless grips.

    The two end faces along *axis* get their normal displacement (0 and
    ``(stretch - 1) L``); lateral motion is free, except the rigid modes: the
    bottom node nearest the face's centre is held laterally, the bottom node
    farthest from it is held across the line joining them.
    """
    if not (np.isfinite(stretch) and 0.5 <= stretch <= 2.0 and stretch != 1.0):
        raise ConfigError(f"stretch: must be in 0.5..2 and not 1, got {stretch!r}", parameter="stretch")
    points = np.asarray(points, dtype=np.float64)
    a = _axis(points, axis)
    lat = [k for k in range(3) if k != a]
    bottom, top, length = end_faces(points, a)
    c, r, k_across = _rigid_pair(points, bottom, lat)
    mask_b = np.zeros((bottom.size, 3), bool)
    mask_b[:, a] = True
    mask_b[bottom == c, lat[0]] = mask_b[bottom == c, lat[1]] = True
    mask_b[bottom == r, k_across] = True
    mask_t = np.zeros((top.size, 3), bool)
    mask_t[:, a] = True
    u_t = np.zeros((top.size, 3))
    u_t[:, a] = (stretch - 1.0) * length
    name = "tension" if stretch > 1 else "compression"
    ax = "xyz"[a]
    cons = _check_disjoint([Constraint("bottom", bottom, mask_b, np.zeros((bottom.size, 3))),
                            Constraint("top", top, mask_t, u_t)])
    desc = (f"uniaxial {name} to stretch {stretch:g} along {ax} (length {length * 1e3:.4g} mm): frictionless "
            f"grips, the {bottom.size} bottom-face nodes at u_{ax} = 0 and the {top.size} top-face nodes at "
            f"u_{ax} = {(stretch - 1) * length * 1e3:.4g} mm, lateral motion free; rigid modes held at two "
            "bottom nodes; reaction on the top face")
    return LoadCase(name, desc, points, oriented(points, tets), cons, "top", density=density,
                    load={"stretch": float(stretch), "axis": ax, "length_m": length,
                          "area_m2": float(np.abs(tet_volumes(points, tets)).sum()) / length})


def shear_case(points, tets, *, gamma: float, axis: int | None = 2, direction: int | None = None,
               density: float = 0.0) -> LoadCase:
    """Simple shear of a block: bottom face clamped, top face clamped and moved by ``gamma L`` sideways."""
    if not (np.isfinite(gamma) and 0 < abs(gamma) <= 1.0):
        raise ConfigError(f"gamma: must be in 0..1 in magnitude and not 0, got {gamma!r}", parameter="gamma")
    points = np.asarray(points, dtype=np.float64)
    a = _axis(points, axis)
    b = [k for k in range(3) if k != a][0] if direction is None else int(direction)
    bottom, top, length = end_faces(points, a)
    shift = np.zeros(3)
    shift[b] = gamma * length
    cons = _check_disjoint([Constraint.clamp("bottom", bottom), Constraint.clamp("top", top, shift)])
    ax, bx = "xyz"[a], "xyz"[b]
    desc = (f"simple shear gamma = {gamma:g} ({bx} displacement over {ax} height {length * 1e3:.4g} mm): the "
            f"{bottom.size} bottom-face nodes clamped, the {top.size} top-face nodes clamped and moved "
            f"{gamma * length * 1e3:.4g} mm along {bx}, lateral faces free; reaction on the top face")
    return LoadCase("shear", desc, points, oriented(points, tets), cons, "top", density=density,
                    load={"gamma": float(gamma), "axis": ax, "direction": bx, "length_m": length})


def _bed(points, scene, fixed: np.ndarray):
    g = np.asarray(scene.gravity, dtype=np.float64)
    if not np.any(g):
        raise ConfigError("scene: the gravity and lift cases need gravity", parameter="scene")
    up = -g / np.linalg.norm(g)
    floor = None
    if scene.floor is not None:
        h = scene.floor.height
        floor = Floor(up, float(np.min(points @ up)) if isinstance(h, str) else float(h))
    if fixed.size == 0 and floor is None:
        raise ConfigError("scene: holds nothing (no fixed nodes, no floor); a static problem needs a support",
                          parameter="scene")
    return g, floor


def gravity_case(points, tets, *, scene, fixed, density: float, weight: float) -> LoadCase:
    """The organ under gravity on its bed: the scene's fixed nodes clamped, the floor as pins."""
    points = np.asarray(points, dtype=np.float64)
    fixed = np.asarray(fixed, dtype=np.int64)
    g, floor = _bed(points, scene, fixed)
    cons = _check_disjoint([Constraint.clamp("anchor", fixed)])
    desc = (f"gravity {np.linalg.norm(g):.4g} m/s2 on the tissue ({weight:.4g} N); the scene's {fixed.size} "
            "fixed nodes clamped (the anchor)"
            + ("; the sticking floor as pins at the plane under each node that would go below it"
               if floor is not None else "") + "; reaction on the anchor, relative to the weight")
    return LoadCase("gravity", desc, points, oriented(points, tets), cons, "anchor", gravity=g,
                    density=float(density), force_scale=float(weight), floor=floor,
                    load={"weight_N": float(weight)})


def lift_case(points, tets, *, scene, fixed, grasped, lift, density: float, weight: float) -> LoadCase:
    """The grasper's lift: the bed of :func:`gravity_case` and the grasped patch moved by *lift* from rest."""
    points = np.asarray(points, dtype=np.float64)
    fixed = np.asarray(fixed, dtype=np.int64)
    grasped = np.setdiff1d(np.asarray(grasped, dtype=np.int64), fixed)
    g, floor = _bed(points, scene, fixed)
    lift = np.asarray(lift, dtype=np.float64).reshape(3)
    if grasped.size == 0:
        raise ConfigError("scene: the grasper holds no free node", parameter="scene")
    cons = _check_disjoint([Constraint.clamp("anchor", fixed), Constraint.clamp("grasper", grasped, lift)])
    desc = (f"the bed of the gravity case and the {grasped.size} grasped surface nodes moved "
            f"{np.linalg.norm(lift) * 1e3:.4g} mm along {np.round(lift / np.linalg.norm(lift), 3).tolist()} "
            "from their rest positions (prescribed); reaction on the grasped nodes (the grasper force)")
    return LoadCase("lift", desc, points, oriented(points, tets), cons, "grasper", gravity=g,
                    density=float(density), floor=floor, load={"lift_m": lift.tolist(), "weight_N": float(weight)})


def with_floor_pins(case: LoadCase, nodes, positions=None) -> LoadCase:
    """*case* with *nodes* pinned on its floor: each at the point of the plane under *positions*.

    A pin holds a node's tangential position (sticking friction) at the plane
    (no penetration). *positions* (k, 3) default to the nodes' rest positions;
    pins keep their place when the case is given more. Nodes already in
    another group are skipped.
    """
    if case.floor is None:
        return case
    nodes = np.asarray(nodes, dtype=np.int64)
    at = case.points[nodes] if positions is None else np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    taken = np.concatenate([c.nodes for c in case.constraints if c.name != "floor"])
    keep = ~np.isin(nodes, taken)
    nodes, at = nodes[keep], at[keep]
    n, h = case.floor.normal, case.floor.height
    target = at - ((at @ n) - h)[:, None] * n[None, :]
    old = [c for c in case.constraints if c.name == "floor"]
    if old:
        fresh = ~np.isin(nodes, old[0].nodes)
        nodes = np.concatenate([old[0].nodes, nodes[fresh]])
        target = np.vstack([case.points[old[0].nodes] + old[0].displacement, target[fresh]])
    others = tuple(c for c in case.constraints if c.name != "floor")
    cons = others + ((Constraint.clamp("floor", nodes, target - case.points[nodes]),) if nodes.size else ())
    return replace(case, constraints=_check_disjoint(cons))


def at_load(case: LoadCase, t: float) -> LoadCase:
    """*case* at load factor *t*: gravity and the prescribed displacements scaled (floor pins kept)."""
    cons = tuple(c if c.name == "floor" else replace(c, displacement=t * c.displacement) for c in case.constraints)
    return replace(case, gravity=t * np.asarray(case.gravity, dtype=np.float64), constraints=cons)


#: A 10-node tetrahedron's four faces as 6-node triangles: corners, then the middles of 01, 12, 20 (local nodes,
#: felupe's ``tetra10`` order: :data:`~esmm.pipeline.mesh.refine.TET10_EDGES`).
_TET10_FACES = ((0, 1, 2, 4, 5, 6), (0, 1, 3, 4, 8, 7), (1, 2, 3, 5, 9, 8), (0, 2, 3, 6, 9, 7))


def parent_faces(cells: np.ndarray) -> np.ndarray:
    """The boundary faces of 10-node tetrahedra *cells* (p, 10) as 6-node triangles (k, 6)."""
    cells = np.asarray(cells, dtype=np.int64)
    f6 = np.concatenate([cells[:, list(ix)] for ix in _TET10_FACES])
    _, first, count = np.unique(np.sort(f6[:, :3], axis=1), axis=0, return_index=True, return_counts=True)
    return f6[first[count == 1]]


def grasp_hold(case: LoadCase, surface_faces) -> dict:
    """What the grasped nodes of a lift *case* hold, on each side.

    The network (and a continuum on its own tetrahedra) holds every surface triangle whose three corners are
    grasped. A P2 field on a split network's parents (``case.quadratic_cells``) is held on a parent face only
    where all six of its nodes are grasped; elsewhere it is held at the grasped points and along edges with
    all three nodes grasped. ``network_only`` counts the triangles the network holds that lie in no parent
    face held whole (each held parent face holds its four children): where it is not 0 the two hold different
    patches (docs/design/validation.md, "Is the reference converged for the grasper force?").
    """
    g = case.constraint("grasper").nodes
    held = int(np.count_nonzero(np.all(np.isin(np.asarray(surface_faces).reshape(-1, 3), g), axis=1)))
    out = {"grasped_nodes": int(g.size), "surface_triangles_held": held}
    if case.quadratic_cells is not None:
        parents = int(np.count_nonzero(np.all(np.isin(parent_faces(case.quadratic_cells), g), axis=1)))
        out.update(parent_faces_held=parents, network_only=held - 4 * parents)
    return out


@dataclass(frozen=True, eq=False)
class LiftStretch:
    """The stretch a lift forces along a straight segment inside the body (:func:`lift_stretch`).

    Attributes
    ----------
    stretch : float
        r = |x_g + u_g - x_h| / |x_g - x_h| (1 where no segment is found).
    length : float
        |x_g - x_h| [m].
    grasped, anchor : int
        The segment's ends (-1 where none is found).
    offset : ndarray, shape (3,), or None
        x_g - x_h [m] (None where none is found).
    direction : ndarray, shape (3,), or None
        The unit direction of u_g.
    """

    stretch: float = 1.0
    length: float = 0.0
    grasped: int = -1
    anchor: int = -1
    offset: np.ndarray | None = None
    direction: np.ndarray | None = None

    def lift_at(self, s: float) -> float:
        """The displacement's length L [m] along its direction at which this segment's ratio reaches *s*:
        the positive root of |d + L e|² = s² |d|²."""
        if self.offset is None:
            return math.inf
        b = float(self.offset @ self.direction)
        return -b + math.sqrt(max(b * b - float(self.offset @ self.offset) * (1.0 - s * s), 0.0))


def lift_stretch(case: LoadCase, *, pairs: int = 30) -> LiftStretch:
    """The largest stretch a lift *case* forces along a straight segment inside the body.

    An anchor node h (held at rest) and a grasped node g (moved by u_g) joined by a straight segment that
    lies inside the body: the deformed segment joins x_h and x_g + u_g, so it is at least |x_g + u_g - x_h|
    long, and somewhere along it the stretch in its direction, hence the largest principal stretch, is at
    least the ratio r of that distance to |x_g - x_h|. An isochoric material then has Ī1 >= r² + 2/r there,
    whatever the continuum does elsewhere: where that passes the material's locking invariant the case has
    no equilibrium. For each grasped node its *pairs* most stretched anchors are tried; a segment counts
    where its midpoint lies in a tetrahedron and it crosses the mesh's boundary nowhere between its ends
    (then all of it is inside: where in doubt, a grazing or a crossing near an end, it does not count).
    """
    import pyvista as pv
    import vtk

    anchor, grasp = case.constraint("anchor"), case.constraint("grasper")
    pts = case.points
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(case.tets, dtype=np.int64)}, pts)
    boundary = vtk.vtkDataSetSurfaceFilter()
    boundary.SetInputData(grid)
    boundary.Update()
    tree = vtk.vtkOBBTree()
    tree.SetDataSet(boundary.GetOutput())
    tree.BuildLocator()
    hits = vtk.vtkPoints()

    def inside(a: np.ndarray, b: np.ndarray) -> bool:
        if grid.find_containing_cell((a + b) / 2.0) < 0:
            return False
        tree.IntersectWithLine(a, b, hits, None)
        tol = 1e-6 * float(np.linalg.norm(b - a))
        return all(min(np.linalg.norm(np.array(hits.GetPoint(k)) - e) for e in (a, b)) <= tol
                   for k in range(hits.GetNumberOfPoints()))

    best = LiftStretch()
    for g, u in zip(grasp.nodes, grasp.displacement):
        d0 = np.linalg.norm(pts[g] - pts[anchor.nodes], axis=1)
        r = np.linalg.norm(pts[g] + u - pts[anchor.nodes], axis=1) / np.where(d0 > 0, d0, np.inf)
        for j in np.argsort(-r)[:pairs]:
            if r[j] <= best.stretch:
                break
            h = anchor.nodes[j]
            if inside(pts[h], pts[g]):
                best = LiftStretch(float(r[j]), float(d0[j]), int(g), int(h), pts[g] - pts[h],
                                   np.asarray(u) / (float(np.linalg.norm(u)) or 1.0))
                break
    return best
