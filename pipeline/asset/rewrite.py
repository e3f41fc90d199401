"""Rewriting the ``/tables`` (and ``/material``) group of an existing asset, atomically."""

from __future__ import annotations

import os
from pathlib import Path

import h5py

from ..atomicio import atomic_path
from ..errors import AssetError
from ..network.tables import StiffnessTables
from ..network.volume import VolumeSpec
from ..progress import ensure
from .hdf5 import seal
from .material import write_material
from .read import read_asset, validate_asset
from .tables import write_per_spring, write_tables
from .volume import write_volume


def update_asset_tables(path: str | os.PathLike, tables: StiffnessTables, *, material=None,
                        per_spring: bool = False, volume: VolumeSpec | None = None, reporter=None) -> Path:
    """Replace the ``/tables`` group (and optionally ``/material``) of an asset, atomically.

    The asset is read and verified first (checksums); a new file is written
    next to it with every other group copied unchanged, the new tables (and,
    with *per_spring*, the materialised ``/tables/k_per_spring``), re-sealed
    (dataset digests and root checksum), validated, and only then renamed
    over the original. The XDMF sidecar stays valid (it does not reference
    ``/tables`` or ``/material``).

    Parameters
    ----------
    path : str or Path
        The ``.h5`` asset.
    tables : StiffnessTables
    material : Material, optional
        Also replace ``/material`` (when the tables were built from another material).
    per_spring : bool
        Write the (s, n) per-spring stiffness table too.
    volume : VolumeSpec, optional
        Also replace ``/volume`` (a volume term sized for a new material; the
        asset's tetrahedra carry it).
    reporter
        Progress reporter.

    Returns
    -------
    Path

    Raises
    ------
    AssetError
        The asset cannot be read, or the rewritten file does not validate.
    """
    rep = ensure(reporter)
    p = Path(path)
    asset = read_asset(p)
    skip = {"tables"} | ({"material"} if material is not None else set()) | ({"volume"} if volume else set())
    if volume is not None and asset.network.tets is None:
        raise AssetError(f"{p}: a volume term needs tetrahedra; this asset ({asset.network.structure}) has none")
    try:
        with atomic_path(p) as tmp:
            with h5py.File(p, "r") as src, h5py.File(tmp, "w") as dst:
                for k, v in src.attrs.items():
                    dst.attrs[k] = v
                for name in src:
                    if name not in skip:
                        src.copy(src[name], dst, name=name)
                if material is not None:
                    write_material(dst, material)
                if volume is not None:
                    write_volume(dst, volume, asset.network.points, asset.network.tets)
                g = dst.create_group("tables")
                write_tables(g, tables)
                if per_spring:
                    write_per_spring(g, tables, asset.network)
                    rep.step(f"per-spring table: {asset.network.n_springs} x {tables.n} (float32, gzip)")
                seal(dst)
            problems = validate_asset(tmp)
            if problems:
                raise AssetError(f"{p}: the rewritten asset does not validate ({problems[0]}); "
                                 "the original file is unchanged")
    except OSError as exc:
        raise AssetError(f"{p}: cannot rewrite the asset ({exc.strerror or exc}); check the folder "
                         "is writable and has space") from None
    return p
