"""Skeleton + surface structure: inside, connected, not a mechanism."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError, MeshingError
from esmm.pipeline.mesh.skeleton import (
    SkeletonStructure,
    skeleton_structure,
    smallest_free_eigenvalue,
    stiffness_matrix,
)
from esmm.pipeline.mesh.surface import Surface


def ellipsoid(a=0.06, b=0.04, c=0.03, nsub=4):
    import pyvista as pv

    s = pv.Icosphere(radius=1.0, nsub=nsub)
    s.points *= np.array([a, b, c])
    return Surface.from_pyvista(s, source="ellipsoid")


def test_single_spring_stiffness_is_analytic():
    pts = np.array([[0, 0, 0], [0.3, 0.4, 0.0]])
    K = stiffness_matrix(pts, np.array([[0, 1]])).toarray()
    u = np.array([0.6, 0.8, 0.0])
    k = 1 / 0.5
    np.testing.assert_allclose(K[:3, :3], k * np.outer(u, u))
    np.testing.assert_allclose(K[:3, 3:], -k * np.outer(u, u))


def test_tetrahedron_frame_has_exactly_the_rigid_modes():
    rng = np.random.default_rng(2)
    pts = rng.random((4, 3))
    edges = np.array([(i, j) for i in range(4) for j in range(i + 1, 4)])
    w = np.linalg.eigvalsh(stiffness_matrix(pts, edges).toarray())
    assert np.sum(np.abs(w) < 1e-10 * w.max()) == 6  # 3 translations + 3 rotations
    # Held at one face (3 nodes), the frame is rigid.
    lam, scale = smallest_free_eigenvalue(pts, edges, np.array([0, 1, 2]))
    assert lam > 1e-3 * scale


def test_a_four_bar_loop_is_a_mechanism():
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    lam, scale = smallest_free_eigenvalue(pts, edges, np.array([0]))
    assert abs(lam) < 1e-12 * scale


def _springs_inside(sk: SkeletonStructure, surf: Surface, samples: int = 9) -> bool:
    """Independent check: points along every spring with an interior end lie inside."""
    import pyvista as pv

    ns = sk.n_surface
    e = sk.edges[sk.edges[:, 1] >= ns]
    t = np.linspace(0.1, 1.0, samples)
    a, b = sk.points[e[:, 0]], sk.points[e[:, 1]]
    pts = (a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]).reshape(-1, 3)
    sel = pv.PolyData(pts).select_interior_points(surf.to_pyvista(), check_surface=False)
    return bool(np.asarray(sel.point_data["selected_points"], bool).all())


def test_ellipsoid_structure():
    surf = ellipsoid()
    sk = skeleton_structure(surf, n_surface=150)
    assert sk.points.shape[0] == sk.kind.shape[0]
    assert sk.n_surface <= 160 and sk.n_skeleton >= 4  # a convex blob thins to a stub: deep points added
    assert np.all(sk.kind[:sk.n_surface] == 0) and np.all(sk.kind[sk.n_surface:] == 1)
    assert Surface(sk.points[:sk.n_surface], sk.surface_faces).is_closed()
    assert np.all(sk.edges[:, 0] < sk.edges[:, 1])
    assert np.unique(sk.edges, axis=0).shape[0] == sk.edges.shape[0]
    dec = Surface(sk.points[:sk.n_surface], sk.surface_faces)
    assert _springs_inside(sk, dec)
    # every surface vertex has k = 2 springs to the interior
    inner = sk.edges[(sk.edges[:, 1] >= sk.n_surface) & (sk.edges[:, 0] < sk.n_surface)]
    links = np.bincount(inner[:, 0], minlength=sk.n_surface)
    assert links.min() >= 2
    # not a mechanism, checked independently with a dense eigen-solve and another held patch
    held = np.argsort(sk.points[:, 0])[:5]
    K = stiffness_matrix(sk.points, sk.edges).toarray()
    free = np.setdiff1d(np.arange(sk.points.shape[0]), held)
    dof = (3 * free[:, None] + np.arange(3)).ravel()
    w = np.linalg.eigvalsh(K[np.ix_(dof, dof)])
    assert w[0] > 1e-9 * np.diag(K).mean()


@pytest.mark.slow
def test_genus_one_organ():
    from esmm.pipeline.mesh.cleaning import clean_surface
    from esmm.pipeline.mesh.synthetic import invesalius_like_surface

    raw = invesalius_like_surface(voxel=(2.0, 2.0, 3.0), handle=True, islands=False, open_border=False)
    clean, _ = clean_surface(raw)
    assert clean.euler_characteristic() == 0
    sk = skeleton_structure(clean, n_surface=800)
    dec = Surface(sk.points[:sk.n_surface], sk.surface_faces)
    assert _springs_inside(sk, dec)


@pytest.mark.slow
def test_shared_liver(shared_data):
    from esmm.pipeline.mesh.cleaning import clean_surface
    from esmm.pipeline.mesh.readers import read_surface

    clean, _ = clean_surface(read_surface(shared_data / "meshes" / "sofa_liver.stl"))
    sk = skeleton_structure(clean)
    dec = Surface(sk.points[:sk.n_surface], sk.surface_faces)
    assert dec.is_closed()
    assert _springs_inside(sk, dec)
    assert any("rigid" in line for line in sk.log)


def test_bad_input():
    s = ellipsoid(nsub=2)
    with pytest.raises(MeshingError, match="closed"):
        skeleton_structure(Surface(s.points, s.faces[1:]))
    with pytest.raises(ConfigError, match="n_surface"):
        skeleton_structure(s, n_surface=5)
    with pytest.raises(ConfigError, match="k"):
        skeleton_structure(s, k=0)
