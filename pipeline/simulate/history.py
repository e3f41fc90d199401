"""Displacement history: HDF5 with an XDMF temporal collection beside it.

``history.h5`` layout (SI units; every dataset has a ``units`` attribute)::

    /mesh/points          (n, 3) float64   rest positions [m]
    /mesh/cells           (c, 4) or (c, 3) int64  tets (or surface triangles)
    /mesh/surface         (k, 3) int64     outward surface triangles
    /mesh/fixed           (f,)  int64      fixed nodes
    /time                 (F,)  float64    frame times [s]
    /displacement         (F, n, 3) float32  node displacement from rest [m]
    /position/<k>         (n, 3) float32     node position of frame k [m] (the XDMF geometry)
    /frame_displacement/<k> (n, 3) float32   displacement of frame k [m] (the XDMF attribute)
    /grasper/tip          (F, 3) float64   tip position per frame [m] (NaN when open)
    /grasper/time         (S,)  float64    time of every integration step [s]
    /grasper/force        (S, 3) float64   force of the tissue on the grasper [N]
    /grasper/nodes        (g,)  int64      held nodes
    attrs: esmm_type = "simulation_history", esmm_version, dt, law, scene, asset, ...

``history.xdmf`` is an XDMF 3 temporal collection: one grid per frame whose
geometry is ``position/<k>`` and which carries ``frame_displacement/<k>`` as a
node vector, so ParaView (XDMF reader) replays the deformation directly and
meshio's time-series reader (``meshio.xdmf.TimeSeriesReader``) reads it: the mesh
of the first frame (its positions, so the rest shape is those points minus the
first frame's displacement), then each frame's time and displacement. Every
piece of data is a plain dataset: VTK's XDMF reader evaluates a Function
``points + displacement`` or a HyperSlab geometry correctly but logs an error for
each frame, and meshio reads neither (hence the per-frame copy of
``displacement``). Both files are written to temporary names and renamed when
complete.
"""

from __future__ import annotations

import json
import sys
from contextlib import ExitStack
from pathlib import Path
from xml.sax.saxutils import escape

import h5py
import numpy as np

from ..atomicio import atomic_path, jsonable
from ..errors import AssetError

ESMM_TYPE = "simulation_history"
ESMM_VERSION = 1


