"""Reading organ surfaces: STL, OBJ, PLY, VTK/VTP, gmsh .msh and NIfTI masks.

Every reader returns a :class:`~esmm.pipeline.mesh.surface.Surface` in metres.
The file's unit is never guessed: ``unit`` says what the coordinates are in
(``"mm"`` by default, as InVesalius and 3D Slicer write), and the size check
(:func:`check_unit_sanity`) refuses an organ whose largest extent is not
between 10 and 400 mm, suggesting the ``unit`` that would make it plausible; an organ
whose volume is implausible for the organ its file name names (a liver of 1 mL: a file
in cm read as mm) gets a warning naming ``unit`` (:mod:`.organsize`).

Formats
-------
* STL, binary and ASCII: parsed here with numpy (a truncated binary file is
  detected from its triangle count); duplicate corners are merged by exact
  coordinates, as every STL writer duplicates them.
* PLY (ASCII, binary little and big endian): parsed here with numpy, header
  and indices checked before anything is built (VTK's PLY reader crashes the
  process on face indices beyond the declared vertices); polygons are
  triangulated as fans, faces with fewer than 3 vertices are dropped.
* OBJ, VTP, legacy VTK (polydata or unstructured grid): VTK readers via
  pyvista, with VTK's error output captured; a volume mesh gives its boundary;
  only the triangles of the triangulated polygons are kept (lines and
  vertices are dropped).
* gmsh ``.msh`` (any version, including MSH 1 that meshio cannot read; meshio
  calls ``sys.exit`` on it): read by gmsh itself in a subprocess; a volume mesh
  gives its boundary surface.
* NIfTI masks (``.nii``, ``.nii.gz``): the label is surfaced as InVesalius'
  "Binary" method does: a 0/255 mask with one voxel of padding (so the surface
  is closed where the organ touches the scan border), marching cubes at 127
  with the voxel spacing from the affine, Y negated, origin at voxel (0, 0, 0).
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..atomicio import atomic_path
from ..errors import InputError
from ..progress import ensure
from ..units import factor, normalise_unit
from .gmsh_worker import GmshFailure, GmshTimeout, run_worker
from .organsize import check_organ_size
from .surface import Surface

#: Plausible organ size: largest bounding-box extent in mm.
ORGAN_EXTENT_MM = (10.0, 400.0)
#: Largest extent [mm] read, with a warning, where the user gives the unit: a lymph node or a small animal's
#: organ lies below the band above; below a millimetre or beyond a metre the given unit is the error
GIVEN_EXTENT_MM = (1.0, 1000.0)

SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".vtu", ".msh", ".nii", ".nii.gz")


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix.lower()


def read_surface(path: str | os.PathLike, *, unit: str | None = None, label: int | None = None,
                 reporter=None) -> Surface:
    """Read an organ surface and convert it to metres.

    Parameters
    ----------
    path
        A surface file (STL, OBJ, PLY, VTK, VTP, VTU, MSH) or a NIfTI mask.
    unit
        Length unit of the file's coordinates (``"mm"``, ``"cm"``, ``"m"``,
        ...). None (default): mm, or a NIfTI header's own spatial unit when
        it sets one; a unit given wins over the header (which may be wrong).
    label
        For a multi-label NIfTI segmentation, the label of the organ
        (TotalSegmentator: liver = 5). Not needed for a binary mask.
    reporter
        Progress reporter (one step: what was read).

    Returns
    -------
    Surface
        Points (n, 3) [m], triangles (m, 3). Not cleaned: islands, holes,
        inward normals and duplicates are left for
        :func:`~esmm.pipeline.mesh.cleaning.clean_surface`.

    Raises
    ------
    InputError
        The file is missing, empty, truncated, of an unknown format, has no
        triangles, or its size is not plausible in ``unit`` (where the unit
        was given, a warning instead).
    """
    rep = ensure(reporter)
    p = Path(path)
    given = unit
    unit = unit if unit is not None else "mm"
    scale = factor(unit, "length", where="unit")
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder; give a surface file (STL, OBJ, PLY, VTK, MSH) or a NIfTI mask")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: the file is empty; export the surface again")
    if label is not None and (isinstance(label, bool) or not isinstance(label, (int, np.integer))):
        raise InputError(f"label: expected an integer label, got {label!r}", parameter="label")
    suf = _suffix(p)
    from_header = False
    if label is not None and suf not in (".nii", ".nii.gz"):
        raise InputError(f"label: applies to NIfTI masks only, not to {p.name}", parameter="label")
    _check_content(p, suf)
    if suf == ".stl":
        pts, faces, what = _read_stl(p)
    elif suf in (".nii", ".nii.gz"):
        pts, faces, unit, what, from_header = _read_nifti(p, label=label, unit=unit, given=given is not None)
        scale = factor(unit, "length")
    elif suf == ".msh":
        pts, faces, what = _read_msh(p)
    elif suf == ".ply":
        pts, faces, what = _read_ply(p)
    elif suf in (".obj", ".vtk", ".vtp", ".vtu"):
        pts, faces, what = _read_vtk_family(p)
    else:  # pragma: no cover - _check_content refuses every other suffix
        raise AssertionError(suf)
    if faces.shape[0] == 0:
        raise InputError(f"{p}: contains no triangles; export the organ as a surface (STL) or a mask (NIfTI)")
    if not np.all(np.isfinite(pts)):
        raise InputError(f"{p}: has non-finite (NaN/inf) coordinates; the file is corrupt, export it again")
    if faces.min() < 0 or faces.max() >= pts.shape[0]:
        raise InputError(f"{p}: a triangle refers to a point that does not exist; the file is corrupt")
    surf = Surface(pts * scale, faces, f"{p.name} ({what}, {unit})")
    odd = check_unit_sanity(surf, unit=unit, where=f"{p} (unit from its header)" if from_header else str(p),
                            given=given is not None and not from_header)
    if odd:
        rep.warn(odd)
    rep.step(f"read {p.name}: {what}, {surf.n_points} points, {surf.n_faces} triangles, "
             f"extent {surf.extent() * 1e3:.1f} mm")
    size = check_organ_size(surf.volume(), surf.extent(), name=p.name, unit=unit)
    if not size.plausible:
        rep.warn(size.message)
    return surf


#: What a file's first bytes say it is -> the suffixes that name it and a description.
_CONTENT = {
    "stl": ((".stl",), "an STL surface", ".stl"), "ply": ((".ply",), "a PLY surface", ".ply"),
    "obj": ((".obj",), "an OBJ surface", ".obj"),
    "vtk": ((".vtk",), "a legacy VTK file", ".vtk"),
    "vtkxml": ((".vtp", ".vtu"), "a VTK XML file", ".vtp (polydata) or .vtu (unstructured grid)"),
    "msh": ((".msh",), "a gmsh mesh", ".msh"), "nifti": ((".nii",), "an uncompressed NIfTI image", ".nii"),
    "gzip": ((".nii.gz",), "a gzip-compressed file", ".nii.gz if it is a NIfTI mask, or decompress it"),
}

_OBJ_LINE = re.compile(rb"^[ \t]*v[ \t]+[-+.\d]", re.MULTILINE)


def _content(p: Path) -> str | None:
    """The format the file's first bytes show (a key of :data:`_CONTENT`), or None when they show none."""
    with open(p, "rb") as fh:
        head = fh.read(65536)
    size = p.stat().st_size
    if size >= 84 and size == 84 + 50 * int(np.frombuffer(head[80:84], "<u4")[0]):
        return "stl"  # a binary STL's header is free text: its size is the only sure sign
    body = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    signs = (("gzip", head[:2] == b"\x1f\x8b"), ("ply", head[:4] in (b"ply\n", b"ply\r")),
             ("vtk", head.startswith(b"# vtk DataFile")), ("vtkxml", b"<VTKFile" in head[:1024]),
             ("msh", body[:11] == b"$MeshFormat" or body[:4] == b"$NOD"),
             ("nifti", head[344:348] in (b"n+1\0", b"ni1\0") or head[4:8] in (b"n+2\0", b"ni2\0")),
             ("stl", body[:5].lower() == b"solid" and b"\0" not in head[:4096] and b"facet" in head.lower()))
    found = next((k for k, hit in signs if hit), None)
    if found is None and b"\0" not in head[:4096] and _OBJ_LINE.search(head):
        found = "obj"
    return found


