"""Uniform refinement of a tetrahedral mesh: every tetrahedron split in eight.

The split puts a node at the middle of every edge, so the refined mesh's nodes
are exactly the nodes of the quadratic (10-node) tetrahedra on the original
mesh. A spring network on the refined mesh therefore has one node per degree
of freedom of a second-order finite element on the original one, and the
continuum reference (``esmm validate``, P2) is solved on those quadratic cells
node for node (docs/design/model.md, "The network on the quadratic tetrahedra's nodes (`--split`)"; docs/design/validation.md).

The split (Bey 1995, "Simplicial grid refinement"): the four corner
tetrahedra, and the inner octahedron cut along one of its three diagonals
into four. The shortest diagonal is taken, which keeps the children's
shapes within a bounded number of classes and gives the best dihedral angles
of the three (Zhang 1995).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .readers import boundary_of_tets
from .volume import VolumeMesh

__all__ = ["TET10_EDGES", "quadratic_tets", "split_in_eight", "split_mesh"]

#: The vertex pairs of a 10-node tetrahedron's middle nodes 4..9, in the order
#: of felupe's and VTK's ``tetra10`` (not gmsh's, which swaps the last two): 01, 12, 20, 03, 13, 23.
TET10_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))


def quadratic_tets(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """10-node tetrahedra on the same vertices: a node at the middle of each edge.

    Returns
    -------
    points10 : ndarray, shape (n + e, 3)
        The *n* vertices first, then the *e* edge midpoints.
    cells10 : ndarray of int, shape (t, 10)
        Vertices, then the middles of :data:`TET10_EDGES`.
    edges : ndarray of int, shape (e, 2)
        The vertices of the edge of each midpoint (midpoint k is node n + k).
    """
    tets = np.asarray(tets, dtype=np.int64)
    pairs = np.sort(tets[:, np.array(TET10_EDGES)], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])
    cells = np.hstack([tets, points.shape[0] + inverse.reshape(-1, 6)])
    return np.vstack([points, mid]), cells, edges


def split_in_eight(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every tetrahedron of a mesh into eight.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tets : ndarray of int, shape (t, 4)
        Tetrahedra (a negatively oriented one is turned first).

    Returns
    -------
    points : ndarray, shape (n + e, 3)
        The *n* original nodes first (same order), then the *e* edge
        midpoints.
    tets : ndarray of int, shape (8 t, 4)
        The children, positively oriented: children ``8 k .. 8 k + 7`` fill
        parent ``k`` exactly.
    quadratic_cells : ndarray of int, shape (t, 10)
        Each parent, positively oriented, as a 10-node tetrahedron on the
        refined nodes: its four vertices, then the middles of :data:`TET10_EDGES`.
    """
    points = np.asarray(points, dtype=np.float64)
    tets = np.array(tets, dtype=np.int64)
    _orient(points, tets)
    out_points, cells, _ = quadratic_tets(points, tets)
    a, b, c, d = tets.T
    m01, m12, m20, m03, m13, m23 = cells[:, 4:].T
    corners = [(a, m01, m20, m03), (m01, b, m12, m13), (m20, m12, c, m23), (m03, m13, m23, d)]
    # The octahedron m01 m12 m20 m03 m13 m23: its diagonals join opposite middles; the
    # four around a diagonal, in cyclic order, are the other four middles.
    diagonals = ((m20, m13, (m01, m12, m23, m03)), (m01, m23, (m20, m12, m13, m03)),
                 (m03, m12, (m01, m13, m23, m20)))
    lengths = np.stack([np.linalg.norm(out_points[p] - out_points[q], axis=1) for p, q, _ in diagonals], axis=1)
    shortest = lengths.argmin(axis=1)
    inner = np.empty((tets.shape[0], 4, 4), np.int64)
    for k, (p, q, ring) in enumerate(diagonals):
        sel = shortest == k
        for j in range(4):
            inner[sel, j] = np.stack([p[sel], q[sel], ring[j][sel], ring[(j + 1) % 4][sel]], axis=1)
    children = np.concatenate([np.stack([np.stack(cn, axis=1) for cn in corners], axis=1), inner], axis=1)
    children = children.reshape(-1, 4)
    _orient(out_points, children)
    return out_points, children, cells


def split_mesh(mesh: VolumeMesh) -> VolumeMesh:
    """*mesh* with every tetrahedron split in eight, and its parents as ``quadratic_cells``."""
    points, tets, cells = split_in_eight(mesh.points, mesh.tets)
    return dataclasses.replace(mesh, points=points, tets=tets, boundary_faces=boundary_of_tets(points, tets),
                               path=f"{mesh.path}+split", quadratic_cells=cells)


def _orient(points: np.ndarray, tets: np.ndarray) -> None:
    """Turn the negatively oriented tetrahedra of *tets* in place (two vertices swapped)."""
    p = points[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    neg = vol < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
