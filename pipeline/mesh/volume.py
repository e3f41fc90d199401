"""Tetrahedral meshing of a cleaned surface (gmsh in a subprocess, repair, pytetwild)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .surface import Surface


@dataclass(frozen=True)
class VolumeMesh:
    """Tetrahedra in metres, positively oriented, with their outward boundary."""

    points: np.ndarray
    tets: np.ndarray
    boundary_faces: np.ndarray
    path: str = "gmsh"
    log: list[str] = field(default_factory=list)

    def tet_volumes(self) -> np.ndarray:
        p = self.points
        t = self.tets
        a = p[t[:, 1]] - p[t[:, 0]]
        b = p[t[:, 2]] - p[t[:, 0]]
        c = p[t[:, 3]] - p[t[:, 0]]
        return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0

    def volume(self) -> float:
        return float(self.tet_volumes().sum())


def mesh_volume(surface: Surface, *, size: float | None = None, nodes: int | None = None,
                timeout: float = 120.0, reporter=None) -> VolumeMesh:
    """Tetrahedralise *surface* (work in progress)."""
    raise NotImplementedError
