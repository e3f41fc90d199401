"""Tetrahedral meshing of a cleaned surface.

:func:`mesh_volume` tries, in order, until one result passes the checks:

1. ``gmsh``: in a child process with a time limit
   (:mod:`~esmm.pipeline.mesh.gmsh_worker`): the surface is classified with a
   wide angle (180 degrees: a smooth organ has no feature edges, and 40 degrees
   breaks a staircase into thousands of patches), split into parametrisable
   patches, remeshed at the target size (Frontal-Delaunay 2D) and filled with
   tetrahedra (Delaunay 3D, then gmsh's and Netgen's optimisers).
2. ``gmsh-after-repair``: the same after a stronger pymeshfix repair of the
   surface (self-intersections are what gmsh's PLC recovery fails on).
3. ``pytetwild``: fTetWild (robust to self-intersections and near-degenerate
   input; it meshes an envelope of the surface, so its boundary moves by at
   most 1e-3 of the bounding-box diagonal).

Checks on every result: more than zero tetrahedra (gmsh only warns when its
boundary recovery fails), no inverted or flat element (all signed volumes
positive once the global orientation is fixed), and the mesh volume within
:data:`MAX_MESH_VOLUME_ERROR` (1 %) of the surface's enclosed volume. The path
taken and every failure are recorded in :attr:`VolumeMesh.path` and
:attr:`VolumeMesh.log`. How fine the mesh is asked for (a size, a node or a
tetrahedron count) is the rule of :mod:`~esmm.pipeline.mesh.targets`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..checks import number
from ..errors import ConfigError, MeshingError
from ..progress import ensure
from .cleaning import face_components, keep_largest, meshfix, meshfix_arrays, orient_outward
from .gmsh_worker import GmshFailure, GmshTimeout, run_worker
from .readers import boundary_of_tets
from .slivers import SLIVER_TARGET_DEG, improve_slivers
from .surface import Surface
from .targets import (
    DEFAULT_NODES,
    ELEMENTS_TOLERANCE,
    NODES_TOLERANCE,
    MeshTarget,
    expected_nodes,
    mesh_target,
    nodes_exponent,
    size_for_elements,
    size_for_nodes,
)

#: Largest accepted relative difference of mesh and surface volume.
MAX_MESH_VOLUME_ERROR = 0.01

#: fTetWild edge length / gmsh size giving about the same node count (measured).
_TETWILD_EDGE_FACTOR = 1.3

#: Most nodes a mesh may be expected to have (beyond: refused before meshing).
MAX_EXPECTED_NODES = 2_000_000


@dataclass(frozen=True)
class VolumeMesh:
    """Tetrahedra in metres, positively oriented, with their outward boundary.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Node coordinates [m]; every node belongs to a tetrahedron.
    tets : ndarray, shape (t, 4), int64
        Node indices; ``det([p1-p0, p2-p0, p3-p0]) > 0`` for every element.
    boundary_faces : ndarray, shape (k, 3), int64
        Faces used by one tetrahedron, counter-clockwise seen from outside.
    path : str
        The mesher that produced it: ``"gmsh"``, ``"gmsh-after-repair"`` or
        ``"pytetwild"`` (``"+split"`` appended by :func:`~.refine.split_mesh`).
    log : list of str
        What was tried, with timings and reasons for failures.
    quadratic_cells : ndarray, shape (p, 10), int64, or None
        A split mesh's parents as 10-node tetrahedra on its nodes (:mod:`.refine`).
    """

    points: np.ndarray
    tets: np.ndarray
    boundary_faces: np.ndarray
    path: str = "gmsh"
    log: list[str] = field(default_factory=list)
    quadratic_cells: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def tet_volumes(self) -> np.ndarray:
        """Signed volume of each tetrahedron [m3], shape (t,)."""
        p = self.points
        t = self.tets
        a = p[t[:, 1]] - p[t[:, 0]]
        b = p[t[:, 2]] - p[t[:, 0]]
        c = p[t[:, 3]] - p[t[:, 0]]
        return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0

    def volume(self) -> float:
        """Total volume [m3]."""
        return float(self.tet_volumes().sum())

    def boundary_surface(self) -> Surface:
        """The boundary as a :class:`Surface` (points compacted)."""
        return Surface(self.points, self.boundary_faces, f"boundary of a {self.path} mesh").compact()


def mesh_volume(surface: Surface, *, size: float | None = None, nodes: int | None = None,
                elements: int | None = None, timeout: float = 120.0, reporter=None) -> VolumeMesh:
    """Fill a closed surface with tetrahedra.

    Parameters
    ----------
    surface
        A closed, outward surface (from
        :func:`~esmm.pipeline.mesh.cleaning.clean_surface`), points in metres.
    size, nodes, elements
        At most one target (:mod:`~esmm.pipeline.mesh.targets`): the
        tetrahedron edge [m], a node count or a tetrahedron count; the size for
        a count is estimated and corrected once if the result is off by more
        than the target's tolerance. Default: :data:`~.targets.DEFAULT_NODES` nodes.
    timeout
        Time limit of each mesher run [s]; a run that exceeds it is killed.
    reporter
        Progress reporter (one step per attempt).

    Returns
    -------
    VolumeMesh

    Raises
    ------
    ConfigError
        A bad target or timeout (naming the parameter).
    MeshingError
        The surface is open, or every path failed (the message lists why).
    """
    rep = ensure(reporter)
    target = mesh_target(size=size, nodes=nodes, elements=elements)
    timeout = number(timeout, "timeout", lo=0.0, lo_open=True)
    _check_closed(surface)
    if target.elements is not None:
        return _mesh_for_elements(surface, target.elements, timeout, rep)
    return _mesh_at(surface, target, timeout, rep)


def _check_closed(surface: Surface) -> None:
    where = surface.source or "surface"
    if not surface.is_closed():
        raise MeshingError(
            f"{where}: the surface is not closed ({surface.n_boundary_edges()} open, "
            f"{surface.n_nonmanifold_edges()} non-manifold edges); clean it first (clean_surface)"
        )
    v_surf = surface.volume()
    if not v_surf > 0:
        raise MeshingError(f"{where}: the surface encloses a volume of {v_surf:.3g} m3 (inward normals?); "
                           f"clean it first (clean_surface)")


def _size_of(surface: Surface, target: MeshTarget) -> tuple[float, int | None]:
    """Element size [m] for a size or node target, and the node target (None for a size)."""
    v_surf = surface.volume()
    if target.size is None:
        target_nodes = target.nodes if target.nodes is not None else DEFAULT_NODES
        h = size_for_nodes(v_surf, target_nodes, surface.area())
    else:
        h, target_nodes = target.size, None
    extent = surface.extent()
    if h > extent:
        raise ConfigError(f"size: {h * 1e3:.3g} mm is larger than the organ ({extent * 1e3:.3g} mm); "
                          f"give a smaller size or more nodes", parameter="size")
    est_nodes = expected_nodes(v_surf, surface.area(), h)
    if est_nodes > MAX_EXPECTED_NODES:
        raise ConfigError(f"size: {h * 1e3:.3g} mm would give about {est_nodes:.3g} nodes; give a larger size",
                          parameter="size")
    return h, target_nodes


def _mesh_at(surface: Surface, target: MeshTarget, timeout: float, rep) -> VolumeMesh:
    """Mesh at a size, or at a node count (one corrected re-run if off by more than the tolerance)."""
    where = surface.source or "surface"
    v_surf = surface.volume()
    h, target_nodes = _size_of(surface, target)
    n_bodies, lab = face_components(surface.n_points, surface.faces)
    bodies = [surface] if n_bodies == 1 else [
        Surface(surface.points, surface.faces[lab == k], f"{where}, body {k}").compact() for k in range(n_bodies)]
    log: list[str] = []
    if n_bodies > 1:
        log.append(f"{n_bodies} bodies, meshed one by one at the same size")
    meshes = [_mesh_one(b, h, timeout, rep, log, where) for b in bodies]
    total = sum(m.n_nodes for m in meshes)
    if target_nodes is not None and abs(total / target_nodes - 1.0) > NODES_TOLERANCE:
        if any(m.path == "pytetwild" for m in meshes):
            log.append(f"{total} nodes for a target of {target_nodes}; not remeshed (fTetWild is slow)")
        else:
            h2 = h * (total / target_nodes) ** (1.0 / nodes_exponent(v_surf, surface.area(), h))
            log.append(f"{total} nodes for a target of {target_nodes}; size {h * 1e3:.3g} -> {h2 * 1e3:.3g} mm")
            try:
                meshes = [_mesh_one(b, h2, timeout, rep, log, where, start=m.path) for b, m in zip(bodies, meshes)]
                h = h2
            except MeshingError as exc:  # keep the first mesh: it is valid
                log.append(f"remeshing at {h2 * 1e3:.3g} mm failed ({exc}); the first mesh is kept")
                rep.warn(f"volume mesh: remeshing for the node target failed; keeping {total} nodes")
    mesh = _combine(meshes)
    path = max((m.path for m in meshes), key=_PATHS.index)
    rep.step(f"volume mesh ({path}): {mesh.n_nodes} nodes, {mesh.n_tets} tetrahedra, size "
             f"{h * 1e3:.3g} mm, volume {mesh.volume() * 1e6:.1f} mL "
             f"({(mesh.volume() / v_surf - 1) * 100:+.2f} % of the surface)")
    return VolumeMesh(mesh.points, mesh.tets, mesh.boundary_faces, path, log)


def _mesh_for_elements(surface: Surface, elements: int, timeout: float, rep) -> VolumeMesh:
    """Mesh for a tetrahedron count: at the size it implies, then once more if off by more than
    :data:`~.targets.ELEMENTS_TOLERANCE` (N ~ h^-3). The second run is an improvement, not a
    requirement: its time is bounded and, if it fails, the first mesh is kept."""
    size = size_for_elements(abs(float(surface.volume())), elements)
    t0 = time.perf_counter()
    mesh = _mesh_at(surface, MeshTarget(size=size), timeout, rep)
    first = time.perf_counter() - t0
    got = mesh.n_tets
    if abs(got / elements - 1.0) <= ELEMENTS_TOLERANCE:
        return mesh
    size2 = size * (got / elements) ** (1.0 / 3.0)
    rep.step(f"mesh: {got} tets for a target of {elements}; remeshing at {size2 * 1e3:.2f} mm "
             f"instead of {size * 1e3:.2f} mm")
    try:
        return _mesh_at(surface, MeshTarget(size=size2), min(timeout, max(30.0, 4.0 * first)), rep)
    except MeshingError as exc:
        rep.warn(f"mesh: remeshing at {size2 * 1e3:.2f} mm failed ({exc}); keeping the first mesh "
                 f"({got} tets at {size * 1e3:.2f} mm)")
        return mesh


_PATHS = ["gmsh", "gmsh-after-repair", "pytetwild"]


def _mesh_one(surface: Surface, h: float, timeout: float, rep, log: list[str], where: str,
              start: str = "gmsh") -> VolumeMesh:
    """Mesh one closed body, trying the paths in order from *start*."""
    v_surf = surface.volume()
    prepares = {"gmsh": lambda s: s, "gmsh-after-repair": _repair_for_gmsh, "pytetwild": lambda s: s}
    failures: list[str] = []
    for path in _PATHS[_PATHS.index(start):]:
        try:
            surf = prepares[path](surface)
        except MeshingError as exc:
            failures.append(f"{path}: {exc}")
            log.append(f"{path}: surface repair failed: {exc}")
            continue
        mesh, msg = _attempt(path, surf, h, v_surf, timeout, log)
        if mesh is not None:
            return mesh
        failures.append(f"{path}: {msg}")
        if path != _PATHS[-1]:
            rep.warn(f"volume mesh: {path} failed ({msg}); trying the next mesher")
    raise MeshingError(f"{where}: every mesher failed ({'; '.join(failures)}); "
                       f"check the surface or give a larger size")


def _combine(meshes: list[VolumeMesh]) -> VolumeMesh:
    if len(meshes) == 1:
        return meshes[0]
    offs = np.cumsum([0] + [m.n_nodes for m in meshes[:-1]])
    return VolumeMesh(np.vstack([m.points for m in meshes]),
                      np.vstack([m.tets + o for m, o in zip(meshes, offs)]),
                      np.vstack([m.boundary_faces + o for m, o in zip(meshes, offs)]), meshes[0].path, [])


def _attempt(path: str, surf: Surface, h: float, v_surf: float, timeout: float,
             log: list[str]) -> tuple[VolumeMesh | None, str]:
    # gmsh works in mm: its geometric tolerances are absolute (1e-8) and suit mm.
    scale = 1e3
    arrays = {"points": surf.points * scale, "faces": surf.faces}
    t0 = time.perf_counter()
    try:
        if path == "pytetwild":
            # fTetWild's output is finer than its "ideal edge length" (its envelope refines
            # near the surface): x1.3 gives about the node count gmsh gives at h. Fewer
            # optimisation passes than its defaults (80, energy 10): several times faster, and
            # the result still passes the floors (docs/guide/prepare.md, "Quality floors").
            out = run_worker("tetwild", {"edge_length": _TETWILD_EDGE_FACTOR * h * scale, "epsilon": 1e-3,
                                         "threads": 2, "num_opt_iter": 20, "stop_energy": 20.0},
                             arrays=arrays, timeout=timeout)
        else:
            out = run_worker("mesh", {"size": h * scale, "angle_deg": 180.0, "algorithm3d": 1,
                                      "threads": 1, "optimize_netgen": True},
                             arrays=arrays, timeout=timeout)
    except GmshTimeout:
        msg = f"no result within {timeout:g} s, killed"
        log.append(f"{path}: {msg}")
        return None, msg
    except GmshFailure as exc:
        msg = str(exc)
        log.append(f"{path}: failed after {time.perf_counter() - t0:.1f} s: {msg}")
        log.extend(f"  {ln}" for ln in exc.log[-5:])
        return None, msg
    dt = time.perf_counter() - t0
    nodes = np.asarray(out["nodes"], np.float64) / scale
    tets = np.asarray(out["tets"], np.int64)
    ok, msg, mesh = check_tets(nodes, tets, v_surf, path=path)
    info = out.get("info", {})
    extra = ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in info.items())
    log.append(f"{path}: size {h * 1e3:.3g} mm, {dt:.1f} s ({extra}): {msg}")
    return (mesh if ok else None), msg


def check_tets(nodes: np.ndarray, tets: np.ndarray, v_surf: float, *, path: str = "") -> tuple[bool, str, VolumeMesh | None]:
    """Check a mesher's output; orient it and build a :class:`VolumeMesh`.

    Returns ``(ok, message, mesh)``; ``mesh`` is None when not ok.
    """
    if tets.shape[0] == 0:
        return False, "0 tetrahedra (boundary recovery failed)", None
    used = np.zeros(nodes.shape[0], bool)
    used[tets.ravel()] = True
    remap = np.cumsum(used) - 1
    pts = nodes[used]
    t = remap[tets]
    p = pts
    det = np.einsum("ij,ij->i", p[t[:, 1]] - p[t[:, 0]],
                    np.cross(p[t[:, 2]] - p[t[:, 0]], p[t[:, 3]] - p[t[:, 0]]))
    if np.sum(det) < 0:
        t = t[:, [0, 1, 3, 2]]
        det = -det
    scale = np.abs(det).mean()
    bad = int(np.count_nonzero(det <= 1e-12 * scale))
    if bad:
        return False, f"{bad} inverted or flat tetrahedra", None
    bfaces = boundary_of_tets(pts, t)
    vol = float(det.sum() / 6.0)
    err = vol / v_surf - 1.0
    note = ""
    if abs(err) > MAX_MESH_VOLUME_ERROR:
        moved = restore_volume(pts, t, bfaces, v_surf)
        if moved is not None:
            pts, delta = moved
            vol2 = float(VolumeMesh(pts, t, bfaces).volume())
            note += (f"; boundary nodes moved {delta * 1e3:+.3f} mm along their normals to restore the "
                    f"volume ({err * 100:+.2f} % -> {(vol2 / v_surf - 1) * 100:+.2f} %)")
            err = vol2 / v_surf - 1.0
    # After the volume restoration, which moves boundary nodes and may flatten elements.
    pts, sliv = improve_slivers(pts, t, bfaces)
    if sliv["moved"]:
        note += (f"; {sliv['below_before']} slivers below {SLIVER_TARGET_DEG:g} deg relocated (min dihedral "
                 f"{sliv['min_dihedral_before']:.1f} -> {sliv['min_dihedral_after']:.1f} deg)")
        err = float(VolumeMesh(pts, t, bfaces).volume()) / v_surf - 1.0
    if abs(err) > MAX_MESH_VOLUME_ERROR:
        return False, (f"mesh volume {vol * 1e6:.1f} mL is {err * 100:+.2f} % off the surface's "
                       f"{v_surf * 1e6:.1f} mL"), None
    mesh = VolumeMesh(pts, t, bfaces, path, [])
    return True, f"{pts.shape[0]} nodes, {t.shape[0]} tets, volume {err * 100:+.2f} %{note}", mesh


def restore_volume(points: np.ndarray, tets: np.ndarray, boundary_faces: np.ndarray,
                   target_volume: float) -> tuple[np.ndarray, float] | None:
    """Move the boundary nodes along their normals so the mesh volume matches.

    A mesh whose boundary nodes lie on a curved surface is inside it by the
    chord sagitta (about h^2 / 8R), so a coarse mesh loses volume (mass). A
    uniform normal offset ``delta = (V_target - V) / A`` (two passes)
    restores it; ``delta`` is a fraction of the element size, so the boundary
    then straddles the surface. Returns None if an element would invert.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tets : ndarray, shape (t, 4), positively oriented
    boundary_faces : ndarray, shape (k, 3), outward
    target_volume : float

    Returns
    -------
    (points, delta) or None
        New coordinates (n, 3) and the total offset [m].
    """
    p = points.copy()
    f = boundary_faces
    bn = np.unique(f)
    total = 0.0
    for _ in range(2):
        n_face = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])  # 2 * area * normal
        area = 0.5 * float(np.linalg.norm(n_face, axis=1).sum())
        vn = np.zeros_like(p)
        for k in range(3):
            np.add.at(vn, f[:, k], n_face)
        ln = np.linalg.norm(vn[bn], axis=1)
        ln[ln == 0] = 1.0
        vol = VolumeMesh(p, tets, f).volume()
        delta = (target_volume - vol) / area
        p[bn] += delta * vn[bn] / ln[:, None]
        total += delta
    if np.any(VolumeMesh(p, tets, f).tet_volumes() <= 0):
        return None
    return p, total


def _repair_for_gmsh(surface: Surface) -> Surface:
    """Stronger pymeshfix repair (joins, removes intersecting triangles, fills)."""
    tm = meshfix(surface.points, surface.faces)  # in mm: its tolerances are absolute
    tm.fill_small_boundaries(0, True)
    tm.clean(20, 5)
    tm.strong_degeneracy_removal(3)
    tm.strong_intersection_removal(10)
    tm.fill_small_boundaries(0, True)
    v, f = meshfix_arrays(tm)
    if f.shape[0] == 0:
        raise MeshingError("nothing left after repair")
    v, f, _ = keep_largest(v, f)
    f, _, _, _ = orient_outward(v, f)
    s = Surface(v, f, surface.source + "; repaired")
    if not s.is_closed():
        raise MeshingError(f"still {s.n_boundary_edges()} open edges after repair")
    return s