def _check_content(p: Path, suf: str) -> None:
    """Refuse an unknown suffix, or a file whose content is another known format than its name says."""
    found = _content(p)
    if suf not in SURFACE_SUFFIXES:
        held = {"gzip": " (it is gzip-compressed: decompress it first)"}.get(
            found, f" (it holds {_CONTENT[found][1]}: rename it to {_CONTENT[found][2]})" if found else "")
        raise InputError(f"{p}: unknown surface format {suf or '(no extension)'!r}{held}; "
                         f"give one of {', '.join(SURFACE_SUFFIXES)}")
    if found is None or suf in _CONTENT[found][0]:
        return
    _, what, rename = _CONTENT[found]
    raise InputError(f"{p}: holds {what}, not the {suf or '(no extension)'} its name says; "
                     f"rename it to {rename}")


def check_unit_sanity(surface: Surface, *, unit: str, where: str = "", given: bool = False) -> str | None:
    """Refuse an organ whose largest extent is not 10-400 mm; suggest a unit.

    Never rescales: a wrong unit changes every stiffness and mass downstream. Where the unit was
    *given* by the user (not defaulted, not read from a mask's header), a size within
    :data:`GIVEN_EXTENT_MM` is theirs to vouch for (a mouse's kidney, a lymph node): the message is
    returned for a warning instead.
    """
    ext_m = surface.extent()
    lo, hi = ORGAN_EXTENT_MM
    if lo <= ext_m * 1e3 <= hi:
        return None
    if given and GIVEN_EXTENT_MM[0] <= ext_m * 1e3 <= GIVEN_EXTENT_MM[1]:
        return (f"unit: {where + ': ' if where else ''}the organ is {ext_m * 1e3:.4g} mm across, outside "
                f"the {lo:g}-{hi:g} mm of most organs; read as {unit}, as given (the scenes' distances, "
                f"such as the default lift of 20 mm, are absolute)")
    f_given = factor(unit, "length")
    raw = ext_m / f_given  # extent in file units
    good = [u for u in ("m", "cm", "mm", "um") if lo <= raw * factor(u, "length") * 1e3 <= hi
            and u != unit]
    loc = f"{where}: " if where else ""
    hint = (f"if the file is in {' or '.join(good)}, read it with unit {good[0]}" if good
            else "check that the file holds one organ and export it again in mm")
    conv = f" ({ext_m * 1e3:.4g} mm)" if normalise_unit(unit) != "mm" else ""
    raise InputError(
        f"unit: {loc}the organ is {raw:.4g} {unit} across{conv}, not a plausible organ size "
        f"({lo:g}-{hi:g} mm); {hint}", parameter="unit"
    )


