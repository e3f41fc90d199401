"""Surface geometry and topology against analytic values."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.mesh.surface import Surface, cross3, triple


def cube(a=2.0, centre=(0.0, 0.0, 0.0)):
    """Closed, outward cube of side a: 8 points, 12 triangles."""
    p = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * a
    p += np.asarray(centre) - a / 2
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = []
    for q in quads:
        f += [(q[0], q[1], q[2]), (q[0], q[2], q[3])]
    return Surface(p, np.array(f))


def icosphere(r=1.0, subdiv=3):
    import pyvista as pv

    s = pv.Icosphere(radius=r, nsub=subdiv)
    return Surface.from_pyvista(s)


def test_cube_volume_area_bounds():
    s = cube(2.0, centre=(5.0, -3.0, 1.0))
    assert s.volume() == pytest.approx(8.0, rel=1e-12)
    assert s.area() == pytest.approx(24.0, rel=1e-12)
    np.testing.assert_allclose(s.bounds(), [[4, -4, 0], [6, -2, 2]])
    assert s.is_closed() and s.n_boundary_edges() == 0 and s.n_nonmanifold_edges() == 0
    assert s.euler_characteristic() == 2


def test_inward_cube_has_negative_volume():
    s = cube()
    inv = Surface(s.points, s.faces[:, ::-1])
    assert inv.volume() == pytest.approx(-8.0)


def test_open_box_counts_its_border_edges():
    s = cube()
    top = np.all(s.points[s.faces][:, :, 2] > 0, axis=1)
    open_box = Surface(s.points, s.faces[~top])
    assert open_box.n_boundary_edges() == 4
    assert not open_box.is_closed()


def test_sphere_volume_converges():
    s = icosphere(0.05, 4)
    assert s.volume() == pytest.approx(4 / 3 * np.pi * 0.05 ** 3, rel=5e-3)
    assert s.area() == pytest.approx(4 * np.pi * 0.05 ** 2, rel=5e-3)


def test_nonmanifold_edge_detected():
    s = cube()
    fin = Surface(np.vstack([s.points, [[0, 0, 5.0]]]),
                  np.vstack([s.faces, [[0, 1, 8]]]))  # a fin on edge (0, 1)
    assert fin.n_nonmanifold_edges() == 1
    assert not fin.is_closed()


def test_cross_and_triple_match_numpy():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 50, 3))
    np.testing.assert_allclose(cross3(a, b), np.cross(a, b))
    np.testing.assert_allclose(triple(a, b, c), np.einsum("ij,ij->i", a, np.cross(b, c)))


def test_compact_and_pyvista_roundtrip():
    s = cube()
    extra = Surface(np.vstack([s.points, [[9, 9, 9]]]), s.faces)
    assert extra.compact().n_points == 8
    back = Surface.from_pyvista(s.to_pyvista())
    assert back.volume() == pytest.approx(s.volume())
