"""The InVesalius-like generator really has the defects the tests rely on."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.mesh.cleaning import capped_volume, face_components
from esmm.pipeline.mesh.surface import Surface
from esmm.pipeline.mesh.synthetic import invesalius_like_surface


def _bodies(s: Surface):
    n, lab = face_components(s.n_points, s.faces)
    return n, lab


def test_all_defects():
    s = invesalius_like_surface(voxel=(2.0, 2.0, 3.0), islands=True, handle=True, open_border=True,
                                second_body=True, seed=0)
    n, lab = _bodies(s)
    assert n == 6  # organ, second body, four specks
    sizes = np.sort(np.bincount(lab))[::-1]
    assert sizes[2] < 0.01 * sizes[0]  # the specks are tiny
    assert s.n_boundary_edges() > 0  # the scan border cuts the organ
    assert 0.1 < s.extent() < 0.4  # an adult-liver size, in metres


def test_clean_variant_is_a_closed_genus_one_body():
    s = invesalius_like_surface(voxel=(2.0, 2.0, 3.0), islands=False, handle=True, open_border=False)
    assert s.is_closed()
    assert _bodies(s)[0] == 1
    assert s.euler_characteristic() == 0  # the handle
    assert s.volume() > 0  # outward after the Y flip
    flat = invesalius_like_surface(voxel=(2.0, 2.0, 3.0), islands=False, handle=False, open_border=False)
    assert flat.euler_characteristic() == 2


def test_inward_normals_and_stl(tmp_path):
    from esmm.pipeline.mesh.readers import read_surface

    a = invesalius_like_surface(voxel=(3.0, 3.0, 4.0), seed=2)
    b = invesalius_like_surface(voxel=(3.0, 3.0, 4.0), seed=2, inward_normals=True, path=tmp_path / "x.stl")
    assert capped_volume(b.points, b.faces) == pytest.approx(-capped_volume(a.points, a.faces))
    back = read_surface(tmp_path / "x.stl")
    assert back.n_faces == b.n_faces


def test_voxel_controls_the_density():
    coarse = invesalius_like_surface(voxel=(3.0, 3.0, 6.0), islands=False)
    fine = invesalius_like_surface(voxel=(1.5, 1.5, 3.0), islands=False)
    assert 3.0 < fine.n_faces / coarse.n_faces < 5.0  # ~ 1 / voxel area
