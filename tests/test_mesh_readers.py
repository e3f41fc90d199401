"""Reading organ surfaces: formats, unit sanity, clear one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.errors import InputError
from esmm.pipeline.mesh.readers import read_surface, surface_from_mask, write_stl
from esmm.pipeline.mesh.surface import Surface


def sphere(r_m=0.04, nsub=3):
    import pyvista as pv

    return Surface.from_pyvista(pv.Icosphere(radius=r_m, nsub=nsub))


@pytest.mark.parametrize("ascii_", [False, True])
def test_stl_roundtrip_in_mm(tmp_path, ascii_):
    s = sphere()
    path = write_stl(s, tmp_path / "organ.stl", unit="mm", ascii=ascii_)
    back = read_surface(path)
    assert back.n_faces == s.n_faces and back.n_points == s.n_points  # corners merged again
    assert back.volume() == pytest.approx(s.volume(), rel=1e-5)
    assert back.is_closed()


def test_stl_in_cm_needs_unit(tmp_path):
    s = sphere(0.04)
    path = write_stl(s, tmp_path / "organ.stl", unit="cm")  # 8 units across
    with pytest.raises(InputError, match=r"unit cm"):
        read_surface(path)
    back = read_surface(path, unit="cm")
    assert back.extent() == pytest.approx(0.08, rel=1e-3)


def test_huge_organ_suggests_smaller_unit(tmp_path):
    s = sphere(0.04)
    path = write_stl(s, tmp_path / "organ.stl", unit="um")  # 80 000 units across
    with pytest.raises(InputError, match=r"not a plausible organ size.*unit um"):
        read_surface(path)


def test_small_organ_read_where_its_unit_is_given(tmp_path):
    """An 8 mm organ (a lymph node, a mouse's kidney) is refused on the default unit, whose error it
    would be, and read with a warning where the user gives the unit: the size is then theirs."""
    from esmm.pipeline.progress import ListReporter

    path = write_stl(sphere(0.004), tmp_path / "node.stl", unit="mm")  # 8 mm across
    with pytest.raises(InputError, match=r"not a plausible organ size.*unit cm"):
        read_surface(path)
    rep = ListReporter()
    back = read_surface(path, unit="mm", reporter=rep)
    assert back.extent() == pytest.approx(0.008, rel=1e-3)
    assert any("8 mm across" in w and "as given" in w for w in rep.warnings)
    with pytest.raises(InputError, match=r"not a plausible organ size.*unit m\b"):     # a liver in metres,
        read_surface(write_stl(sphere(0.1), tmp_path / "m.stl", unit="m"), unit="mm")   # 0.2 mm "as given"


def test_unknown_unit_is_named(tmp_path):
    path = write_stl(sphere(), tmp_path / "organ.stl")
    with pytest.raises(InputError, match="unit"):
        read_surface(path, unit="furlong")


def test_truncated_binary_stl(tmp_path):
    path = write_stl(sphere(), tmp_path / "organ.stl")
    data = path.read_bytes()
    (tmp_path / "cut.stl").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated") as ei:
        read_surface(tmp_path / "cut.stl")
    assert "\n" not in str(ei.value)


def test_truncated_ascii_stl(tmp_path):
    path = write_stl(sphere(), tmp_path / "organ.stl", ascii=True)
    text = path.read_text()
    (tmp_path / "cut.stl").write_text(text[: len(text) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_surface(tmp_path / "cut.stl")


@pytest.mark.parametrize("name,content,match", [
    ("empty.stl", b"", "empty"),
    ("x.stp", b"hello", "unknown surface format"),
    ("tiny.stl", b"abc", "too short"),
])
def test_bad_files(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_surface(tmp_path / name)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_surface(tmp_path / "nope.stl")
    with pytest.raises(InputError, match="folder"):
        read_surface(tmp_path)


def test_label_only_for_nifti(tmp_path):
    path = write_stl(sphere(), tmp_path / "organ.stl")
    with pytest.raises(InputError, match="NIfTI"):
        read_surface(path, label=3)


@pytest.mark.parametrize("ext", ["obj", "ply", "vtp", "vtk"])
def test_vtk_family(tmp_path, ext):
    s = sphere()
    poly = s.to_pyvista()
    poly.points *= 1e3  # file in mm
    poly.save(tmp_path / f"organ.{ext}")
    back = read_surface(tmp_path / f"organ.{ext}")
    assert back.volume() == pytest.approx(s.volume(), rel=1e-5)


def test_volume_mesh_gives_its_boundary(tmp_path):
    import pyvista as pv

    grid = pv.ImageData(dimensions=(5, 5, 5), spacing=(10.0, 10.0, 10.0)).cast_to_unstructured_grid()
    tets = grid.triangulate()
    tets.save(tmp_path / "box.vtu")
    back = read_surface(tmp_path / "box.vtu")
    assert back.is_closed()
    assert abs(back.volume()) == pytest.approx(0.04 ** 3, rel=1e-9)


def test_nifti_mask_surfaced_like_invesalius(tmp_path):
    import nibabel as nib

    spacing = (2.0, 2.0, 3.0)
    n = (40, 40, 30)
    x, y, z = np.meshgrid(*[np.arange(k) * s for k, s in zip(n, spacing)], indexing="ij")
    mask = ((x - 40) ** 2 + (y - 40) ** 2 + (z - 45) ** 2) < 30.0 ** 2
    seg = np.where(mask, 7, 0).astype(np.uint8)
    seg[0, 0, 0] = 0
    img = nib.Nifti1Image(seg, np.diag([*spacing, 1.0]))
    nib.save(img, tmp_path / "seg.nii.gz")
    s = read_surface(tmp_path / "seg.nii.gz")  # binary mask: no label needed
    assert s.is_closed()
    voxel_volume = mask.sum() * np.prod(spacing) * 1e-9
    assert s.volume() == pytest.approx(voxel_volume, rel=0.03)
    b = s.bounds()
    assert b[1, 1] <= 0.0  # Y negated
    with pytest.raises(InputError, match="not in seg.nii.gz"):
        read_surface(tmp_path / "seg.nii.gz", label=3)


def test_surface_from_mask_touching_border_is_closed():
    mask = np.ones((6, 7, 8), bool)  # touches every border: the padding closes it
    pts, faces = surface_from_mask(mask, spacing=(1.0, 1.0, 1.0))
    s = Surface(pts, faces)
    assert s.is_closed()
    # The 127-level surface of a 0/255 box lies half a voxel outside the voxel centres.
    assert abs(s.volume()) == pytest.approx(6 * 7 * 8, rel=0.1)


# ---------------------------------------------------------------- shared data
def test_shared_smooth_ascii_needs_cm(shared_data):
    path = shared_data / "meshes" / "sofa_liver_smooth_ascii.stl"
    with pytest.raises(InputError, match=r"6\.\d+ mm across.*unit cm"):
        read_surface(path)
    s = read_surface(path, unit="cm")
    assert s.n_faces == 4384 and s.is_closed()
    assert 0.05 < s.extent() < 0.08


def test_shared_broken_vtk_fails_clearly(shared_data):
    with pytest.raises(InputError, match="corrupt or truncated") as ei:
        read_surface(shared_data / "meshes" / "sofa_liver_broken.vtk")
    assert "\n" not in str(ei.value) and len(str(ei.value)) < 300


def test_shared_sofa_liver_vtk_and_stl_agree(shared_data):
    a = read_surface(shared_data / "meshes" / "sofa_liver.vtk")
    b = read_surface(shared_data / "meshes" / "sofa_liver.stl")
    assert a.n_faces == b.n_faces == 10000
    # Inward normals: negative signed volume of 1.48 L (README).
    assert a.volume() == pytest.approx(-1.477e-3, rel=2e-3)
    assert b.volume() == pytest.approx(a.volume(), rel=1e-6)


def test_shared_msh_v1_boundary(shared_data):
    """MSH 1 (meshio cannot read it): gmsh reads it; the tets' boundary is the surface."""
    path = shared_data / "meshes" / "sofa_liver_v1.msh"
    with pytest.raises(InputError, match="unit cm"):
        read_surface(path)
    s = read_surface(path, unit="cm")
    assert s.is_closed()
    assert s.volume() > 0  # outward
    assert "596 tetrahedra" in s.source or "tetrahedra" in s.source


def test_shared_nifti_matches_its_stl_export(shared_data):
    path = shared_data / "meshes" / "ts_example_seg.nii.gz"
    with pytest.raises(InputError, match="^label: .*multi-label segmentation"):
        read_surface(path)
    s = read_surface(path, label=5)
    stl = read_surface(shared_data / "meshes" / "ts_liver_3mm_closed.stl")
    assert s.is_closed()
    # Same surfacing as the README's InVesalius-style export: same volume and extent.
    assert abs(s.volume()) == pytest.approx(abs(stl.volume()), rel=1e-3)
    np.testing.assert_allclose(s.bounds(), stl.bounds(), atol=1e-6)


def test_binary_stl_whose_header_starts_with_solid(tmp_path):
    """Many CAD tools write 'solid' at the start of a binary STL header."""
    path = write_stl(sphere(), tmp_path / "organ.stl")
    data = bytearray(path.read_bytes())
    data[:11] = b"solid organ"
    (tmp_path / "solid.stl").write_bytes(bytes(data))
    back = read_surface(tmp_path / "solid.stl")
    assert back.volume() == pytest.approx(sphere().volume(), rel=1e-5)


# ------------------------------------------- exports seen in the wild (second input sweep)
def _binary_stl(tmp_path, name="organ.stl"):
    return write_stl(sphere(), tmp_path / name).read_bytes()


def test_binary_stl_starting_with_solid_and_truncated_says_truncated(tmp_path):
    data = bytearray(_binary_stl(tmp_path))
    data[:11] = b"solid organ"
    (tmp_path / "cut.stl").write_bytes(bytes(data[:-1000]))
    with pytest.raises(InputError, match=r"binary STL header announces 1280 triangles .*truncated"):
        read_surface(tmp_path / "cut.stl")


def test_binary_stl_with_a_bogus_triangle_count(tmp_path):
    """A count of 0 (or too small) that the records fill exactly is ignored; extra bytes are not."""
    data = _binary_stl(tmp_path)
    for count in (0, 1000):
        (tmp_path / "bogus.stl").write_bytes(data[:80] + np.uint32(count).tobytes() + data[84:])
        back = read_surface(tmp_path / "bogus.stl")
        assert back.volume() == pytest.approx(sphere().volume(), rel=1e-5)
        assert f"count {count} ignored: 1280 triangles" in back.source
    (tmp_path / "tail.stl").write_bytes(data + bytes(17))
    with pytest.raises(InputError, match=r"1280 whole triangles and 17 bytes more\); it is damaged"):
        read_surface(tmp_path / "tail.stl")


def test_ascii_stl_in_capitals_with_crlf(tmp_path):
    write_stl(sphere(), tmp_path / "low.stl", ascii=True)
    text = (tmp_path / "low.stl").read_text().upper().replace("\n", "\r\n")
    (tmp_path / "up.stl").write_text(text, newline="")
    back = read_surface(tmp_path / "up.stl")
    assert back.n_faces == 1280 and back.volume() == pytest.approx(sphere().volume(), rel=1e-6)


@pytest.mark.parametrize("ext", ["vtp", "vtk"])
def test_triangle_strips_are_read(tmp_path, ext):
    import pyvista as pv

    strips = pv.Icosphere(radius=40.0, nsub=3).strip()
    assert strips.n_strips > 0 and strips.GetNumberOfPolys() == 0
    strips.save(tmp_path / f"strips.{ext}")
    back = read_surface(tmp_path / f"strips.{ext}")
    assert back.n_faces == 1280 and abs(back.volume()) == pytest.approx(abs(sphere().volume()), rel=1e-6)


def test_obj_with_lines_and_points_is_read_quietly(tmp_path, capfd):
    s = sphere()
    v = "".join(f"v {x * 1e3} {y * 1e3} {z * 1e3}\n" for x, y, z in s.points)
    f = "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in s.faces)
    (tmp_path / "organ.obj").write_text(v + f + "l 1 2 3\np 4\n")
    back = read_surface(tmp_path / "organ.obj")
    assert back.n_faces == 1280
    out, err = capfd.readouterr()
    assert out == "" and err == ""


@pytest.mark.parametrize("name, content, match", [
    ("ply_named.stl", b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n", "holds a PLY surface, not the .stl"),
    ("mask.stl", b"\x1f\x8b\x08\x00" + bytes(40), r"gzip-compressed file, not the \.stl.*\.nii\.gz"),
    ("organ.stl.gz", b"\x1f\x8b\x08\x00" + bytes(40), r"unknown surface format '\.gz' \(it is gzip-compressed"),
    ("xml.vtk", b'<?xml version="1.0"?>\n<VTKFile type="PolyData">', r"VTK XML file, not the \.vtk.*\.vtp"),
    ("organ.obj", b"solid x\nfacet normal 0 0 0\nouter loop\n", "holds an STL surface, not the .obj"),
    ("organ.ply", b"# made by x\nv 1 2 3\nv 4 5 6\nf 1 2 3\n", "holds an OBJ surface, not the .ply"),
    ("organ", b"ply\nformat ascii 1.0\n", r"unknown surface format '\(no extension\)' \(it holds a PLY surface: "
                                          r"rename it to \.ply\)"),
])
def test_content_of_another_format_is_named(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_surface(tmp_path / name)


def test_binary_stl_under_another_suffix_is_named(tmp_path):
    (tmp_path / "organ.vtk").write_bytes(_binary_stl(tmp_path))
    with pytest.raises(InputError, match=r"holds an STL surface, not the \.vtk its name says; rename it to \.stl"):
        read_surface(tmp_path / "organ.vtk")


def test_nifti_with_a_sheared_affine_keeps_its_volume(tmp_path):
    """Gantry-tilted CT: the columns of the affine are not orthogonal; column norms alone grow the organ."""
    import nibabel as nib

    g = np.indices((40, 40, 40)) - 20.0
    mask = ((g ** 2).sum(axis=0) <= 144).astype(np.uint8)
    ortho = np.diag([1.5, 1.5, 1.5, 1.0])
    sheared = ortho.copy()
    sheared[0, 1] = 0.5  # the y column leans towards x; voxel volume still 1.5**3
    for name, aff in (("o.nii.gz", ortho), ("s.nii.gz", sheared)):
        nib.save(nib.Nifti1Image(mask, aff), tmp_path / name)
    a, b = read_surface(tmp_path / "o.nii.gz"), read_surface(tmp_path / "s.nii.gz")
    assert b.is_closed() and "sheared affine" in b.source
    assert abs(b.volume()) == pytest.approx(abs(a.volume()), rel=1e-9)
    singular = ortho.copy()
    singular[:3, 1] = singular[:3, 0]
    nib.save(nib.Nifti1Image(mask, singular), tmp_path / "z.nii.gz")
    with pytest.raises(InputError, match="affine is singular"):
        read_surface(tmp_path / "z.nii.gz")


def test_nifti_header_unit_is_used_unless_a_unit_is_given(tmp_path):
    """Some writers set 'meter' over voxel sizes in mm: the refusal named --unit, which had no effect."""
    import nibabel as nib

    g = np.indices((30, 30, 30)) - 15.0
    mask = ((g ** 2).sum(axis=0) <= 100).astype(np.uint8)
    for name, spacing in (("right.nii.gz", 0.0015), ("wrong.nii.gz", 1.5)):
        img = nib.Nifti1Image(mask, np.diag([spacing] * 3 + [1.0]))
        img.header.set_xyzt_units("meter")
        nib.save(img, tmp_path / name)
    right = read_surface(tmp_path / "right.nii.gz")
    assert 0.02 < right.extent() < 0.04 and "header's unit m used" in right.source
    with pytest.raises(InputError, match=r"^unit: .*wrong.nii.gz \(unit from its header\): the organ is 31.5\d* m "):
        read_surface(tmp_path / "wrong.nii.gz")
    wrong = read_surface(tmp_path / "wrong.nii.gz", unit="mm")
    assert wrong.extent() == pytest.approx(right.extent(), rel=1e-6)  # the header stores float32 and "overridden" in wrong.source


def test_nifti_with_nan_is_not_called_a_probability_map(tmp_path):
    import nibabel as nib

    data = np.zeros((20, 20, 20), np.float32)
    data[5:15, 5:15, 5:15] = 1.0
    data[0, 0, 0] = np.nan
    nib.save(nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0])), tmp_path / "nan.nii.gz")
    with pytest.raises(InputError, match="holds NaN or infinite values; the mask is corrupt"):
        read_surface(tmp_path / "nan.nii.gz")


