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
from ..network.tables import StiffnessTables
from . import hdf5
from .accuracy import write_fit
from .material import write_material
from .provenance import Provenance, collect_provenance, utc_now
from .schema import ASSET_TYPE, ASSET_VERSION, GROUPS
from .tables import write_tables
from .volume import write_volume
from .xdmf import dtype_for_indices, sidecar_paths, xdmf_texts

VOLUME_RULES = {
    "tetra": "V_ij = sum over the tets t containing edge ij of V_t / 6 (sum of V_ij = mesh volume)",
    "skeleton": "V_ij = V * L0_ij**p / sum_k L0_k**p (p = weight exponent; sum of V_ij = organ volume)",
}


def _report_group(f: h5py.File, name: str, report, summary_keys=(), floors: dict | None = None) -> None:
    g = hdf5.typed_group(f, name, *GROUPS["/" + name][:2])
    text = hdf5.to_json(report)
    hdf5.put_text(g, "report", text, description=f"the {name} report as JSON")
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
    g = hdf5.typed_group(f, "provenance", *GROUPS["/provenance"][:2])
    g.attrs["input_path"] = prov.input_path
    g.attrs["input_sha256"] = prov.input_sha256
    g.attrs["utc_time"] = prov.utc_time or utc_now()
    g.attrs["host"] = prov.host
    g.attrs["python"] = prov.python
    g.attrs["platform"] = prov.platform
    g.attrs["esmm_package_version"] = prov.packages.get("esmm", "")
    g.attrs["extra"] = hdf5.to_json(prov.extra)
    hdf5.put_text(g, "config_toml", prov.config_toml, description="the full prepare configuration (TOML)")
    hdf5.put_text(g, "command_line", json.dumps(prov.command_line),
                 description="argv of the command that made this asset (JSON list)")
    hdf5.put_text(g, "packages", json.dumps(prov.packages, sort_keys=True),
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

    g = hdf5.typed_group(f, "mesh", *GROUPS["/mesh"][:2])
    g.attrs["structure"] = net.structure
    hdf5.put(g, "points", net.points, "m", dtype=np.float64, description="node positions at rest")
    if net.tets is not None:
        hdf5.put(g, "tets", net.tets, "index", dtype=idx, description="positively oriented tetrahedra")
    if net.quadratic_cells is not None:
        hdf5.put(g, "quadratic_cells", net.quadratic_cells, "index", dtype=idx,
                 description="the tetrahedra the tets were split from, as 10-node cells on these nodes "
                             "(vertices, then the middles of edges 01 12 20 03 13 23)")
    hdf5.put(g, "surface_faces", net.surface_faces, "index", dtype=idx,
            description="boundary triangles, counter-clockwise seen from outside")
    ds = hdf5.put(g, "node_kind", net.node_kind, "1", dtype=np.uint8, description="node kind code")
    ds.attrs["codes"] = json.dumps({str(k): v for k, v in NODE_KIND_NAMES.items()})

    g = hdf5.typed_group(f, "springs", *GROUPS["/springs"][:2])
    g.attrs["volume_rule"] = VOLUME_RULES.get(net.structure, "")
    g.attrs["stiffness"] = "k_ij = c * v_ij * sum_d cos2_d * mu_e_d(lam) (see /tables)"
    hdf5.put(g, "pairs", net.springs, "index", dtype=idx, description="node pairs i < j, sorted by (i, j)")
    hdf5.put(g, "rest_length", net.rest_length, "m", dtype=np.float64, description="L0")
    hdf5.put(g, "volume", net.volume, "m3", dtype=np.float64, description="V_ij, tissue volume of the spring")
    hdf5.put(g, "volume_weight", net.volume_weight, "m", dtype=np.float64, description="v_ij = V_ij / L0^2")
    hdf5.put(g, "cos2", net.cos2, "1", dtype=np.float64,
            description="squared direction cosines along the fibre axes (rows sum to 1)")
    hdf5.put(g, "fibre_frame", net.fibre_frame, "1", dtype=np.float64,
            description="rows: the fibre axes x, y, z in mesh coordinates (orthonormal)")
    hdf5.put(g, "affine_elasticity", affine_elasticity(net), "1", dtype=np.float64,
            description="affine (unrelaxed) elasticity tensor of the network per unit mu_e, Voigt "
                        "xx yy zz yz xz xy in mesh coordinates: C = sum V_ij n n n n / V")

    g = hdf5.typed_group(f, "nodes", *GROUPS["/nodes"][:2])
    g.attrs["density_kg_m3"] = net.density
    g.attrs["fixed_region"] = fixed_region
    hdf5.put(g, "mass", net.mass, "kg", dtype=np.float64, description="lumped node masses")
    hdf5.put(g, "fixed", net.fixed, "index", dtype=idx, description="fixed node indices, sorted")
    hdf5.put(g, "fixed_mask", net.fixed_mask(), "1", dtype=np.uint8, description="1 on fixed nodes")


def _write_groups(f: h5py.File, network: SpringNetwork, *, material, tables: StiffnessTables | None, quality,
                  cleaning, quality_floors: dict | None, fixed_region: str, fit: dict | None) -> None:
    """The network and each optional group that is given (material, tables, volume, reports, the fit's
    error), in file order."""
    _write_core(f, network, fixed_region)
    if material is not None:
        write_material(f, material)
    if tables is not None:
        write_tables(f.create_group("tables"), tables)
    if network.volume_term is not None:
        write_volume(f, network.volume_term, network.points, network.tets)
    if quality is not None:
        _report_group(f, "quality", quality, ("min_dihedral_deg", "n_tets", "n_nodes", "volume"),
                      floors=quality_floors)
    if cleaning is not None:
        _report_group(f, "cleaning", cleaning, ("volume_before", "volume_after", "bodies_found",
                                                "relative_volume_change"))
    if fit is not None:
        write_fit(f, fit)


def _write_sidecars(path: Path, texts: dict[str, str]) -> None:
    """Write the XDMF sidecars (each atomically) and remove any other sidecar of *path* an earlier
    asset of that name left (it would describe arrays this asset does not have)."""
    for key, side in sidecar_paths(path).items():
        if key in texts:
            with atomic_path(side) as tmp:
                tmp.write_text(texts[key], encoding="utf-8")
        elif texts and side.is_file():
            side.unlink()


def write_asset(path: str | os.PathLike, network: SpringNetwork, *, material=None,
                tables: StiffnessTables | None = None,
                quality=None, cleaning=None, provenance: Provenance | None = None,
                quality_floors: dict | None = None, fixed_region: str = "", xdmf: bool = True,
                fit: dict | None = None) -> Path:
    """Write *network* and what goes with it to an HDF5 asset (docs/reference/asset-format.md).

    The file is written to a temporary name and renamed when complete; the
    XDMF sidecars (``<name>.xdmf``, the mesh, and ``<name>.springs.xdmf``,
    ``<name>.surface.xdmf``; :mod:`.xdmf`) likewise. Every dataset gets a ``units`` and a
    ``sha256`` attribute and the root a checksum over all attributes, and the
    file starts with a 512-byte user block holding the SHA-256 and length of
    every later byte, so that :func:`~esmm.pipeline.asset.read.read_asset`
    detects any later change (the file hash before libhdf5 parses anything).

    Parameters
    ----------
    path
        Target ``.h5`` file (folders are created).
    network : SpringNetwork
        Checked with :meth:`SpringNetwork.validate` first. Its ``volume_term``
        (when not None) is written as ``/volume`` (asset/volume.py).
    material
        A ``Material`` (or its TOML text) for ``/material``; None to omit.
    tables : StiffnessTables, optional
        For ``/tables`` (:func:`~esmm.pipeline.asset.tables.write_tables`); None to omit.
    quality, cleaning
        The mesh quality and cleaning reports (dataclasses or dicts); None to omit.
    quality_floors : dict, optional
        The floors the quality report was judged against (default: its own defaults).
    provenance : Provenance, optional
        Default: collected for this process without an input file.
    fixed_region : str
        Description of how the fixed nodes were chosen.
    xdmf : bool
        Also write the ParaView (and meshio) sidecars.
    fit : dict, optional
        The material fit's error (:func:`~esmm.pipeline.asset.accuracy.fit_record`) for
        ``/accuracy/fit``; None to omit.

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
    if network.volume_term is not None and network.tets is None:
        raise InputError("network: a volume term needs tetrahedra (the skeleton structure has none)")
    prov = provenance if provenance is not None else collect_provenance()
    try:
        with atomic_path(path) as tmp:
            # The user block carries the file header (hash of every later byte), written by
            # seal() when the file is closed, before the rename (docs/reference/asset-format.md).
            with hdf5.create(tmp) as f:
                _write_groups(f, network, material=material, tables=tables, quality=quality, cleaning=cleaning,
                              quality_floors=quality_floors, fixed_region=fixed_region, fit=fit)
                _write_provenance(f, prov)
                hdf5.seal(f)
                texts = xdmf_texts(f, path.name) if xdmf else {}
            _write_sidecars(path, texts)
    except OSError as exc:
        raise AssetError(f"{path}: cannot write the asset ({exc.strerror or exc}); check the folder "
                         f"is writable and has space") from None
    return path
