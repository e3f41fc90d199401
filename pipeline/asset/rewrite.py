"""Rewriting parts of an existing asset, atomically: its ``/tables`` (and ``/material``), or the
validation figures ``esmm validate`` records in ``/accuracy``."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import h5py

from .. import __version__
from ..atomicio import atomic_path
from ..errors import AssetError
from ..network.tables import StiffnessTables
from ..network.volume import VolumeSpec
from ..progress import ensure
from .accuracy import read_records, validation_record, write_fit, write_validation
from .hdf5 import seal
from .material import write_material
from .provenance import utc_now
from .read import read_asset, validate_asset
from .report import report_path, write_asset_report
from .tables import write_per_spring, write_tables
from .volume import write_volume


def _rewrite(p: Path, *, skip: set[str], drop: tuple[str, ...], fill: Callable[[h5py.File], None]) -> None:
    """Copy the asset *p* into a new file but its top-level groups *skip* and the objects *drop*,
    let *fill* write the rest, re-seal, validate, and only then rename it over *p*."""
    try:
        with atomic_path(p) as tmp:
            with h5py.File(p, "r") as src, h5py.File(tmp, "w") as dst:
                for k, v in src.attrs.items():
                    dst.attrs[k] = v
                for name in src:
                    if name not in skip:
                        src.copy(src[name], dst, name=name)
                for path in drop:
                    if path in dst:
                        del dst[path]
                if "accuracy" in dst and not len(dst["accuracy"]):
                    del dst["accuracy"]
                fill(dst)
                seal(dst)
            problems = validate_asset(tmp)
            if problems:
                raise AssetError(f"{p}: the rewritten asset does not validate ({problems[0]}); "
                                 "the original file is unchanged")
    except OSError as exc:
        raise AssetError(f"{p}: cannot rewrite the asset ({exc.strerror or exc}); check the folder "
                         "is writable and has space") from None


def update_asset_tables(path: str | os.PathLike, tables: StiffnessTables, *, material=None,
                        per_spring: bool = False, volume: VolumeSpec | None = None, fit: dict | None = None,
                        reporter=None) -> Path:
    """Replace the ``/tables`` group (and optionally ``/material``) of an asset, atomically.

    The asset is read and verified first (checksums); a new file is written
    next to it with every other group copied unchanged, the new tables (and,
    with *per_spring*, the materialised ``/tables/k_per_spring``), re-sealed
    (dataset digests and root checksum), validated, and only then renamed
    over the original. The XDMF sidecars stay valid (they do not reference
    ``/tables`` or ``/material``). The validation figures (``/accuracy/validation``)
    are dropped: they were measured with the old tables; so is the fit's error
    (``/accuracy/fit``) when the material is replaced, unless *fit* gives the new one's.

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
    fit : dict, optional
        The new material's fit error (:func:`~esmm.pipeline.asset.accuracy.fit_record`).
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
    drop = ("accuracy/validation",) + (("accuracy/fit",) if material is not None or fit is not None else ())

    def fill(dst: h5py.File) -> None:
        if material is not None:
            write_material(dst, material)
        if volume is not None:
            write_volume(dst, volume, asset.network.points, asset.network.tets)
        if fit is not None:
            write_fit(dst, fit)
        g = dst.create_group("tables")
        write_tables(g, tables)
        if per_spring:
            write_per_spring(g, tables, asset.network)
            rep.step(f"per-spring table: {asset.network.n_springs} x {tables.n} (float32, gzip)")

    _rewrite(p, skip=skip, drop=drop, fill=fill)
    return p


def record_validation(path: str | os.PathLike, figures: dict, *, scene: str = "default") -> Path:
    """Record ``esmm validate``'s figures in the asset's ``/accuracy/validation``, atomically.

    Each case of *figures* (the validation's JSON document: ``cases``, ``failed``,
    ``law``, ``volume_term``, ``element``) replaces the asset's record of that case;
    the other cases recorded stay. The asset is verified first and the rewritten
    file validated before it replaces the original; the asset's report
    (``NAME.report.html``), when there is one, is written again.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` asset that was validated.
    figures : dict
        ``ValidationReport.figures()``.
    scene : str
        The scene of the organ cases (its name or file), recorded with each case.

    Raises
    ------
    AssetError
        The asset cannot be read or rewritten (not writable: the figures stay in the
        validation's own outputs).
    """
    p = Path(path)
    read_asset(p)
    with h5py.File(p, "r") as f:
        _, old = read_records(f)
    record = validation_record(figures, old=old, scene=str(scene), utc_time=utc_now(), version=__version__)
    _rewrite(p, skip=set(), drop=("accuracy/validation",), fill=lambda dst: write_validation(dst, record))
    if report_path(p).is_file():       # the asset's report says how far to trust it: renew it
        write_asset_report(p)
    return p
