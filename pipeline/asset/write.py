"""Writing an asset: one HDF5 file (+ an XDMF sidecar), atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from ..atomicio import atomic_path
from ..errors import AssetError, InputError
from ..network.springs import NODE_KIND_NAMES, SpringNetwork, affine_elasticity
from . import _h5
from .provenance import Provenance, collect_provenance, utc_now
from .schema import ASSET_TYPE, ASSET_VERSION, GROUPS
from .xdmf import dtype_for_indices, sidecar_path, xdmf_text

VOLUME_RULES = {
    "tetra": "V_ij = sum over the tets t containing edge ij of V_t / 6 (sum of V_ij = mesh volume)",
    "skeleton": "V_ij = V * L0_ij**p / sum_k L0_k**p (p = weight exponent; sum of V_ij = organ volume)",
}


def material_text(material) -> tuple[str, dict[str, str]]:
    """TOML text and a few descriptive attributes of a material (object or TOML string)."""
    if material is None:
        return "", {}
    if isinstance(material, str):
        return material, {}
    text = ""
    for attr in ("to_toml_string", "to_toml", "dumps"):
        fn = getattr(material, attr, None)
        if callable(fn):
            try:
                out = fn()
            except TypeError:
                continue
            if isinstance(out, str):
                text = out
                break
    attrs = {}
    for key in ("name", "model"):
        v = getattr(material, key, None)
        if v is not None:
            attrs[key] = v if isinstance(v, str) else getattr(v, "name", str(v))
    return text, attrs


def _param_units(material) -> dict[str, str]:
    """Parameter name -> SI unit ("Pa" for stress-like parameters, "1" otherwise)."""
    try:
        specs = material.model_obj.parameters
    except (AttributeError, Exception):  # noqa: BLE001 - a duck-typed material without specs
        return {}
    return {p.name: ("Pa" if getattr(p, "kind", "") == "stress" else "1") for p in specs}


def _write_material(f: h5py.File, material) -> None:
    if isinstance(material, str):
        from .read import _material

        parsed = _material(material)  # validates the text (ConfigError naming the key)
        if parsed is not None:
            attrs = {"name": parsed.name, "model": parsed.model}
            text, material = material, parsed
        else:
            text, attrs = material, {}
    else:
        text, attrs = material_text(material)
    if not text:
        raise InputError("material: cannot serialise it as TOML; pass a Material (or its TOML text)")
    g = _h5.typed_group(f, "material", *GROUPS["/material"][:2])
    for k, v in attrs.items():
        g.attrs[k] = str(v)
    _h5.put_text(g, "toml", text, description="the Material as TOML text (esmm material format)")
    _write_effects(g, material)
    params = getattr(material, "params", None)
    if not isinstance(params, dict) or not params:
        return
    units = _param_units(material)
    sets = [("parameters", params)]
    for d, over in sorted((getattr(material, "directions", None) or {}).items()):
        if over:
            sets.append((f"directions/{d}", over))
    for sub, values in sets:
        pg = g.require_group(sub)
        for grp in (pg, pg.parent):
            if grp.name != g.name and "esmm_type" not in grp.attrs:
                grp.attrs["esmm_type"] = "material_parameters"
                grp.attrs["esmm_version"] = 1
        for name, value in values.items():
            try:
                val = float(value)
            except (TypeError, ValueError):
                continue
            _h5.put(pg, name, val, units.get(name, "1"), dtype=np.float64,
                    description="SI value (stress-like parameters in Pa)")


def material_effects(material):
    """The material effects of a ``Material`` (``metadata["effects"]``, the ``[material.effects]``
    table of a discovery's params.toml) as a ``MaterialEffects``, or None when it has none.

    Raises
    ------
    ConfigError
        The table is malformed (one line naming the effect and key).
    """
    table = (getattr(material, "metadata", None) or {}).get("effects") if material is not None else None
    if not table:
        return None
    from ..materials.effects import MaterialEffects

    fx = MaterialEffects.from_toml_table(table, stress_unit=getattr(material, "stress_unit", None),
                                         where=f"{getattr(material, 'name', '') or 'material'}: [material.effects]")
    return fx if fx else None


def _write_effects(g: h5py.Group, material) -> None:
    """``/material/effects``: the kept material effects in SI (docs/asset-format.md)."""
    fx = material_effects(material)
    if fx is None:
        return
    d = fx.to_dict()
    eg = _h5.typed_group(g, "effects", *GROUPS["/material/effects"][:2])
    eg.attrs["schema"] = d["schema"]
    eg.attrs["composition"] = d["composition"]
    eg.attrs["names"] = json.dumps(fx.names)
    eg.attrs["intervals"] = json.dumps(d.get("intervals", {}), sort_keys=True)
    if fx.viscoelastic is not None:
        v = fx.viscoelastic
        sg = _h5.typed_group(eg, "viscoelastic", *GROUPS["/material/effects/viscoelastic"][:2])
        sg.attrs["model"] = "QLV: F = g_inf P + sum_i g_i h_i, G(t) = g_inf + sum_i g_i exp(-t/tau_i)"
        sg.attrs["reference"] = "instantaneous"
        sg.attrs["g_inf"] = float(v.g_inf)
        _h5.put(sg, "g", np.asarray(v.g, float), "1", dtype=np.float64,
                description="Prony weights, sorted by tau; g_inf = 1 - sum(g)")
        _h5.put(sg, "tau", np.asarray(v.tau, float), "s", dtype=np.float64, description="relaxation times")
    if fx.mullins is not None:
        m = fx.mullins
        sg = _h5.typed_group(eg, "mullins", *GROUPS["/material/effects/mullins"][:2])
        sg.attrs["model"] = "Ogden-Roxburgh: eta = 1 - (1/r) erf((W_max - W) / (m + beta W_max))"
        _h5.put(sg, "r", float(m.r), "1", dtype=np.float64, description="largest softening is 1/r")
        _h5.put(sg, "m", float(m.m), "Pa", dtype=np.float64, description="energy scale of the softening")
        _h5.put(sg, "beta", float(m.beta), "1", dtype=np.float64, description="growth of the scale with W_max")
    if fx.damage is not None:
        da = fx.damage
        sg = _h5.typed_group(eg, "damage", *GROUPS["/material/effects/damage"][:2])
        sg.attrs["model"] = "Weibull: 1 - D = exp(-(((xi_max - onset)_+) / scale)^shape)"
        _h5.put(sg, "onset", float(da.onset), "1", dtype=np.float64,
                description="uniaxial-equivalent stretch where damage starts")
        _h5.put(sg, "scale", float(da.scale), "1", dtype=np.float64, description="stretch scale")
        _h5.put(sg, "shape", float(da.shape), "1", dtype=np.float64, description="Weibull shape")


def _report_group(f: h5py.File, name: str, report, summary_keys=(), floors: dict | None = None) -> None:
    g = _h5.typed_group(f, name, *GROUPS["/" + name][:2])
    text = _h5.to_json(report)
    _h5.put_text(g, "report", text, description=f"the {name} report as JSON")
    data = json.loads(text)
    if isinstance(data, dict):
        for k in summary_keys:
            v = data.get(k)
            if isinstance(v, (int, float, str, bool)):
                g.attrs[k] = v
    if name == "quality":
        passes = getattr(report, "passes", None)
        if callable(passes):
            try:
                ok, problems = passes(floors) if floors is not None else passes()
            except Exception as exc:  # noqa: BLE001 - a report that cannot judge itself is recorded as such
                ok, problems = False, [f"passes() failed: {exc}"]
            g.attrs["passes"] = bool(ok)
            g.attrs["problems"] = json.dumps(list(problems))
            if floors is not None:
                g.attrs["floors"] = json.dumps(floors, sort_keys=True)


def _write_provenance(f: h5py.File, prov: Provenance) -> None:
    g = _h5.typed_group(f, "provenance", *GROUPS["/provenance"][:2])
    g.attrs["input_path"] = prov.input_path
    g.attrs["input_sha256"] = prov.input_sha256
    g.attrs["utc_time"] = prov.utc_time or utc_now()
    g.attrs["host"] = prov.host
    g.attrs["python"] = prov.python
    g.attrs["platform"] = prov.platform
    g.attrs["esmm_package_version"] = prov.packages.get("esmm", "")
    g.attrs["extra"] = _h5.to_json(prov.extra)
    _h5.put_text(g, "config_toml", prov.config_toml, description="the full prepare configuration (TOML)")
    _h5.put_text(g, "command_line", json.dumps(prov.command_line),
                 description="argv of the command that made this asset (JSON list)")
    _h5.put_text(g, "packages", json.dumps(prov.packages, sort_keys=True),
                 description="versions of the software that made this asset (JSON object)")


def _write_core(f: h5py.File, net: SpringNetwork, fixed_region: str) -> None:
    n = net.n_nodes
    idx = dtype_for_indices(n)
    f.attrs["esmm_type"] = ASSET_TYPE
    f.attrs["esmm_version"] = ASSET_VERSION
    f.attrs["structure"] = net.structure
    f.attrs["created_utc"] = utc_now()
    f.attrs["n_nodes"] = n
    f.attrs["n_springs"] = net.n_springs
    f.attrs["n_tets"] = net.n_tets
    f.attrs["volume_m3"] = net.total_volume()
    f.attrs["mass_kg"] = net.total_mass()

    g = _h5.typed_group(f, "mesh", *GROUPS["/mesh"][:2])
    g.attrs["structure"] = net.structure
    _h5.put(g, "points", net.points, "m", dtype=np.float64, description="node positions at rest")
    if net.tets is not None:
        _h5.put(g, "tets", net.tets, "index", dtype=idx, description="positively oriented tetrahedra")
    _h5.put(g, "surface_faces", net.surface_faces, "index", dtype=idx,
            description="boundary triangles, counter-clockwise seen from outside")
    ds = _h5.put(g, "node_kind", net.node_kind, "1", dtype=np.uint8, description="node kind code")
    ds.attrs["codes"] = json.dumps({str(k): v for k, v in NODE_KIND_NAMES.items()})

    g = _h5.typed_group(f, "springs", *GROUPS["/springs"][:2])
    g.attrs["volume_rule"] = VOLUME_RULES.get(net.structure, "")
    g.attrs["stiffness"] = "k_ij = c * v_ij * sum_d cos2_d * mu_e_d(lam) (see /tables)"
    _h5.put(g, "pairs", net.springs, "index", dtype=idx, description="node pairs i < j, sorted by (i, j)")
    _h5.put(g, "rest_length", net.rest_length, "m", dtype=np.float64, description="L0")
    _h5.put(g, "volume", net.volume, "m3", dtype=np.float64, description="V_ij, tissue volume of the spring")
    _h5.put(g, "volume_weight", net.volume_weight, "m", dtype=np.float64, description="v_ij = V_ij / L0^2")
    _h5.put(g, "cos2", net.cos2, "1", dtype=np.float64,
            description="squared direction cosines along the fibre axes (rows sum to 1)")
    _h5.put(g, "fibre_frame", net.fibre_frame, "1", dtype=np.float64,
            description="rows: the fibre axes x, y, z in mesh coordinates (orthonormal)")
    _h5.put(g, "affine_elasticity", affine_elasticity(net), "1", dtype=np.float64,
            description="affine (unrelaxed) elasticity tensor of the network per unit mu_e, Voigt "
                        "xx yy zz yz xz xy in mesh coordinates: C = sum V_ij n n n n / V")

    g = _h5.typed_group(f, "nodes", *GROUPS["/nodes"][:2])
    g.attrs["density_kg_m3"] = net.density
    g.attrs["fixed_region"] = fixed_region
    _h5.put(g, "mass", net.mass, "kg", dtype=np.float64, description="lumped node masses")
    _h5.put(g, "fixed", net.fixed, "index", dtype=idx, description="fixed node indices, sorted")
    _h5.put(g, "fixed_mask", net.fixed_mask(), "1", dtype=np.uint8, description="1 on fixed nodes")


def write_asset(path: str | os.PathLike, network: SpringNetwork, *, material=None, tables=None,
                quality=None, cleaning=None, provenance: Provenance | None = None,
                quality_floors: dict | None = None, fixed_region: str = "", xdmf: bool = True) -> Path:
    """Write *network* and what goes with it to an HDF5 asset (docs/asset-format.md).

    The file is written to a temporary name and renamed when complete; the
    XDMF sidecar ``<name>.xdmf`` likewise. Every dataset gets a ``units`` and a
    ``sha256`` attribute and the root a checksum over all attributes, and the
    file starts with a 512-byte user block holding the SHA-256 and length of
    every later byte, so that :func:`~esmm.pipeline.asset.read.read_asset`
    detects any later change (the file hash before libhdf5 parses anything).

    Parameters
    ----------
    path
        Target ``.h5`` file (folders are created).
    network : SpringNetwork
        Checked with :meth:`SpringNetwork.validate` first.
    material
        A ``Material`` (or its TOML text) for ``/material``; None to omit.
    tables
        :class:`~esmm.pipeline.network.tables.StiffnessTables` for ``/tables``
        (written by its ``to_hdf5``); None to omit.
    quality, cleaning
        The mesh quality and cleaning reports (dataclasses or dicts); None to omit.
    quality_floors : dict, optional
        The floors the quality report was judged against (default: its own defaults).
    provenance : Provenance, optional
        Default: collected for this process without an input file.
    fixed_region : str
        Description of how the fixed nodes were chosen.
    xdmf : bool
        Also write the ParaView sidecar.

    Returns
    -------
    Path
        The asset path.

    Raises
    ------
    InputError
        The network is invalid or the material cannot be serialised.
    AssetError
        The file cannot be written (folder not writable, disk full).
    """
    path = Path(path)
    if path.suffix.lower() not in (".h5", ".hdf5"):
        raise InputError(f"{path}: an asset file name must end in .h5 (or .hdf5)")
    network.validate()
    prov = provenance if provenance is not None else collect_provenance()
    try:
        with atomic_path(path) as tmp:
            # The user block carries the file header (hash of every later byte), written by
            # seal() when the file is closed, before the rename (docs/asset-format.md).
            with _h5.create(tmp) as f:
                _write_core(f, network, fixed_region)
                if material is not None:
                    _write_material(f, material)
                if tables is not None:
                    g = f.create_group("tables")
                    tables.to_hdf5(g)
                    if "esmm_type" not in g.attrs or "esmm_version" not in g.attrs:
                        raise AssetError("tables: StiffnessTables.to_hdf5 did not set esmm_type/esmm_version")
                if quality is not None:
                    _report_group(f, "quality", quality, ("min_dihedral_deg", "n_tets", "n_nodes", "volume"),
                                  floors=quality_floors)
                if cleaning is not None:
                    _report_group(f, "cleaning", cleaning, ("volume_before", "volume_after", "bodies_found",
                                                            "relative_volume_change"))
                _write_provenance(f, prov)
                _h5.seal(f)
                text = xdmf_text(f, path.name) if xdmf else None
            if text is not None:
                with atomic_path(sidecar_path(path)) as tmp_x:
                    tmp_x.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise AssetError(f"{path}: cannot write the asset ({exc.strerror or exc}); check the folder "
                         f"is writable and has space") from None
    return path
