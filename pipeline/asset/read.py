"""Reading and validating assets.

Both functions first check the file header (SHA-256 and length of the bytes after
the HDF5 user block; :func:`~esmm.pipeline.asset.hdf5.check_file`) so that libhdf5,
which can crash or hang on damaged metadata, never parses a damaged esmm file.
:func:`read_asset` dispatches on each group's ``esmm_type``/``esmm_version``,
verifies every dataset's SHA-256 and the root checksum, and raises a one-line
:class:`~esmm.pipeline.errors.AssetError` for anything it cannot trust
(truncated, tampered, of another schema or a newer version).
:func:`validate_asset` collects every problem instead of stopping at the first.
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import AssetError, EsmmError
from ..materials.effects import MaterialEffects
from ..network.springs import SpringNetwork
from ..network.tables import StiffnessTables
from . import hdf5
from .accuracy import accuracy_problems, compensation_summary, read_records
from .material import material_effects, material_from_toml, read_effects, storable_effects
from .provenance import Provenance
from .schema import ASSET_TYPE, ASSET_VERSION, CHECKSUM_ATTR, DATASETS, GROUPS, KNOWN_UNITS
from .tables import read_tables
from .trust import Accuracy
from .volume import read_volume, volume_problems
from .xdmf import check_sidecar, sidecar_paths

ADVICE = "re-create it with 'esmm prepare'"


@dataclass
class Asset:
    """An asset read back from disk.

    Attributes
    ----------
    path : Path
    network : SpringNetwork
    material : object or None
        The ``Material`` (when the materials module can parse ``material_toml``).
    material_toml : str
        The material as stored ("" when the asset has none).
    tables : StiffnessTables or None
    effects : MaterialEffects or None
        The material effects kept by a discovery (``/material/effects``; for an
        asset without that group, the ``[material.effects]`` of its material).
    quality, cleaning : dict or None
        The reports as stored (JSON objects).
    quality_passes : bool or None
    provenance : Provenance
    fixed_region : str
        How the fixed nodes were chosen.
    schema_version : int
    attrs : dict
        The root attributes (sizes, volume, creation time).
    accuracy : Accuracy
        How far to trust the asset: the fit's, the compensation's and the validation's
        errors, as far as the asset records them (:mod:`.trust`).
    """

    path: Path
    network: SpringNetwork
    material: Any = None
    material_toml: str = ""
    tables: StiffnessTables | None = None
    effects: MaterialEffects | None = None
    quality: dict | None = None
    quality_passes: bool | None = None
    cleaning: dict | None = None
    provenance: Provenance = field(default_factory=Provenance)
    fixed_region: str = ""
    schema_version: int = ASSET_VERSION
    attrs: dict = field(default_factory=dict)
    accuracy: Accuracy = field(default_factory=Accuracy)

    def summary(self) -> dict[str, Any]:
        """Figures for ``esmm info`` (JSON-serialisable)."""
        net = self.network
        out: dict[str, Any] = {
            "path": str(self.path), "schema_version": self.schema_version, "structure": net.structure,
            "nodes": net.n_nodes, "springs": net.n_springs, "tets": net.n_tets,
            "split_from": None if net.quadratic_cells is None else int(net.quadratic_cells.shape[0]),
            "surface_faces": int(net.surface_faces.shape[0]), "volume_mL": net.total_volume() * 1e6,
            "mass_g": net.total_mass() * 1e3, "density_kg_m3": net.density, "fixed_nodes": int(net.fixed.size),
            "fixed_region": self.fixed_region,
            "rest_length_mm": _stats(net.rest_length * 1e3),
            "bounds_mm": (np.vstack([net.points.min(0), net.points.max(0)]) * 1e3).round(3).tolist(),
            "bandwidth": net.bandwidth(),
            "material": _material_name(self.material_toml),
            "effects": None if not self.effects else _effects_summary(self.effects),
            "volume_term": None if net.volume_term is None else net.volume_term.describe(),
            "tables": None if self.tables is None else {
                "lam_min": self.tables.lam_min, "lam_max": self.tables.lam_max, "n": self.tables.n,
                "volume_factor": getattr(self.tables, "volume_factor", 1.0),
                "default_law": getattr(self.tables, "default_law", "")},
            "quality_passes": self.quality_passes,
            "accuracy": self.accuracy.summary(),
            "created_utc": hdf5.attr_str(self.attrs.get("created_utc", "")),
            "input": self.provenance.input_path, "input_sha256": self.provenance.input_sha256,
            "esmm_version": self.provenance.packages.get("esmm", ""),
        }
        if self.quality:
            q = self.quality
            out["quality"] = {k: q[k] for k in ("min_dihedral_deg", "sicn", "gamma", "radius_ratio")
                              if k in q}
        return out


def _effects_summary(fx) -> dict[str, Any]:
    """Names and SI parameters of the material effects (for ``esmm info``)."""
    d = fx.to_dict()
    out: dict[str, Any] = {"names": list(fx.names)}
    for k in fx.names:
        out[k] = {key: val for key, val in d[k].items() if not key.startswith("unit_")}
    return out


def _stats(a: np.ndarray) -> dict[str, float]:
    if a.size == 0:
        return {}
    return {"min": float(a.min()), "mean": float(a.mean()), "max": float(a.max())}


def _material_name(text: str) -> str:
    if not text:
        return ""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return "(unreadable TOML)"
    m = data.get("material", data)
    return str(m.get("name") or m.get("model") or "")


# -- opening --------------------------------------------------------------------------------

#: What h5py raises on a damaged or unexpected file. RuntimeError and AttributeError count only
#: when raised inside h5py (see :func:`_is_damage`): from esmm's own code they are bugs.
_DAMAGE = (OSError, KeyError, ValueError, TypeError, OverflowError, RuntimeError, AttributeError)


def _is_damage(exc: BaseException) -> bool:
    """Whether *exc* (one of :data:`_DAMAGE`) reports a damaged file rather than a bug in esmm."""
    if not isinstance(exc, (RuntimeError, AttributeError)):
        return True
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and "h5py" in Path(tb.tb_frame.f_code.co_filename).parts


def _damaged(p: Path, exc: BaseException) -> AssetError:
    what = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
    return AssetError(f"{p}: damaged asset ({what}); {ADVICE}")


def _check_bytes(path: Path) -> None:
    """The file header check (docs/reference/asset-format.md), before libhdf5 sees the file."""
    try:
        _sealed, problem = hdf5.check_file(path)
    except OSError as exc:
        raise AssetError(f"{path}: cannot be read ({exc.strerror or exc}); check the file's permissions") from None
    if problem:
        advice = "" if problem.endswith("upgrade esmm") else f"; {ADVICE}"
        raise AssetError(f"{path}: {problem}{advice}")


def _open(path: Path) -> h5py.File:
    if not path.exists():
        raise AssetError(f"{path}: no such file; give the .h5 written by 'esmm prepare'")
    if path.is_dir():
        raise AssetError(f"{path}: is a folder; give the .h5 file written by 'esmm prepare'")
    _check_bytes(path)
    try:
        return h5py.File(path, "r")
    except (RuntimeError, AttributeError) as exc:
        if not _is_damage(exc):
            raise
        raise _damaged(path, exc) from None
    except OSError as exc:
        reason = str(exc).split("(")[-1].rstrip(")") if "(" in str(exc) else str(exc)
        if "truncated" in str(exc).lower():
            raise AssetError(f"{path}: the file is truncated ({reason}); {ADVICE}") from None
        if not _looks_hdf5(path):
            raise AssetError(f"{path}: not an HDF5 file (an esmm asset is written by 'esmm prepare')") from None
        raise AssetError(f"{path}: cannot open the HDF5 file ({reason}); {ADVICE}") from None


def _looks_hdf5(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError:
        return False
    return head == b"\x89HDF\r\n\x1a\n"


#: Other files esmm writes in HDF5 (root ``esmm_type``): what they are, for the message on them.
OTHER_ESMM_FILES = {"simulation_history": "a simulation history written by 'esmm simulate' (open its .xdmf "
                                          "in ParaView)"}


def _root_problems(f: h5py.File) -> list[str]:
    """Problems of the root (type, schema version); each message says what to do."""
    kind = hdf5.attr_str(f.attrs.get("esmm_type"))
    if kind in OTHER_ESMM_FILES:
        return [f"not an asset but {OTHER_ESMM_FILES[kind]}; give the .h5 written by 'esmm prepare'"]
    if kind != ASSET_TYPE:
        return [f"not an esmm asset (root esmm_type is {kind or 'missing'!r}, expected {ASSET_TYPE!r}); "
                f"give the .h5 written by 'esmm prepare'"]
    raw = f.attrs.get("esmm_version")
    version = hdf5.attr_int(raw)
    whole = raw is not None and np.asarray(raw).shape == () and np.asarray(raw).dtype.kind in "iu"
    if version < 1 or not whole:  # 1.5 or True would otherwise pass for version 1
        return [f"root esmm_version {hdf5.attr_str(raw) or 'missing'!r} is not a schema version; {ADVICE}"]
    if version > ASSET_VERSION:
        return [f"asset schema version {version} is newer than this esmm reads ({ASSET_VERSION}); "
                f"upgrade esmm"]
    return []


def _integrity_problems(f: h5py.File) -> list[str]:
    out: list[str] = []

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            stored = hdf5.attr_str(obj.attrs.get("sha256"))
            if not stored:
                out.append(f"/{name}: no sha256 attribute")
                return
            try:
                digest = hdf5.dataset_digest(obj)
            except (OSError, ValueError, TypeError) as exc:
                out.append(f"/{name}: cannot be read ({exc})")
                return
            if digest != stored:
                out.append(f"/{name}: content does not match its sha256 (modified or damaged)")

    try:
        f.visititems(visit)
    except (OSError, RuntimeError, ValueError) as exc:
        out.append(f"the file structure cannot be read ({exc})")
        return out
    stored = hdf5.attr_str(f.attrs.get(CHECKSUM_ATTR))
    if not stored:
        out.append(f"root attribute {CHECKSUM_ATTR} is missing")
    else:
        try:
            if hdf5.manifest(f) != stored:
                out.append("attributes do not match the root checksum (an attribute was modified)")
        except (OSError, RuntimeError, ValueError) as exc:
            out.append(f"attributes cannot be read ({exc})")
    return out


def _schema_problems(f: h5py.File) -> tuple[list[str], bool]:
    """Schema problems, and whether one of them makes the content checks impossible."""
    out: list[str] = []
    fatal = False
    for gpath, (gtype, gver, required) in GROUPS.items():
        if gpath not in f:
            if required:
                out.append(f"{gpath}: required group is missing")
                fatal = True
            continue
        g = f[gpath]
        if not isinstance(g, h5py.Group):
            out.append(f"{gpath}: expected a group")
            fatal = True
            continue
        t = hdf5.attr_str(g.attrs.get("esmm_type"))
        v = hdf5.attr_int(g.attrs.get("esmm_version"))
        if t != gtype:
            out.append(f"{gpath}: esmm_type is {t or 'missing'!r}, expected {gtype!r}")
            fatal = True
        elif v < 1:
            out.append(f"{gpath}: esmm_version {g.attrs.get('esmm_version')!r} is not a version")
        elif v > gver:
            out.append(f"{gpath}: {gtype} version {v} is newer than this esmm reads ({gver}); upgrade esmm")
            fatal = True
    for dpath, (units, kinds, required) in DATASETS.items():
        gpath = dpath.rsplit("/", 1)[0]
        if gpath not in f:
            continue
        if dpath not in f:
            if required:
                out.append(f"{dpath}: required dataset is missing")
                fatal = True
            continue
        ds = f[dpath]
        if not isinstance(ds, h5py.Dataset):
            out.append(f"{dpath}: expected a dataset")
            fatal = True
            continue
        u = hdf5.attr_str(ds.attrs.get("units"))
        if u != units:
            out.append(f"{dpath}: units are {u or 'missing'!r}, expected {units!r}")
        if ds.dtype.kind not in kinds:
            out.append(f"{dpath}: dtype {ds.dtype} is not of the expected kind")
            fatal = True

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            u = hdf5.attr_str(obj.attrs.get("units"))
            if not u:
                out.append(f"/{name}: no units attribute")
            elif u not in KNOWN_UNITS:
                out.append(f"/{name}: unknown units {u!r}")
        elif isinstance(obj, h5py.Group) and ("esmm_type" not in obj.attrs or "esmm_version" not in obj.attrs):
            out.append(f"/{name}: group without esmm_type/esmm_version")

    f.visititems(visit)
    return out, fatal


def _arr(f: h5py.File, path: str, dtype=None) -> np.ndarray:
    a = np.asarray(f[path][()])
    return a.astype(dtype) if dtype is not None else a


def _shape_problems(f: h5py.File) -> list[str]:
    out: list[str] = []
    pts = f["/mesh/points"]
    if pts.ndim != 2 or pts.shape[1] != 3:
        return [f"/mesh/points: shape {pts.shape}, expected (n, 3)"]
    n = pts.shape[0]
    s = f["/springs/pairs"].shape[0] if f["/springs/pairs"].ndim == 2 else -1
    expect = {
        "/mesh/node_kind": (n,), "/nodes/mass": (n,), "/nodes/fixed_mask": (n,),
        "/springs/pairs": (s, 2), "/springs/rest_length": (s,), "/springs/volume": (s,),
        "/springs/volume_weight": (s,), "/springs/cos2": (s, 3), "/springs/fibre_frame": (3, 3),
        "/springs/affine_elasticity": (6, 6),
    }
    for path, shape in expect.items():
        if f[path].shape != shape:
            out.append(f"{path}: shape {f[path].shape}, expected {shape}")
    for path, width in (("/mesh/tets", 4), ("/mesh/surface_faces", 3), ("/mesh/quadratic_cells", 10)):
        if path in f and (f[path].ndim != 2 or f[path].shape[1] != width):
            out.append(f"{path}: shape {f[path].shape}, expected (k, {width})")
    if f["/nodes/fixed"].ndim != 1:
        out.append(f"/nodes/fixed: shape {f['/nodes/fixed'].shape}, expected (f,)")
    structure = hdf5.attr_str(f["/mesh"].attrs.get("structure"))
    if structure == "tetra" and "/mesh/tets" not in f:
        out.append("/mesh/tets: missing for a tetra structure")
    if out:
        return out
    for path in ("/mesh/points", "/springs/rest_length", "/springs/volume", "/springs/volume_weight",
                 "/springs/cos2", "/nodes/mass", "/springs/fibre_frame"):
        if not np.all(np.isfinite(_arr(f, path))):
            out.append(f"{path}: contains NaN or infinite values")
    if "/mesh/quadratic_cells" in f:
        q = _arr(f, "/mesh/quadratic_cells", np.int64)
        if q.size and (q.min() < 0 or q.max() >= n):
            out.append(f"/mesh/quadratic_cells: indices outside 0..{n - 1}")
    mask = _arr(f, "/nodes/fixed_mask")
    fixed = _arr(f, "/nodes/fixed", np.int64)
    if fixed.size and (fixed.min() < 0 or fixed.max() >= n):
        out.append(f"/nodes/fixed: indices outside 0..{n - 1}")
    elif not np.array_equal(np.flatnonzero(mask), np.unique(fixed)) or np.any(mask > 1):
        out.append("/nodes/fixed and /nodes/fixed_mask disagree")
    return out


def _network(f: h5py.File, *, with_volume: bool = True) -> SpringNetwork:
    """The spring network stored in *f* (with its volume term from ``/volume`` unless *with_volume* is False)."""
    return SpringNetwork(
        points=_arr(f, "/mesh/points", np.float64),
        springs=_arr(f, "/springs/pairs", np.int64),
        rest_length=_arr(f, "/springs/rest_length", np.float64),
        volume=_arr(f, "/springs/volume", np.float64),
        volume_weight=_arr(f, "/springs/volume_weight", np.float64),
        cos2=_arr(f, "/springs/cos2", np.float64),
        mass=_arr(f, "/nodes/mass", np.float64),
        surface_faces=_arr(f, "/mesh/surface_faces", np.int64),
        fixed=_arr(f, "/nodes/fixed", np.int64),
        tets=_arr(f, "/mesh/tets", np.int64) if "/mesh/tets" in f else None,
        node_kind=_arr(f, "/mesh/node_kind", np.uint8),
        structure=hdf5.attr_str(f["/mesh"].attrs.get("structure", "tetra")),
        fibre_frame=_arr(f, "/springs/fibre_frame", np.float64),
        density=float(f["/nodes"].attrs.get("density_kg_m3", 0.0)),
        volume_term=read_volume(f) if with_volume else None,
        quadratic_cells=_arr(f, "/mesh/quadratic_cells", np.int64) if "/mesh/quadratic_cells" in f else None,
    )


def _tables(f: h5py.File) -> StiffnessTables | None:
    return read_tables(f["/tables"]) if "/tables" in f else None


def _effects_disagree(a, b) -> str:
    """Why two MaterialEffects differ beyond the 6 significant digits of TOML text ('' if they agree)."""
    if a.names != b.names:
        return f"effects {a.names} vs {b.names}"
    da, db = a.to_dict(), b.to_dict()
    for name in a.names:
        for key, va in da[name].items():
            vb = db[name].get(key)
            if isinstance(va, (int, float, list)):
                x, y = np.atleast_1d(np.asarray(va, float)), np.atleast_1d(np.asarray(vb, float))
                if x.shape != y.shape or not np.allclose(x, y, rtol=1e-5, atol=0.0):
                    return f"{name}.{key} {va} vs {vb}"
    return ""


def _json(f: h5py.File, path: str) -> dict | None:
    if path not in f:
        return None
    try:
        return json.loads(hdf5.get_text(f[path]))
    except json.JSONDecodeError:
        return None


def _provenance(f: h5py.File) -> Provenance:
    g = f["/provenance"]
    a = g.attrs
    try:
        argv = json.loads(hdf5.get_text(g["command_line"]))
        packages = json.loads(hdf5.get_text(g["packages"]))
        extra = json.loads(hdf5.attr_str(a.get("extra", "{}")) or "{}")
    except json.JSONDecodeError as exc:
        raise AssetError(f"/provenance: damaged JSON ({exc})") from None
    return Provenance(
        input_path=hdf5.attr_str(a.get("input_path")), input_sha256=hdf5.attr_str(a.get("input_sha256")),
        config_toml=hdf5.get_text(g["config_toml"]), command_line=list(argv), utc_time=hdf5.attr_str(a.get("utc_time")),
        host=hdf5.attr_str(a.get("host")), packages=dict(packages), python=hdf5.attr_str(a.get("python")),
        platform=hdf5.attr_str(a.get("platform")), extra=extra,
    )


def _accuracy(f: h5py.File, asset: Asset) -> Accuracy:
    """The asset's :class:`Accuracy` (its records checked by :func:`accuracy_problems` before)."""
    fit, validation = read_records(f)
    tables = asset.tables
    return Accuracy(fit=fit, compensation=compensation_summary(tables), validation=validation,
                    material=_material_name(asset.material_toml), law=tables.default_law if tables else "",
                    volume_term=asset.network.volume_term is not None)


