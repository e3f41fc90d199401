"""A built-in specimen for ``esmm validate --specimen``: a cube meshed like an asset.

The cube (default 20 mm, elements of 2.5 mm) is meshed by gmsh in-process
with the settings of ``esmm prepare`` (Delaunay, optimised with Netgen), turned
into a spring network by :func:`~esmm.pipeline.network.springs.network_from_tets`
and given the tables ``esmm prepare`` gives an asset: the material's tables,
compensated on a cylinder meshed like it (:func:`~esmm.pipeline.compensation.calibration.compensate`,
cached). Its faces are exact planes, so the specimen cases grip whole faces.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..compensation.calibration import calibration_stretches, compensate
from ..errors import ConfigError, MeshingError
from ..mesh.gmsh_model import gmsh_model, tetrahedra
from ..mesh.refine import split_in_eight
from ..network.springs import network_from_tets
from ..network.tables import build_tables
from ..network.volume import bulk_modulus
from ..progress import ensure

__all__ = ["Specimen", "cube_specimen"]


@dataclass(frozen=True, eq=False)
class Specimen:
    """A specimen network with its tables and material (what an asset gives)."""

    network: object
    tables: object
    material: object
    label: str


def cube_specimen(material, *, side: float = 20e-3, size: float = 2.5e-3, compensated: bool = True,
                  volume: bool = True, split: bool = False, reporter=None) -> Specimen:
    """A meshed cube with its spring network and the material's (compensated) tables.

    Parameters
    ----------
    material : Material
    side : float
        Edge of the cube [m].
    size : float
        Target element size [m] (at least 3 elements along an edge).
    compensated : bool
        Compensate the tables as ``esmm prepare`` does (default) or not.
    volume : bool
        Give the network the volume term ``esmm prepare`` gives it (default; the
        compensation then runs with it) or none.
    split : bool
        Split every tetrahedron in eight, as ``esmm prepare --split`` does (the
        springs are then half *size* long; the continuum is solved on the
        *size* mesh's quadratic tetrahedra, node for node).
    """
    rep = ensure(reporter)
    for name, v in (("side", side), ("size", size)):
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise ConfigError(f"{name}: must be a positive length in metres, got {v!r}", parameter=name)
    if size > side / 3:
        raise ConfigError(f"size: {size * 1e3:g} mm gives fewer than 3 elements along the {side * 1e3:g} mm "
                          "cube; use a smaller size", parameter="size")
    if (side / size) ** 3 * 6 > 3e5:
        raise ConfigError(f"size: {size * 1e3:g} mm would give about {(side / size) ** 3 * 6:.0f} tetrahedra; "
                          "use a larger size", parameter="size")
    points, tets = _gmsh_cube(side, size)

    class _Mesh:  # what network_from_tets reads
        quadratic_cells = None

    mesh = _Mesh()
    mesh.points, mesh.tets = points, tets
    if split:
        mesh.points, mesh.tets, mesh.quadratic_cells = split_in_eight(points, tets)
    net = network_from_tets(mesh, fibre_frame=None, reorder="rcm")
    tables = build_tables(material)
    if volume:
        net = dataclasses.replace(net, volume_term=bulk_modulus(tables, calibration_range=calibration_stretches(tables)))
    if compensated:
        tables = compensate(tables, net, material=material, volume=net.volume_term, reporter=rep).tables
    label = f"cube {side * 1e3:g} mm, elements {size * 1e3:g} mm{', split in eight' if split else ''}"
    rep.step(f"specimen: {label}: {net.n_nodes} nodes, {net.n_springs} springs, {net.n_tets} tets, "
             f"volume factor c = {tables.volume_factor:.4g}")
    return Specimen(network=net, tables=tables, material=material, label=label)


def _gmsh_cube(side: float, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Points [m] and tetrahedra of a cube [0, side]^3 (gmsh Delaunay + Netgen, in mm inside gmsh)."""
    with gmsh_model("the specimen cube") as gmsh:
        s = side * 1e3
        gmsh.model.occ.addBox(0.0, 0.0, 0.0, s, s, s)
        gmsh.model.occ.synchronize()
        for key, value in (("MeshSizeMin", size * 1e3), ("MeshSizeMax", size * 1e3), ("MeshSizeFromCurvature", 0),
                           ("Algorithm", 5), ("Algorithm3D", 1), ("Optimize", 1), ("OptimizeNetgen", 1)):
            gmsh.option.setNumber(f"Mesh.{key}", value)
        gmsh.model.mesh.generate(3)
        pts, tets = tetrahedra(gmsh)
    pts = pts * 1e-3
    if tets.shape[0] == 0:
        raise MeshingError("gmsh made no tetrahedra for the specimen cube; try another size")
    used = np.unique(tets)
    remap = np.full(pts.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return pts[used], remap[tets]
