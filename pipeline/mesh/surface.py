"""The triangle surface that flows between the mesh stages.

A :class:`Surface` holds points in metres and triangles as indices. It is
immutable; the cleaning steps return new surfaces. Geometric figures (enclosed
volume, area, boundary edges) are computed on demand with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of two (n, 3) arrays (several times faster than np.cross)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def triple(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Row-wise a . (b x c) of three (n, 3) arrays."""
    return (a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
            + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
            + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]))


@dataclass(frozen=True)
class Surface:
    """A triangle surface in SI units.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Vertex coordinates [m].
    faces : ndarray, shape (m, 3), int64
        Triangles as indices into ``points``; counter-clockwise seen from
        outside for an outward-oriented closed surface.
    source : str
        Where the surface came from (file name and what was done), for reports.
    """

    points: np.ndarray
    faces: np.ndarray
    source: str = field(default="")

    def __post_init__(self) -> None:
        pts = np.ascontiguousarray(np.asarray(self.points, dtype=np.float64).reshape(-1, 3))
        fcs = np.ascontiguousarray(np.asarray(self.faces, dtype=np.int64).reshape(-1, 3))
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "faces", fcs)

    # -- sizes ---------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    # -- geometry ------------------------------------------------------------
    def _corners(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = self.points
        f = self.faces
        return p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]

    def face_normals(self, *, unit: bool = True) -> np.ndarray:
        """Face normals, shape (m, 3); unit length (or twice the area if ``unit=False``)."""
        a, b, c = self._corners()
        n = cross3(b - a, c - a)
        if unit:
            ln = np.linalg.norm(n, axis=1)
            ln[ln == 0] = 1.0
            n = n / ln[:, None]
        return n

    def face_areas(self) -> np.ndarray:
        """Triangle areas [m2], shape (m,)."""
        return 0.5 * np.linalg.norm(self.face_normals(unit=False), axis=1)

    def volume(self) -> float:
        """Signed enclosed volume [m3] by the divergence theorem.

        Positive for a closed surface with outward normals. The sum is taken
        about the bounding-box centre, which keeps it exact for a closed
        surface and makes it translation invariant (and less sensitive to
        round-off) for an open one.
        """
        if self.n_faces == 0:
            return 0.0
        c0 = 0.5 * (self.points.min(axis=0) + self.points.max(axis=0))
        p = self.points - c0
        f = self.faces
        a, b, c = p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]
        return float(triple(a, b, c).sum() / 6.0)

    def area(self) -> float:
        """Total surface area [m2]."""
        return float(self.face_areas().sum())

    def bounds(self) -> np.ndarray:
        """Bounding box, shape (2, 3): row 0 the minimum, row 1 the maximum [m]."""
        if self.n_points == 0:
            return np.zeros((2, 3))
        used = self.points[self.used_mask()] if self.n_faces else self.points
        return np.vstack([used.min(axis=0), used.max(axis=0)])

    def used_mask(self) -> np.ndarray:
        """Boolean mask (n,) of the points that some face uses."""
        used = np.zeros(self.n_points, bool)
        used[self.faces.ravel()] = True
        return used

    def extent(self) -> float:
        """Largest bounding-box side [m]."""
        b = self.bounds()
        return float((b[1] - b[0]).max())

    # -- topology ------------------------------------------------------------
    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Unique undirected edges and how many faces use each.

        Returns
        -------
        edges : ndarray, shape (e, 2), int64
            Sorted vertex pairs.
        counts : ndarray, shape (e,), int64
            Number of faces sharing each edge (1: border, 2: manifold, >2: non-manifold).
        """
        f = self.faces
        if f.shape[0] == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
        a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
        b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        n = np.int64(max(self.n_points, int(f.max()) + 1))
        key, counts = np.unique(lo * n + hi, return_counts=True)
        return np.column_stack([key // n, key % n]), counts

    def n_boundary_edges(self) -> int:
        """Number of edges used by exactly one face."""
        _, counts = self.edges()
        return int(np.count_nonzero(counts == 1))

    def n_nonmanifold_edges(self) -> int:
        """Number of edges used by more than two faces."""
        _, counts = self.edges()
        return int(np.count_nonzero(counts > 2))

    def is_closed(self) -> bool:
        """True when every edge is shared by exactly two faces (watertight, manifold edges)."""
        if self.n_faces == 0:
            return False
        _, counts = self.edges()
        return bool(np.all(counts == 2))

    def euler_characteristic(self) -> int:
        """V - E + F over the used vertices (2 for a sphere, 0 for a torus)."""
        e, _ = self.edges()
        v = int(np.count_nonzero(self.used_mask()))
        return int(v - e.shape[0] + self.n_faces)

    # -- conversions ---------------------------------------------------------
    def compact(self) -> Surface:
        """The same surface without unused points."""
        used = np.flatnonzero(self.used_mask())
        if used.size == self.n_points:
            return self
        remap = np.full(self.n_points, -1, np.int64)
        remap[used] = np.arange(used.size)
        return Surface(self.points[used], remap[self.faces], self.source)

    def with_source(self, note: str) -> Surface:
        """The same surface with *note* appended to :attr:`source`."""
        src = f"{self.source}; {note}" if self.source else note
        return Surface(self.points, self.faces, src)

    def to_pyvista(self):
        """A ``pyvista.PolyData`` of this surface (coordinates in metres)."""
        import pyvista as pv

        cells = np.hstack([np.full((self.n_faces, 1), 3, np.int64), self.faces]).ravel()
        return pv.PolyData(self.points.copy(), cells)

    @classmethod
    def from_pyvista(cls, poly, *, source: str = "") -> Surface:
        """Build a surface from a triangulated ``pyvista.PolyData`` (in metres)."""
        poly = poly.triangulate() if not poly.is_all_triangles else poly
        faces = np.asarray(poly.faces, dtype=np.int64).reshape(-1, 4)[:, 1:] if poly.n_cells else np.zeros((0, 3), np.int64)
        return cls(np.asarray(poly.points, dtype=np.float64), faces, source)

    def summary(self) -> str:
        """One line: points, faces, extent, volume, borders."""
        return (f"{self.n_points} points, {self.n_faces} faces, extent {self.extent() * 1e3:.1f} mm, "
                f"volume {self.volume() * 1e6:.1f} mL, {self.n_boundary_edges()} border edges")
