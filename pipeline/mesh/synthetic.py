"""Synthetic organ surfaces with the defects of an InVesalius export.

:func:`invesalius_like_surface` builds an organ-like implicit shape (a smooth
union of ellipsoids), voxelises it into a 0/255 mask on an anisotropic grid,
and surfaces it the way InVesalius' "Binary" method does: marching cubes at
127 with the voxel spacing, Y negated, in millimetres. On request it adds the
defects real exports have:

* ``islands``: a few small blobs of one or two voxels beside the organ;
* ``handle``: a torus-like tunnel (a ring half inside, half outside), genus 1;
* ``open_border``: the grid cuts the organ (no padding), leaving open loops
  where the organ meets the scan border;
* ``second_body``: a separate, smaller organ-sized body in the same file.

Marching cubes followed by the Y flip gives outward normals (as InVesalius'
auto-orientation does); ``inward_normals=True`` reverses them, as in the SOFA
liver. Tests use it to produce inputs nobody hand-tuned; the benchmark uses
it with a fine voxel to reach 1 M triangles.
"""

from __future__ import annotations

import itertools
import os
from types import SimpleNamespace

import numpy as np

from .readers import write_stl
from .surface import Surface

#: Organ-like shapes: lists of ellipsoids (centre mm, semi-axes mm) blended smoothly.
SHAPES: dict[str, list[tuple[tuple[float, float, float], tuple[float, float, float]]]] = {
    # A liver-like wedge: a big right lobe, a thinner left lobe, a bulge below.
    "liver": [
        ((0.0, 0.0, 0.0), (75.0, 60.0, 55.0)),
        ((70.0, 10.0, 10.0), (65.0, 45.0, 28.0)),
        ((-20.0, -25.0, -25.0), (45.0, 35.0, 30.0)),
    ],
    # A kidney-like bean.
    "kidney": [
        ((0.0, 25.0, 0.0), (30.0, 30.0, 22.0)),
        ((0.0, -25.0, 0.0), (30.0, 30.0, 22.0)),
        ((10.0, 0.0, 0.0), (25.0, 30.0, 20.0)),
    ],
    "sphere": [((0.0, 0.0, 0.0), (40.0, 40.0, 40.0))],
}


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (union with a fillet of width ~k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _field(x, y, z, ellipsoids, *, scale: float, blend: float) -> np.ndarray:
    f = None
    for (c, r) in ellipsoids:
        cx, cy, cz = (scale * ci for ci in c)
        rx, ry, rz = (scale * ri for ri in r)
        rm = min(rx, ry, rz)
        # Approximate signed distance in mm (exact on the smallest axis).
        e = (np.sqrt(((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 + ((z - cz) / rz) ** 2) - 1.0) * rm
        f = e if f is None else _smin(f, e, blend)
    return f


def invesalius_like_surface(*, shape: str = "liver", voxel: tuple[float, float, float] = (1.0, 1.0, 2.0),
                            scale: float = 1.0, islands: bool = True, handle: bool = True,
                            open_border: bool = True, second_body: bool = False,
                            inward_normals: bool = False, seed: int = 0,
                            path: str | os.PathLike | None = None) -> Surface:
    """An InVesalius-style organ surface (marching cubes of a 0/255 mask).

    Parameters
    ----------
    shape
        A key of :data:`SHAPES` (``"liver"``, ``"kidney"``, ``"sphere"``).
    voxel
        Voxel size (x, y, z) [mm]; clinical CT is about (0.7-1, 0.7-1, 1-3).
    scale
        Multiplies the shape's dimensions (1: an adult liver, ~250 mm across).
    islands, handle, open_border, second_body
        Which InVesalius defects to add (see the module docstring).
    inward_normals
        Reverse every triangle (normals pointing into the organ).
    seed
        Seed of the random placement of the islands.
    path
        If given, also write the surface there as a binary STL in mm.

    Returns
    -------
    Surface
        Points in metres; ``source`` records the options.
    """
    if shape not in SHAPES:
        raise ValueError(f"shape: unknown {shape!r}; choose one of {', '.join(SHAPES)}")
    voxel = tuple(float(v) for v in voxel)
    if len(voxel) != 3 or min(voxel) <= 0:
        raise ValueError("voxel: give three positive sizes in mm")
    rng = np.random.default_rng(seed)
    ells = SHAPES[shape]
    lo = np.min([np.array(c) - np.array(r) for c, r in ells], axis=0) * scale
    hi = np.max([np.array(c) + np.array(r) for c, r in ells], axis=0) * scale
    size = hi - lo
    lo_g, (x, y, z) = _voxel_grid(lo, hi, voxel, second_body=second_body, open_border=open_border)
    blend = 0.12 * float(np.min(size))
    f = _field(x, y, z, ells, scale=scale, blend=blend)
    if handle:
        f = _with_handle(f, x, y, z, ells[0], scale, voxel)
    if second_body:
        f = _with_second_body(f, x, y, z, lo, hi)
    mask = np.where(f < 0.0, 255, 0).astype(np.uint8)
    if islands:
        _add_islands(mask, rng)
    if not open_border:
        mask = np.pad(mask, 1)
        origin = lo_g - np.array(voxel)
    else:
        origin = lo_g
    verts, faces = _marching_cubes(mask, voxel, origin)
    if inward_normals:
        faces = faces[:, ::-1]
    src = (f"synthetic InVesalius-like {shape} voxel={voxel} mm islands={islands} handle={handle} "
           f"open_border={open_border} second_body={second_body} inward_normals={inward_normals} seed={seed}")
    surf = Surface(verts * 1e-3, faces, src)
    if path is not None:
        write_stl(surf, path, unit="mm")
    return surf


def _voxel_grid(lo, hi, voxel, *, second_body: bool, open_border: bool):
    """The grid's lower corner (3,) [mm] and its voxel centres ``(x, y, z)``, each (nx, ny, nz) [mm].

    The organ's box *lo*-*hi* with a margin for the defects; wider for a
    second body; cut 15 % into the organ's bottom for an open border.
    """
    size = hi - lo
    margin = 0.12 * size  # room for islands, the handle and the second body
    lo_g = lo - margin
    hi_g = hi + margin
    if second_body:
        hi_g[0] += 0.6 * size[0]
    if open_border:
        # The scan stops inside the organ: cut 15 % off its bottom (z).
        lo_g[2] = lo[2] + 0.15 * size[2]
    axes = [np.arange(lo_g[i], hi_g[i] + voxel[i], voxel[i]) for i in range(3)]
    return lo_g, np.meshgrid(*axes, indexing="ij")


def _with_handle(f, x, y, z, main, scale: float, voxel) -> np.ndarray:
    """The field *f* with a handle (genus + 1) on the *main* lobe ``(centre, radii)``.

    A ring whose centre sits on the top of the main lobe, its plane vertical:
    half of it is inside the organ, half outside.
    """
    c0, r0 = main
    cx, cy, cz = c0[0] * scale, c0[1] * scale, (c0[2] + r0[2]) * scale
    big = 0.35 * r0[2] * scale
    small = max(0.09 * r0[2] * scale, 2.5 * max(voxel))
    q = np.sqrt((x - cx) ** 2 + (z - cz) ** 2) - big
    torus = np.sqrt(q ** 2 + (y - cy) ** 2) - small
    return _smin(f, torus, 0.3 * small)


def _with_second_body(f, x, y, z, lo, hi) -> np.ndarray:
    """The field *f* with a separate ellipsoid beside the organ's box *lo*-*hi* (along x)."""
    size = hi - lo
    sx = hi[0] + 0.35 * size[0]
    r2 = 0.2 * size
    e2 = (np.sqrt(((x - sx) / r2[0]) ** 2 + ((y - 0.5 * (lo[1] + hi[1])) / r2[1]) ** 2
                  + ((z - 0.5 * (lo[2] + hi[2])) / r2[2]) ** 2) - 1.0) * float(r2.min())
    return np.minimum(f, e2)


def _add_islands(mask: np.ndarray, rng: np.random.Generator) -> None:
    """Set a few specks of 1-2 voxels in the empty margin of *mask* (segmentation noise), in place."""
    shape_idx = np.array(mask.shape)
    placed = 0
    tries = 0
    while placed < 4 and tries < 200:
        tries += 1
        idx = np.array([rng.integers(1, s - 3) for s in shape_idx])
        block = mask[idx[0] - 1:idx[0] + 4, idx[1] - 1:idx[1] + 4, idx[2] - 1:idx[2] + 4]
        if block.any():
            continue
        ext = rng.integers(1, 3, size=3)
        mask[idx[0]:idx[0] + ext[0], idx[1]:idx[1] + ext[1], idx[2]:idx[2] + ext[2]] = 255
        placed += 1


def _marching_cubes(mask: np.ndarray, voxel, origin) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) [mm] and triangles (m, 3) of the 0/255 *mask*, Y negated as InVesalius writes it."""
    from skimage.measure import marching_cubes

    verts, faces, _n, _v = marching_cubes(mask.astype(np.float32), level=127.0, spacing=voxel,
                                          allow_degenerate=False)
    verts = verts + origin
    verts[:, 1] *= -1.0  # InVesalius negates Y
    return verts, faces.astype(np.int64)


def box_tets(nx: int, ny: int, nz: int, size) -> SimpleNamespace:
    """A structured box split into 6 Kuhn tetrahedra per cell (conforming).

    Parameters
    ----------
    nx, ny, nz : int
        Cells along x, y, z.
    size : sequence of 3 floats
        Box edge lengths [m].

    Returns
    -------
    SimpleNamespace
        ``points`` (n, 3) and ``tets`` (6·nx·ny·nz, 4), positively oriented.
    """
    xs = [np.linspace(0.0, size[k], n + 1) for k, n in enumerate((nx, ny, nz))]
    X, Y, Z = np.meshgrid(*xs, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(pts.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    cells = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for perm in itertools.permutations(range(3)):
        corners = [cells.copy()]
        c = cells.copy()
        for ax in perm:
            c = c.copy()
            c[:, ax] += 1
            corners.append(c)
        tets.append(np.stack([idx[q[:, 0], q[:, 1], q[:, 2]] for q in corners], axis=1))
    return SimpleNamespace(points=pts, tets=np.concatenate(tets))
