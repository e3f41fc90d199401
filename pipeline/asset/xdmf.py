"""The XDMF sidecars of an asset: let ParaView (and VTK, meshio) open the HDF5 arrays.

One grid per file, so that meshio (whose XDMF reader takes one grid per file) reads
each, and ParaView opens each (File > Open, "Xdmf Reader"):

* ``asset.xdmf`` - the mesh: the tetrahedra (``structure="tetra"``), or the springs
  as line cells for the skeleton structure (which has no tetrahedra), with the node
  fields ``mass``, ``fixed``, ``node_kind``; ``meshio.read("asset.xdmf")`` gives it;
* ``asset.springs.xdmf`` - one line cell per spring with the cell fields
  ``rest_length``, ``volume``, ``volume_weight`` and the node fields (tetra only: for
  the skeleton this is ``asset.xdmf``);
* ``asset.surface.xdmf`` - the boundary triangles with the node fields.

XDMF 3 syntax, also read by the XDMF 2 reader of VTK/ParaView. Data are referenced,
never copied, by the file name of the ``.h5`` relative to the sidecar, so the files
must stay together.
"""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import h5py
import numpy as np

_NUMBER = {"f": "Float", "i": "Int", "u": "UInt"}

NODE_FIELDS = (("mass", "/nodes/mass"), ("fixed", "/nodes/fixed_mask"), ("node_kind", "/mesh/node_kind"))
SPRING_FIELDS = (("rest_length", "/springs/rest_length"), ("volume", "/springs/volume"),
                 ("volume_weight", "/springs/volume_weight"))


def xdmf_number_type(dtype) -> tuple[str, int]:
    """XDMF ``(NumberType, Precision)`` of a numpy dtype."""
    dt = np.dtype(dtype)
    if dt.kind not in _NUMBER:
        raise ValueError(f"dtype {dt} cannot be described in XDMF")
    # 1-byte integers are written as UInt/Int with Precision 1 (not UChar/Char): both
    # VTK's XDMF reader and meshio read that spelling.
    return _NUMBER[dt.kind], dt.itemsize


def _item(f: h5py.File, h5name: str, path: str, indent: str) -> str:
    ds = f[path]
    number, precision = xdmf_number_type(ds.dtype)
    dims = " ".join(str(d) for d in ds.shape)
    return (f'{indent}<DataItem Dimensions="{dims}" NumberType="{number}" '
            f'Precision="{precision}" Format="HDF">{escape(h5name)}:{path}</DataItem>\n')


def _attribute(f, h5name, name, path, center, indent) -> str:
    return (f'{indent}<Attribute Name={quoteattr(name)} AttributeType="Scalar" Center="{center}">\n'
            + _item(f, h5name, path, indent + "  ") + f"{indent}</Attribute>\n")


def _grid(f, h5name, name, topo_type, topo_path, per, cell_fields) -> str:
    n_cells = f[topo_path].shape[0]
    out = [f'    <Grid Name="{name}" GridType="Uniform">\n',
           f'      <Topology TopologyType="{topo_type}" NumberOfElements="{n_cells}" NodesPerElement="{per}">\n',
           _item(f, h5name, topo_path, "        "),
           "      </Topology>\n",
           '      <Geometry GeometryType="XYZ">\n',
           _item(f, h5name, "/mesh/points", "        "),
           "      </Geometry>\n"]
    for fname, path in NODE_FIELDS:
        if path in f:
            out.append(_attribute(f, h5name, fname, path, "Node", "      "))
    for fname, path in cell_fields:
        if path in f:
            out.append(_attribute(f, h5name, fname, path, "Cell", "      "))
    out.append("    </Grid>\n")
    return "".join(out)


