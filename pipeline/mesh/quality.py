"""Tetrahedron quality measures (vectorised numpy) and the documented floors.

Measures (all 1 for the regular tetrahedron, 0 for a flat one):

* **SICN**, signed inverse condition number, as gmsh computes it for a linear
  tetrahedron: ``3 det(S) / (|S|_F |adj S|_F)`` with ``S = J W^-1``, the
  Jacobian mapped from the regular tetrahedron ``W``; negative when inverted.
  Identical to gmsh's ``minSICN`` (checked in the tests).
* **gamma**, ``2 sqrt(6) r_in / l_max`` (inradius over longest edge: the
  "vol / sum_face / max_edge" measure of gmsh's older documentation and
  Netgen); it is the measure most sensitive to needles.
* **radius ratio**, ``3 r_in / R_circ`` (what current gmsh reports as
  "gamma"); it is the classic sliver detector.
* **dihedral angles** (six per element); the regular value is
  ``arccos(1/3) = 70.53`` degrees; slivers have angles near 0 and 180.

The floors (:data:`QUALITY_FLOORS`) and their reasons are in docs/guide/prepare.md ("Quality floors").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..checks import number
from ..errors import ConfigError

#: Minimum quality accepted by ``esmm prepare`` (unless forced); see docs/guide/prepare.md, "Quality floors".
QUALITY_FLOORS: dict[str, float] = {
    # No inverted, flat or nearly flat element (volume below ~2 % of the regular one of the
    # same size): its volume weight and its springs' directions are meaningless.
    "sicn_min": 0.02,
    # Slivers: with a small dihedral angle the four nodes are nearly coplanar, the element's
    # springs give little stiffness across that plane (a local soft mode) and a finite-element
    # solve on it is poorly conditioned; the mesher's slivers are relocated up to it
    # (pipeline/mesh/slivers.py): every shared input reaches 11-22 deg (docs/guide/prepare.md, "Quality floors").
    "min_dihedral_deg": 10.0,
    # The worst 1 % of the elements must still be reasonable shapes; gmsh+Netgen meshes of
    # organs reach 0.55-0.65 (SICN) and 0.43-0.50 (gamma, radius ratio), the fTetWild
    # fallback 0.34 / 0.27 / 0.23.
    "sicn_p1": 0.25,
    "gamma_p1": 0.15,
    "radius_ratio_p1": 0.15,
}

#: The figures of a :class:`QualityReport` a floor may be set on (:meth:`QualityReport.values`).
QUALITY_FIGURES = ("sicn_min", "sicn_p1", "gamma_min", "gamma_p1", "radius_ratio_min", "radius_ratio_p1",
                   "min_dihedral_deg")


def check_floors(floors: Mapping[str, Any], where: str = "[quality]") -> dict[str, float]:
    """Quality floors to use instead of the defaults: known figure names, numeric values.

    Raises
    ------
    ConfigError
        An unknown figure or a value that is not a number (naming ``where`` and the key).
    """
    unknown = sorted(set(floors) - set(QUALITY_FIGURES))
    if unknown:
        raise ConfigError(f"{where}: unknown figure(s) {', '.join(unknown)}; known: {', '.join(sorted(QUALITY_FIGURES))}",
                          parameter=where)
    return {k: number(v, f"{where} {k}") for k, v in floors.items()}


_REGULAR_W_INV = np.linalg.inv(np.array([[1.0, 0.5, 0.5],
                                         [0.0, math.sqrt(3.0) / 2.0, math.sqrt(3.0) / 6.0],
                                         [0.0, 0.0, math.sqrt(2.0 / 3.0)]]))


@dataclass
class QualityReport:
    """Quality figures of a tetrahedral mesh.

    Attributes
    ----------
    min_dihedral_deg, max_dihedral_deg : float
        Smallest and largest dihedral angle over all elements [degrees].
    sicn, gamma, radius_ratio : tuple of float
        (minimum, 1st percentile, median) of each measure.
    n_tets, n_nodes : int
    volume : float
        Mesh volume [m3].
    percentiles : dict
        ``{measure: {"p0": .., "p1": .., "p5": .., "p50": ..}}`` and histograms
        ``{measure + "_hist": (counts, edges)}`` (lists, JSON-ready).
    """

    min_dihedral_deg: float
    sicn: tuple[float, float, float]
    gamma: tuple[float, float, float]
    radius_ratio: tuple[float, float, float]
    n_tets: int
    n_nodes: int
    volume: float
    max_dihedral_deg: float = 180.0
    percentiles: dict = field(default_factory=dict)

    def values(self) -> dict[str, float]:
        """The figures compared with :data:`QUALITY_FLOORS` (keys: :data:`QUALITY_FIGURES`)."""
        return {
            "sicn_min": self.sicn[0], "sicn_p1": self.sicn[1],
            "gamma_min": self.gamma[0], "gamma_p1": self.gamma[1],
            "radius_ratio_min": self.radius_ratio[0], "radius_ratio_p1": self.radius_ratio[1],
            "min_dihedral_deg": self.min_dihedral_deg,
        }

    def passes(self, floors: dict[str, float] | None = None) -> tuple[bool, list[str]]:
        """Compare with the floors; return (ok, one line per failed floor)."""
        floors = QUALITY_FLOORS if floors is None else floors
        vals = self.values()
        failed = []
        for key, floor in floors.items():
            if key not in vals:
                raise KeyError(f"floors: unknown quality figure {key!r}; known: {', '.join(vals)}")
            if not vals[key] >= floor:
                failed.append(f"{key} = {vals[key]:.4g} is below the floor {floor:g}")
        return not failed, failed

    def summary(self) -> str:
        """One line for reports."""
        return (f"{self.n_nodes} nodes, {self.n_tets} tets; SICN min {self.sicn[0]:.3f} p1 {self.sicn[1]:.3f} "
                f"median {self.sicn[2]:.3f}; gamma min {self.gamma[0]:.3f} p1 {self.gamma[1]:.3f}; "
                f"radius ratio min {self.radius_ratio[0]:.3f} p1 {self.radius_ratio[1]:.3f}; "
                f"dihedral {self.min_dihedral_deg:.1f}-{self.max_dihedral_deg:.1f} deg")


def tet_measures(points: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    """Per-element quality measures, vectorised.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tets : ndarray, shape (t, 4)

    Returns
    -------
    dict of ndarray, each shape (t,) (``"dihedral_deg"``: (t, 6))
        ``volume`` (signed), ``sicn``, ``gamma``, ``radius_ratio``,
        ``inradius``, ``circumradius``, ``min_dihedral_deg``,
        ``max_dihedral_deg``, ``dihedral_deg``.
    """
    p = np.asarray(points, np.float64)
    t = np.asarray(tets, np.int64)
    p0, p1, p2, p3 = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]], p[t[:, 3]]
    a, b, c = p1 - p0, p2 - p0, p3 - p0
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    vol = det / 6.0
    # SICN: S = J W^-1 with J = [a b c] (columns); |adj S|_F from the cross products of S's columns.
    J = np.stack([a, b, c], axis=2)  # (t, 3, 3), columns a, b, c
    S = J @ _REGULAR_W_INV
    s0, s1, s2 = S[:, :, 0], S[:, :, 1], S[:, :, 2]
    adj2 = (np.cross(s1, s2) ** 2).sum(1) + (np.cross(s2, s0) ** 2).sum(1) + (np.cross(s0, s1) ** 2).sum(1)
    detS = det * np.linalg.det(_REGULAR_W_INV)
    nS = np.sqrt((S ** 2).sum(axis=(1, 2)))
    denom = nS * np.sqrt(adj2)
    with np.errstate(invalid="ignore", divide="ignore"):
        sicn = np.where(denom > 0, 3.0 * detS / denom, 0.0)
    # Face normals (area vectors), face k opposite vertex k, outward for det > 0.
    n0 = np.cross(p2 - p1, p3 - p1)
    n1 = np.cross(p3 - p0, p2 - p0)
    n2 = np.cross(p1 - p0, p3 - p0)
    n3 = np.cross(p2 - p0, p1 - p0)
    normals = np.stack([n0, n1, n2, n3], axis=1) * np.sign(det)[:, None, None]
    areas = 0.5 * np.linalg.norm(normals, axis=2)  # (t, 4)
    total_area = areas.sum(axis=1)
    absvol = np.abs(vol)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_in = np.where(total_area > 0, 3.0 * absvol / total_area, 0.0)
    # Circumradius: offset of the circumcentre from p0.
    num = ((a * a).sum(1)[:, None] * np.cross(b, c) + (b * b).sum(1)[:, None] * np.cross(c, a)
           + (c * c).sum(1)[:, None] * np.cross(a, b))
    with np.errstate(invalid="ignore", divide="ignore"):
        R = np.linalg.norm(num, axis=1) / np.abs(2.0 * det)
    edges = np.stack([a, b, c, p2 - p1, p3 - p1, p3 - p2], axis=1)
    lmax = np.linalg.norm(edges, axis=2).max(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = np.where(lmax > 0, 2.0 * math.sqrt(6.0) * r_in / lmax, 0.0)
        rr = np.where(np.isfinite(R) & (R > 0), 3.0 * r_in / R, 0.0)
    # Dihedral angle along the edge shared by faces k and l: pi - angle(n_k, n_l).
    unit = normals / np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-300)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cosines = np.stack([np.einsum("ij,ij->i", unit[:, k], unit[:, m]) for k, m in pairs], axis=1)
    dihedral = 180.0 - np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
    flat = absvol <= 0
    dihedral[flat] = 0.0
    sign = np.sign(det)
    return {
        "volume": vol, "sicn": sicn, "gamma": gamma * np.where(sign < 0, -1.0, 1.0),
        "radius_ratio": rr * np.where(sign < 0, -1.0, 1.0), "inradius": r_in, "circumradius": R,
        "dihedral_deg": dihedral, "min_dihedral_deg": dihedral.min(axis=1),
        "max_dihedral_deg": dihedral.max(axis=1),
    }


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    if x.size == 0:
        return (float("nan"),) * 3
    q = np.percentile(x, [0, 1, 50])
    return float(q[0]), float(q[1]), float(q[2])


def tet_quality(mesh) -> QualityReport:
    """Quality report of a :class:`~esmm.pipeline.mesh.volume.VolumeMesh`.

    Parameters
    ----------
    mesh
        Anything with ``points`` (n, 3) and ``tets`` (t, 4).

    Returns
    -------
    QualityReport
        Vectorised: fast enough to run on every mesh.
    """
    m = tet_measures(mesh.points, mesh.tets)
    pct = {}
    for key in ("sicn", "gamma", "radius_ratio", "min_dihedral_deg"):
        x = m[key]
        if x.size:
            q = np.percentile(x, [0, 1, 5, 50])
            pct[key] = {"p0": float(q[0]), "p1": float(q[1]), "p5": float(q[2]), "p50": float(q[3])}
        rng = (0.0, 180.0) if key == "min_dihedral_deg" else (0.0, 1.0)
        counts, edges = np.histogram(np.clip(x, *rng), bins=20, range=rng)
        pct[key + "_hist"] = (counts.tolist(), edges.tolist())
    n_nodes = int(np.unique(mesh.tets).size) if mesh.tets.size else 0
    return QualityReport(
        min_dihedral_deg=float(m["min_dihedral_deg"].min()) if mesh.tets.size else float("nan"),
        max_dihedral_deg=float(m["max_dihedral_deg"].max()) if mesh.tets.size else float("nan"),
        sicn=_stats(m["sicn"]), gamma=_stats(m["gamma"]), radius_ratio=_stats(m["radius_ratio"]),
        n_tets=int(mesh.tets.shape[0]), n_nodes=n_nodes, volume=float(m["volume"].sum()),
        percentiles=pct,
    )