class HistoryWriter:
    """Append frames to ``<stem>.h5``; write ``<stem>.xdmf`` on :meth:`close`.

    Use as a context manager: on an exception nothing is left behind.

    Parameters
    ----------
    path : path-like
        The ``.h5`` file (the ``.xdmf`` goes beside it with the same stem).
    points : ndarray, shape (n, 3)
        Rest positions [m].
    cells : ndarray, shape (c, 4) or (c, 3)
        Tets or triangles for the XDMF topology.
    surface : ndarray, shape (k, 3)
    fixed : ndarray, shape (f,)
    attrs : dict
        Extra root attributes (strings, numbers; dicts are stored as JSON).
    dtype : numpy dtype
        Storage of the displacement (float32 by default).
    """

    def __init__(self, path, *, points, cells, surface, fixed=(), attrs=None, dtype=np.float32):
        self.path = Path(path)
        self.xdmf_path = self.path.with_suffix(".xdmf")
        self.points = np.asarray(points, dtype=np.float64)
        self.cells = np.asarray(cells, dtype=np.int64)
        self.surface = np.asarray(surface, dtype=np.int64).reshape(-1, 3)
        self.fixed = np.asarray(fixed, dtype=np.int64)
        self.attrs = dict(attrs or {})
        self.dtype = np.dtype(dtype)
        self._stack = ExitStack()
        self._h5 = None
        self.n_frames = 0
        self._force_rows = 0

    def __enter__(self) -> HistoryWriter:
        tmp = self._stack.enter_context(atomic_path(self.path))
        self._tmp = tmp
        self._h5 = h5py.File(tmp, "w")
        f = self._h5
        n = self.points.shape[0]
        f.attrs["esmm_type"] = ESMM_TYPE
        f.attrs["esmm_version"] = ESMM_VERSION
        for k, v in self.attrs.items():
            f.attrs[k] = _attr(v)
        m = f.create_group("mesh")
        _ds(m, "points", self.points, "m", "rest positions")
        _ds(m, "cells", self.cells, "1", "tetrahedra" if self.cells.shape[1] == 4 else "triangles")
        _ds(m, "surface", self.surface, "1", "outward surface triangles")
        _ds(m, "fixed", self.fixed, "1", "fixed nodes")
        self._time = f.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
        self._time.attrs["units"] = "s"
        self._disp = f.create_dataset("displacement", shape=(0, n, 3), maxshape=(None, n, 3), dtype=self.dtype,
                                      chunks=(1, n, 3), compression="gzip", compression_opts=1, shuffle=True)
        self._disp.attrs["units"] = "m"
        self._pos = f.create_group("position")
        self._pos.attrs["units"] = "m"
        self._fdisp = f.create_group("frame_displacement")
        self._fdisp.attrs["units"] = "m"
        g = f.create_group("grasper")
        self._tip = g.create_dataset("tip", shape=(0, 3), maxshape=(None, 3), dtype="f8", chunks=(256, 3))
        self._tip.attrs["units"] = "m"
        self._ft = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(65536,),
                                    compression="gzip", compression_opts=1)
        self._ft.attrs["units"] = "s"
        self._ff = g.create_dataset("force", shape=(0, 3), maxshape=(None, 3), dtype="f8", chunks=(65536, 3),
                                    compression="gzip", compression_opts=1)
        self._ff.attrs["units"] = "N"
        self._ff.attrs["description"] = "force of the tissue (and its weight) on the grasper, per step"
        return self

    def add_frame(self, t: float, displacement: np.ndarray, tip=None) -> None:
        """Append one frame at time *t* [s] (displacement (n, 3) [m], tip (3,) or None)."""
        k = self.n_frames
        self._time.resize((k + 1,))
        self._time[k] = t
        self._disp.resize((k + 1,) + self._disp.shape[1:])
        d = displacement.astype(self.dtype, copy=False)
        self._disp[k] = d
        self._pos.create_dataset(f"{k}", data=(self.points + displacement).astype(self.dtype, copy=False),
                                 compression="gzip", compression_opts=1, shuffle=True)
        self._fdisp.create_dataset(f"{k}", data=d, compression="gzip", compression_opts=1, shuffle=True)
        self._tip.resize((k + 1, 3))
        self._tip[k] = np.full(3, np.nan) if tip is None else tip
        self.n_frames = k + 1

    def add_forces(self, times: np.ndarray, forces: np.ndarray) -> None:
        """Append per-step grasper forces (times (s,), forces (s, 3))."""
        m = int(np.asarray(times).shape[0])
        if m == 0:
            return
        r = self._force_rows
        self._ft.resize((r + m,))
        self._ft[r:] = times
        self._ff.resize((r + m, 3))
        self._ff[r:] = forces
        self._force_rows = r + m

    def set_attrs(self, **attrs) -> None:
        for k, v in attrs.items():
            self._h5.attrs[k] = _attr(v)

    def set_grasped(self, nodes) -> None:
        g = self._h5["grasper"]
        if "nodes" in g:
            del g["nodes"]
        _ds(g, "nodes", np.asarray(nodes, dtype=np.int64), "1", "held nodes")

    def __exit__(self, exc_type, exc, tb) -> bool:
        times = None
        try:
            self._h5.close()
            if exc_type is None:
                with h5py.File(self._tmp, "r") as f:
                    times = f["time"][()]
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise
        # Renames the .h5 into place on success, removes the temporary file on failure.
        self._stack.__exit__(exc_type, exc, tb)
        if exc_type is None:
            xml = xdmf_text(self.path.name, n_nodes=self.points.shape[0], cells=self.cells, times=times,
                            disp_dtype=self.dtype)
            with atomic_path(self.xdmf_path) as tmp:
                tmp.write_text(xml, encoding="utf-8")
        return False


