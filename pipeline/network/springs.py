"""The spring network: nodes with lumped masses joined by springs.

A :class:`SpringNetwork` is what the simulator integrates. Each spring ``ij``
carries its rest length ``L0``, the volume ``V_ij`` of tissue it stands for and
its *volume weight* ``v_ij = V_ij / L0**2`` [m]: a spring whose tissue has the
equivalent modulus ``mu_e(lambda)`` [Pa] has the stiffness

.. math::  k_{ij}(\\lambda) = \\mu_e(\\lambda)\\, v_{ij}, \\qquad v_{ij} = V_{ij} / L_{0,ij}^2

(docs/design/model.md, "The spring network", derives it from an energy match and states what the
network's effective modulus then is). ``cos2`` holds the squared direction
cosines of each spring in the fibre frame, which select the per-direction
stiffness tables.

Two builders:

* :func:`network_from_tets` - springs on the unique edges of a tetrahedral mesh
  (``structure="tetra"``), ``V_ij = sum over the tets containing ij of V_t / 6``.
* :func:`network_from_skeleton` - springs of a surface + skeleton structure
  (``structure="skeleton"``), the organ volume shared over the springs in
  proportion to ``L0**2`` (uniform ``v_ij``).

All quantities are SI: metres, kilograms, cubic metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError, MeshingError
from ..progress import ensure

#: node_kind codes (uint8) stored with every network and asset.
NODE_INTERIOR = 0
NODE_SURFACE = 1
NODE_SKELETON = 2
NODE_KIND_NAMES: dict[int, str] = {NODE_INTERIOR: "interior", NODE_SURFACE: "surface",
                                   NODE_SKELETON: "skeleton"}

STRUCTURES = ("tetra", "skeleton")
REORDER_METHODS = ("rcm", "morton", None)

#: default tissue density [kg/m3] (soft tissue, liver ~1050-1070).
DEFAULT_DENSITY = 1060.0
#: Densities accepted for tissue [kg/m3] (soft tissue is ~1000-1100; outside: a unit slip).
DENSITY_RANGE = (100.0, 20000.0)

# The 6 edges and the 4 outward faces of a positively oriented tetrahedron (a, b, c, d):
# det(b - a, c - a, d - a) > 0. Face k is opposite vertex k.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


@dataclass
class SpringNetwork:
    """Nodes, springs and what the simulator needs about them (SI units).

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Node positions at rest [m].
    springs : ndarray, shape (s, 2), int64
        Node index pairs with ``i < j``, sorted by ``i`` then ``j``.
    rest_length : ndarray, shape (s,), float64
        ``L0`` [m].
    volume : ndarray, shape (s,), float64
        ``V_ij``, the tissue volume each spring stands for [m3]; sums to the organ volume.
    volume_weight : ndarray, shape (s,), float64
        ``v_ij = V_ij / L0**2`` [m]; stiffness ``k_ij = mu_e * v_ij``.
    cos2 : ndarray, shape (s, 3), float64
        Squared direction cosines of each spring along the three fibre axes (rows sum to 1).
    mass : ndarray, shape (n,), float64
        Lumped node masses [kg].
    surface_faces : ndarray, shape (k, 3), int64
        Outward boundary triangles (for rendering and contact).
    fixed : ndarray, shape (f,), int64
        Indices of the nodes held fixed, sorted, unique.
    tets : ndarray, shape (t, 4), int64, or None
        Positively oriented tetrahedra (``structure="tetra"``).
    node_kind : ndarray, shape (n,), uint8
        :data:`NODE_INTERIOR`, :data:`NODE_SURFACE` or :data:`NODE_SKELETON`.
    structure : str
        ``"tetra"`` or ``"skeleton"``.
    fibre_frame : ndarray, shape (3, 3), float64
        Orthonormal rows: the fibre axes in mesh coordinates. ``cos2[:, a] = (frame[a] . d)**2``.
    density : float
        Tissue density used for the masses [kg/m3].
    volume_term : VolumeSpec or None
        The volume term the network carries (:mod:`esmm.pipeline.network.volume`:
        bulk modulus and formulation, on ``tets``); None: springs alone.
    quadratic_cells : ndarray, shape (p, 10), int64, or None
        When ``tets`` were made by splitting a coarser mesh's tetrahedra in eight
        (:func:`~esmm.pipeline.mesh.refine.split_in_eight`): those parents as
        10-node tetrahedra on this network's nodes (every node is a vertex or an
        edge middle of one), for the second-order continuum reference. None otherwise.
    """

    points: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    volume: np.ndarray
    volume_weight: np.ndarray
    cos2: np.ndarray
    mass: np.ndarray
    surface_faces: np.ndarray
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tets: np.ndarray | None = None
    node_kind: np.ndarray | None = None
    structure: str = "tetra"
    fibre_frame: np.ndarray = field(default_factory=lambda: np.eye(3))
    density: float = DEFAULT_DENSITY
    volume_term: Any = None        # a volume.VolumeSpec (that module builds on this one)
    quadratic_cells: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(np.asarray(self.points, dtype=np.float64).reshape(-1, 3))
        self.springs = np.ascontiguousarray(np.asarray(self.springs, dtype=np.int64).reshape(-1, 2))
        for name in ("rest_length", "volume", "volume_weight", "mass"):
            setattr(self, name, np.ascontiguousarray(np.asarray(getattr(self, name), dtype=np.float64).ravel()))
        self.cos2 = np.ascontiguousarray(np.asarray(self.cos2, dtype=np.float64).reshape(-1, 3))
        self.surface_faces = np.ascontiguousarray(np.asarray(self.surface_faces, dtype=np.int64).reshape(-1, 3))
        self.fixed = np.ascontiguousarray(np.asarray(self.fixed, dtype=np.int64).ravel())
        if self.tets is not None:
            self.tets = np.ascontiguousarray(np.asarray(self.tets, dtype=np.int64).reshape(-1, 4))
        if self.quadratic_cells is not None:
            self.quadratic_cells = np.ascontiguousarray(np.asarray(self.quadratic_cells, dtype=np.int64).reshape(-1, 10))
        if self.node_kind is None:
            self.node_kind = np.zeros(self.points.shape[0], np.uint8)
        self.node_kind = np.ascontiguousarray(np.asarray(self.node_kind, dtype=np.uint8).ravel())
        self.fibre_frame = np.asarray(self.fibre_frame, dtype=np.float64).reshape(3, 3)
        self.density = float(self.density)

    # -- sizes -----------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_springs(self) -> int:
        return int(self.springs.shape[0])

    @property
    def n_tets(self) -> int:
        return 0 if self.tets is None else int(self.tets.shape[0])

    def total_volume(self) -> float:
        """Organ volume [m3]: the tets' volume, else the springs' ``sum V_ij``."""
        if self.tets is not None and self.tets.shape[0]:
            return float(tet_volumes(self.points, self.tets).sum())
        return float(self.volume.sum())

    def total_mass(self) -> float:
        """Sum of node masses [kg]."""
        return float(self.mass.sum())

    def fixed_mask(self) -> np.ndarray:
        """Boolean mask of shape (n,), True on fixed nodes."""
        mask = np.zeros(self.n_nodes, bool)
        mask[self.fixed] = True
        return mask

    def bandwidth(self) -> int:
        """Largest ``j - i`` over the springs (the stiffness matrix's half bandwidth in nodes)."""
        if self.n_springs == 0:
            return 0
        return int((self.springs[:, 1] - self.springs[:, 0]).max())

    def with_fixed(self, fixed) -> SpringNetwork:
        """A copy with another set of fixed nodes (sorted, unique)."""
        return dataclasses.replace(self, fixed=np.unique(np.asarray(fixed, dtype=np.int64)))

    def summary(self) -> str:
        """One line: nodes, springs, tets, volume, mass, fixed nodes."""
        tets = f", {self.n_tets} tets" if self.tets is not None else ""
        return (f"{self.structure}: {self.n_nodes} nodes, {self.n_springs} springs{tets}, "
                f"volume {self.total_volume() * 1e6:.1f} mL, mass {self.total_mass() * 1e3:.1f} g, "
                f"{self.fixed.size} fixed nodes")

    # -- checks ----------------------------------------------------------------
    def problems(self, *, rtol: float = 1e-9) -> list[str]:
        """Every inconsistency found, one line each (empty when the network is sound)."""
        out: list[str] = []
        n, s = self.n_nodes, self.n_springs
        if self.structure not in STRUCTURES:
            out.append(f"structure {self.structure!r} is not one of {', '.join(STRUCTURES)}")
        if n == 0:
            out.append("network has no nodes")
        if s == 0:
            out.append("network has no springs")
        if not np.all(np.isfinite(self.points)):
            out.append("points contain NaN or infinite coordinates")
        for name, arr, shape in (("rest_length", self.rest_length, (s,)), ("volume", self.volume, (s,)),
                                 ("volume_weight", self.volume_weight, (s,)), ("cos2", self.cos2, (s, 3)),
                                 ("mass", self.mass, (n,)), ("node_kind", self.node_kind, (n,))):
            if arr.shape != shape:
                out.append(f"{name} has shape {arr.shape}, expected {shape}")
            elif arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                out.append(f"{name} contains NaN or infinite values")
        if out:
            return out
        if s:
            i, j = self.springs[:, 0], self.springs[:, 1]
            if i.min() < 0 or j.max() >= n:
                out.append(f"spring indices outside 0..{n - 1}")
            if np.any(i >= j):
                out.append(f"{int(np.count_nonzero(i >= j))} springs do not have i < j")
            key = i * max(n, 1) + j
            if np.any(np.diff(key) <= 0):
                out.append("springs are not sorted by (i, j) or contain duplicates")
            if not out:
                length = np.linalg.norm(self.points[j] - self.points[i], axis=1)
                if np.any(self.rest_length <= 0):
                    out.append(f"{int(np.count_nonzero(self.rest_length <= 0))} springs have zero rest length")
                elif not np.allclose(length, self.rest_length, rtol=1e-6, atol=0):
                    out.append("rest_length differs from the distance between the spring's nodes")
            if np.any(self.volume < 0):
                out.append(f"{int(np.count_nonzero(self.volume < 0))} springs have negative volume V_ij")
            if np.all(self.rest_length > 0) and not np.allclose(
                    self.volume_weight, self.volume / self.rest_length**2, rtol=1e-9, atol=0):
                out.append("volume_weight is not volume / rest_length**2")
            if not np.allclose(self.cos2.sum(axis=1), 1.0, rtol=0, atol=1e-9) or np.any(self.cos2 < -1e-12):
                out.append("cos2 rows do not sum to 1 (or have negative entries)")
        if n and np.any(self.mass <= 0):
            out.append(f"{int(np.count_nonzero(self.mass <= 0))} nodes have zero or negative mass")
        if n and s and np.unique(self.springs).size != n:
            out.append(f"{n - np.unique(self.springs).size} nodes are attached to no spring")
        if self.fixed.size:
            if self.fixed.min() < 0 or self.fixed.max() >= n:
                out.append(f"fixed node indices outside 0..{n - 1}")
            elif np.any(np.diff(self.fixed) <= 0):
                out.append("fixed node indices are not sorted and unique")
        if self.surface_faces.size and (self.surface_faces.min() < 0 or self.surface_faces.max() >= n):
            out.append(f"surface face indices outside 0..{n - 1}")
        if self.tets is not None and self.tets.size:
            if self.tets.min() < 0 or self.tets.max() >= n:
                out.append(f"tet indices outside 0..{n - 1}")
            else:
                vt = tet_volumes(self.points, self.tets)
                if np.any(vt <= 0):
                    out.append(f"{int(np.count_nonzero(vt <= 0))} tetrahedra have zero or negative volume")
                elif s and not np.isclose(self.volume.sum(), vt.sum(), rtol=1e-6):
                    out.append(f"sum of V_ij ({self.volume.sum():.6g} m3) differs from the tet volume "
                               f"({vt.sum():.6g} m3)")
        if np.any(self.node_kind > max(NODE_KIND_NAMES)):
            out.append(f"node_kind has codes other than {sorted(NODE_KIND_NAMES)}")
        frame = self.fibre_frame
        if not np.all(np.isfinite(frame)) or not np.allclose(frame @ frame.T, np.eye(3), atol=1e-8):
            out.append("fibre_frame is not orthonormal")
        if not (np.isfinite(self.density) and self.density > 0):
            out.append(f"density {self.density} is not a positive number")
        return out

    def validate(self) -> SpringNetwork:
        """Raise :class:`~esmm.pipeline.errors.InputError` listing the problems; return self if none."""
        probs = self.problems()
        if probs:
            more = f" (and {len(probs) - 1} more)" if len(probs) > 1 else ""
            raise InputError(f"invalid spring network: {probs[0]}{more}")
        return self


# -- geometry helpers -----------------------------------------------------------------------

def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tetrahedron volumes [m3], shape (t,); positive for ``det(b-a, c-a, d-a) > 0``."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    a = p[t[:, 1]] - p[t[:, 0]]
    b = p[t[:, 2]] - p[t[:, 0]]
    c = p[t[:, 3]] - p[t[:, 0]]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Outward boundary triangles of positively oriented tets, shape (k, 3).

    A face is on the boundary when exactly one tet has it. Faces are oriented
    counter-clockwise seen from outside (normal away from the owning tet).
    """
    t = np.asarray(tets, dtype=np.int64)
    if t.shape[0] == 0:
        return np.zeros((0, 3), np.int64)
    faces = t[:, _TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    return np.ascontiguousarray(faces[once])


def fibre_frame_matrix(frame, *, points: np.ndarray | None = None, where: str = "fibre_frame") -> np.ndarray:
    """Turn a fibre-frame specification into an orthonormal (3, 3) matrix (rows = axes).

    Parameters
    ----------
    frame
        ``None`` or ``"identity"`` (the mesh axes), ``"principal"`` (the principal
        axes of *points*, longest first, each with its largest component
        positive), or a 3x3 array-like of rows; the rows are checked to be
        orthonormal within 1e-6 and re-orthonormalised.
    points : ndarray, shape (n, 3), optional
        Needed for ``"principal"``.
    where
        Name of the option, for messages.
    """
    if frame is None or (isinstance(frame, str) and frame.lower() == "identity"):
        return np.eye(3)
    if isinstance(frame, str):
        if frame.lower() != "principal":
            raise InputError(f"{where}: unknown frame {frame!r}; use \"identity\", \"principal\" "
                             f"or a 3x3 list of orthonormal rows")
        if points is None or len(points) < 4:
            raise InputError(f"{where}: \"principal\" needs the mesh points")
        return principal_axes(points)
    try:
        m = np.asarray(frame, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {frame!r} is not a 3x3 list of numbers") from None
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InputError(f"{where}: expected a 3x3 list of finite numbers (rows = fibre axes), got shape {m.shape}")
    norms = np.linalg.norm(m, axis=1)
    if np.any(norms == 0):
        raise InputError(f"{where}: a fibre axis is the zero vector")
    m = m / norms[:, None]
    if not np.allclose(m @ m.T, np.eye(3), atol=1e-6):
        raise InputError(f"{where}: the three fibre axes are not mutually perpendicular; give orthogonal rows")
    u, _, vt = np.linalg.svd(m)
    return u @ vt  # nearest orthonormal matrix (removes the round-off of typed-in values)


def principal_axes(points: np.ndarray) -> np.ndarray:
    """Principal axes of a point cloud as rows, longest extent first, shape (3, 3).

    Each axis is signed so that its largest-magnitude component is positive (a
    deterministic choice; the sign of an eigenvector is arbitrary).
    """
    p = np.asarray(points, dtype=np.float64)
    q = p - p.mean(axis=0)
    w, v = np.linalg.eigh(q.T @ q)
    axes = v[:, ::-1].T.copy()
    for a in axes:
        if a[np.argmax(np.abs(a))] < 0:
            a *= -1
    return axes


def direction_cos2(points: np.ndarray, springs: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Squared direction cosines of the springs along the rows of *frame*, shape (s, 3)."""
    d = points[springs[:, 1]] - points[springs[:, 0]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    c = d @ np.asarray(frame, dtype=np.float64).T
    c2 = c * c
    return c2 / c2.sum(axis=1)[:, None]


# -- node ordering ------------------------------------------------------------------------

def node_order(points: np.ndarray, edges: np.ndarray, method: str | None) -> np.ndarray:
    """A permutation of the nodes for memory locality: ``new_points = points[order]``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    edges : ndarray, shape (e, 2)
        Node pairs (the springs).
    method
        ``"rcm"``: reverse Cuthill-McKee on the spring graph (small stiffness
        bandwidth); ``"morton"``: Z-order of the positions on a 2**21 grid per
        axis (spatial locality); ``None``: identity.

    Returns
    -------
    order : ndarray, shape (n,), int64
    """
    n = int(np.asarray(points).shape[0])
    if method is None or method == "none":
        return np.arange(n, dtype=np.int64)
    if method == "rcm":
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        e = np.asarray(edges, dtype=np.int64)
        data = np.ones(2 * e.shape[0], np.int8)
        rows = np.concatenate([e[:, 0], e[:, 1]])
        cols = np.concatenate([e[:, 1], e[:, 0]])
        graph = coo_matrix((data, (rows, cols)), shape=(n, n)).tocsr()
        return np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), dtype=np.int64)
    if method == "morton":
        return np.argsort(morton_codes(points), kind="stable").astype(np.int64)
    raise InputError(f"reorder: unknown method {method!r}; use \"rcm\", \"morton\" or none")


