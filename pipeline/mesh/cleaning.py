"""Cleaning an InVesalius-style surface into one closed, outward, smooth body.

:func:`clean_surface` runs these steps, each reported with its figures
(points, faces, volume and area before and after, time):

1. ``merge``: merge duplicate points (quantised to 1e-7 of the extent).
2. ``degenerate``: drop faces with a repeated corner, of zero area, or
   duplicated.
3. ``bodies``: split into connected bodies; keep the largest by enclosed
   volume (open bodies are measured with their holes capped), or all of them,
   or the one chosen by ``body=N``; report what was dropped.
4. ``orient``: consistent orientation (parity propagation over the manifold
   edges, vectorised) and positive signed volume per body.
5. ``smooth``: volume-preserving windowed-sinc smoothing (VTK; Taubin's
   lambda/mu family) to remove the marching-cubes staircase, borders held.
6. ``decimate``: quadric decimation to the target (fast_simplification).
7. ``close``: fill the open borders (pymeshfix hole filling with refinement).
8. ``repair``: non-manifold edges, degeneracies and self-intersections
   (pymeshfix), keep the largest resulting piece, orient outward again.

Steps 5-6 come before 7-8: pymeshfix is slow to load a mesh of a million faces
and the decimator may leave non-manifold edges, which the repair then removes;
smoothing has to see the staircase at full resolution. See docs/guide/prepare.md, "Cleaning".

The result must stay within :data:`MAX_VOLUME_CHANGE` (2 %) of the enclosed
volume of the kept body (for an open body, its volume with the holes capped).
If it does not, the smoothing is halved and the steps 5-8 run again; if even no
smoothing keeps the volume, :class:`~esmm.pipeline.errors.MeshingError`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from ..checks import choice, number
from ..errors import ConfigError, InputError, MeshingError
from ..progress import ensure
from .surface import Surface, cross3, triple

#: Largest accepted relative change of the enclosed volume by the cleaning.
MAX_VOLUME_CHANGE = 0.02

#: Decimation target when neither ``target_faces`` nor ``target_edge`` is given.
DEFAULT_TARGET_FACES = 20_000

#: Fewest triangles a decimation target may ask for.
MIN_TARGET_FACES = 100

#: Points closer than this fraction of the extent are merged.
MERGE_TOLERANCE = 1e-7

#: pymeshfix is given millimetres (as gmsh is): MeshFix's degeneracy and
#: intersection tests have absolute tolerances that suit coordinates of order
#: 1-1000. In metres its clean deleted a valid vessel of 0.5 mm voxels (an 8 mm
#: tube, 41 720 faces -> none: "nothing is left after repair"); in mm it is kept.
TOOL_SCALE = 1e3


def decimate(points: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (fast_simplification) of (points [m], faces), run in metres.

    Its error threshold is absolute too (1e-9 (k+3)^7 in length units squared),
    and in mm it decimates further: it reaches the target where in metres it
    stops short (the bundled liver: 20 000 faces instead of 24 540), and on the
    vessel above it leaves 108 intersecting faces instead of 3 213. It stays in
    metres because that changes every asset already made from a surface (the
    bundled liver's paper preset: 1 446 nodes instead of 1 660, smallest
    dihedral angle 11.0 instead of 17.0 degrees) and every figure measured on
    them (docs/guide/prepare.md, "How far to trust it").
    """
    import fast_simplification

    p, f = fast_simplification.simplify(np.ascontiguousarray(points, np.float64), faces.astype(np.int32),
                                        target_count=int(target))
    return np.asarray(p, np.float64), np.asarray(f, np.int64)


def meshfix(points: np.ndarray, faces: np.ndarray):
    """A quiet pymeshfix mesh of (points [m], faces), loaded in mm; read it back with :func:`meshfix_arrays`."""
    import pymeshfix

    tm = pymeshfix.PyTMesh()
    tm.set_quiet(True)
    tm.load_array(np.ascontiguousarray(points * TOOL_SCALE, np.float64), np.ascontiguousarray(faces, np.int32))
    return tm


def meshfix_arrays(tm) -> tuple[np.ndarray, np.ndarray]:
    """(points [m], faces) of a mesh made by :func:`meshfix`."""
    v, f = tm.return_arrays()
    return np.asarray(v, np.float64) / TOOL_SCALE, np.asarray(f, np.int64)