def _ds(group, name, data, units, description):
    d = group.create_dataset(name, data=data)
    d.attrs["units"] = units
    d.attrs["description"] = description
    return d


def _attr(value):
    """An HDF5 attribute value: dicts, lists and tuples as (strict) JSON text, the rest as it is."""
    return json.dumps(jsonable(value)) if isinstance(value, (dict, list, tuple)) else value


def xdmf_text(h5_name: str, *, n_nodes: int, cells: np.ndarray, times: np.ndarray, disp_dtype) -> str:
    """The XDMF 3 temporal collection for a history file named *h5_name* (same folder)."""
    c = np.asarray(cells)
    kind = "Tetrahedron" if c.shape[1] == 4 else "Triangle"
    prec = np.dtype(disp_dtype).itemsize
    h5 = escape(h5_name)

    def item(path: str, dims: str, number: str = "Float", precision: int = prec) -> str:
        return (f'<DataItem Dimensions="{dims}" NumberType="{number}" Precision="{precision}" '
                f'Format="HDF">{h5}:{path}</DataItem>')

    out = ['<?xml version="1.0" ?>', '<Xdmf Version="3.0">', " <Domain>",
           '  <Grid Name="organ" GridType="Collection" CollectionType="Temporal">']
    for k, t in enumerate(times):
        out += [
            f'   <Grid Name="frame_{k}" GridType="Uniform">',
            f'    <Time Value="{float(t):.17g}"/>',
            f'    <Topology TopologyType="{kind}" NumberOfElements="{c.shape[0]}">',
            f'     {item("/mesh/cells", f"{c.shape[0]} {c.shape[1]}", "Int", 8)}',
            "    </Topology>",
            '    <Geometry GeometryType="XYZ">',
            f'     {item(f"/position/{k}", f"{n_nodes} 3")}',
            "    </Geometry>",
            '    <Attribute Name="displacement" AttributeType="Vector" Center="Node">',
            f'     {item(f"/frame_displacement/{k}", f"{n_nodes} 3")}',
            "    </Attribute>",
            "   </Grid>",
        ]
    out += ["  </Grid>", " </Domain>", "</Xdmf>", ""]
    return "\n".join(out)


class History:
    """A history file opened for reading (see the module doc for the layout)."""

    def __init__(self, path):
        self.path = Path(path)
        try:
            self._f = h5py.File(self.path, "r")
        except (OSError, FileNotFoundError) as exc:
            raise AssetError(f"{self.path}: cannot open the history file ({exc}); rerun esmm simulate") from None
        if self._f.attrs.get("esmm_type") != ESMM_TYPE:
            self._f.close()
            raise AssetError(f"{self.path}: not an esmm simulation history; rerun esmm simulate")
        f = self._f
        self.points = f["mesh/points"][()]
        self.cells = f["mesh/cells"][()]
        self.surface = f["mesh/surface"][()]
        self.fixed = f["mesh/fixed"][()]
        self.times = f["time"][()]
        self.tips = f["grasper/tip"][()]
        self.attrs = dict(f.attrs)

    @property
    def n_frames(self) -> int:
        return int(self.times.size)

    def displacement(self, k: int) -> np.ndarray:
        """Displacement of frame *k*, shape (n, 3) float64 [m]."""
        return self._f["displacement"][k].astype(np.float64)

    def max_displacement(self) -> float:
        """Largest node displacement over all frames [m]."""
        d = self._f["displacement"]
        return max((float(np.linalg.norm(d[k], axis=1).max()) for k in range(d.shape[0])), default=0.0)

    def forces(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (S,), forces (S, 3)) of the grasper."""
        return self._f["grasper/time"][()], self._f["grasper/force"][()]

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
