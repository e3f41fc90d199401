"""The ``/tables`` group of an asset: stiffness tables stored and read back (docs/reference/asset-format.md).

:func:`write_tables` stores a :class:`~esmm.pipeline.network.tables.StiffnessTables`
in an open HDF5 group, :func:`read_tables` reads it back (refusing anything
damaged or of another version) and :func:`write_per_spring` adds the
materialised per-spring table ``k_per_spring``.

Layout of the group: attributes ``esmm_type``, ``esmm_version``, ``lam_min``,
``lam_max``, ``n``, ``dlam``, ``default_law``, ``laws``, ``volume_factor``,
``directions``, ``isotropic``, ``grid_rule``, ``extrapolation``, ``force_law``,
``material_toml``, ``metadata`` (JSON); datasets (each with ``units`` and
``description``): ``lam`` (n,), ``mu_e`` (= ``values``), ``stress``, ``energy``
(3, n) and ``correction`` (2, n). ``mu_e`` and ``stress`` are what a simulator
interpolates (the correction is already applied).
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np

from ..atomicio import jsonable
from ..errors import AssetError
from ..materials.material import DIRECTIONS
from ..network.tables import (
    EXTRAPOLATION,
    FORCE_LAW,
    GRID_RULE,
    LAWS,
    StiffnessTables,
    spring_factors,
)
from .hdf5 import attr_str
from .schema import GROUPS

#: ``esmm_type`` and version of the group.
TABLES_TYPE, TABLES_VERSION = GROUPS["/tables"][:2]
#: Datasets of the group (replaced when the tables are rewritten).
TABLE_DATASETS = ("lam", "mu_e", "stress", "energy", "correction", "k_per_spring")


def write_tables(group: h5py.Group, tables: StiffnessTables) -> None:
    """Write *tables* into an open h5py group (existing datasets are replaced)."""
    for name in TABLE_DATASETS:
        if name in group:
            del group[name]
    a = group.attrs
    a["esmm_type"] = TABLES_TYPE
    a["esmm_version"] = TABLES_VERSION
    a["lam_min"] = tables.lam_min
    a["lam_max"] = tables.lam_max
    a["n"] = tables.n
    a["dlam"] = tables.dlam
    a["default_law"] = tables.default_law
    a["laws"] = ",".join(LAWS)
    a["volume_factor"] = tables.volume_factor
    a["directions"] = ",".join(DIRECTIONS)
    a["isotropic"] = tables.isotropic
    a["grid_rule"] = GRID_RULE
    a["extrapolation"] = EXTRAPOLATION
    a["force_law"] = FORCE_LAW
    a["material_toml"] = tables.material_toml
    a["metadata"] = json.dumps(jsonable(tables.metadata), sort_keys=True)
    for name, data, units, desc in (
        ("lam", tables.lam, "1", "stretch grid (uniform)"),
        ("mu_e", tables.values, "Pa", "secant-law table: correction[0] * material mu_e, mu_e = 2 W_T / "
         "(lam-1)^2; k_ij = volume_factor * v_ij * sum_d cos2_d * mu_e_d(lam); rows x, y, z"),
        ("stress", tables.stress, "Pa", "energy-law table: correction[1] * material W_T'(lam) (nominal "
         "uniaxial stress); F = volume_factor * V_ij / L0 * sum_d cos2_d * stress_d(lam); rows x, y, z"),
        ("energy", tables.energy, "Pa", "integral from 1 of the interpolated stress (energy-law potential "
         "per volume); rows x, y, z"),
        ("correction", tables.correction, "1", "stretch correction g(lam) already applied to mu_e "
         "(row 0, secant) and stress (row 1, energy); the material's curves are mu_e/g, stress/g"),
    ):
        ds = group.create_dataset(name, data=np.asarray(data, dtype=np.float64))
        ds.attrs["units"] = units
        ds.attrs["description"] = desc


def read_tables(group: h5py.Group) -> StiffnessTables:
    """Read tables written by :func:`write_tables`.

    Raises
    ------
    AssetError
        Not a stiffness-table group, another version, or damaged.
    """
    where = f"{getattr(getattr(group, 'file', None), 'filename', '?')}:{getattr(group, 'name', '?')}"
    a = group.attrs
    kind = attr_str(a.get("esmm_type"))
    if kind != TABLES_TYPE:
        raise AssetError(f"{where}: not a stiffness-table group (esmm_type={kind!r}); "
                         "rebuild the tables with 'esmm tables'")
    version = int(a.get("esmm_version", -1))
    if version != TABLES_VERSION:
        raise AssetError(f"{where}: stiffness tables of version {version}, this esmm reads "
                         f"version {TABLES_VERSION}; rebuild them with 'esmm tables'")
    try:
        tables = StiffnessTables(
            lam_min=float(a["lam_min"]), lam_max=float(a["lam_max"]), n=int(a["n"]),
            values=np.asarray(group["mu_e"][()]), stress=np.asarray(group["stress"][()]),
            energy=np.asarray(group["energy"][()]),
            default_law=attr_str(a.get("default_law", "secant")),
            volume_factor=float(a.get("volume_factor", 1.0)),
            correction=np.asarray(group["correction"][()]) if "correction" in group else None,
            material_toml=attr_str(a.get("material_toml", "")),
            metadata=json.loads(attr_str(a.get("metadata", "{}")) or "{}"),
        )
    except (KeyError, ValueError, TypeError, OSError) as exc:
        raise AssetError(f"{where}: damaged stiffness tables ({exc}); rebuild them with "
                         "'esmm tables'") from None
    if "dlam" in a and not math.isclose(float(a["dlam"]), tables.dlam, rel_tol=1e-9):
        raise AssetError(f"{where}: dlam attribute disagrees with lam_min/lam_max/n; "
                         "rebuild the tables with 'esmm tables'")
    return tables


def write_per_spring(group: h5py.Group, tables: StiffnessTables, network, *, name: str = "k_per_spring",
                     dtype=np.float32, compression: str = "gzip", level: int = 4,
                     chunk_springs: int = 4096) -> None:
    """Write :func:`~esmm.pipeline.network.tables.per_spring_table` into *group*, chunked and compressed.

    The dataset ``name`` has shape (s, n), units N/m, and attributes
    ``lam_min``, ``lam_max``, ``n`` (the grid of the tables). It is written
    block by block, so memory stays at one block of ``chunk_springs`` rows.
    """
    a = spring_factors(tables, network)
    s = a.shape[0]
    if name in group:
        del group[name]
    rows = max(1, min(chunk_springs, s))
    cols = tables.n
    chunk_rows = max(1, min(s, (1 << 16) // cols))  # ~256 KiB chunks of float32
    ds = group.create_dataset(name, shape=(s, cols), dtype=dtype, chunks=(chunk_rows, cols) if s else None,
                              compression=compression if s else None,
                              compression_opts=level if s and compression == "gzip" else None,
                              shuffle=bool(s))
    for start in range(0, s, rows):
        stop = min(s, start + rows)
        ds[start:stop] = (a[start:stop] @ tables.values).astype(dtype, copy=False)
    ds.attrs["units"] = "N/m"
    ds.attrs["description"] = "k_ij(lam) = volume_factor * v_ij * sum_d cos2_d * mu_e_d(lam) on the table grid (secant law)"
    ds.attrs["lam_min"] = tables.lam_min
    ds.attrs["lam_max"] = tables.lam_max
    ds.attrs["n"] = tables.n
    ds.attrs["volume_factor"] = tables.volume_factor