@dataclass(frozen=True)
class CleaningOptions:
    """Options of :func:`clean_surface`.

    Attributes
    ----------
    keep : {"largest", "all"}
        Keep the largest body (by enclosed volume) or all bodies.
    body : int or None
        Keep this body instead: its index in the list sorted by decreasing
        volume (0 is the largest), as reported by the ``bodies`` step.
    smooth_iterations : int
        Windowed-sinc iterations (0: no smoothing).
    smooth_passband : float
        Windowed-sinc pass band in (0, 2); smaller smooths more.
    target_faces : int or None
        Decimate to about this many triangles (at least :data:`MIN_TARGET_FACES`).
    target_edge : float or None
        Decimate to a mean edge of about this length [m] (ignored if
        ``target_faces`` is given). Half the tetrahedron size is a good value.
    """

    keep: str = "largest"
    body: int | None = None
    smooth_iterations: int = 20
    smooth_passband: float = 0.1
    target_faces: int | None = None
    target_edge: float | None = None

    def validate(self, names: Mapping[str, str] | None = None) -> None:
        """Raise ConfigError naming the bad option.

        *names* maps an attribute to the parameter name used in messages
        (default: the attribute's name; e.g. ``[cleaning] body`` for a config key).
        """
        def name(key: str) -> str:
            return (names or {}).get(key, key)

        choice(self.keep, ("largest", "all"), name("keep"))
        if self.body is not None:
            number(self.body, name("body"), lo=0, integer=True)
        number(self.smooth_iterations, name("smooth_iterations"), lo=0, integer=True)
        if self.smooth_iterations == 1:
            raise ConfigError(f"{name('smooth_iterations')}: 1 is not a smoothing (VTK's windowed-sinc filter "
                              "collapses the surface with one iteration); give 0 or at least 2",
                              parameter=name("smooth_iterations"))
        number(self.smooth_passband, name("smooth_passband"), lo=0.0, hi=2.0, lo_open=True, hi_open=True)
        if self.target_faces is not None:
            number(self.target_faces, name("target_faces"), lo=MIN_TARGET_FACES, integer=True)
        if self.target_edge is not None:
            number(self.target_edge, name("target_edge"), lo=0.0, lo_open=True)


@dataclass
class CleaningReport:
    """What each cleaning step did.

    Attributes
    ----------
    steps : list of dict
        One dict per step: ``name``, ``seconds``, ``points_before/after``,
        ``faces_before/after``, ``volume_before/after`` [m3],
        ``area_before/after`` [m2] and step-specific figures.
    volume_before, volume_after : float
        Enclosed volume of the kept body before cleaning (holes capped) and
        of the cleaned surface [m3].
    area_before, area_after : float
        Areas [m2] (before: of the input, all bodies).
    bodies_found : int
        Connected bodies in the input.
    bodies_dropped : list of (int, float)
        (faces, volume [m3]) of each dropped body.
    relative_volume_change : float
        ``volume_after / volume_before - 1``.
    """

    steps: list[dict] = field(default_factory=list)
    volume_before: float = 0.0
    volume_after: float = 0.0
    area_before: float = 0.0
    area_after: float = 0.0
    bodies_found: int = 0
    bodies_dropped: list[tuple[int, float]] = field(default_factory=list)
    relative_volume_change: float = 0.0
    smooth_iterations_used: int = 0

    def step(self, name: str) -> dict:
        """The figures of the step called *name* (the last one if repeated)."""
        for s in reversed(self.steps):
            if s["name"] == name:
                return s
        raise KeyError(name)


# ------------------------------------------------------------------ helpers
def capped_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume with every open border capped by a fan.

    Each boundary loop is closed by triangles from its centroid; for a closed
    surface this is the ordinary divergence-theorem volume. Exact for planar
    holes (the scan-border cuts of a marching-cubes export).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)

    Returns
    -------
    float
        Signed volume (positive for outward orientation).
    """
    if faces.shape[0] == 0:
        return 0.0
    return float(capped_volumes(points, faces, np.zeros(faces.shape[0], np.int64), 1)[0])


def capped_volumes(points: np.ndarray, faces: np.ndarray, label: np.ndarray, n: int,
                   loops: tuple | None = None) -> np.ndarray:
    """:func:`capped_volume` of each body, vectorised.

    Parameters
    ----------
    points : ndarray, shape (n_points, 3)
    faces : ndarray, shape (m, 3)
    label : ndarray, shape (m,)
        Body id (0 .. n-1) of each face; bodies must not share vertices.
    n : int
        Number of bodies.
    loops : tuple, optional
        ``_boundary_loops(n_points, faces)`` if already known (it depends on
        the faces only).

    Returns
    -------
    ndarray, shape (n,)
        Signed capped volume of each body [m3 if points are in m].
    """
    if faces.shape[0] == 0:
        return np.zeros(n)
    c0 = points[faces[:, 0]].mean(axis=0)
    p = points - c0
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    vol = np.bincount(label, triple(a, b, c), minlength=n) / 6.0
    heads, tails, loop, hface = loops if loops is not None else _boundary_loops(points.shape[0], faces)
    if heads.size:
        # The cap runs along each border half-edge (u -> v) backwards: triangle (c_L, v, u).
        n_loops = int(loop.max()) + 1
        cnt = np.bincount(loop, minlength=n_loops).astype(float)
        cent = np.column_stack([np.bincount(loop, p[heads][:, k], minlength=n_loops) for k in range(3)]) / cnt[:, None]
        cap = triple(cent[loop], p[tails], p[heads])
        vol += np.bincount(label[hface], cap, minlength=n) / 6.0
    return vol


def _half_edge_keys(faces: np.ndarray, n: int):
    u = faces.ravel()
    v = np.roll(faces, -1, axis=1).ravel()
    return u, v, np.minimum(u, v) * np.int64(n) + np.maximum(u, v)


def _boundary_loops(n_points: int, faces: np.ndarray):
    """Border half-edges (u -> v, used by one face), a loop id and the face of each."""
    u, v, key = _half_edge_keys(faces, n_points)
    order = np.argsort(key)
    sk = key[order]
    first = np.ones(sk.size, bool)
    first[1:] = sk[1:] != sk[:-1]
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, sk.size))
    single = order[starts[counts == 1]]
    heads, tails = u[single], v[single]
    if heads.size == 0:
        return heads, tails, np.zeros(0, np.int64), np.zeros(0, np.int64)
    g = sparse.coo_matrix((np.ones(heads.size), (heads, tails)), shape=(n_points, n_points))
    _, lab = connected_components(g, directed=False)
    _, loop = np.unique(lab[heads], return_inverse=True)
    return heads, tails, loop, single // 3


def face_components(n_points: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected bodies (through shared edges): (count, body id per face).

    Two closed bodies touching at one vertex (a bow tie, as marching cubes
    makes where two blobs of a mask meet at a voxel corner) are two bodies;
    through shared vertices they were one, which the repair then cut in two.
    """
    m = faces.shape[0]
    if m == 0:
        return 0, np.zeros(0, np.int64)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, edge = np.unique(e[:, 0] * np.int64(n_points) + e[:, 1], return_inverse=True)
    f = np.repeat(np.arange(m), 3)
    g = sparse.coo_matrix((np.ones(f.size, np.int8), (f, m + edge.ravel())), shape=(m + edge.max() + 1,) * 2)
    _, lab = connected_components(g, directed=False)
    uniq, inv = np.unique(lab[:m], return_inverse=True)
    return int(uniq.size), inv.astype(np.int64)


