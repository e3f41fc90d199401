"""What a lift's grasped nodes hold: the network's surface triangles against P2's parent faces (analytic counts)."""

from __future__ import annotations

import dataclasses

import numpy as np
from esmm.pipeline.fidelity.cases import Constraint, LoadCase, grasp_hold, parent_faces
from esmm.pipeline.fidelity.validate import _warn_patch
from esmm.pipeline.mesh.readers import boundary_of_tets
from esmm.pipeline.mesh.refine import split_in_eight


def _split_tet():
    """One tetrahedron split in eight; its 10-node cell lists its corners, then the middles of 01, 12, 20, 03,
    13, 23."""
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    pts, tets, cells = split_in_eight(p, np.array([[0, 1, 2, 3]]))
    return pts, tets, cells


def _lift(pts, tets, cells, grasped) -> LoadCase:
    g = np.asarray(grasped)
    cons = (Constraint.clamp("grasper", g, (0.0, 0.0, 1e-3)),)
    return LoadCase("lift", "", pts, tets, cons, "grasper", quadratic_cells=cells)


class _Rep:
    def __init__(self):
        self.warnings = []

    def warn(self, message):
        self.warnings.append(message)


def test_parent_faces_are_the_four_faces_of_a_single_parent():
    pts, tets, cells = _split_tet()
    f = parent_faces(cells)
    assert f.shape == (4, 6)
    # each face's middles are the middles of its corners' edges
    for face in f:
        for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
            assert np.allclose(pts[face[3 + k]], 0.5 * (pts[face[a]] + pts[face[b]]))


def test_a_corner_and_its_two_middles_hold_one_child_triangle_and_no_parent_face():
    pts, tets, cells = _split_tet()
    surface = boundary_of_tets(pts, tets)
    assert surface.shape[0] == 16          # four faces, four children each
    c = cells[0]
    case = _lift(pts, tets, cells, c[[0, 4, 6]])      # corner 0, the middles of 01 and 20: face 012's corner child
    hold = grasp_hold(case, surface)
    assert hold == {"grasped_nodes": 3, "surface_triangles_held": 1, "parent_faces_held": 0, "network_only": 1}
    rep = _Rep()
    _warn_patch(dataclasses.replace(case, load={"grasp_hold": hold}), rep)
    assert len(rep.warnings) == 1 and "different patches" in rep.warnings[0]


def test_a_whole_parent_face_is_held_alike_by_both():
    pts, tets, cells = _split_tet()
    surface = boundary_of_tets(pts, tets)
    case = _lift(pts, tets, cells, cells[0, [0, 1, 2, 4, 5, 6]])     # face 012 with its middles
    hold = grasp_hold(case, surface)
    assert hold == {"grasped_nodes": 6, "surface_triangles_held": 4, "parent_faces_held": 1, "network_only": 0}
    rep = _Rep()
    _warn_patch(dataclasses.replace(case, load={"grasp_hold": hold}), rep)
    assert rep.warnings == []


def test_an_unsplit_network_is_not_compared_with_parent_faces():
    pts, tets, _ = _split_tet()
    case = _lift(pts, tets, None, [0, 1, 2])       # three corners: no split triangle has them all
    assert grasp_hold(case, boundary_of_tets(pts, tets)) == {"grasped_nodes": 3, "surface_triangles_held": 0}