def morton_codes(points: np.ndarray, *, bits: int = 21) -> np.ndarray:
    """63-bit Morton (Z-order) codes of points quantised on a ``2**bits`` grid per axis."""
    p = np.asarray(points, dtype=np.float64)
    lo = p.min(axis=0)
    span = float((p.max(axis=0) - lo).max()) or 1.0
    q = np.minimum(((p - lo) / span * (2**bits - 1)).round().astype(np.uint64), np.uint64(2**bits - 1))

    def spread(x: np.ndarray) -> np.ndarray:  # insert two zero bits between the bits of x
        x = x & np.uint64(0x1FFFFF)
        x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
        return x

    return spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))


def check_reorder(reorder, name: str = "reorder") -> str | None:
    """The node ordering method: ``"rcm"``, ``"morton"``, or None for ``None``/``"none"``.

    Raises
    ------
    InputError
        Another method (the message starts with *name*).
    """
    if reorder in (None, "none"):
        return None
    if reorder not in REORDER_METHODS:
        raise InputError(f"{name}: unknown method {reorder!r}; use \"rcm\", \"morton\" or none", parameter=name)
    return reorder


def check_density(density, name: str = "density") -> float:
    """A tissue density [kg/m3] within :data:`DENSITY_RANGE` (a unit slip is refused, not guessed).

    Raises
    ------
    InputError
        Not a positive number, or not plausible for tissue (the message starts with *name*).
    """
    try:
        rho = float(density)
    except (TypeError, ValueError):
        raise InputError(f"{name}: {density!r} is not a number (kg/m3)", parameter=name) from None
    if not np.isfinite(rho) or rho <= 0:
        raise InputError(f"{name}: {density!r} must be a positive number of kg/m3", parameter=name)
    lo, hi = DENSITY_RANGE
    if not lo <= rho <= hi:
        raise InputError(f"{name}: {rho:g} kg/m3 is not plausible for tissue (soft tissue is ~1000-1100); "
                         f"give it in kg/m3", parameter=name)
    return rho