def orient_consistently(n_points: int, faces: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Flip faces so that neighbours agree, component by component.

    Works on the manifold edges (two faces): faces f, g sharing an edge agree
    if they run through it in opposite directions. The parity of each face is
    found as the connected components of a doubled graph (face f kept or
    flipped), all in scipy, so it is fast on a million faces.

    Returns
    -------
    faces : ndarray, shape (m, 3)
        Consistently oriented faces (each component oriented like its first face).
    n_flipped : int
        Faces that were flipped.
    n_conflicts : int
        Components that are not orientable (Moebius-like); left as they were.
    """
    m = faces.shape[0]
    if m == 0:
        return faces, 0, 0
    u, v, key = _half_edge_keys(faces, n_points)
    fid = np.repeat(np.arange(m), 3)
    order = np.argsort(key)
    sk = key[order]
    first = np.ones(sk.size, bool)
    first[1:] = sk[1:] != sk[:-1]
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, sk.size))
    pairs = starts[counts == 2]
    h1, h2 = order[pairs], order[pairs + 1]
    f1, f2 = fid[h1], fid[h2]
    same_dir = u[h1] == u[h2]  # both faces run u->v the same way: they disagree
    # Node 2f: face f as is; node 2f+1: face f flipped.
    a = np.where(same_dir, 2 * f1, 2 * f1)
    b = np.where(same_dir, 2 * f2 + 1, 2 * f2)
    a2 = np.where(same_dir, 2 * f1 + 1, 2 * f1 + 1)
    b2 = np.where(same_dir, 2 * f2, 2 * f2 + 1)
    rows = np.concatenate([a, a2])
    cols = np.concatenate([b, b2])
    g = sparse.coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(2 * m, 2 * m))
    _, lab = connected_components(g, directed=False)
    keep_lab, flip_lab = lab[0::2], lab[1::2]
    conflict = keep_lab == flip_lab
    # In each component, the face with the smallest index decides: "as is" wins.
    # Assign each doubled-graph component the smallest face index whose *kept* copy is in it.
    big = np.iinfo(np.int64).max
    min_keep = np.full(lab.max() + 1, big, np.int64)
    np.minimum.at(min_keep, keep_lab, np.arange(m))
    min_flip = np.full(lab.max() + 1, big, np.int64)
    np.minimum.at(min_flip, flip_lab, np.arange(m))
    # Face f is kept if the component of its kept copy has an earlier kept face than flipped face.
    flip = (min_flip[keep_lab] < min_keep[keep_lab]) & ~conflict
    out = faces.copy()
    out[flip] = out[flip][:, ::-1]
    n_conf_comp = int(np.unique(keep_lab[conflict]).size) if conflict.any() else 0
    return out, int(flip.sum()), n_conf_comp


def winding_number(point: np.ndarray, points: np.ndarray, faces: np.ndarray) -> float:
    """Generalised winding number of a closed (or capped) surface around *point*.

    The sum of the signed solid angles of the faces seen from *point* over 4 pi
    (van Oosterom and Strackee): +-1 inside a closed body (the sign of its
    orientation), 0 outside; robust to small holes.
    """
    a = points[faces[:, 0]] - point
    b = points[faces[:, 1]] - point
    c = points[faces[:, 2]] - point
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = triple(a, b, c)
    den = (la * lb * lc + (a * b).sum(1) * lc + (b * c).sum(1) * la + (c * a).sum(1) * lb)
    return float(2.0 * np.arctan2(num, den).sum() / (4.0 * np.pi))


def nested_bodies(points: np.ndarray, faces: np.ndarray, label: np.ndarray, order) -> list[tuple[int, int]]:
    """Pairs (inner, outer) of bodies of *order* where *inner* lies inside *outer*.

    *order* lists body ids by decreasing volume; a body is tested against the
    larger ones whose bounding box holds its own (one vertex, by the winding
    number: a body inside another is a cavity of it, or a body within it).
    """
    order = [int(k) for k in order]
    lo = {k: points[faces[label == k].ravel()].min(axis=0) for k in order}
    hi = {k: points[faces[label == k].ravel()].max(axis=0) for k in order}
    out = []
    for i, k in enumerate(order[1:], start=1):
        q = points[faces[label == k][0, 0]]
        for j in order[:i]:
            if np.all(lo[k] >= lo[j]) and np.all(hi[k] <= hi[j]) \
                    and abs(winding_number(q, points, faces[label == j])) > 0.5:
                out.append((k, j))
                break
    return out


def _merge_points(points: np.ndarray, faces: np.ndarray, tol: float):
    q = np.round((points - points.min(axis=0)) / tol).astype(np.int64)
    order = np.lexsort((q[:, 2], q[:, 1], q[:, 0]))
    sq = q[order]
    new = np.ones(order.size, bool)
    new[1:] = np.any(sq[1:] != sq[:-1], axis=1)
    ids = np.cumsum(new) - 1
    remap = np.empty(order.size, np.int64)
    remap[order] = ids
    if new.all():
        return points, faces, 0  # nothing to merge: the same arrays
    pts = points[order[new]]
    return pts, remap[faces], int(points.shape[0] - pts.shape[0])


def _drop_degenerate(points: np.ndarray, faces: np.ndarray, area_tol: float):
    f = faces
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    a, b, c = points[f[:, 0]], points[f[:, 1]], points[f[:, 2]]
    area = 0.5 * np.linalg.norm(cross3(b - a, c - a), axis=1)
    zero = (area <= area_tol) & ~repeated
    keep = ~(repeated | zero)
    f = f[keep]
    s = np.sort(f, axis=1)
    n = np.int64(points.shape[0])
    key = (s[:, 0] * n + s[:, 1]) * n + s[:, 2] if points.shape[0] < 2_000_000 else None
    if key is not None:
        _, idx = np.unique(key, return_index=True)
    else:
        _, idx = np.unique(s, axis=0, return_index=True)
    idx.sort()
    dup = f.shape[0] - idx.size
    if idx.size == faces.shape[0]:
        return faces, 0, 0, 0  # nothing dropped: the same array
    return f[idx], int(repeated.sum()), int(zero.sum()), int(dup)


def _compact(points: np.ndarray, faces: np.ndarray):
    used = np.zeros(points.shape[0], bool)
    used[faces.ravel()] = True
    if used.all():
        return points, faces
    remap = np.cumsum(used) - 1
    return points[used], remap[faces]


def _smooth(points: np.ndarray, faces: np.ndarray, iterations: int, passband: float) -> np.ndarray:
    """VTK's windowed-sinc smoothing; never with one iteration (:func:`_fewer`), where the filter writes
    "An optimal offset ... could not be found" straight to stderr and collapses the surface."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray, vtk_to_numpy

    poly = vtk.vtkPolyData()
    vp = vtk.vtkPoints()
    vp.SetData(numpy_to_vtk(np.ascontiguousarray(points), deep=True))
    poly.SetPoints(vp)
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, 3 * faces.shape[0] + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(np.ascontiguousarray(faces.ravel(), dtype=np.int64), deep=True))
    poly.SetPolys(cells)
    f = vtk.vtkWindowedSincPolyDataFilter()
    f.SetInputData(poly)
    f.SetNumberOfIterations(int(iterations))
    f.SetPassBand(float(passband))
    f.NormalizeCoordinatesOn()
    f.BoundarySmoothingOff()
    f.FeatureEdgeSmoothingOff()
    f.NonManifoldSmoothingOn()
    f.Update()
    out = vtk_to_numpy(f.GetOutput().GetPoints().GetData()).astype(np.float64)
    if out.shape != points.shape:  # pragma: no cover - VTK keeps the points
        raise MeshingError("smoothing changed the number of points; set smooth_iterations to 0")
    return out