# -- public API -----------------------------------------------------------------------------

def read_asset(path: str | os.PathLike, *, verify: bool = True) -> Asset:
    """Read an asset written by :func:`~esmm.pipeline.asset.write.write_asset`.

    Parameters
    ----------
    path
        The ``.h5`` file.
    verify : bool
        Check every dataset's SHA-256 and the root checksum (default; costs
        one pass over the data). The file header's hash (docs/reference/asset-format.md)
        is checked either way: it keeps libhdf5 away from damaged bytes.

    Raises
    ------
    AssetError
        Missing, truncated, not HDF5, not an esmm asset, a newer schema,
        tampered with or inconsistent; the message names the first problem.
    """
    p = Path(path)
    f = _open(p)
    try:
        with f:
            root = _root_problems(f)
            if root:  # the message carries its own advice
                raise AssetError(f"{p}: {root[0]}")
            probs = _schema_problems(f)[0]
            if not probs and verify:
                probs = _integrity_problems(f)
            if not probs:
                probs = _shape_problems(f)
            if not probs:
                probs = volume_problems(f) + accuracy_problems(f)
            if probs:
                more = f" (and {len(probs) - 1} more; run 'esmm info' to list them)" if len(probs) > 1 else ""
                raise AssetError(f"{p}: {probs[0]}{more}; {ADVICE}")
            net = _network(f)
            net_probs = net.problems()
            if net_probs:
                raise AssetError(f"{p}: {net_probs[0]}; {ADVICE}")
            text = hdf5.get_text(f["/material/toml"]) if "/material/toml" in f else ""
            quality = _json(f, "/quality/report")
            passes = f["/quality"].attrs.get("passes") if "/quality" in f else None
            asset = Asset(
                path=p, network=net, material=None, material_toml=text, tables=_tables(f), effects=read_effects(f),
                quality=quality, quality_passes=None if passes is None else bool(passes),
                cleaning=_json(f, "/cleaning/report"), provenance=_provenance(f),
                fixed_region=hdf5.attr_str(f["/nodes"].attrs.get("fixed_region", "")),
                schema_version=hdf5.attr_int(f.attrs.get("esmm_version")),
                attrs={k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()},
            )
            asset.accuracy = _accuracy(f, asset)
    except _DAMAGE as exc:
        if not _is_damage(exc):
            raise
        raise _damaged(p, exc) from None
    try:
        asset.material = material_from_toml(text)
    except Exception as exc:  # noqa: BLE001 - the stored text is kept; say why it could not be parsed
        raise AssetError(f"{p}: /material/toml cannot be read as a material ({exc}); {ADVICE}") from None
    if asset.effects is None and asset.material is not None:
        try:
            asset.effects = storable_effects(material_effects(asset.material))[0]
        except EsmmError as exc:
            raise AssetError(f"{p}: /material/toml has unreadable [material.effects] ({exc}); {ADVICE}") from None
    return asset