def xdmf_texts(f: h5py.File, h5name: str) -> dict[str, str]:
    """The XDMF documents of the open asset *f*, whose file will be called *h5name*: suffix -> text.

    Suffixes as :func:`sidecar_paths` names the files: ``""`` (the mesh), ``"springs"``, ``"surface"``.
    """
    grids = {}
    springs = _grid(f, h5name, "springs", "Polyline", "/springs/pairs", 2, SPRING_FIELDS)
    if "/mesh/tets" in f and f["/mesh/tets"].shape[0]:
        grids[""] = _grid(f, h5name, "tetrahedra", "Tetrahedron", "/mesh/tets", 4, ())
        grids["springs"] = springs
    else:
        grids[""] = springs
    if "/mesh/surface_faces" in f and f["/mesh/surface_faces"].shape[0]:
        grids["surface"] = _grid(f, h5name, "surface", "Triangle", "/mesh/surface_faces", 3, ())
    return {k: _document(grid, h5name) for k, grid in grids.items()}


def _document(grid: str, h5name: str) -> str:
    return ('<?xml version="1.0" encoding="utf-8"?>\n'
            '<!-- esmm asset sidecar: open this file in ParaView; the data stay in '
            f'{escape(h5name)} (keep the files together). -->\n'
            '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">\n'
            '  <Domain>\n' + grid + '  </Domain>\n</Xdmf>\n')


def sidecar_path(h5_path: str | os.PathLike) -> Path:
    """``asset.h5`` -> ``asset.xdmf`` (same folder): the mesh's sidecar."""
    p = Path(h5_path)
    return p.with_suffix(".xdmf")


def sidecar_paths(h5_path: str | os.PathLike) -> dict[str, Path]:
    """Every sidecar an asset may have: suffix of :func:`xdmf_texts` -> ``asset.xdmf``,
    ``asset.springs.xdmf``, ``asset.surface.xdmf``."""
    main = sidecar_path(h5_path)
    return {"": main, **{k: main.with_name(f"{main.stem}.{k}.xdmf") for k in ("springs", "surface")}}


def referenced_datasets(xdmf: str | os.PathLike) -> list[tuple[str, str, tuple[int, ...], str, int]]:
    """Every HDF reference of a sidecar: (h5 file, dataset path, dimensions, number type, precision)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(xdmf).getroot()
    out = []
    for item in root.iter("DataItem"):
        ref = (item.text or "").strip()
        h5, _, path = ref.partition(":")
        dims = tuple(int(d) for d in item.attrib.get("Dimensions", "").split())
        out.append((h5, path, dims, item.attrib.get("NumberType", "Float"), int(item.attrib.get("Precision", "4"))))
    return out


def check_sidecar(xdmf: str | os.PathLike) -> list[str]:
    """Problems of a sidecar: unreadable XML, missing file or dataset, wrong shape or type."""
    import xml.etree.ElementTree as ET

    xdmf = Path(xdmf)
    try:
        refs = referenced_datasets(xdmf)
    except (OSError, ET.ParseError) as exc:
        return [f"{xdmf.name}: not readable XML ({exc})"]
    problems = []
    opened: dict[str, h5py.File] = {}
    try:
        for h5, path, dims, number, precision in refs:
            target = xdmf.parent / h5
            if h5 not in opened:
                try:
                    opened[h5] = h5py.File(target, "r")
                except OSError as exc:
                    problems.append(f"{xdmf.name}: refers to {h5}, which cannot be opened ({exc})")
                    opened[h5] = None  # type: ignore[assignment]
            f = opened[h5]
            if f is None:
                continue
            if path not in f:
                problems.append(f"{xdmf.name}: refers to {h5}:{path}, which does not exist")
                continue
            ds = f[path]
            if tuple(ds.shape) != dims:
                problems.append(f"{xdmf.name}: {path} has shape {ds.shape}, the sidecar says {dims}")
            try:
                expected = xdmf_number_type(ds.dtype)
            except ValueError:
                expected = (str(ds.dtype), ds.dtype.itemsize)
            if expected != (number, precision):
                problems.append(f"{xdmf.name}: {path} is {ds.dtype}, the sidecar says {number} {precision}")
    finally:
        for f in opened.values():
            if f is not None:
                f.close()
    return problems


def dtype_for_indices(n: int) -> np.dtype:
    """int32 when the indices fit (they always do below 2**31 nodes), else int64."""
    return np.dtype(np.int32) if n < 2**31 - 1 else np.dtype(np.int64)
