"""The PLY reader (numpy, validated before use) and the triangle filter of the VTK-family reader."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.errors import InputError
from esmm.pipeline.mesh.readers import read_surface

HEADER = ("ply\nformat {fmt} 1.0\ncomment made by a test\nelement vertex {nv}\nproperty {vt} x\nproperty {vt} y\n"
          "property {vt} z\n{vextra}element face {nf}\nproperty list {ct} {it} vertex_indices\n{fextra}end_header\n")


def sphere():
    import pyvista as pv

    return pv.Sphere(radius=40.0, theta_resolution=24, phi_resolution=18)  # mm


def binary_ply(points, faces, *, order="<", vt="f4", ct="u1", it="i4", fmt=None) -> bytes:
    names = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u4": "uint", "i2": "short"}
    fmt = fmt or ("binary_little_endian" if order == "<" else "binary_big_endian")
    head = HEADER.format(fmt=fmt, nv=len(points), vt=names[vt], vextra="", nf=len(faces), ct=names[ct],
                         it=names[it], fextra="").encode()
    k = len(faces[0])
    rec = np.zeros(len(faces), dtype=[("n", order + ct), ("i", order + it, (k,))])
    rec["n"], rec["i"] = k, faces
    return head + np.asarray(points, order + vt).tobytes() + rec.tobytes()


@pytest.mark.parametrize("binary", [True, False])
def test_same_surface_as_pyvista_wrote(tmp_path, binary):
    s = sphere()
    s.save(tmp_path / "organ.ply", binary=binary)
    back = read_surface(tmp_path / "organ.ply")
    np.testing.assert_allclose(back.points * 1e3, s.points, atol=1e-5)
    np.testing.assert_array_equal(back.faces, s.faces.reshape(-1, 4)[:, 1:])
    assert back.volume() == pytest.approx(s.volume * 1e-9, rel=1e-12)


@pytest.mark.parametrize("order,vt,ct,it", [(">", "f4", "u1", "i4"), ("<", "f8", "u4", "u4"),
                                            (">", "f8", "i4", "i2")])
def test_binary_byte_orders_and_types(tmp_path, order, vt, ct, it):
    s = sphere()
    faces = s.faces.reshape(-1, 4)[:, 1:]
    (tmp_path / "o.ply").write_bytes(binary_ply(s.points, faces, order=order, vt=vt, ct=ct, it=it))
    back = read_surface(tmp_path / "o.ply")
    np.testing.assert_array_equal(back.faces, faces)
    np.testing.assert_allclose(back.points * 1e3, s.points, atol=1e-5)


def _cube_text(faces_block: str, nf: int, extra_elements: str = "", extra_data: str = "") -> str:
    pts = "0 0 0 1\n50 0 0 2\n50 50 0 3\n0 50 0 4\n0 0 50 5\n50 0 50 6\n50 50 50 7\n0 50 50 8\n"
    return ("ply\nformat ascii 1.0\nelement vertex 8\nproperty double x\nproperty double y\nproperty double z\n"
            f"property uchar red\nelement face {nf}\nproperty list uchar int vertex_indices\nproperty int flag\n"
            f"{extra_elements}end_header\n{pts}{faces_block}{extra_data}")


CUBE_QUADS = "4 0 3 2 1 0\n4 4 5 6 7 0\n4 0 1 5 4 0\n4 1 2 6 5 0\n4 2 3 7 6 0\n4 3 0 4 7 0\n"


def test_quads_are_fanned_and_close_the_cube(tmp_path):
    p = tmp_path / "cube.ply"
    p.write_text(_cube_text(CUBE_QUADS, 6, "element edge 1\nproperty int vertex1\nproperty int vertex2\n", "0 1\n"))
    s = read_surface(p)
    assert s.n_faces == 12 and s.is_closed()
    assert abs(s.volume()) == pytest.approx(0.05 ** 3, rel=1e-12)
    np.testing.assert_array_equal(s.faces[:2], [[0, 3, 2], [0, 2, 1]])  # fan from the first vertex


def test_mixed_polygons_keep_file_order_and_lines_are_dropped(tmp_path):
    faces = "4 0 3 2 1 0\n2 0 1 0\n3 4 5 6 0\n5 0 1 5 4 7 0\n1 3 0\n"
    p = tmp_path / "mixed.ply"
    p.write_text(_cube_text(faces, 5))
    s = read_surface(p)
    np.testing.assert_array_equal(s.faces, [[0, 3, 2], [0, 2, 1], [4, 5, 6], [0, 1, 5], [0, 5, 4], [0, 4, 7]])
    assert "2 faces with fewer than 3 vertices dropped" in s.source


def test_crlf_header(tmp_path):
    p = tmp_path / "crlf.ply"
    p.write_bytes(_cube_text(CUBE_QUADS, 6).replace("\n", "\r\n").encode())
    assert read_surface(p).n_faces == 12


@pytest.mark.parametrize("faces,nf,match", [
    ("3 0 1 8 0\n", 1, "face 0 has vertex index 8, not one of the 8 declared vertices"),
    ("3 0 1 2 0\n3 0 -1 2 0\n", 2, "face 1 has vertex index -1"),
    ("3 0 1 2.5 0\n", 1, "vertex index 2.5"),
    ("3 0 1 2 0\n", 2, "ends inside the 2 declared 'face' records; the file is truncated"),
    ("3 0 1 x 0\n", 1, "non-numeric value 'x'"),
    ("3.5 0 1 2 0\n", 1, "list length 3.5 is not a count"),
    ("-1 0 0\n", 3, "list length -1 is not a count"),
])
def test_bad_ascii_faces_are_refused(tmp_path, faces, nf, match):
    p = tmp_path / "bad.ply"
    p.write_text(_cube_text(faces, nf))
    with pytest.raises(InputError, match=match) as info:
        read_surface(p)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("text,match", [
    (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
     b"element face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n", "declares 0 vertices"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n0 0 0\n", "no 'face' element"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     b"element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0\n", "no 'vertex' element with x, y, z"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "no 'end_header'"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown format"),
    (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "a property before any element"),
    (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", "expected 'element NAME COUNT'"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "expected 'property TYPE NAME'"),
    (b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no 'format' line"),
    (b"plyx\nformat ascii 1.0\n", "not a PLY file"),
])
def test_bad_headers_are_refused(tmp_path, text, match):
    p = tmp_path / "bad.ply"
    p.write_bytes(text)
    with pytest.raises(InputError, match=match):
        read_surface(p)


def test_bad_binary_files_are_refused(tmp_path):
    s = sphere()
    faces = s.faces.reshape(-1, 4)[:, 1:].copy()
    data = binary_ply(s.points, faces)
    p = tmp_path / "b.ply"
    p.write_bytes(data[:-7])
    with pytest.raises(InputError, match="truncated"):
        read_surface(p)
    faces[-1, 2] = s.n_points  # one past the last vertex: VTK's reader crashed the process on this
    p.write_bytes(binary_ply(s.points, faces))
    with pytest.raises(InputError, match=f"face {len(faces) - 1} has vertex index {s.n_points}"):
        read_surface(p)
    faces[-1, 2] = 2**31 - 1
    p.write_bytes(binary_ply(s.points, faces, order=">"))
    with pytest.raises(InputError, match="vertex index 2147483647"):
        read_surface(p)


def test_binary_polygons_of_several_sizes(tmp_path):
    """The general (record by record) path of the binary reader."""
    pts = np.array([[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0], [0, 0, 50]], "<f4")
    head = HEADER.format(fmt="binary_little_endian", nv=5, vt="float", vextra="", nf=3, ct="uchar", it="int",
                         fextra="").encode()
    body = pts.tobytes()
    for f in ([0, 3, 2, 1], [0, 1], [0, 1, 4]):
        body += np.uint8(len(f)).tobytes() + np.asarray(f, "<i4").tobytes()
    p = tmp_path / "g.ply"
    p.write_bytes(head + body)
    np.testing.assert_array_equal(read_surface(p).faces, [[0, 3, 2], [0, 2, 1], [0, 1, 4]])
    p.write_bytes(head + body[:-2])
    with pytest.raises(InputError, match="truncated"):
        read_surface(p)


def test_vtk_polydata_with_a_line_cell_keeps_its_triangles(tmp_path):
    """A 2-vertex polygon next to a triangle: only the triangle is kept (no reshape error)."""
    p = tmp_path / "organ.vtk"
    p.write_text("# vtk DataFile Version 3.0\norgan\nASCII\nDATASET POLYDATA\nPOINTS 4 float\n0 0 0\n50 0 0\n"
                 "0 50 0\n0 0 50\nPOLYGONS 3 12\n2 0 1\n3 0 1 2\n4 0 1 3 2\n")
    s = read_surface(p)
    assert s.n_faces == 3 and sorted(map(tuple, s.faces.tolist()))[0] == (0, 1, 2)
