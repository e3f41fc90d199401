"""Tetrahedron quality measures (vectorised) and the documented floors."""

from __future__ import annotations

from dataclasses import dataclass, field

QUALITY_FLOORS: dict[str, float] = {}


@dataclass
class QualityReport:
    min_dihedral_deg: float
    sicn: tuple[float, float, float]
    gamma: tuple[float, float, float]
    radius_ratio: tuple[float, float, float]
    n_tets: int
    n_nodes: int
    volume: float
    percentiles: dict = field(default_factory=dict)

    def passes(self, floors=None) -> tuple[bool, list[str]]:
        raise NotImplementedError


def tet_quality(mesh) -> QualityReport:
    raise NotImplementedError
