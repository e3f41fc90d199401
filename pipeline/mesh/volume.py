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
:attr:`VolumeMesh.log`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, MeshingError
from ..progress import ensure
from .gmsh_worker import GmshFailure, GmshTimeout, run_worker
from .readers import boundary_of_tets
from .surface import Surface

#: Largest accepted relative difference of mesh and surface volume.
MAX_MESH_VOLUME_ERROR = 0.01

#: Node count aimed at when neither ``size`` nor ``nodes`` is given.
DEFAULT_NODES = 5000

#: Tetrahedra per node in a gmsh Delaunay mesh of an organ, measured (see docs/prepare.md).
_TETS_PER_NODE = 5.0

#: Ratio of the mean tetrahedron volume to that of a regular one of edge h.
_VOLUME_FILL = 0.75


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
        ``"pytetwild"``.
    log : list of str
        What was tried, with timings and reasons for failures.
    """

    points: np.ndarray
    tets: np.ndarray
    boundary_faces: np.ndarray
    path: str = "gmsh"
    log: list[str] = field(default_factory=list)

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


def size_for_nodes(volume: float, nodes: int) -> float:
    """Element size h [m] expected to give about *nodes* nodes in *volume* [m3].

    A regular tetrahedron of edge h has volume h^3 / (6 sqrt 2); a Delaunay
    mesh has about 5 tetrahedra per node, filling the volume at ~75 % of the
    regular value (both measured on organ meshes; :func:`mesh_volume` corrects
    the size once from the first result).
    """
    return (6.0 * math.sqrt(2.0) * volume / (_TETS_PER_NODE * _VOLUME_FILL * nodes)) ** (1.0 / 3.0)


def mesh_volume(surface: Surface, *, size: float | None = None, nodes: int | None = None,
                timeout: float = 120.0, reporter=None) -> VolumeMesh:
    """Fill a closed surface with tetrahedra.

    Parameters
    ----------
    surface
        A closed, outward surface (from
        :func:`~esmm.pipeline.mesh.cleaning.clean_surface`), points in metres.
    size
        Target tetrahedron edge [m].
    nodes
        Target number of nodes instead (ignored if ``size`` is given); the size
        is estimated from the volume and corrected once if the result is more
        than 25 % off. Default: :data:`DEFAULT_NODES`.
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
        ``size`` or ``nodes`` is not positive.
    MeshingError
        The surface is open, or every path failed (the message lists why).
    """
    rep = ensure(reporter)
    where = surface.source or "surface"
    if size is not None and not (float(size) > 0 and math.isfinite(float(size))):
        raise ConfigError(f"size: expected a positive element size in m, got {size!r}")
    if nodes is not None and (isinstance(nodes, bool) or not isinstance(nodes, (int, np.integer)) or nodes < 10):
        raise ConfigError(f"nodes: expected an integer >= 10, got {nodes!r}")
    if not (float(timeout) > 0):
        raise ConfigError(f"timeout: expected a positive number of seconds, got {timeout!r}")
    if not surface.is_closed():
        raise MeshingError(
            f"{where}: the surface is not closed ({surface.n_boundary_edges()} open, "
            f"{surface.n_nonmanifold_edges()} non-manifold edges); clean it first (clean_surface)"
        )
    v_surf = surface.volume()
    if not v_surf > 0:
        raise MeshingError(f"{where}: the surface encloses a volume of {v_surf:.3g} m3 (inward normals?); "
                           f"clean it first (clean_surface)")
    target_nodes = None
    if size is None:
        target_nodes = int(nodes) if nodes is not None else DEFAULT_NODES
        h = size_for_nodes(v_surf, target_nodes)
    else:
        h = float(size)
    extent = surface.extent()
    if h > extent:
        raise ConfigError(f"size: {h * 1e3:.3g} mm is larger than the organ ({extent * 1e3:.3g} mm); "
                          f"give a smaller --size or more --nodes")
    est_nodes = _TETS_PER_NODE and v_surf / (h ** 3 / (6 * math.sqrt(2)) * _VOLUME_FILL * _TETS_PER_NODE)
    if est_nodes > 2_000_000:
        raise ConfigError(f"size: {h * 1e3:.3g} mm would give about {est_nodes:.3g} nodes; give a larger --size")

    log: list[str] = []
    attempts = [("gmsh", lambda s: s), ("gmsh-after-repair", _repair_for_gmsh), ("pytetwild", lambda s: s)]
    failures: list[str] = []
    for path, prepare in attempts:
        try:
            surf = prepare(surface)
        except MeshingError as exc:
            failures.append(f"{path}: {exc}")
            log.append(f"{path}: surface repair failed: {exc}")
            continue
        mesh, msg = _attempt(path, surf, h, v_surf, timeout, log)
        if mesh is not None and target_nodes is not None:
            ratio = mesh.n_nodes / target_nodes
            if abs(ratio - 1.0) > 0.25:
                h2 = h * ratio ** (1.0 / 3.0)
                log.append(f"{path}: {mesh.n_nodes} nodes for a target of {target_nodes}; "
                           f"size {h * 1e3:.3g} -> {h2 * 1e3:.3g} mm")
                mesh2, msg2 = _attempt(path, surf, h2, v_surf, timeout, log)
                if mesh2 is not None:
                    mesh, msg, h = mesh2, msg2, h2
        if mesh is not None:
            rep.step(f"volume mesh ({path}): {mesh.n_nodes} nodes, {mesh.n_tets} tetrahedra, size "
                     f"{h * 1e3:.3g} mm, volume {mesh.volume() * 1e6:.1f} mL "
                     f"({(mesh.volume() / v_surf - 1) * 100:+.2f} % of the surface)")
            return VolumeMesh(mesh.points, mesh.tets, mesh.boundary_faces, path, log)
        failures.append(f"{path}: {msg}")
        rep.warn(f"volume mesh: {path} failed ({msg}); trying the next mesher")
    raise MeshingError(f"{where}: every mesher failed ({'; '.join(failures)}); "
                       f"check the surface or give a larger --size")


def _attempt(path: str, surf: Surface, h: float, v_surf: float, timeout: float,
             log: list[str]) -> tuple[VolumeMesh | None, str]:
    # gmsh works in mm: its geometric tolerances are absolute (1e-8) and suit mm.
    scale = 1e3
    arrays = {"points": surf.points * scale, "faces": surf.faces}
    t0 = time.perf_counter()
    try:
        if path == "pytetwild":
            out = run_worker("tetwild", {"edge_length": h * scale, "epsilon": 1e-3, "threads": 2},
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
    vol = float(det.sum() / 6.0)
    err = vol / v_surf - 1.0
    if abs(err) > MAX_MESH_VOLUME_ERROR:
        return False, (f"mesh volume {vol * 1e6:.1f} mL is {err * 100:+.2f} % off the surface's "
                       f"{v_surf * 1e6:.1f} mL"), None
    bfaces = boundary_of_tets(pts, t)
    mesh = VolumeMesh(pts, t, bfaces, path, [])
    return True, f"{pts.shape[0]} nodes, {t.shape[0]} tets, volume {err * 100:+.2f} %", mesh


def _repair_for_gmsh(surface: Surface) -> Surface:
    """Stronger pymeshfix repair (joins, removes intersecting triangles, fills)."""
    import pymeshfix

    from .cleaning import _keep_largest, _orient_outward

    tm = pymeshfix.PyTMesh()
    tm.set_quiet(True)
    tm.load_array(surface.points, surface.faces.astype(np.int32))
    tm.fill_small_boundaries(0, True)
    tm.clean(20, 5)
    tm.strong_degeneracy_removal(3)
    tm.strong_intersection_removal(10)
    tm.fill_small_boundaries(0, True)
    v, f = tm.return_arrays()
    v = np.asarray(v, np.float64)
    f = np.asarray(f, np.int64)
    if f.shape[0] == 0:
        raise MeshingError("nothing left after repair")
    v, f, _ = _keep_largest(v, f)
    f, _, _, _ = _orient_outward(v, f)
    s = Surface(v, f, surface.source + "; repaired")
    if not s.is_closed():
        raise MeshingError(f"still {s.n_boundary_edges()} open edges after repair")
    return s
