"""The optional ``/volume`` group: the volume term of the network (docs/reference/asset-format.md).

``esmm prepare`` writes it by default for the tet structure: what the
simulator needs to keep the organ's volume (the bulk modulus, the
formulation, the rest volume of every element) and how the bulk modulus was
chosen. Adding the group did not change any schema version (an optional
group); an asset without it is simulated with the springs alone.
"""

from __future__ import annotations

import math

import h5py
import numpy as np

from ..errors import ConfigError
from ..network.springs import tet_volumes
from ..network.volume import FORMULATIONS, VolumeSpec, nodal_volumes
from . import hdf5
from .schema import GROUPS

#: Relative tolerance of the stored rest volumes against the mesh's own.
REST_RTOL = 1e-9


def write_volume(f: h5py.File, spec: VolumeSpec, points: np.ndarray, tets: np.ndarray) -> None:
    """Write ``/volume`` for *spec* on the mesh (*points* (n, 3) [m] at rest, *tets* (t, 4))."""
    g = hdf5.typed_group(f, "volume", *GROUPS["/volume"][:2])
    g.attrs["formulation"] = spec.formulation
    g.attrs["energy"] = "U = sum_e V_e0 * kappa/2 * (J_e - 1)^2, J_e = V_e / V_e0 (docs/design/model.md, 'The volume term')"
    g.attrs["rule"] = spec.rule
    for key in ("poisson_ratio", "at_stretch"):
        value = getattr(spec, key)
        if value is not None:
            g.attrs[key] = float(value)
    if spec.shear_modulus is not None:
        hdf5.put(g, "shear_modulus", np.float64(spec.shear_modulus), "Pa", dtype=np.float64,
                 description="the material's largest tangent shear modulus the bulk modulus was sized on")
    hdf5.put(g, "bulk_modulus", np.float64(spec.bulk_modulus), "Pa", dtype=np.float64,
             description="kappa of the volume penalty")
    rest = nodal_volumes(points, tets) if spec.formulation == "nodal" else tet_volumes(points, tets)
    hdf5.put(g, "rest_volume", rest, "m3", dtype=np.float64,
             description=f"rest volume of each {'node (sum of V_t/4)' if spec.formulation == 'nodal' else 'tet'}")


def read_volume(f: h5py.File) -> VolumeSpec | None:
    """The volume term stored in ``/volume`` (None when the asset has none).

    Raises
    ------
    ConfigError
        An unknown formulation or a bulk modulus that is not a finite number >= 0.
    """
    if "/volume" not in f:
        return None
    g = f["/volume"]
    a = g.attrs

    def opt(key):
        v = a.get(key)
        return None if v is None else float(v)

    form = hdf5.attr_str(a.get("formulation", "nodal"))
    if form not in FORMULATIONS:
        raise ConfigError(f"formulation {form!r} is not one of {', '.join(FORMULATIONS)}")
    shear = float(g["shear_modulus"][()]) if "shear_modulus" in g else None
    return VolumeSpec(bulk_modulus=float(g["bulk_modulus"][()]), formulation=form, poisson_ratio=opt("poisson_ratio"),
                      shear_modulus=shear, at_stretch=opt("at_stretch"), rule=hdf5.attr_str(a.get("rule", "")))


def volume_problems(f: h5py.File) -> list[str]:
    """Problems of ``/volume``: readable, a tet mesh under it, rest volumes equal to the mesh's."""
    if "/volume" not in f:
        return []
    try:
        spec = read_volume(f)
    except (ConfigError, ValueError, TypeError) as exc:
        return [f"/volume: {exc}"]
    if "/mesh/tets" not in f:
        return ["/volume: the asset has no tetrahedra (/mesh/tets) for its volume elements"]
    points = np.asarray(f["/mesh/points"][()], dtype=np.float64)
    tets = np.asarray(f["/mesh/tets"][()], dtype=np.int64)
    if tets.size == 0 or tets.min() < 0 or tets.max() >= points.shape[0]:
        return []                     # reported by the shape checks
    rest = np.asarray(f["/volume/rest_volume"][()], dtype=np.float64)
    expect = nodal_volumes(points, tets) if spec.formulation == "nodal" else tet_volumes(points, tets)
    if rest.shape != expect.shape:
        return [f"/volume/rest_volume: shape {rest.shape}, expected {expect.shape} ({spec.formulation} elements)"]
    if not np.all(np.isfinite(rest)) or not np.allclose(rest, expect, rtol=REST_RTOL, atol=0.0):
        return ["/volume/rest_volume: differs from the volumes of the mesh's tetrahedra"]
    if not math.isfinite(spec.bulk_modulus):
        return ["/volume/bulk_modulus: not finite"]
    return []
