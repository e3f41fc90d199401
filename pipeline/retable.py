"""``esmm tables``: rebuild an asset's stiffness tables (material, grid, force law, compensation).

:func:`rebuild_tables` rewrites the ``/tables`` group of an asset (and, for a
new material, ``/material`` and a re-sized ``/volume``), atomically. Its
policy:

* the material is the asset's own unless another is given;
* the grid is the asset's own (points and stretch ends) unless given, and its
  stretch ends are kept only for the same material (another material has
  another admissible range);
* a compensation already in the asset is kept when the material and the grid
  do not change (it was calibrated for exactly these tables); otherwise it is
  dropped, with a warning, unless a new one is calibrated;
* the volume term is kept for the same material and re-sized (same Poisson
  ratio) for another one, since its bulk modulus follows the material's
  stiffness;
* a new compensation is :func:`~esmm.pipeline.compensation.calibration.compensate`'s,
  the policy and cache of ``esmm prepare``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .asset import Asset, update_asset_tables
from .checks import number_text
from .compensation.calibration import Compensation, calibration_stretches, compensate
from .errors import ConfigError
from .materials.material import Material, load_material
from .network.tables import LAWS, StiffnessTables, build_tables
from .network.volume import DEFAULT_POISSON, VolumeSpec, bulk_modulus
from .progress import ensure


@dataclass(frozen=True)
class RetableResult:
    """What :func:`rebuild_tables` wrote and how it got there.

    Attributes
    ----------
    path : Path
        The asset rewritten.
    tables : StiffnessTables
        The tables written.
    material : Material
        The material they were built from.
    compensation_kept : bool
        The asset's compensation was carried over (same material and grid).
    compensation : Compensation or None
        The compensation calibrated (or reused from the cache) now.
    volume : VolumeSpec or None
        The volume term re-sized for a new material and written; None when
        the asset's was kept as it was (or it has none).
    """

    path: Path
    tables: StiffnessTables
    material: Material
    compensation_kept: bool
    compensation: Compensation | None
    volume: VolumeSpec | None


#: What each option that needs the compensation is for (the message when it would go unused).
_USES = {"radius_elements": "only used by the virtual tensile test",
         "calibration_range": "only used by the virtual tensile test (and to re-size the asset's volume term "
                              "for a new material)"}


def unused_options(asset: Asset, *, material_given: bool, compensate: bool, calibration_range=None,
                   radius_elements=None) -> list[str]:
    """The options given that :func:`rebuild_tables` would not use (parameter names).

    *radius_elements* sizes the virtual tensile test's specimen, so it needs
    *compensate*; *calibration_range* also sizes the volume term re-sized for
    a new material, so it needs *compensate* or a new material on an asset
    with a volume term.
    """
    unused = []
    if radius_elements is not None and not compensate:
        unused.append("radius_elements")
    if (calibration_range is not None and not compensate
            and not (material_given and asset.network.volume_term is not None)):
        unused.append("calibration_range")
    return unused


def rebuild_tables(asset: Asset, *, material: Material | str | os.PathLike | None = None, law: str | None = None,
                   points: int | str | None = None, stretch_range=None, per_spring: bool = False,
                   compensate: bool = False, calibration_range=None, radius_elements: float | str | None = None,
                   argv: list[str] | None = None, reporter=None) -> RetableResult:
    """Rebuild *asset*'s stiffness tables and rewrite its file (the module docstring gives the policy).

    Parameters
    ----------
    asset : Asset
        The asset as read (:func:`~esmm.pipeline.asset.read_asset`); its file
        is rewritten.
    material : Material, name or path, optional
        Build the tables from this material (it also replaces ``/material``);
        default the asset's.
    law : {"secant", "energy"}, optional
        The default force law (default: the asset's, else secant).
    points : int or text, optional
        Grid points (default: the asset's, else the tables' default).
    stretch_range : (lo, hi), numbers or text, optional
        Grid ends, ``0 < lo < 1 < hi`` (default: the asset's for the same
        material, else just inside the material's admissible range).
    per_spring : bool
        Also write the per-spring stiffness table.
    compensate : bool
        Calibrate the volumetric compensation of the default law.
    calibration_range : (lo, hi), numbers or text, optional
        Compression and tension ends of the calibration, also used to re-size
        the volume term (default: the compensation's).
    radius_elements : float or text, optional
        The calibration cylinder's radius in element sizes (with *compensate*).
    argv : list of str, optional
        The command line, recorded in the tables' ``metadata["written_by"]``.
    reporter
        Progress; a dropped compensation and a reused one that did not
        converge are warnings.

    Returns
    -------
    RetableResult

    Raises
    ------
    ConfigError
        No material, an option that would not be used, a bad grid, range or
        radius (named by its parameter).
    SimulationError
        The virtual tensile test failed.
    AssetError
        The asset cannot be rewritten.
    """
    rep = ensure(reporter)
    mat = _material(asset, material)
    for name in unused_options(asset, material_given=material is not None, compensate=compensate,
                               calibration_range=calibration_range, radius_elements=radius_elements):
        raise ConfigError(f"{name}: {_USES[name]}; set compensate or leave it out", parameter=name)
    law = law or (asset.tables.default_law if asset.tables is not None else "secant")
    tables = _build(mat, law, _grid(asset.tables, points, stretch_range, same_material=material is None),
                    stretch_range=stretch_range)
    tables, kept = _carry(tables, asset.tables)
    if not kept and _has_compensation(asset.tables) and not compensate:
        rep.warn("the asset's compensation was dropped (the material or the grid changed); compensate the new "
                 "tables to calibrate one")
    volume = None if material is None else _resized_volume(tables, asset.network.volume_term, calibration_range, rep)
    comp = None
    if compensate:
        comp = _compensate(tables, asset, mat, asset.network.volume_term if volume is None else volume,
                           calibration_range, radius_elements, rep)
        tables, kept = comp.tables, False
    tables = _written_by(tables, argv)
    update_asset_tables(asset.path, tables, material=mat if material is not None else None,
                        per_spring=per_spring, volume=volume, reporter=rep)
    return RetableResult(Path(asset.path), tables, mat, kept, comp, volume)


def _material(asset: Asset, material) -> Material:
    """The material given (loaded if a name or path), else the asset's."""
    if material is not None:
        return material if isinstance(material, Material) else load_material(material)
    if asset.material is not None:
        return asset.material
    raise ConfigError(f"material: {asset.path}: the asset stores no material; give one", parameter="material")


def _grid(old: StiffnessTables | None, points, stretch_range, *, same_material: bool) -> dict[str, Any]:
    """The grid options of build_tables: those given, else the asset's (its ends for the same material only)."""
    n = None if points is None else number_text(points, "points", lo=3, hi=1_000_000, integer=True)
    n = n or (old.n if old is not None else None)
    lo = hi = None
    if stretch_range is not None:
        lo, hi = (number_text(v, "stretch_range") for v in stretch_range)
        if not 0 < lo < 1 < hi:
            raise ConfigError(f"stretch_range: need 0 < LO < 1 < HI, got {lo:g} {hi:g}", parameter="stretch_range")
    elif old is not None and same_material:
        lo, hi = old.lam_min, old.lam_max
    return {"lam_min": lo, "lam_max": hi, **({} if n is None else {"n": n})}


def _build(material: Material, law: str, grid: dict[str, Any], *, stretch_range) -> StiffnessTables:
    """:func:`build_tables`, a bad grid named ``stretch_range`` when the ends were given as that."""
    try:
        return build_tables(material, law=law, **grid)
    except ConfigError as exc:   # build_tables names its grid "lam_min/lam_max"
        prefix = "lam_min/lam_max:"
        if stretch_range is None or not str(exc).startswith(prefix):
            raise
        raise ConfigError("stretch_range:" + str(exc)[len(prefix):], parameter="stretch_range") from None


def _has_compensation(tables: StiffnessTables | None) -> bool:
    return tables is not None and (tables.volume_factor != 1.0 or any(tables.is_corrected(lw) for lw in LAWS))


def _carry(tables: StiffnessTables, old: StiffnessTables | None) -> tuple[StiffnessTables, bool]:
    """*tables* with the asset's compensation when the material and grid are unchanged: (tables, kept)."""
    if not _has_compensation(old):
        return tables, False
    same = (old.material_toml == tables.material_toml and old.n == tables.n
            and math.isclose(old.lam_min, tables.lam_min, rel_tol=1e-12)
            and math.isclose(old.lam_max, tables.lam_max, rel_tol=1e-12))
    if not same:
        return tables, False
    return tables.with_compensation(
        old.volume_factor, correction={lw: old.correction[i] for i, lw in enumerate(LAWS)},
        record=old.metadata.get("compensation")), True


def _calibration_range(calibration_range) -> tuple[float, float] | None:
    if calibration_range is None:
        return None
    return tuple(number_text(v, "calibration_range") for v in calibration_range)


def _resized_volume(tables: StiffnessTables, old: VolumeSpec | None, calibration_range, rep) -> VolumeSpec | None:
    """The asset's volume term re-sized for a new material (same Poisson ratio); None if it has none."""
    if old is None:
        return None
    nu = DEFAULT_POISSON if old.poisson_ratio is None else old.poisson_ratio
    spec = bulk_modulus(tables, poisson=nu,
                        calibration_range=calibration_stretches(tables, _calibration_range(calibration_range)),
                        formulation=old.formulation)
    rep.step(f"volume term re-sized for the new material: bulk modulus {old.bulk_modulus / 1e3:.4g} -> "
             f"{spec.bulk_modulus / 1e3:.4g} kPa (Poisson ratio {nu:g})")
    return spec


def _compensate(tables: StiffnessTables, asset: Asset, material: Material, volume: VolumeSpec | None,
                calibration_range, radius_elements, rep) -> Compensation:
    """The compensation of ``esmm prepare`` (same policy and cache), with the given range and radius."""
    r_el = None if radius_elements is None else number_text(radius_elements, "radius_elements")
    comp = compensate(tables, asset.network, material=material, calibration_range=_calibration_range(calibration_range),
                      radius_elements=r_el, volume=volume, reporter=rep)
    if comp.reused is not None and not comp.record.get("converged", True):
        # calibrated earlier (its warning then is not repeated by the calibration): say it again
        rep.warn(f"the reused compensation did not converge (max |stress error| "
                 f"{100 * comp.record['errors_after']['max_abs_rel_error']:.2f} %); try a narrower "
                 f"calibration range")
    return comp


def _written_by(tables: StiffnessTables, argv: list[str] | None) -> StiffnessTables:
    """*tables* with ``metadata["written_by"]``: the command line and the time (UTC)."""
    meta = dict(tables.metadata)
    meta["written_by"] = {"command": list(argv or []), "utc": datetime.now(UTC).isoformat(timespec="seconds")}
    return dataclasses.replace(tables, metadata=meta)
