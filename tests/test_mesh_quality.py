"""Tetrahedron quality measures against analytic values and against gmsh."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.mesh.quality import QUALITY_FLOORS, QualityReport, tet_measures, tet_quality
from esmm.pipeline.mesh.volume import VolumeMesh

FIXTURE = Path(__file__).parent / "data" / "meshes" / "gmsh_tet_qualities.json"

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
T = np.array([[0, 1, 3, 2]])  # positive orientation


def test_regular_tetrahedron():
    m = tet_measures(REGULAR, T)
    assert m["volume"][0] == pytest.approx(8 / 3)
    np.testing.assert_allclose(m["dihedral_deg"], math.degrees(math.acos(1 / 3)), rtol=1e-12)
    assert math.degrees(math.acos(1 / 3)) == pytest.approx(70.5288, abs=1e-4)
    for key in ("sicn", "gamma", "radius_ratio"):
        assert m[key][0] == pytest.approx(1.0, rel=1e-12)
    # edge a = 2 sqrt 2: r_in = a / (2 sqrt 6), R = a sqrt 6 / 4
    a = 2 * math.sqrt(2)
    assert m["inradius"][0] == pytest.approx(a / (2 * math.sqrt(6)))
    assert m["circumradius"][0] == pytest.approx(a * math.sqrt(6) / 4)


def test_measures_are_invariant_to_scale_rotation_and_vertex_order():
    rng = np.random.default_rng(5)
    pts = rng.random((4, 3))
    if np.linalg.det(np.array([pts[1] - pts[0], pts[2] - pts[0], pts[3] - pts[0]])) < 0:
        pts[[2, 3]] = pts[[3, 2]]
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    base = tet_measures(pts, np.array([[0, 1, 2, 3]]))
    moved = tet_measures(pts @ q.T * 7.5 + 3.0, np.array([[0, 1, 2, 3]]))
    cycled = tet_measures(pts, np.array([[1, 2, 0, 3]]))  # even permutation keeps the sign
    for key in ("sicn", "gamma", "radius_ratio", "min_dihedral_deg"):
        assert moved[key][0] == pytest.approx(base[key][0], rel=1e-10)
        assert cycled[key][0] == pytest.approx(base[key][0], rel=1e-10)


def test_right_corner_tetrahedron():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    m = tet_measures(pts, np.array([[0, 1, 2, 3]]))
    np.testing.assert_allclose(np.sort(m["dihedral_deg"][0]),
                               [math.degrees(math.acos(1 / math.sqrt(3)))] * 3 + [90.0] * 3)
    r, R = 1 / (3 + math.sqrt(3)), math.sqrt(3) / 2
    assert m["inradius"][0] == pytest.approx(r)
    assert m["circumradius"][0] == pytest.approx(R)
    assert m["radius_ratio"][0] == pytest.approx(3 * r / R)
    assert m["gamma"][0] == pytest.approx(2 * math.sqrt(6) * r / math.sqrt(2))


@pytest.mark.parametrize("eps", [1e-2, 1e-4])
def test_sliver_is_near_zero(eps):
    # Four points almost on a square: all edges fine, volume ~ 0.
    pts = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, eps], [0, -1, eps]], float)
    t = np.array([[0, 1, 2, 3]])
    if tet_measures(pts, t)["volume"][0] < 0:
        t = np.array([[0, 1, 3, 2]])
    m = tet_measures(pts, t)
    assert 0 < m["sicn"][0] < 5 * eps
    assert 0 < m["gamma"][0] < 5 * eps
    assert 0 < m["radius_ratio"][0] < 5 * eps
    assert m["min_dihedral_deg"][0] < 1.0 and m["max_dihedral_deg"][0] > 179.0 - 1e3 * eps


def test_inverted_element_has_negative_sicn():
    m = tet_measures(REGULAR, np.array([[0, 1, 2, 3]]))
    assert m["sicn"][0] == pytest.approx(-1.0)


def test_matches_gmsh():
    data = json.loads(FIXTURE.read_text())
    m = tet_measures(np.array(data["points"]), np.array(data["tets"]))
    np.testing.assert_allclose(m["sicn"], data["minSICN"], rtol=1e-6)
    np.testing.assert_allclose(m["radius_ratio"], data["gamma"], rtol=1e-6)  # gmsh's "gamma"
    np.testing.assert_allclose(m["inradius"], data["innerRadius"], rtol=1e-6)
    np.testing.assert_allclose(m["circumradius"], data["outerRadius"], rtol=1e-6)
    np.testing.assert_allclose(m["volume"], data["volume"], rtol=1e-6)


def _cube_mesh():
    """A unit cube cut into 6 tetrahedra (Kuhn triangulation)."""
    pts = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    idx = lambda x, y, z: 4 * x + 2 * y + z  # noqa: E731
    tets = []
    import itertools

    for perm in itertools.permutations(range(3)):
        path = [np.zeros(3, int)]
        for axis in perm:
            nxt = path[-1].copy()
            nxt[axis] = 1
            path.append(nxt)
        t = [idx(*v) for v in path]
        p = pts[t]
        if np.linalg.det(np.array([p[1] - p[0], p[2] - p[0], p[3] - p[0]])) < 0:
            t[2], t[3] = t[3], t[2]
        tets.append(t)
    return VolumeMesh(pts, np.array(tets), np.zeros((0, 3), int), "test", [])


def test_report_and_floors():
    mesh = _cube_mesh()
    q = tet_quality(mesh)
    assert isinstance(q, QualityReport)
    assert q.n_tets == 6 and q.n_nodes == 8
    assert q.volume == pytest.approx(1.0)
    # Kuhn tetrahedra: dihedral angles 45, 60 and 90 degrees.
    assert q.min_dihedral_deg == pytest.approx(45.0)
    assert q.max_dihedral_deg == pytest.approx(90.0)
    ok, problems = q.passes()
    assert ok and problems == []
    ok, problems = q.passes({**QUALITY_FLOORS, "min_dihedral_deg": 50.0})
    assert not ok and len(problems) == 1 and "min_dihedral_deg" in problems[0]
    with pytest.raises(KeyError):
        q.passes({"nonsense": 1.0})
    assert sum(q.percentiles["sicn_hist"][0]) == 6


def test_inverted_mesh_fails_the_floors():
    mesh = _cube_mesh()
    tets = mesh.tets.copy()
    tets[0, [2, 3]] = tets[0, [3, 2]]
    q = tet_quality(VolumeMesh(mesh.points, tets, mesh.boundary_faces, "test", []))
    ok, problems = q.passes()
    assert not ok and any("sicn_min" in p for p in problems)


def test_slivers_are_relocated_above_the_floor():
    """Slivers made by pushing an interior vertex towards a neighbour: relocated above 10 deg, volume kept."""
    from esmm.pipeline.mesh.quality import tet_measures
    from esmm.pipeline.mesh.slivers import SLIVER_TARGET_DEG, improve_slivers
    from esmm.pipeline.mesh.synthetic import box_tets
    from esmm.pipeline.network.springs import boundary_faces, tet_volumes

    b = box_tets(3, 3, 3, (0.03, 0.03, 0.03))
    t = b.tets.copy()
    neg = tet_volumes(b.points, t) < 0
    t[neg, 2], t[neg, 3] = t[neg, 3], t[neg, 2].copy()
    p = b.points.copy()
    v = 21                                     # the interior vertex at (1, 1, 1) cells
    assert np.allclose(p[v], 0.01)
    p[v] += np.array([0.0085, 0.0, 0.0])       # towards a neighbouring vertex: slivers (4.6 deg) around it
    before = tet_measures(p, t)["min_dihedral_deg"].min()
    assert before < 10.0 and np.all(tet_volumes(p, t) > 0)
    q, info = improve_slivers(p, t, boundary_faces(t))
    after = tet_measures(q, t)["min_dihedral_deg"].min()
    assert after >= SLIVER_TARGET_DEG and info["below_after"] == 0
    assert info["min_dihedral_before"] == pytest.approx(before)
    # boundary vertices move in their tangent plane only: the volume changes to second order
    assert tet_volumes(q, t).sum() == pytest.approx(tet_volumes(p, t).sum(), rel=1e-4)
    assert np.all(tet_volumes(q, t) > 0)


def test_boundary_sliver_is_relocated_in_the_face():
    """A sliver made by sliding a vertex of a flat face towards its neighbour: the vertex slides back in
    the face (the boundary and the volume do not change) and every angle ends above the floor."""
    from esmm.pipeline.mesh.quality import QUALITY_FLOORS, tet_measures
    from esmm.pipeline.mesh.slivers import SLIVER_TARGET_DEG, improve_slivers
    from esmm.pipeline.mesh.synthetic import box_tets
    from esmm.pipeline.network.springs import boundary_faces, tet_volumes

    assert SLIVER_TARGET_DEG == QUALITY_FLOORS["min_dihedral_deg"] >= 10.0
    b = box_tets(3, 3, 3, (0.03, 0.03, 0.03))
    t = b.tets.copy()
    neg = tet_volumes(b.points, t) < 0
    t[neg, 2], t[neg, 3] = t[neg, 3], t[neg, 2].copy()
    p = b.points.copy()
    v = int(np.flatnonzero(np.all(np.isclose(p, [0.0, 0.01, 0.01]), axis=1))[0])   # on the face x = 0
    p[v, 1] += 0.0085                          # towards its neighbour in the face
    before = tet_measures(p, t)["min_dihedral_deg"].min()
    assert before < SLIVER_TARGET_DEG and np.all(tet_volumes(p, t) > 0)
    q, info = improve_slivers(p, t, boundary_faces(t))
    assert tet_measures(q, t)["min_dihedral_deg"].min() >= SLIVER_TARGET_DEG and info["below_after"] == 0
    assert q[v, 0] == pytest.approx(0.0, abs=1e-12)          # stayed in its face
    assert tet_volumes(q, t).sum() == pytest.approx(0.03 ** 3, rel=1e-12)