def _sorted_unique_edges(pairs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (i < j, sorted) and, for each input pair, its edge index."""
    p = np.sort(np.asarray(pairs, dtype=np.int64), axis=1)
    key = p[:, 0] * n + p[:, 1]
    ukey, inverse = np.unique(key, return_inverse=True)
    edges = np.stack([ukey // n, ukey % n], axis=1)
    return edges, inverse.ravel()


# -- builders -----------------------------------------------------------------------------

def network_from_tets(mesh, *, density: float = DEFAULT_DENSITY, fibre_frame=None,
                      reorder: str | None = "rcm", reporter=None) -> SpringNetwork:
    """Build the spring network of a tetrahedral mesh.

    Springs are the unique tet edges. Each tet's volume ``V_t`` is shared
    equally by its 6 edges, ``V_ij = sum_{t containing ij} V_t / 6`` (so that
    ``sum V_ij`` is the mesh volume), and ``v_ij = V_ij / L0**2``. Each tet's
    mass ``density * V_t`` is lumped a quarter to each of its nodes. Nodes
    used by no tet are dropped, negatively oriented tets are flipped, and the
    boundary triangles are recomputed from the tets (outward).

    Parameters
    ----------
    mesh
        Anything with ``points`` (n, 3) [m] and ``tets`` (t, 4) int, e.g. a
        :class:`~esmm.pipeline.mesh.volume.VolumeMesh`; its ``quadratic_cells``
        (p, 10), if it has them (a split mesh), are carried over renumbered.
    density : float
        Tissue density [kg/m3].
    fibre_frame
        See :func:`fibre_frame_matrix` (default: the mesh axes).
    reorder : {"rcm", "morton", None}
        Node renumbering for memory locality (see :func:`node_order`).

    Returns
    -------
    SpringNetwork
        With no fixed nodes (see :mod:`esmm.pipeline.network.regions`).

    Raises
    ------
    InputError
        Bad arrays, indices out of range, non-finite coordinates.
    MeshingError
        Degenerate (zero-volume) tetrahedra.
    """
    rep = ensure(reporter)
    rho = check_density(density)
    reorder = check_reorder(reorder)
    points, tets = _checked_tets(mesh)
    quadratic = _quadratic_cells(mesh, points.shape[0])
    points, tets, quadratic = _drop_unused_nodes(points, tets, quadratic, rep)
    n = points.shape[0]
    tets, vt = _oriented_tets(points, tets, rep)
    points, tets, quadratic = _renumbered(points, tets, quadratic, reorder)

    edges, inverse = _sorted_unique_edges(tets[:, _TET_EDGES].reshape(-1, 2), n)
    volume = np.bincount(inverse, weights=np.repeat(vt / 6.0, 6), minlength=edges.shape[0])
    mass = np.bincount(tets.ravel(), weights=np.repeat(rho * vt / 4.0, 4), minlength=n)

    d = points[edges[:, 1]] - points[edges[:, 0]]
    rest = np.linalg.norm(d, axis=1)
    frame = fibre_frame_matrix(fibre_frame, points=points)
    faces = boundary_faces(tets)
    kind = np.full(n, NODE_INTERIOR, np.uint8)
    kind[np.unique(faces)] = NODE_SURFACE

    net = SpringNetwork(
        points=points, springs=edges, rest_length=rest, volume=volume, volume_weight=volume / rest**2,
        cos2=direction_cos2(points, edges, frame), mass=mass, surface_faces=faces, tets=tets,
        node_kind=kind, structure="tetra", fibre_frame=frame, density=rho, quadratic_cells=quadratic,
    )
    return net


def _checked_tets(mesh) -> tuple[np.ndarray, np.ndarray]:
    """*mesh*'s points (n, 3) float and tets (t, 4) int64, checked for shape, range and finiteness."""
    points = np.asarray(getattr(mesh, "points", None), dtype=np.float64)
    tets = np.asarray(getattr(mesh, "tets", None))
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"mesh.points: expected shape (n, 3), got {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise InputError(f"mesh.tets: expected shape (t, 4) with t > 0, got {tets.shape}; the mesh has no tetrahedra")
    if tets.dtype.kind not in "iu":
        raise InputError(f"mesh.tets: expected integer indices, got {tets.dtype}")
    tets = tets.astype(np.int64)
    if tets.min() < 0 or tets.max() >= points.shape[0]:
        raise InputError(f"mesh.tets: indices outside 0..{points.shape[0] - 1}")
    if np.any(np.sort(tets, axis=1)[:, 1:] == np.sort(tets, axis=1)[:, :-1]):
        raise InputError("mesh.tets: a tetrahedron repeats a node")
    if not np.all(np.isfinite(points)):
        raise InputError("mesh.points: NaN or infinite coordinates")
    return points, tets


def _drop_unused_nodes(points, tets, quadratic, rep):
    """``(points, tets, quadratic)`` without the nodes that no tetrahedron uses, renumbered."""
    used = np.unique(tets)
    if used.size != points.shape[0]:
        remap = np.full(points.shape[0], -1, np.int64)
        remap[used] = np.arange(used.size)
        rep.step(f"dropped {points.shape[0] - used.size} nodes used by no tetrahedron")
        points, tets = points[used], remap[tets]
        quadratic = None if quadratic is None else remap[quadratic]
        if quadratic is not None and quadratic.min() < 0:
            raise InputError("mesh.quadratic_cells: a 10-node cell uses a node of no tetrahedron")
    return points, tets, quadratic


def _oriented_tets(points, tets, rep) -> tuple[np.ndarray, np.ndarray]:
    """Tets turned to positive orientation and their volumes, shape (t,); degenerate ones refused."""
    vt = tet_volumes(points, tets)
    scale = float(np.ptp(points, axis=0).max()) ** 3
    tiny = 1e-12 * scale
    degenerate = np.abs(vt) <= tiny
    if np.any(degenerate):
        raise MeshingError(f"{int(degenerate.sum())} of {tets.shape[0]} tetrahedra have zero volume; "
                           f"remesh it (a smaller element size, or the surface repair first)")
    neg = vt < 0
    if np.any(neg):
        tets = tets.copy()
        tets[neg] = tets[neg][:, [0, 1, 3, 2]]
        vt = np.abs(vt)
        rep.step(f"flipped {int(neg.sum())} negatively oriented tetrahedra")
    return tets, vt


def _renumbered(points, tets, quadratic, reorder: str | None):
    """``(points, tets, quadratic)`` with the nodes in the order :func:`node_order` finds on the edge graph."""
    n = points.shape[0]
    pairs = tets[:, _TET_EDGES].reshape(-1, 2)
    edges, _ = _sorted_unique_edges(pairs, n)
    order = node_order(points, edges, reorder)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    return points[order], rank[tets], None if quadratic is None else rank[quadratic]


def _quadratic_cells(mesh, n: int) -> np.ndarray | None:
    """*mesh*'s ``quadratic_cells`` (p, 10) checked against its *n* nodes, or None when it has none."""
    q = getattr(mesh, "quadratic_cells", None)
    if q is None:
        return None
    q = np.asarray(q)
    if q.ndim != 2 or q.shape[1] != 10 or q.dtype.kind not in "iu":
        raise InputError(f"mesh.quadratic_cells: expected integer indices of shape (p, 10), got {q.dtype} {q.shape}")
    q = q.astype(np.int64)
    if q.size and (q.min() < 0 or q.max() >= n):
        raise InputError(f"mesh.quadratic_cells: indices outside 0..{n - 1}")
    return q


def network_from_skeleton(points, edges, *, volume: float, surface_faces=None, node_kind=None,
                          density: float = DEFAULT_DENSITY, fibre_frame=None,
                          reorder: str | None = "rcm", weight_exponent: float = 2.0) -> SpringNetwork:
    """Build the spring network of a surface + skeleton structure.

    There are no tetrahedra to share the volume, so the organ volume ``V`` is
    distributed over the springs in proportion to ``L0**p`` (``p =
    weight_exponent``, default 2)::

        V_ij = V * L0_ij**p / sum_k L0_k**p

    With ``p = 2`` every spring gets the same volume weight ``v_ij = V / sum
    L0**2`` (docs/design/model.md, "The spring network", gives the reasons). Each spring's mass
    ``density * V_ij`` is lumped half to each end, so ``sum m = density * V``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Node positions [m].
    edges : ndarray, shape (e, 2), int
        Springs (any order, duplicates and orientation are merged).
    volume : float
        Organ volume [m3] (of the cleaned surface).
    surface_faces : ndarray, shape (k, 3), optional
        Surface triangles into *points* (for rendering).
    node_kind : ndarray, shape (n,), optional
        Node kinds with this module's codes; by default surface nodes (in
        *surface_faces*) are :data:`NODE_SURFACE`, the others :data:`NODE_SKELETON`.
    density, fibre_frame, reorder
        As in :func:`network_from_tets`.
    weight_exponent : float
        ``p`` above.
    """
    rho = check_density(density)
    reorder = check_reorder(reorder)
    pts, e = _checked_skeleton(points, edges)
    n = pts.shape[0]
    vol = _checked_volume(volume, weight_exponent)
    faces, kind = _skeleton_faces_and_kinds(surface_faces, node_kind, n)

    edges_u, _ = _sorted_unique_edges(e, n)
    used = np.unique(edges_u)
    if used.size != n:
        raise InputError(f"skeleton: {n - used.size} nodes are attached to no edge; every node needs a spring")
    order = node_order(pts, edges_u, reorder)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    pts = pts[order]
    kind = kind[order]
    faces = rank[faces]
    edges_u, _ = _sorted_unique_edges(rank[edges_u], n)

    rest = np.linalg.norm(pts[edges_u[:, 1]] - pts[edges_u[:, 0]], axis=1)
    if np.any(rest <= 0):
        raise InputError(f"skeleton: {int(np.count_nonzero(rest <= 0))} edges join coincident points")
    w = rest**weight_exponent
    vij = vol * w / w.sum()
    mass = np.bincount(edges_u.ravel(), weights=np.repeat(rho * vij / 2.0, 2), minlength=n)
    frame = fibre_frame_matrix(fibre_frame, points=pts)
    net = SpringNetwork(
        points=pts, springs=edges_u, rest_length=rest, volume=vij, volume_weight=vij / rest**2,
        cos2=direction_cos2(pts, edges_u, frame), mass=mass, surface_faces=faces, tets=None,
        node_kind=kind, structure="skeleton", fibre_frame=frame, density=rho,
    )
    return net


def _checked_skeleton(points, edges) -> tuple[np.ndarray, np.ndarray]:
    """Skeleton points (n, 3) float and edges (e, 2) int64, checked for shape, range and self-loops."""
    pts = np.asarray(points, dtype=np.float64)
    e = np.asarray(edges)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 2:
        raise InputError(f"skeleton points: expected shape (n, 3) with n >= 2, got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("skeleton points: NaN or infinite coordinates")
    if e.ndim != 2 or e.shape[1] != 2 or e.shape[0] == 0 or e.dtype.kind not in "iu":
        raise InputError(f"skeleton edges: expected an integer array of shape (e, 2) with e > 0, got {e.shape}")
    e = e.astype(np.int64)
    n = pts.shape[0]
    if e.min() < 0 or e.max() >= n:
        raise InputError(f"skeleton edges: indices outside 0..{n - 1}")
    if np.any(e[:, 0] == e[:, 1]):
        raise InputError("skeleton edges: an edge joins a node to itself")
    return pts, e


def _checked_volume(volume, weight_exponent) -> float:
    """The organ volume [m3] as a positive float; the weight exponent checked finite."""
    try:
        vol = float(volume)
    except (TypeError, ValueError):
        raise InputError(f"volume: {volume!r} is not a number (m3)") from None
    if not np.isfinite(vol) or vol <= 0:
        raise InputError(f"volume: {volume!r} must be a positive number of m3 (the organ volume)")
    if not np.isfinite(weight_exponent):
        raise InputError(f"weight_exponent: {weight_exponent!r} is not a finite number")
    return vol


def _skeleton_faces_and_kinds(surface_faces, node_kind, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Surface triangles (k, 3) int64 and node kinds (n,) uint8 (default: surface nodes, the rest skeleton)."""
    faces = np.zeros((0, 3), np.int64) if surface_faces is None else np.asarray(surface_faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= n):
        raise InputError(f"skeleton surface_faces: indices outside 0..{n - 1}")
    if node_kind is None:
        kind = np.full(n, NODE_SKELETON, np.uint8)
        kind[np.unique(faces)] = NODE_SURFACE
    else:
        kind = np.asarray(node_kind, dtype=np.uint8).ravel()
        if kind.shape != (n,):
            raise InputError(f"skeleton node_kind: expected shape ({n},), got {kind.shape}")
    return faces, kind


# -- linear analysis (for checks and documentation) -----------------------------------------

def affine_elasticity(network: SpringNetwork, *, modulus: float = 1.0) -> np.ndarray:
    """Affine (Cauchy-Born) elasticity tensor of the network in Voigt form, shape (6, 6) [Pa].

    Every spring with stiffness ``k = modulus * v_ij`` stretched by a uniform
    small strain ``eps`` stores ``1/2 k (L0 n.eps.n)**2``, so the energy density
    is ``1/2 eps:C:eps`` with ``C_abcd = modulus / V * sum V_ij n_a n_b n_c n_d``
    (mesh frame; ``V`` = organ volume). This is the upper bound of the
    network's stiffness (no relaxation of the nodes). Voigt order xx, yy, zz,
    yz, xz, xy; shear entries are for engineering shear strains.
    """
    d = network.points[network.springs[:, 1]] - network.points[network.springs[:, 0]]
    n = d / np.linalg.norm(d, axis=1)[:, None]
    voigt = np.stack([n[:, 0] ** 2, n[:, 1] ** 2, n[:, 2] ** 2, n[:, 1] * n[:, 2],
                      n[:, 0] * n[:, 2], n[:, 0] * n[:, 1]], axis=1)
    c = (voigt * network.volume[:, None]).T @ voigt
    return modulus * c / network.total_volume()


def engineering_constants(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Young's moduli (3,) and Poisson ratios (3, 3) (``nu[a, b] = -S_ab / S_aa``) of a Voigt tensor."""
    s = np.linalg.inv(np.asarray(c, dtype=np.float64))
    e = 1.0 / np.diag(s)[:3]
    nu = -s[:3, :3] / np.diag(s)[:3, None]
    np.fill_diagonal(nu, 0.0)
    return e, nu


def stiffness_matrix(network: SpringNetwork, *, modulus: float | np.ndarray = 1.0):
    """Linear stiffness matrix of the network at rest, ``scipy.sparse.csr_matrix`` (3n, 3n) [N/m].

    Spring ``ij`` with ``k = modulus * v_ij`` contributes ``k n n^T`` to the
    (i, i) and (j, j) blocks and ``-k n n^T`` to (i, j), (j, i); degrees of
    freedom are ordered node by node (x, y, z).
    """
    from scipy.sparse import coo_matrix

    i, j = network.springs[:, 0], network.springs[:, 1]
    d = network.points[j] - network.points[i]
    n = d / np.linalg.norm(d, axis=1)[:, None]
    k = np.broadcast_to(np.asarray(modulus, dtype=np.float64), (network.n_springs,)) * network.volume_weight
    blk = k[:, None, None] * n[:, :, None] * n[:, None, :]  # (s, 3, 3)
    a = np.arange(3)
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((3 * p[:, None, None] + a[None, :, None]).repeat(3, axis=2).ravel())
        cols.append((3 * q[:, None, None] + a[None, None, :]).repeat(3, axis=1).ravel())
        vals.append(sign * blk.ravel())
    size = 3 * network.n_nodes
    return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(size, size)).tocsr()
