"""Every tet split in eight: the mesh, the network on the quadratic tets' nodes, its asset, its continuum reference.

The checks are geometric identities (volumes, midpoints), felupe's own
quadratic element (its Jacobians), and the P2 continuum solved two ways on
the same mesh (quadratic tets added by validate, and the split's own
quadratic cells), which must agree node for node.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.fidelity.cases import shear_case
from esmm.pipeline.fidelity.continuum import solve_continuum
from esmm.pipeline.fidelity.specimen import _gmsh_cube
from esmm.pipeline.materials.material import load_material
from esmm.pipeline.mesh.refine import TET10_EDGES, split_in_eight
from esmm.pipeline.network.springs import network_from_tets, tet_volumes


@pytest.fixture(scope="module")
def cube():
    """A coarse gmsh cube (20 mm, elements of 6.5 mm)."""
    return _gmsh_cube(20e-3, 6.5e-3)


def _split(points, tets):
    """A split mesh as network_from_tets reads it (points, tets, quadratic_cells)."""
    p, t, q = split_in_eight(points, tets)
    return SimpleNamespace(points=p, tets=t, quadratic_cells=q)


def test_split_fills_each_parent_with_eight_positive_children(cube):
    points, tets = cube
    p, t, q = split_in_eight(points, tets)
    edges = np.unique(np.sort(tets[:, np.array(TET10_EDGES)], axis=2).reshape(-1, 2), axis=0)
    assert p.shape[0] == points.shape[0] + edges.shape[0]
    assert np.array_equal(p[:points.shape[0]], points)
    assert t.shape == (8 * tets.shape[0], 4) and q.shape == (tets.shape[0], 10)
    child = tet_volumes(p, t)
    assert child.min() > 0
    np.testing.assert_allclose(child.reshape(-1, 8).sum(axis=1), np.abs(tet_volumes(points, tets)), rtol=1e-12)
    # every child lies in its parent: its nodes are among the parent's ten
    assert all(set(c) <= set(par) for c, par in zip(t.reshape(-1, 32), q, strict=True))
    for k, (i, j) in enumerate(TET10_EDGES):
        np.testing.assert_allclose(p[q[:, 4 + k]], 0.5 * (p[q[:, i]] + p[q[:, j]]), rtol=0, atol=1e-15)


def test_split_turns_a_negatively_oriented_parent(cube):
    points, tets = cube
    flipped = tets.copy()
    flipped[::2] = flipped[::2][:, [0, 2, 1, 3]]
    _, t, q = split_in_eight(points, flipped)
    _, t0, q0 = split_in_eight(points, tets)
    assert tet_volumes(points, q[:, :4]).min() > 0
    assert tet_volumes(*split_in_eight(points, flipped)[:2]).min() > 0
    assert np.array_equal(np.sort(q, axis=1), np.sort(q0, axis=1))


def test_quadratic_cells_are_felupe_tetra10(cube):
    """felupe's quadratic tetrahedron on the cells: constant positive Jacobian (straight edges), the exact volume."""
    import felupe as fem

    points, tets = cube
    p, _, q = split_in_eight(points, tets)
    region = fem.RegionQuadraticTetra(fem.Mesh(p, q, "tetra10"))
    dV = region.dV                                        # (quadrature points, cells)
    assert dV.min() > 0
    np.testing.assert_allclose(dV.sum(), 8e-6, rtol=1e-10)
    np.testing.assert_allclose(dV.sum(axis=0), np.abs(tet_volumes(points, tets)), rtol=1e-10)


def test_the_network_carries_its_quadratic_cells_through_the_renumbering(cube):
    points, tets = cube
    m = _split(points, tets)
    net = network_from_tets(m, reorder="rcm")
    q = net.quadratic_cells
    assert q.shape == (tets.shape[0], 10)
    assert not np.array_equal(net.points, m.points)      # RCM renumbered the nodes ...
    for k, (i, j) in enumerate(TET10_EDGES):              # ... and the cells with them
        np.testing.assert_allclose(net.points[q[:, 4 + k]], 0.5 * (net.points[q[:, i]] + net.points[q[:, j]]),
                                   atol=1e-15)
    assert np.array_equal(np.unique(q), np.arange(net.n_nodes))