# --------------------------------------------------------------------- STL
_STL_RECORD = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _read_stl(p: Path) -> tuple[np.ndarray, np.ndarray, str]:
    data = p.read_bytes()
    size = len(data)
    n_bin = int(np.frombuffer(data[80:84], "<u4")[0]) if size >= 84 else -1
    # Text: starts with 'solid' and has no NUL byte (a binary STL whose header starts with 'solid' has
    # NULs in its triangle count, normals or attribute words), or NULs only in its name line.
    text = data.lstrip(b"\xef\xbb\xbf \t\r\n")[:5].lower() == b"solid" and (
        b"\0" not in data[:4096] or _ASCII_VERTEX.search(data[:4096]) is not None)
    if size >= 84 and size == 84 + 50 * n_bin and not (text and n_bin == 0):
        return _merge_exact(_binary_corners(p, data, n_bin)) + ("STL",)
    if text:
        return _merge_exact(_parse_ascii_stl(p, data)) + ("STL",)
    if size < 84:
        raise InputError(f"{p}: only {size} bytes, too short for an STL file; export it again")
    whole, rest = divmod(size - 84, 50)
    if n_bin > whole or rest:
        raise InputError(
            f"{p}: binary STL header announces {n_bin} triangles ({84 + 50 * n_bin} bytes) but the file has "
            f"{size} bytes ({whole} whole triangles{f' and {rest} bytes more' if rest else ''}); it is "
            f"{'truncated' if n_bin > whole else 'damaged'} or not an STL file, export it again"
        )
    # Fewer announced than held, to the byte: a writer that never filled in its count (VTK reads such
    # files to their end as well).
    pts, faces = _merge_exact(_binary_corners(p, data, whole))
    return pts, faces, f"STL, its header's triangle count {n_bin} ignored: {whole} triangles fill the file"


def _binary_corners(p: Path, data: bytes, n: int) -> np.ndarray:
    arr = np.frombuffer(data, _STL_RECORD, count=n, offset=84)
    corners = arr["v"].reshape(-1, 3) + np.float32(0.0)  # -0.0 -> 0.0
    if corners.shape[0] == 0:
        raise InputError(f"{p}: contains no triangles; export the organ surface again")
    return corners


