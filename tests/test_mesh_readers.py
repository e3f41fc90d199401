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