def _effects_problems(f: h5py.File) -> list[str]:
    """/material/effects readable, in range, and the same as the material TOML's [material.effects]."""
    if "/material/effects" not in f:
        return []
    try:
        fx = read_effects(f)
    except EsmmError as exc:
        return [f"/material/effects: {exc}"]
    if not fx:
        return ["/material/effects: the group holds no effect"]
    if "/material/toml" not in f:
        return []
    try:
        text_fx = storable_effects(material_effects(material_from_toml(hdf5.get_text(f["/material/toml"]))))[0]
    except Exception as exc:  # noqa: BLE001 - any parse failure of the stored text is a problem to report
        return [f"/material/toml: cannot be read with its effects ({exc})"]
    if text_fx is None:
        return ["/material/effects: the material TOML has no [material.effects] table"]
    why = _effects_disagree(fx, text_fx)
    return [f"/material/effects disagrees with /material/toml ({why})"] if why else []


def validate_asset(path: str | os.PathLike) -> list[str]:
    """Every problem of an asset file, one line each (empty list: valid).

    Checks the schema (types, versions, required groups and datasets, units),
    integrity (per-dataset SHA-256, root checksum), shapes, NaNs, index
    ranges, positive tet volumes, ``i < j`` springs inside the node range,
    positive masses, ``cos2`` rows summing to 1, the stiffness tables and the
    XDMF sidecar when present.
    """
    p = Path(path)
    try:
        f = _open(p)
    except AssetError as exc:
        return [str(exc)]
    problems: list[str] = []
    try:
        with f:
            problems += _root_problems(f)
            if problems:
                return problems
            schema, fatal = _schema_problems(f)
            problems += schema
            problems += _integrity_problems(f)
            if fatal:
                return problems
            shapes = _shape_problems(f)
            problems += shapes
            if shapes:
                return problems
            problems += _network(f, with_volume=False).problems()
            if "/tables" in f:
                try:
                    _tables(f)
                except EsmmError as exc:
                    problems.append(f"/tables: {exc}")
            if "/provenance" in f:
                try:
                    _provenance(f)
                except AssetError as exc:
                    problems.append(str(exc))
            problems += _effects_problems(f)
            problems += volume_problems(f)
            problems += accuracy_problems(f)
    except _DAMAGE as exc:
        if not _is_damage(exc):
            raise
        problems.append(" ".join(f"damaged asset ({type(exc).__name__}: {exc})".split())[:300])
        return problems
    for side in sidecar_paths(p).values():
        if side.exists():
            problems += check_sidecar(side)
    return problems