_ASCII_VERTEX = re.compile(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", re.IGNORECASE)


def _parse_ascii_stl(p: Path, data: bytes) -> np.ndarray:
    found = _ASCII_VERTEX.findall(data)
    if len(found) % 3:
        raise InputError(f"{p}: ASCII STL with {len(found)} vertices, not a multiple of 3; the file is truncated")
    if not re.search(rb"endsolid", data[-4096:], re.IGNORECASE) and found:
        raise InputError(f"{p}: ASCII STL without 'endsolid'; the file is truncated, export it again")
    try:
        corners = np.array(found, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        bad = next(t for v in found for t in v if not _is_float(t))
        raise InputError(f"{p}: ASCII STL has a non-numeric coordinate {bad[:20]!r}; the file is corrupt") from None
    if corners.shape[0] == 0:
        raise InputError(f"{p}: contains no triangles; export the organ surface again")
    return corners


def _is_float(t: bytes) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _merge_exact(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge triangle corners with identical coordinates; return points and faces.

    Sorts the coordinates' bit patterns (two keys: x|y packed in 64 bits, then
    z), which is several times faster than ``np.unique(axis=0)``.
    """
    c = np.ascontiguousarray(corners)
    if c.dtype == np.float32:
        u = c.view(np.uint32).astype(np.uint64)
        shift = np.uint64(32)
        k1 = (u[:, 0] << shift) | u[:, 1]
        k2 = u[:, 2]
        order = np.lexsort((k2, k1))
        s1, s2 = k1[order], k2[order]
        new = np.ones(order.size, bool)
        new[1:] = (s1[1:] != s1[:-1]) | (s2[1:] != s2[:-1])
    else:
        c = c.astype(np.float64) + 0.0  # +0.0 turns -0.0 into 0.0 so they merge
        u = c.view(np.uint64)
        order = np.lexsort((u[:, 2], u[:, 1], u[:, 0]))
        su = u[order]
        new = np.ones(order.size, bool)
        new[1:] = np.any(su[1:] != su[:-1], axis=1)
    ids = np.cumsum(new) - 1
    inverse = np.empty(order.size, np.int64)
    inverse[order] = ids
    pts = c[order[new]].astype(np.float64)
    return pts, inverse.reshape(-1, 3)


def write_stl(surface: Surface, path: str | os.PathLike, *, unit: str = "mm", ascii: bool = False) -> Path:
    """Write *surface* as an STL file (binary by default) in *unit*, atomically.

    Parameters
    ----------
    surface
        The surface (points in metres).
    path
        Target file.
    unit
        Unit of the written coordinates (``"mm"`` like InVesalius).
    ascii
        Write ASCII STL instead of binary.
    """
    s = 1.0 / factor(unit, "length", where="unit")
    pts = surface.points * s
    tri = pts[surface.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1)
    ln[ln == 0] = 1
    n = n / ln[:, None]
    with atomic_path(path) as tmp:
        if ascii:
            with open(tmp, "w", encoding="ascii") as fh:
                fh.write("solid esmm\n")
                for k in range(tri.shape[0]):
                    fh.write(f"facet normal {n[k, 0]:.6e} {n[k, 1]:.6e} {n[k, 2]:.6e}\n outer loop\n")
                    for j in range(3):
                        fh.write(f"  vertex {tri[k, j, 0]:.9e} {tri[k, j, 1]:.9e} {tri[k, j, 2]:.9e}\n")
                    fh.write(" endloop\nendfacet\n")
                fh.write("endsolid esmm\n")
        else:
            arr = np.zeros(tri.shape[0], _STL_RECORD)
            arr["n"] = n
            arr["v"] = tri
            header = b"esmm binary STL, unit " + unit.encode() + b" "
            header = header.ljust(80, b" ")[:80]
            with open(tmp, "wb") as fh:
                fh.write(header)
                fh.write(np.uint32(tri.shape[0]).tobytes())
                fh.write(arr.tobytes())
    return Path(path)


# --------------------------------------------------------------- VTK family
def _read_vtk_family(p: Path) -> tuple[np.ndarray, np.ndarray, str]:
    import pyvista as pv
    import vtk

    what = p.suffix.lower().lstrip(".").upper()
    logger = vtk.vtkLogger
    prev = logger.GetCurrentVerbosityCutoff()
    logger.SetStderrVerbosity(logger.VERBOSITY_OFF)  # the library never prints; errors are caught below
    try:
        with pv.VtkErrorCatcher(raise_errors=False, send_to_logging=False) as catcher, \
                warnings.catch_warnings():
            # VTK's warnings come back as Python warnings from pyvista; the data is checked below.
            warnings.simplefilter("ignore", pv.VTKExecutionWarning)
            # pyvista checks the arrays it reads: an OBJ with lines gets a GroupIds array sized for
            # its polygons only; only the geometry is used (the data arrays are dropped below).
            warnings.simplefilter("ignore", pv.InvalidMeshWarning)
            try:
                # The reader itself, not pv.read: pv.read's own error observer logs VTK's errors
                # (printed by the root logger) and warns, where the catcher above keeps them.
                mesh = pv.get_reader(str(p)).read()
            except (Exception, SystemExit) as exc:  # meshio (behind pyvista) may call sys.exit
                raise InputError(f"{p}: cannot read it as {what} ({_short(exc)}); export the surface again") from None
    finally:
        logger.SetStderrVerbosity(prev)
    errors = [e for e in catcher.events if e.kind == "ERROR"]
    if errors:
        raise InputError(
            f"{p}: the {what} file is corrupt or truncated (VTK reader: {_short(errors[0].alert.split(':')[0])}); export it again"
        )
    if isinstance(mesh, pv.MultiBlock):
        mesh = mesh.combine()
    if not isinstance(mesh, pv.PolyData):
        # A volume mesh (unstructured grid of tetrahedra): take its boundary.
        try:
            mesh = mesh.extract_surface(algorithm="dataset_surface")
        except TypeError:  # older pyvista without the keyword
            mesh = mesh.extract_surface()
        what += " volume mesh, boundary"
    if mesh.n_points == 0 or mesh.n_cells == 0:
        raise InputError(f"{p}: contains no points or cells; the file is empty or corrupt")
    poly = mesh
    if poly.GetNumberOfPolys() == 0 and poly.GetNumberOfStrips() == 0:
        raise InputError(f"{p}: has no polygons (only points or lines); export the organ as a surface")
    poly = pv.PolyData(poly.points, faces=poly.GetPolys(), strips=poly.GetStrips())  # geometry only
    tri = poly.triangulate()  # polygons fanned, triangle strips split
    return np.asarray(tri.points, np.float64), _triangles_of(tri), what


def _triangles_of(poly) -> np.ndarray:
    """The 3-vertex cells of a triangulated PolyData's polygons, (m, 3) int64.

    ``triangulate()`` leaves degenerate polygons (1 or 2 vertices, which some
    writers emit for lines) as they are, so the cell array is walked by its
    offsets instead of being reshaped as if every cell were a triangle.
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy

    polys = poly.GetPolys()
    if polys is None or polys.GetNumberOfCells() == 0:
        return np.empty((0, 3), np.int64)
    offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
    conn = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    start = offsets[:-1][np.diff(offsets) == 3]
    return conn[start[:, None] + np.arange(3)]


# ---------------------------------------------------------------------- PLY
#: PLY scalar types (both spellings of the 1.0 spec) -> numpy type characters.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_MAX_HEADER = 1 << 20
_PLY_FACE_PROPS = ("vertex_indices", "vertex_index")


class _PlyProp:
    __slots__ = ("name", "type", "count")

    def __init__(self, name: str, typ: str, count: str | None = None):
        self.name, self.type, self.count = name, typ, count  # count: type of a list's length, None if scalar


class _PlyElement:
    __slots__ = ("name", "n", "props")

    def __init__(self, name: str, n: int):
        self.name, self.n, self.props = name, n, []


def _ply_header(p: Path, data: bytes) -> tuple[str | None, list[_PlyElement], int]:
    """Parse the header: (byte order or None for ASCII, elements, offset of the body)."""
    if not data.startswith(b"ply") or data[3:4] not in (b"\n", b"\r"):
        raise InputError(f"{p}: not a PLY file (it does not start with a 'ply' line); export the surface again")
    m = re.search(rb"(?:^|[\r\n])end_header[ \t]*(\r\n|\n|\r)", data[:_PLY_MAX_HEADER])
    if m is None:
        raise InputError(f"{p}: the PLY header has no 'end_header' line; the file is truncated or corrupt")
    try:
        header = data[: m.start()].decode("ascii")
    except UnicodeDecodeError:
        raise InputError(f"{p}: the PLY header is not ASCII text; the file is corrupt") from None
    fmt: str | None = None
    order: str | None = None
    elements: list[_PlyElement] = []
    for no, raw_line in enumerate(header.splitlines()[1:], start=2):
        words = raw_line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = f"{p}: PLY header line {no} ({_short(raw_line)!r})"
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _PLY_FORMATS:
                raise InputError(f"{bad}: unknown format; expected ascii, binary_little_endian or "
                                 f"binary_big_endian")
            fmt, order = words[1], _PLY_FORMATS[words[1]]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{bad}: expected 'element NAME COUNT' with a count >= 0; the file is corrupt")
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{bad}: a property before any element; the file is corrupt")
            if len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES:
                if _PLY_TYPES[words[2]][0] == "f":
                    raise InputError(f"{bad}: a list length of floating type; the file is corrupt")
                elements[-1].props.append(_PlyProp(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].props.append(_PlyProp(words[2], _PLY_TYPES[words[1]]))
            else:
                raise InputError(f"{bad}: expected 'property TYPE NAME' or 'property list TYPE TYPE NAME' with "
                                 f"types among {', '.join(sorted(set(_PLY_TYPES)))}")
        else:
            raise InputError(f"{bad}: unknown header keyword {words[0][:20]!r}; the file is corrupt")
    if fmt is None:
        raise InputError(f"{p}: the PLY header has no 'format' line; the file is corrupt")
    return order, elements, m.end()


def _ply_read_ascii(p: Path, elements: list[_PlyElement], body: bytes) -> dict[str, dict]:
    tokens = body.split()
    try:
        vals = np.array(tokens, dtype=np.float64) if tokens else np.empty(0)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise InputError(f"{p}: PLY data has a non-numeric value {_short(bad.decode('latin-1'))!r}; "
                         f"the file is corrupt, export it again") from None
    pos = 0
    out: dict[str, dict] = {}
    for el in elements:
        if not any(pr.count is not None for pr in el.props):
            width = len(el.props)
            need = el.n * width
            if pos + need > vals.size:
                raise _ply_truncated(p, el)
            block = vals[pos: pos + need].reshape(el.n, width)
            out[el.name] = {pr.name: block[:, i] for i, pr in enumerate(el.props)}
            pos += need
            continue
        # Fast path: every list as long as in the first record.
        first, q = [], pos
        for pr in el.props:
            k = int(vals[q]) if pr.count is not None and q < vals.size and _whole(vals[q]) else 0
            k = max(k, 0)  # a negative length fails the check below and is refused record by record
            first.append(k)
            q += 1 + k if pr.count is not None else 1
        width = sum(1 + k if pr.count is not None else 1 for pr, k in zip(el.props, first))
        if el.n and pos + el.n * width <= vals.size:
            block = vals[pos: pos + el.n * width].reshape(el.n, width)
            cols, c, ok = {}, 0, True
            for pr, k in zip(el.props, first):
                if pr.count is None:
                    cols[pr.name] = block[:, c]
                    c += 1
                else:
                    ok = ok and bool(np.all(block[:, c] == k))
                    cols[pr.name] = block[:, c + 1: c + 1 + k]
                    c += 1 + k
            if ok:
                out[el.name] = cols
                pos += el.n * width
                continue
        # General path: one record at a time.
        cols = {pr.name: [] for pr in el.props}
        for _ in range(el.n):
            for pr in el.props:
                if pos >= vals.size:
                    raise _ply_truncated(p, el)
                if pr.count is None:
                    cols[pr.name].append(vals[pos])
                    pos += 1
                    continue
                k = vals[pos]
                if not _whole(k) or k < 0:
                    raise InputError(f"{p}: PLY {el.name} list length {k:g} is not a count; the file is corrupt")
                k = int(k)
                if pos + 1 + k > vals.size:
                    raise _ply_truncated(p, el)
                cols[pr.name].append(vals[pos + 1: pos + 1 + k])
                pos += 1 + k
        out[el.name] = {name: (np.asarray(v) if el.props[i].count is None else v)
                        for i, (name, v) in enumerate(cols.items())}
    return out


def _whole(x) -> bool:
    return bool(np.isfinite(x)) and float(x) == int(x)


def _ply_truncated(p: Path, el: _PlyElement) -> InputError:
    return InputError(f"{p}: the PLY data ends inside the {el.n} declared '{el.name}' records; the file is "
                      f"truncated, export it again")


def _ply_read_binary(p: Path, elements: list[_PlyElement], body: bytes, order: str) -> dict[str, dict]:
    pos = 0
    out: dict[str, dict] = {}
    for el in elements:
        if not any(pr.count is not None for pr in el.props):
            dt = np.dtype([(f"f{i}", order + pr.type) for i, pr in enumerate(el.props)])
            if pos + el.n * dt.itemsize > len(body):
                raise _ply_truncated(p, el)
            arr = np.frombuffer(body, dt, count=el.n, offset=pos)
            out[el.name] = {pr.name: arr[f"f{i}"] for i, pr in enumerate(el.props)}
            pos += el.n * dt.itemsize
            continue
        # Fast path: every list as long as in the first record.
        first, q, ok = [], pos, True
        for pr in el.props:
            if pr.count is None:
                first.append(0)
                q += np.dtype(pr.type).itemsize
                continue
            cs = np.dtype(pr.count).itemsize
            if q + cs > len(body):
                ok = False
                break
            k = int(np.frombuffer(body, order + pr.count, count=1, offset=q)[0])
            first.append(max(k, 0))
            q += cs + max(k, 0) * np.dtype(pr.type).itemsize
        if ok and el.n and q <= len(body):  # the first record fits
            fields = []
            for i, (pr, k) in enumerate(zip(el.props, first)):
                if pr.count is None:
                    fields.append((f"f{i}", order + pr.type))
                else:
                    fields += [(f"n{i}", order + pr.count), (f"f{i}", order + pr.type, (k,))]
            dt = np.dtype(fields)
            if pos + el.n * dt.itemsize <= len(body):
                arr = np.frombuffer(body, dt, count=el.n, offset=pos)
                if all(bool(np.all(arr[f"n{i}"] == k)) for i, (pr, k) in enumerate(zip(el.props, first))
                       if pr.count is not None):
                    out[el.name] = {pr.name: arr[f"f{i}"].reshape(el.n, -1) if pr.count is not None
                                    else arr[f"f{i}"] for i, pr in enumerate(el.props)}
                    pos += el.n * dt.itemsize
                    continue
        # General path: one record at a time.
        cols = {pr.name: [] for pr in el.props}
        for _ in range(el.n):
            for pr in el.props:
                if pr.count is None:
                    size = np.dtype(pr.type).itemsize
                    if pos + size > len(body):
                        raise _ply_truncated(p, el)
                    cols[pr.name].append(np.frombuffer(body, order + pr.type, count=1, offset=pos)[0])
                    pos += size
                    continue
                cs = np.dtype(pr.count).itemsize
                if pos + cs > len(body):
                    raise _ply_truncated(p, el)
                k = int(np.frombuffer(body, order + pr.count, count=1, offset=pos)[0])
                if k < 0:
                    raise InputError(f"{p}: PLY {el.name} list length {k} is negative; the file is corrupt")
                size = k * np.dtype(pr.type).itemsize
                if pos + cs + size > len(body):
                    raise _ply_truncated(p, el)
                cols[pr.name].append(np.frombuffer(body, order + pr.type, count=k, offset=pos + cs))
                pos += cs + size
        out[el.name] = {name: (np.asarray(v) if el.props[i].count is None else v)
                        for i, (name, v) in enumerate(cols.items())}
    return out


def _fan(lists, n_vertices: int, p: Path) -> tuple[np.ndarray, int]:
    """Triangles (m, 3) of polygons given as an (f, k) array or a list of 1-D arrays; dropped count.

    Polygons are split into fans from their first vertex; faces with fewer
    than 3 vertices (lines, points) are dropped and counted. Every index must
    be a whole number in 0..n_vertices-1.
    """
    if isinstance(lists, np.ndarray):
        groups = {lists.shape[1]: (np.arange(lists.shape[0]), lists)} if lists.shape[0] else {}
    else:
        lens = np.fromiter((len(a) for a in lists), np.int64, count=len(lists))
        groups = {}
        for k in np.unique(lens):
            rows = np.flatnonzero(lens == k)
            groups[int(k)] = (rows, np.array([lists[i] for i in rows]).reshape(rows.size, int(k)))
    rows_out, tris, dropped = [], [], 0
    for k, (rows, idx) in sorted(groups.items()):
        if k < 3:
            dropped += rows.size
            continue
        with np.errstate(invalid="ignore"):
            bad = (idx < 0) | (idx >= n_vertices)
            if idx.dtype.kind == "f":
                bad |= ~np.isfinite(idx) | (idx != np.floor(idx))
        if bad.any():
            r, c = np.argwhere(bad)[0]
            x = idx[r, c]
            shown = str(int(x)) if np.isfinite(x) and x == np.floor(x) else repr(float(x))
            raise InputError(
                f"{p}: PLY face {int(rows[r])} has vertex index {shown}, not one of the {n_vertices} declared "
                f"vertices (0..{n_vertices - 1}); the file is corrupt, export it again"
            )
        idx = idx.astype(np.int64)
        j = np.arange(1, k - 1)
        fan = np.stack([np.repeat(idx[:, :1], k - 2, axis=1), idx[:, j], idx[:, j + 1]], axis=2)
        tris.append(fan.reshape(-1, 3))
        rows_out.append(np.repeat(rows, k - 2))
    if not tris:
        return np.empty((0, 3), np.int64), dropped
    # Keep the file's face order (the groups were processed by polygon size).
    order = np.argsort(np.concatenate(rows_out), kind="stable")
    return np.concatenate(tris)[order], dropped


def _read_ply(p: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """Points (n, 3) and triangles (m, 3) of a PLY file (ASCII or binary), validated."""
    data = p.read_bytes()
    order, elements, start = _ply_header(p, data)
    by_name = {el.name: el for el in elements}
    vert = by_name.get("vertex")
    if vert is None or not {"x", "y", "z"} <= {pr.name for pr in vert.props if pr.count is None}:
        raise InputError(f"{p}: the PLY file has no 'vertex' element with x, y, z properties; the file is corrupt")
    face = by_name.get("face")
    if face is None:
        has = ", ".join(el.name for el in elements)
        raise InputError(f"{p}: the PLY file has no 'face' element (it has: {has}); export the organ as a surface "
                         f"of triangles or polygons")
    lists = [pr for pr in face.props if pr.count is not None]
    prop = next((pr for pr in lists if pr.name in _PLY_FACE_PROPS), lists[0] if len(lists) == 1 else None)
    if prop is None:
        raise InputError(f"{p}: the PLY 'face' element has no 'vertex_indices' list; the file is corrupt")
    if prop.type[0] == "f":
        raise InputError(f"{p}: PLY face indices are declared as floating point; the file is corrupt")
    if vert.n == 0 or face.n == 0:
        raise InputError(f"{p}: the PLY file declares {vert.n} vertices and {face.n} faces; the file is empty "
                         f"or corrupt, export the surface again")
    body = data[start:]
    if order is None:
        what = "PLY"
        values = _ply_read_ascii(p, elements, body)
    else:
        what = "PLY binary"
        values = _ply_read_binary(p, elements, body, order)
    v = values["vertex"]
    pts = np.column_stack([np.asarray(v[c], np.float64) for c in "xyz"])
    faces, dropped = _fan(values["face"][prop.name], vert.n, p)
    if dropped:
        what += f", {dropped} faces with fewer than 3 vertices dropped"
    return pts, faces, what


def _short(x) -> str:
    s = " ".join(str(x).split())
    s = "".join(ch if ch.isprintable() else "?" for ch in s)
    return s[:120] + ("..." if len(s) > 120 else "")


# ----------------------------------------------------------------- gmsh MSH
def _read_msh(p: Path) -> tuple[np.ndarray, np.ndarray, str]:
    try:
        out = run_worker("read", {"path": str(p.resolve())}, timeout=60.0)
    except GmshTimeout:
        raise InputError(f"{p}: gmsh did not finish reading it within 60 s; the file is corrupt or huge") from None
    except GmshFailure as exc:
        raise InputError(f"{p}: gmsh cannot read it ({_short(exc)}); export the surface again") from None
    nodes = out["nodes"]
    tets = out["tets"]
    tris = out["triangles"]
    if tets.shape[0]:
        faces = boundary_of_tets(nodes, tets)
        what = f"MSH volume mesh ({tets.shape[0]} tetrahedra), boundary"
    else:
        faces = tris
        what = "MSH surface mesh"
    if faces.shape[0] == 0:
        raise InputError(f"{p}: holds no triangles or tetrahedra; export the organ surface again")
    used = np.unique(faces)
    remap = np.full(nodes.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return nodes[used], remap[faces], what


def boundary_of_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tetrahedral mesh, oriented outward.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tets : ndarray, shape (t, 4)
        Any orientation; each tetrahedron is first made positive.

    Returns
    -------
    ndarray, shape (k, 3), int64
        The faces used by exactly one tetrahedron, counter-clockwise seen
        from outside.
    """
    t = np.asarray(tets, np.int64).copy()
    p = np.asarray(points, np.float64)
    d = np.einsum("ij,ij->i", p[t[:, 1]] - p[t[:, 0]],
                  np.cross(p[t[:, 2]] - p[t[:, 0]], p[t[:, 3]] - p[t[:, 0]]))
    neg = d < 0
    t[neg, 2], t[neg, 3] = t[neg, 3].copy(), t[neg, 2].copy()
    # Faces of a positive tet (0,1,2,3), outward: (0,2,1), (0,1,3), (0,3,2), (1,2,3).
    f = np.concatenate([t[:, [0, 2, 1]], t[:, [0, 1, 3]], t[:, [0, 3, 2]], t[:, [1, 2, 3]]])
    key = np.sort(f, axis=1)
    _, idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return f[idx[counts == 1]]


# -------------------------------------------------------------------- NIfTI
def _read_nifti(p: Path, *, label: int | None, unit: str, given: bool
                ) -> tuple[np.ndarray, np.ndarray, str, str, bool]:
    """Points, triangles, their unit (the header's unless *unit* was *given*), a description, and
    whether the unit is the header's."""
    import nibabel as nib

    try:
        img = nib.load(str(p))
        data = np.asanyarray(img.dataobj)
    except Exception as exc:  # nibabel raises many kinds on corrupt files
        raise InputError(f"{p}: cannot read it as NIfTI ({_short(exc)}); export the mask again") from None
    if data.ndim > 3:
        if all(s == 1 for s in data.shape[3:]):
            data = data.reshape(data.shape[:3])
        else:
            raise InputError(f"{p}: a {data.ndim}-D image of shape {data.shape}; give a 3-D mask")
    if data.ndim != 3:
        raise InputError(f"{p}: a {data.ndim}-D image; give a 3-D mask")
    try:
        spatial_unit = img.header.get_xyzt_units()[0]
    except (KeyError, ValueError):  # an unknown xyzt_units code in a damaged header
        spatial_unit = "unknown"
    header_unit = {"meter": "m", "mm": "mm", "micron": "um"}.get(spatial_unit)
    spacing, linear = _voxel_geometry(p, np.asarray(img.affine, np.float64)[:3, :3])
    if not np.issubdtype(data.dtype, np.integer):
        if not np.all(np.isfinite(data)):
            raise InputError(f"{p}: holds NaN or infinite values; the mask is corrupt, export it again")
        rounded = np.rint(data)
        if not np.allclose(rounded, data):
            raise InputError(f"{p}: holds non-integer values (a probability map?); give a label mask")
        data = rounded.astype(np.int64)
    values, counts = np.unique(data, return_counts=True)
    nonzero = [(int(v), int(c)) for v, c in zip(values, counts) if v != 0]
    if not nonzero:
        raise InputError(f"{p}: the mask is empty (all voxels are 0)")
    if label is None:
        if len(nonzero) > 1:
            listing = ", ".join(f"{v} ({c} voxels)" for v, c in sorted(nonzero, key=lambda t: -t[1])[:8])
            raise InputError(
                f"label: {p} is a multi-label segmentation ({len(nonzero)} labels: {listing}"
                f"{', ...' if len(nonzero) > 8 else ''}); choose the organ's label (TotalSegmentator liver: 5)",
                parameter="label")
        label = nonzero[0][0]
    elif label not in {v for v, _ in nonzero}:
        listing = ", ".join(str(v) for v, _ in nonzero[:20])
        raise InputError(f"label: {label} is not in {p.name}; labels present: {listing}", parameter="label")
    verts, faces = surface_from_mask(data == label, spacing=spacing, linear=linear)
    what = f"NIfTI label {label}, voxel {'x'.join(f'{s:g}' for s in spacing)}"
    if linear is not None:
        what += " (sheared affine: its shape and volume kept)"
    if header_unit is not None and header_unit != unit:
        what += f", the header's unit {header_unit} {'overridden' if given else 'used'}"
    from_header = header_unit is not None and not given
    return verts, faces, header_unit if from_header else unit, what, from_header


def _voxel_geometry(p: Path, lin: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Voxel sizes (the affine's column norms) and, for a sheared affine, its rotation-free part.

    A rotation or a flipped axis is dropped, as InVesalius drops it. A shear
    (columns not orthogonal: gantry-tilted CT) is not a voxel size: the column
    norms alone would change the organ's volume, so the symmetric factor S of
    the polar decomposition lin = R S (S = sqrt(lin^T lin)) is returned and
    applied instead; it keeps the shape, and the volume |det lin| per voxel.
    """
    spacing = np.sqrt((lin ** 2).sum(axis=0))
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise InputError(f"{p}: the affine gives voxel sizes {spacing}; the header is corrupt")
    gram = lin.T @ lin
    w, v = np.linalg.eigh(gram)
    if not w.min() > 1e-12 * w.max():
        raise InputError(f"{p}: the affine is singular (its voxels have no volume); the header is corrupt")
    off = gram - np.diag(np.diag(gram))
    if np.abs(off).max() <= 1e-6 * np.diag(gram).max():  # orthogonal up to the header's float32 rounding
        return spacing, None
    return spacing, (v * np.sqrt(w)) @ v.T


def surface_from_mask(mask: np.ndarray, *, spacing, linear: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Surface a boolean mask as InVesalius' "Binary" method does.

    Parameters
    ----------
    mask : ndarray, shape (nx, ny, nz), bool
    spacing : sequence of 3 floats
        Voxel size along each axis (file units).
    linear : ndarray, shape (3, 3), optional
        Instead of *spacing*, the symmetric positive matrix taking voxel
        indices to file units (a sheared affine's, :func:`_voxel_geometry`).

    Returns
    -------
    points : ndarray, shape (n, 3)
        Vertex coordinates in file units, origin at voxel (0, 0, 0), Y negated.
    faces : ndarray, shape (m, 3), int64
    """
    from skimage.measure import marching_cubes

    mask = np.asarray(mask, bool)
    if not mask.any():
        return np.empty((0, 3)), np.empty((0, 3), np.int64)
    # Only the label's bounding box is surfaced: a CT-sized label map (512 x 512 x 300) took 1.2 GB as a
    # whole float volume.
    occupied = [np.flatnonzero(mask.any(axis=tuple(j for j in range(3) if j != i))) for i in range(3)]
    lo = np.array([k[0] for k in occupied])
    hi = np.array([k[-1] + 1 for k in occupied])
    vol = np.pad(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32) * np.float32(255.0), 1)
    spacing = (1.0, 1.0, 1.0) if linear is not None else tuple(float(s) for s in spacing)
    verts, faces, _n, _v = marching_cubes(vol, level=127.0, spacing=spacing, allow_degenerate=False)
    verts = verts + (lo - 1) * np.asarray(spacing)  # back to voxel (0, 0, 0), the padding undone
    if linear is not None:
        verts = verts @ np.asarray(linear, np.float64).T
    verts[:, 1] *= -1.0
    return verts.astype(np.float64), faces.astype(np.int64)