def keep_largest(points: np.ndarray, faces: np.ndarray, n_keep: int = 1) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep the *n_keep* bodies of largest enclosed volume.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)
    n_keep : int

    Returns
    -------
    points : ndarray, shape (n', 3)
        Compacted (only the kept bodies' points).
    faces : ndarray, shape (m', 3)
    dropped : int
        Number of bodies dropped.
    """
    n, lab = face_components(points.shape[0], faces)
    if n <= n_keep:
        return points, faces, 0
    vols = np.abs(capped_volumes(points, faces, lab, n))
    keep = np.argsort(-vols)[:n_keep]
    p, f = _compact(points, faces[np.isin(lab, keep)])
    return p, f, n - n_keep


def orient_outward(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """Consistent orientation and positive (outward) volume for each body.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)

    Returns
    -------
    faces : ndarray, shape (m, 3)
        Reoriented.
    flipped : int
        Faces flipped.
    conflicts : int
        Components that are not orientable (left as they were).
    bodies_turned : int
        Bodies turned outward as a whole.
    """
    f, n_flip, conflicts = orient_consistently(points.shape[0], faces)
    n, lab = face_components(points.shape[0], f)
    vols = capped_volumes(points, f, lab, n)
    neg = vols < 0
    sel = neg[lab]
    if sel.any():
        f[sel] = f[sel][:, ::-1]
        n_flip += int(sel.sum())
    return f, n_flip, conflicts, int(neg.sum())


# ------------------------------------------------------------------- main
class _StepRecorder:
    """Records one cleaning step: its figures into the report and a line to the reporter.

    Called as ``record(name, t0, p0, f0, p1, f1, note, **figures)`` with the
    surface before (``p0, f0``) and after (``p1, f1``) the step. The volume and
    area of a surface are computed once: consecutive steps share the arrays,
    so the figures are cached by the arrays' identity (the arrays are held, so
    the identities stay valid), and the border loops by the faces' identity.
    """

    def __init__(self, report: CleaningReport, rep):
        self.report = report
        self.rep = rep
        self._cache: dict = {}
        self._loops: dict = {}

    def figures(self, p, f) -> tuple[float, float]:
        """Enclosed volume (holes capped) [m3] and area [m2] of the surface ``(p, f)``."""
        cache, loops_cache = self._cache, self._loops
        if cache.get("key") == (id(p), id(f)):
            return cache["v"], cache["a"]
        if loops_cache.get("key") != id(f):  # the border loops depend on the faces only
            loops_cache.update(key=id(f), loops=_boundary_loops(p.shape[0], f), keep=f)
        lab0 = np.zeros(f.shape[0], np.int64)
        v = float(capped_volumes(p, f, lab0, 1, loops_cache["loops"])[0]) if f.shape[0] else 0.0
        a = Surface(p, f).area()
        cache.update(key=(id(p), id(f)), v=v, a=a, keep=(p, f))  # keep: ids stay valid
        return v, a

    def __call__(self, name: str, t0: float, p0, f0, p1, f1, note: str, **figures_) -> dict:
        dt = time.perf_counter() - t0
        v0, a0 = self.figures(p0, f0)
        v1, a1 = self.figures(p1, f1)
        d = {"name": name, "seconds": dt,
             "points_before": int(p0.shape[0]), "points_after": int(p1.shape[0]),
             "faces_before": int(f0.shape[0]), "faces_after": int(f1.shape[0]),
             "volume_before": v0, "volume_after": v1, "area_before": a0, "area_after": a1}
        d.update(figures_)
        self.report.steps.append(d)
        self.rep.step(f"{name}: {note}; {f0.shape[0]} -> {f1.shape[0]} faces, volume {abs(v0) * 1e6:.1f} -> "
                      f"{abs(v1) * 1e6:.1f} mL ({d['seconds']:.2f} s)")
        return d


def clean_surface(surface: Surface, *, options: CleaningOptions | None = None,
                  reporter=None) -> tuple[Surface, CleaningReport]:
    """Turn a raw organ surface into one closed, outward, smooth, decimated body.

    Parameters
    ----------
    surface
        The raw surface (points (n, 3) [m], faces (m, 3)).
    options
        :class:`CleaningOptions` (defaults: keep the largest body, 20
        windowed-sinc iterations with pass band 0.1, decimate to
        :data:`DEFAULT_TARGET_FACES` if larger).
    reporter
        Each step is reported with its figures (``reporter.step``); dropped
        bodies and a large volume change are warnings.

    Returns
    -------
    surface : Surface
        Closed (every edge shared by two faces), consistently oriented with
        positive volume, within 2 % of the kept body's enclosed volume.
    report : CleaningReport
        The figures of each step.

    Raises
    ------
    MeshingError
        Nothing is left after cleaning, the surface cannot be closed, or the
        volume cannot be kept within 2 %.
    """
    opts = options or CleaningOptions()
    opts.validate()
    rep = ensure(reporter)
    report = CleaningReport()
    where = surface.source or "surface"
    pts = np.asarray(surface.points, np.float64)
    fcs = np.asarray(surface.faces, np.int64)
    if fcs.shape[0] == 0:
        raise MeshingError(f"{where}: no triangles to clean; check the input file")
    pts, fcs = _compact(pts, fcs)
    report.area_before = Surface(pts, fcs).area()
    extent = float((pts.max(axis=0) - pts.min(axis=0)).max())
    record = _StepRecorder(report, rep)

    pts, fcs = _merge_step(pts, fcs, extent, record)
    pts, fcs = _degenerate_step(pts, fcs, extent, record, where)
    pts, fcs, fcs_or, n_kept = _bodies_step(pts, fcs, opts, record, rep, where)
    fcs = _orient_step(pts, fcs, fcs_or, record)
    v_ref = capped_volume(pts, fcs)
    report.volume_before = v_ref
    if not v_ref > 0:
        raise MeshingError(f"{where}: the kept body encloses no volume (a flat sheet?); check the input file")
    out, iters = _smooth_keeping_volume(pts, fcs, v_ref, opts, record, rep, where, n_bodies=n_kept)
    out = Surface(*out, surface.source)
    if not out.is_closed():
        raise MeshingError(
            f"{where}: the surface still has {out.n_boundary_edges()} open or {out.n_nonmanifold_edges()} "
            f"non-manifold edges after repair; export the organ again with holes filled"
        )
    report.smooth_iterations_used = iters
    report.volume_after = out.volume()
    report.area_after = out.area()
    report.relative_volume_change = report.volume_after / report.volume_before - 1.0
    rep.step(f"cleaned: {out.n_points} points, {out.n_faces} faces, volume {report.volume_after * 1e6:.1f} mL "
             f"({report.relative_volume_change * 100:+.2f} % of the kept body)")
    return out.with_source(f"cleaned ({iters} smoothing iterations)"), report


def _merge_step(pts, fcs, extent: float, record: _StepRecorder):
    """Step 1: merge duplicate points (closer than :data:`MERGE_TOLERANCE` of the extent)."""
    t0 = time.perf_counter()
    p1, f1, merged = _merge_points(pts, fcs, MERGE_TOLERANCE * max(extent, 1e-12))
    record("merge", t0, pts, fcs, p1, f1, f"{merged} duplicate points merged", points_merged=merged)
    return p1, f1


def _degenerate_step(pts, fcs, extent: float, record: _StepRecorder, where: str):
    """Step 2: drop faces with a repeated corner, of zero area, or duplicated."""
    t0 = time.perf_counter()
    f1, n_rep, n_zero, n_dup = _drop_degenerate(pts, fcs, (1e-9 * extent) ** 2)
    p1, f1 = _compact(pts, f1) if f1.shape[0] else (pts, f1)
    if f1.shape[0] == 0:
        raise MeshingError(f"{where}: every triangle is degenerate (zero area); check the input file")
    record("degenerate", t0, pts, fcs, p1, f1,
           f"{n_rep} with a repeated corner, {n_zero} of zero area, {n_dup} duplicates dropped",
           repeated_corner=n_rep, zero_area=n_zero, duplicates=n_dup)
    return p1, f1


def _chosen_bodies(opts: CleaningOptions, rank, nf, vols) -> list[int]:
    """The bodies kept (indices into the components): ``body=N``, all of them, or the largest."""
    n_bodies = len(rank)
    if opts.body is not None:
        if opts.body >= n_bodies:
            listing = ", ".join(f"{i}: {nf[k]} faces {vols[k] * 1e6:.3g} mL" for i, k in enumerate(rank[:6]))
            raise ConfigError(f"body: {opts.body} does not exist; the surface has {n_bodies} bodies ({listing})")
        return [int(rank[opts.body])]
    if opts.keep == "all":
        return [int(k) for k in rank]
    return [int(rank[0])]


def _bodies_step(pts, fcs, opts: CleaningOptions, record: _StepRecorder, rep, where: str):
    """Step 3: split into bodies and keep the chosen ones.

    Returns the kept surface ``(points, faces)``, the same faces consistently
    oriented within each body, and the number of bodies kept.
    """
    t0 = time.perf_counter()
    n_bodies, lab = face_components(pts.shape[0], fcs)
    # Orientation inside each body must be consistent before its volume means anything.
    f_or, _, _ = orient_consistently(pts.shape[0], fcs)
    vols = np.abs(capped_volumes(pts, f_or, lab, n_bodies))
    p0 = pts
    tri_area = 0.5 * np.linalg.norm(cross3(p0[fcs[:, 1]] - p0[fcs[:, 0]], p0[fcs[:, 2]] - p0[fcs[:, 0]]), axis=1)
    areas = np.bincount(lab, tri_area, minlength=n_bodies)
    nf = np.bincount(lab, minlength=n_bodies)
    rank = np.lexsort((-areas, -vols))  # by volume, then area
    record.report.bodies_found = n_bodies
    kept = _chosen_bodies(opts, rank, nf, vols)
    dropped = [int(k) for k in rank if k not in kept]
    record.report.bodies_dropped = [(int(nf[k]), float(vols[k])) for k in dropped]
    if len(kept) == n_bodies:
        p1, f1, f1_or = pts, fcs, f_or
    else:
        sel = np.isin(lab, kept)
        p1, f1 = _compact(pts, fcs[sel])
        _, f1_or = _compact(pts, f_or[sel])
    note = f"{n_bodies} found, {len(kept)} kept"
    if dropped:
        note += ", dropped " + ", ".join(f"{nf[k]} faces/{vols[k] * 1e6:.3g} mL" for k in dropped[:5])
        if len(dropped) > 5:
            note += f" and {len(dropped) - 5} more"
    record("bodies", t0, pts, fcs, p1, f1, note, bodies_found=n_bodies, bodies_kept=len(kept),
           bodies_dropped=[(int(nf[k]), float(vols[k])) for k in dropped],
           body_volumes=[float(vols[k]) for k in rank], body_faces=[int(nf[k]) for k in rank])
    _refuse_cavities(where, pts, fcs, lab, rank, kept, dropped, vols, opts)
    _refuse_soup(where, int(nf[kept].sum()), fcs.shape[0], n_bodies)
    if dropped and vols[dropped].max() > 0.1 * vols[kept].sum():
        rep.warn(f"{where}: dropped a second body of {vols[dropped].max() * 1e6:.3g} mL "
                 f"(kept {vols[kept].sum() * 1e6:.3g} mL); use keep='all' or body=N to choose")
    return p1, f1, f1_or, len(kept)


def _orient_step(pts, fcs, fcs_or, record: _StepRecorder):
    """Step 4: turn each body outward (its consistent orientation *fcs_or* was found with the bodies)."""
    t0 = time.perf_counter()
    n_kept, lab_k = face_components(pts.shape[0], fcs_or)
    signs = capped_volumes(pts, fcs_or, lab_k, n_kept)
    neg = signs < 0
    f1 = fcs_or.copy()
    fl = neg[lab_k]
    f1[fl] = f1[fl][:, ::-1]
    changed = np.any(f1 != fcs, axis=1)
    n_flip = int(np.count_nonzero(changed))
    if n_flip == 0:
        f1 = fcs
    record("orient", t0, pts, fcs, pts, f1,
           f"{n_flip} faces flipped ({int(neg.sum())} bodies turned outward)",
           faces_flipped=n_flip, bodies_flipped=int(neg.sum()))
    return f1


def _smooth_keeping_volume(pts, fcs, v_ref: float, opts: CleaningOptions, record: _StepRecorder, rep,
                           where: str, *, n_bodies: int):
    """Steps 5-8 with less smoothing each time until the volume stays within :data:`MAX_VOLUME_CHANGE`.

    Returns the surface ``(points, faces)`` and the smoothing iterations used.
    """
    target = _target_faces(opts, Surface(pts, fcs).area())
    iters = int(opts.smooth_iterations)
    tried: list[str] = []
    while True:
        result = _smooth_to_closed(pts, fcs, iters, opts.smooth_passband, target, record, where,
                                   n_bodies=n_bodies)
        p_out, f_out = result
        v_out = capped_volume(p_out, f_out)
        change = v_out / v_ref - 1.0
        tried.append(f"{iters} iterations: {change * 100:+.2f} %")
        if abs(change) <= MAX_VOLUME_CHANGE:
            return (p_out, f_out), iters
        if iters == 0:
            raise MeshingError(
                f"{where}: cleaning changes the enclosed volume by more than "
                f"{MAX_VOLUME_CHANGE * 100:g} % ({'; '.join(tried)}); give a larger target_faces "
                f"or check the input surface"
            )
        iters = _fewer(iters)
        rep.warn(f"{where}: volume changed {change * 100:+.2f} % with {tried[-1].split(':')[0]}; "
                 f"retrying with {iters}")


def _fewer(iters: int) -> int:
    """The next smoothing tried when the volume moved: half, but never 1 (VTK's windowed-sinc filter of
    one iteration finds no offset and collapses the surface: a sphere of 50 mm to 7 mm)."""
    half = iters // 2
    return half if half >= 2 else 0


def _refuse_cavities(where, pts, fcs, lab, rank, kept, dropped, vols, opts) -> None:
    """A body inside another is a cavity (a hollow organ's inner wall): never fill or double it silently.

    Kept with ``keep="all"`` it would be meshed as a second solid inside the
    first; dropped by ``keep="largest"`` the cavity is filled. The first is
    refused always, the second when the cavity is more than 10 % of the kept
    volume (a small void, e.g. an unlabelled vessel of a mask, is filled as
    before). ``body=N`` is the user's explicit choice and is not checked.
    """
    if opts.body is not None or len(rank) < 2:
        return
    big = [int(k) for k in rank if k in kept or vols[k] > 0.1 * vols[kept].sum()]
    if len(big) < 2:
        return
    index = {int(k): i for i, k in enumerate(rank)}
    for inner, outer in nested_bodies(pts, fcs, lab, big):
        if inner in dropped and outer not in kept:
            continue
        what = (f"body {index[inner]} ({vols[inner] * 1e6:.3g} mL) lies inside body {index[outer]} "
                f"({vols[outer] * 1e6:.3g} mL): the organ is hollow (a wall of "
                f"{(vols[outer] - vols[inner]) * 1e6:.3g} mL) and only solid organs are meshed")
        if inner in kept:
            act = "keeping every body would mesh the cavity as a second solid inside the first"
        else:
            act = (f"keeping the largest body would fill the cavity (volume and mass x"
                   f"{vols[outer] / (vols[outer] - vols[inner]):.3g})")
        raise InputError(f"body: {where}: {what}; {act}; give body {index[outer]} to keep the outer "
                         f"surface filled on purpose, or export a solid organ", parameter="body")


def _refuse_soup(where, n_kept: int, n_faces: int, n_bodies: int) -> None:
    """Pieces of fewer than 4 triangles (a tetrahedron's) close no volume: the triangles share no edges."""
    if n_kept >= 4 or n_bodies < 2:
        return
    raise MeshingError(
        f"{where}: its {n_faces} triangles make {n_bodies} separate pieces and the largest has {n_kept}: "
        f"neighbouring triangles do not share their corners (not merged within {MERGE_TOLERANCE:g} of the "
        f"extent), so no closed body can be made; export the surface with merged (welded) vertices")


def _target_faces(opts: CleaningOptions, area: float) -> int:
    if opts.target_faces is not None:
        return int(opts.target_faces)
    if opts.target_edge is not None:
        # Equilateral triangles of edge e: area sqrt(3)/4 e^2 each.
        return max(200, int(round(area / (np.sqrt(3.0) / 4.0 * float(opts.target_edge) ** 2))))
    return DEFAULT_TARGET_FACES


def _smooth_to_closed(pts, fcs, iters, passband, target, record, where, n_bodies: int = 1):
    # 5. smooth
    t0 = time.perf_counter()
    if iters > 0:
        p1 = _smooth(pts, fcs, iters, passband)
        note = f"windowed sinc, {iters} iterations, pass band {passband:g}, borders held"
    else:
        p1 = pts
        note = "skipped (0 iterations)"
    d = np.linalg.norm(p1 - pts, axis=1)
    record("smooth", t0, pts, fcs, p1, fcs, note, iterations=iters, passband=passband,
           max_displacement=float(d.max()) if d.size else 0.0, mean_displacement=float(d.mean()) if d.size else 0.0)
    pts = p1

    # 6. decimate
    t0 = time.perf_counter()
    if fcs.shape[0] > 1.1 * target:
        # Borders are not preserved: holding them keeps the scan-border loops at voxel
        # resolution, and the hole filling then refines the caps down to it.
        p1, f1 = _compact(*decimate(pts, fcs, target))
        note = f"quadric decimation to {target} faces"
    else:
        p1, f1 = pts, fcs
        note = f"skipped ({fcs.shape[0]} faces, target {target})"
    record("decimate", t0, pts, fcs, p1, f1, note, target_faces=int(target))
    pts, fcs = p1, f1

    # 7. close open borders and 8. repair, in one pymeshfix session (in mm)
    t0 = time.perf_counter()
    s = Surface(pts, fcs)
    n_border = s.n_boundary_edges()
    n_nonman = s.n_nonmanifold_edges()
    tm = meshfix(pts, fcs)
    loops = int(tm.n_boundaries)
    filled = int(tm.fill_small_boundaries(0, True)) if loops else 0
    p1, f1 = meshfix_arrays(tm)
    if f1.shape[0] == 0:
        raise MeshingError(f"{where}: nothing is left after hole filling; check the input file")
    record("close", t0, pts, fcs, p1, f1,
           f"{filled} holes filled ({n_border} border edges, {n_nonman} non-manifold edges split)",
           border_edges=n_border, nonmanifold_edges=n_nonman, holes_filled=filled)
    pts, fcs = p1, f1

    t0 = time.perf_counter()
    converged = bool(tm.clean(10, 3))
    refilled = int(tm.fill_small_boundaries(0, True)) if tm.n_boundaries else 0
    p1, f1 = meshfix_arrays(tm)
    p1, f1, n_pieces = keep_largest(p1, f1, n_bodies) if f1.shape[0] else (p1, f1, 0)
    if f1.shape[0] == 0:
        raise MeshingError(f"{where}: nothing is left after repair; check the input file")
    f1, n_flip, _, _ = orient_outward(p1, f1)
    s1 = Surface(p1, f1)
    record("repair", t0, pts, fcs, p1, f1,
           f"degeneracies and self-intersections (pymeshfix, converged={converged}); "
           f"{n_pieces} stray pieces dropped; closed={s1.is_closed()}",
           pieces_dropped=n_pieces, converged=converged, holes_refilled=refilled)
    return p1, f1