def test_ply_with_strips_only_names_its_elements(tmp_path):
    (tmp_path / "strips.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                         "property float z\nelement tristrips 1\nproperty list int int vertex_indices\n"
                                         "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(InputError, match=r"no 'face' element \(it has: vertex, tristrips\)"):
        read_surface(tmp_path / "strips.ply")


def test_surface_from_mask_crops_to_the_label_and_keeps_the_origin():
    """Only the label's bounding box is surfaced (a CT-sized map took 1.2 GB); coordinates stay the scan's."""
    small = np.zeros((8, 8, 8), bool)
    small[2:6, 2:6, 2:6] = True
    big = np.zeros((60, 50, 40), bool)
    big[32:36, 22:26, 12:16] = True
    spacing = (0.8, 0.8, 1.5)
    p0, f0 = surface_from_mask(small, spacing=spacing)
    p1, f1 = surface_from_mask(big, spacing=spacing)
    np.testing.assert_array_equal(f0, f1)
    np.testing.assert_allclose(p1 - p0, np.tile([30 * 0.8, -20 * 0.8, 10 * 1.5], (p0.shape[0], 1)), atol=1e-12)
    assert p0[:, 0].min() == pytest.approx(1.5 * 0.8, abs=0.01)  # the 127 level: ~half a voxel outside