def test_a_bad_quadratic_cells_array_is_refused(cube):
    from esmm.pipeline.errors import InputError

    m = _split(*cube)
    m.quadratic_cells = m.quadratic_cells[:, :9]
    with pytest.raises(InputError, match="quadratic_cells"):
        network_from_tets(m)


def test_p2_on_the_split_nodes_is_p2_on_the_parent_mesh(cube):
    """The clamped shear: P2 with validate's own midside nodes and P2 on the split's quadratic cells agree."""
    import dataclasses

    points, tets = cube
    mat = load_material("porcine_liver_paper")
    parent = shear_case(points, tets, gamma=0.1)
    p, t, q = split_in_eight(points, tets)
    split = dataclasses.replace(shear_case(p, t, gamma=0.1), quadratic_cells=q)
    a = solve_continuum(parent, mat, steps=2)
    b = solve_continuum(split, mat, steps=2)
    n = points.shape[0]
    scale = np.abs(a.displacement).max()
    np.testing.assert_allclose(b.displacement[:n], a.displacement, atol=1e-7 * scale)
    np.testing.assert_allclose(b.reactions["top"], a.reactions["top"], rtol=1e-6)
    assert b.info["dofs"] == a.info["dofs"]


def test_split_config_key_is_checked():
    from esmm.pipeline.prepare import prepare_config

    assert prepare_config(None).split is False
    assert prepare_config(None, split=True).split is True
    assert prepare_config({"mesh": {"split": True}}).split is True
    with pytest.raises(ConfigError, match=r"\[mesh\] split: expected true or false"):
        prepare_config({"mesh": {"split": "yes"}})
    with pytest.raises(ConfigError, match="split: sets the tet mesh"):
        prepare_config({"prepare": {"structure": "skeleton"}}, split=True)


def test_prepare_split_writes_the_quadratic_cells(tmp_path, bundled_data):
    """The coarse liver split: 8x the tets, the asset keeps the parents, and the mesh passes the floors."""
    from esmm.pipeline.asset import read_asset, validate_asset
    from esmm.pipeline.prepare import prepare

    stl = bundled_data / "meshes" / "ts_liver_3mm_closed.stl"
    res = prepare(stl, output=tmp_path / "split.h5", config="coarse", compensate=False, split=True)
    assert res.quality_passed and res.mesher.endswith("+split")
    net = read_asset(res.asset).network
    assert validate_asset(res.asset) == []
    assert read_asset(res.asset).summary()["split_from"] == net.quadratic_cells.shape[0]
    q = net.quadratic_cells
    assert net.n_tets == 8 * q.shape[0]
    np.testing.assert_allclose(net.total_volume(), np.abs(tet_volumes(net.points, q[:, :4])).sum(), rtol=1e-12)
    np.testing.assert_allclose(net.points[q[:, 4]], 0.5 * (net.points[q[:, 0]] + net.points[q[:, 1]]), atol=1e-15)


def test_validate_solves_p2_on_a_split_networks_parents(cube):
    """Through validate_network: the continuum's unknowns are exactly the split network's nodes."""
    from esmm.pipeline.fidelity.validate import LoadOptions, validate_network
    from esmm.pipeline.network.tables import build_tables

    points, tets = cube
    net = network_from_tets(_split(points, tets))
    mat = load_material("porcine_liver_paper")
    rep = validate_network(net, build_tables(mat), mat, cases=["shear"], loads=LoadOptions(gamma=0.05))
    res = rep.results[0]
    assert rep.info["element"] == "p2" and rep.info["split_from"] == tets.shape[0]
    assert res.continuum.info["dofs"] == 3 * net.n_nodes
    assert res.continuum.displacement.shape == net.points.shape
