"""esmm validate: the continuum reference verified against analytic solutions, the network solve,
the cases and the command (docs/design/validation.md)."""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
from esmm.cli.main import main
from esmm.pipeline.errors import ConfigError, SimulationError
from esmm.pipeline.fidelity.cases import (
    Constraint,
    Floor,
    LoadCase,
    oriented,
    shear_case,
    uniaxial_case,
    with_floor_pins,
)
from esmm.pipeline.fidelity.continuum import quadratic_tets, solve_continuum
from esmm.pipeline.fidelity.material import IsochoricMaterial, bulk_modulus, tangent_shear_modulus
from esmm.pipeline.fidelity.network_solve import solve_network
from esmm.pipeline.fidelity.validate import network_terms, validate_network
from esmm.pipeline.materials.loading import nominal_stress, stress_tangent
from esmm.pipeline.materials.material import Material
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.tables import build_tables
from esmm.pipeline.network.volume import bulk_modulus as bulk_modulus_spec
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.volumeterm import build_volume_term

L = 0.01


@pytest.fixture(scope="module")
def block():
    b = box_tets(3, 3, 3, (L, L, L))
    return b.points, oriented(b.points, b.tets)


def _reference(material, mode, x):
    return float(nominal_stress(material.model_obj, material.params_for(None), mode, x))


def test_material_derivatives_match_finite_differences(liver):
    um = IsochoricMaterial(liver, bulk=1e6)
    rng = np.random.default_rng(3)
    F = np.eye(3)[:, :, None, None] + 0.08 * rng.standard_normal((3, 3, 2, 3))
    P = um.gradient([F, None])[0]
    A = um.hessian([F, None])[0]
    h = 1e-7
    for k in range(3):
        for m in range(3):
            dF = np.zeros_like(F)
            dF[k, m] = h
            dA = (um.gradient([F + dF, None])[0] - um.gradient([F - dF, None])[0]) / (2 * h)
            assert np.abs(dA - A[:, :, k, m]).max() < 1e-6 * np.abs(A).max()
    # the isochoric stress is the derivative of the energy
    iso = IsochoricMaterial(liver)
    P0 = iso.gradient([F, None])[0]
    for k in range(3):
        for m in range(3):
            dF = np.zeros_like(F)
            dF[k, m] = h
            dW = (iso.energy(F + dF) - iso.energy(F - dF)) / (2 * h)
            assert np.abs(dW - P0[k, m]).max() < 1e-6 * np.abs(P0).max()
    assert not np.allclose(P, P0)   # the volumetric part acts off J = 1


def test_bulk_modulus_is_sized_on_the_tangent(liver):
    mu_t = tangent_shear_modulus(liver)
    et13 = float(stress_tangent(liver.model_obj, liver.params_for(None), "uniaxial", 1.3))
    assert mu_t == pytest.approx(et13 / 3, rel=1e-3)          # the stiffest point of 0.9..1.3 is 1.3
    assert mu_t > 30 * liver.youngs_modulus() / 3     # far above the small-strain modulus
    assert bulk_modulus(liver, ratio=500) == pytest.approx(500 * mu_t)
    with pytest.raises(ConfigError, match="bulk_ratio"):
        bulk_modulus(liver, ratio=-1)


@pytest.mark.parametrize("element", ["p2", "mini"])
@pytest.mark.parametrize("stretch", [0.8, 0.9, 1.1, 1.3])
def test_continuum_uniaxial_matches_analytic(block, liver, element, stretch):
    case = uniaxial_case(*block, stretch=stretch)
    sol = solve_continuum(case, liver, element=element)
    P = -sol.reactions["top"][2] / case.load["area_m2"]
    assert P == pytest.approx(_reference(liver, "uniaxial", stretch), rel=5e-3)
    # homogeneous: lateral contraction lambda^-1/2 about the held centre node, volume kept
    bottom = case.constraint("bottom")
    c = bottom.nodes[bottom.mask[:, 0] & bottom.mask[:, 1]][0]
    X = case.points
    lateral = (stretch ** -0.5 - 1.0) * (X[:, :2] - X[c, :2])
    umax = np.abs(sol.displacement).max()
    assert np.abs(sol.displacement[:, :2] - lateral).max() < 5e-3 * umax
    assert abs(sol.volume_ratio - 1) < 1e-3 and sol.inverted == 0


@pytest.mark.parametrize("gamma", [0.1, 0.3, 0.5])
def test_continuum_simple_shear_matches_analytic(block, liver, gamma):
    X, tets = block
    on_boundary = np.any((X < 1e-9) | (X > L - 1e-9), axis=1)
    top = np.flatnonzero(X[:, 1] > L - 1e-9)
    rest = np.setdiff1d(np.flatnonzero(on_boundary), top)
    U = np.zeros_like(X)
    U[:, 0] = gamma * X[:, 1]
    case = LoadCase("shear", "homogeneous simple shear", X, tets,
                    (Constraint.clamp("top", top, U[top]), Constraint.clamp("sides", rest, U[rest])), "top")
    sol = solve_continuum(case, liver)
    # the x-faces are translates of each other: their shares of P11 on the top edges cancel
    P12 = -sol.reactions["top"][0] / (L * L)
    assert P12 == pytest.approx(_reference(liver, "simple_shear", gamma), rel=5e-3)
    assert np.abs(sol.displacement - U).max() < 1e-8 * gamma * L


def test_condensed_mini_solves_the_whole_system(block, liver):
    """The MINI system with its bubbles condensed element by element gives the whole LU's answer."""
    import felupe as fem
    from esmm.pipeline.fidelity.continuum import _discretise
    from esmm.pipeline.fidelity.linear import CondensedMini, lu_solve

    case = uniaxial_case(*block, stretch=1.1)
    field, solid, _, mask, _, ncells = _discretise(fem, case, liver, bulk_modulus(liver), "mini")
    dof1 = np.flatnonzero(~np.concatenate([mask.ravel(), np.zeros(field.fieldsizes[1] * 2, bool)]))
    A = solid.assemble.matrix(field).tocsr()[dof1][:, dof1]
    b = np.cos(np.arange(A.shape[0]))
    solver = CondensedMini(dof1, case.n_nodes, ncells)
    x = solver(A, b)
    assert solver.count == 1 and np.abs(A @ x - b).max() < 1e-10 * abs(A).max() * np.abs(x).max()
    assert np.abs(x - lu_solve(A, b)).max() < 1e-6 * np.abs(x).max()


def test_p2_factorization_in_node_order_is_the_lu(block, liver):
    """The P2 system's LDLᵀ in nested-dissection order gives the LU's answer, with less fill than its COLAMD."""
    import felupe as fem
    import scipy.sparse.linalg as spl
    from esmm.pipeline.fidelity.continuum import _discretise
    from esmm.pipeline.fidelity.linear import NodeDissection, lu_solve

    case = shear_case(*block, gamma=0.2)
    field, solid, _, mask, _, _ = _discretise(fem, case, liver, bulk_modulus(liver), "p2")
    dof1 = np.flatnonzero(~mask.ravel())
    A = solid.assemble.matrix(field).tocsr()[dof1][:, dof1]
    b = np.cos(np.arange(A.shape[0]))
    solver = NodeDissection(dof1)
    x = solver(A, b)
    assert solver.count == 1 and solver.fallbacks == 0
    assert np.abs(x - lu_solve(A, b)).max() < 1e-8 * np.abs(x).max()
    p = solver.perm
    assert np.array_equal(np.sort(p), np.arange(A.shape[0]))
    ours = spl.splu(A[p][:, p].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    colamd = spl.splu(A.tocsc(), permc_spec="COLAMD")
    assert ours.L.nnz + ours.U.nnz < colamd.L.nnz + colamd.U.nnz


def test_p2_factorization_falls_back_to_the_lu_on_a_tiny_pivot():
    """An indefinite matrix whose diagonal pivots grow without bound is solved by the LU instead."""
    import scipy.sparse as sp
    from esmm.pipeline.fidelity.linear import NodeDissection

    A = sp.bmat([[1e-17 * sp.identity(3), sp.identity(3)], [sp.identity(3), None]]).tocsr()
    solver = NodeDissection(np.arange(6))
    x = solver(A, np.arange(6.0))
    assert solver.fallbacks == 1 and np.allclose(x, [3, 4, 5, 0, 1, 2])


@pytest.mark.parametrize("element", ["p2", "mini"])
def test_continuum_warm_start_reaches_the_same_equilibrium(block, liver, element):
    """Started from the solution of another stretch, the solve ends where a solve from rest does."""
    cold = solve_continuum(uniaxial_case(*block, stretch=1.2), liver, element=element)
    first = solve_continuum(uniaxial_case(*block, stretch=1.1), liver, element=element)
    warm = solve_continuum(uniaxial_case(*block, stretch=1.2), liver, element=element, start=first, steps=1)
    assert warm.info["warm_start"] and not cold.info["warm_start"]
    assert np.abs(warm.displacement - cold.displacement).max() < 1e-6 * np.abs(cold.displacement).max()
    assert warm.reactions["top"] == pytest.approx(cold.reactions["top"], rel=1e-6)


def test_continuum_gives_up_after_its_iteration_budget(block, liver):
    with pytest.raises(SimulationError, match="Newton iterations"):
        solve_continuum(uniaxial_case(*block, stretch=1.2), liver, element="mini", budget=2)


def test_a_case_without_equilibrium_is_reported_and_the_others_run(small_network, liver, monkeypatch):
    import esmm.pipeline.fidelity.validate as V

    real = V.solve_continuum

    def fails_on_tension(case, *args, **kw):
        if case.name == "tension":
            raise SimulationError("continuum reference: no equilibrium (test)")
        return real(case, *args, **kw)

    monkeypatch.setattr(V, "solve_continuum", fails_on_tension)
    net, tables = small_network
    rep = validate_network(net, tables, liver, cases=["tension", "shear"], element="p2")
    assert [r.case.name for r in rep.results] == ["shear"]
    assert "tension" in rep.info["failed"] and "| tension | no equilibrium:" in rep.table()


def test_auto_element_solves_with_mini_a_case_p2_finds_no_equilibrium_for(small_network, liver, monkeypatch):
    import esmm.pipeline.fidelity.validate as V

    real, tried = V.solve_continuum, []

    def p2_fails_on_tension(case, *args, element, **kw):
        tried.append((case.name, element))
        if case.name == "tension" and element == "p2":
            raise SimulationError("continuum reference: no equilibrium (test)")
        return real(case, *args, element=element, **kw)

    monkeypatch.setattr(V, "solve_continuum", p2_fails_on_tension)
    net, tables = small_network
    rep = validate_network(net, tables, liver, cases=["tension", "shear"], jobs=1)   # *tried* is this process's
    assert tried == [("tension", "p2"), ("tension", "mini"), ("shear", "p2")]
    tension, shear = rep.results
    assert tension.continuum.info["element"] == "mini" and "p2: " in tension.continuum.info["element_fallback"]
    assert "element_fallback" not in shear.continuum.info
    assert "| tension (mini) |" in rep.table() and "| shear |" in rep.table() and not rep.info["failed"]


def test_continuum_prints_nothing(block, liver, capsys):
    solve_continuum(uniaxial_case(*block, stretch=1.1), liver, steps=2)
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_quadratic_tets_put_a_node_on_every_edge(block):
    X, tets = block
    p10, cells, edges = quadratic_tets(X, tets)
    n = X.shape[0]
    assert np.array_equal(p10[:n], X) and cells.shape == (tets.shape[0], 10)
    assert np.allclose(p10[cells[:, 4]], 0.5 * (X[tets[:, 0]] + X[tets[:, 1]]))
    assert np.allclose(p10[n:], 0.5 * (X[edges[:, 0]] + X[edges[:, 1]]))


def test_anisotropic_material_is_refused(block):
    m = Material("esedf", {"mu": 2.973, "N": 1.1074, "A1": 3.9106e6, "A2": 4.519193e8, "f": 0.0019},
                 directions={"x": {"A1": 4.2e6}})
    with pytest.raises(ConfigError, match="isotropic"):
        IsochoricMaterial(m)


def test_rigid_modes_do_not_restrain_the_lateral_strain(block):
    case = uniaxial_case(*block, stretch=1.2)
    bottom = case.constraint("bottom")
    held = bottom.nodes[bottom.mask[:, 0] | bottom.mask[:, 1]]
    assert held.size == 2
    c = bottom.nodes[bottom.mask[:, 0] & bottom.mask[:, 1]][0]
    r = held[held != c][0]
    k = int(np.flatnonzero(bottom.mask[bottom.nodes == r][0, :2])[0])
    assert case.points[r, k] == pytest.approx(case.points[c, k])   # c-r is a coordinate line


def test_floor_pins_sit_on_the_plane_under_the_rest_position(block):
    X, tets = block
    case = LoadCase("gravity", "", X, tets, (Constraint.clamp("anchor", [0]),), "anchor",
                    gravity=np.array([0, 0, -9.8]), floor=Floor(np.array([0.0, 0, 1]), -1e-3))
    pinned = with_floor_pins(case, [0, 5, 7])
    fl = pinned.constraint("floor")
    assert list(fl.nodes) == [5, 7]                       # node 0 belongs to the anchor
    assert np.allclose((X[fl.nodes] + fl.displacement)[:, 2], -1e-3)
    assert np.allclose(fl.displacement[:, :2], 0.0)       # sticking: no tangential motion


@pytest.fixture(scope="module")
def small_network(liver):
    b = box_tets(4, 3, 3, (0.04, 0.03, 0.03))
    net = network_from_tets(b)
    return net, build_tables(liver)


def test_network_newton_is_the_simulators_equilibrium(small_network):
    net, tables = small_network
    anchor = np.flatnonzero(net.points[:, 0] < 1e-9)
    g = np.array([0.0, 0.0, -9.80665])   # uncompensated tables: a sag of a few % of the length
    case = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=g, density=1.0)
    sol = solve_network(case, net, tables)
    sim = Simulator(build_spring_term(net, tables), net.points, net.mass, fixed=anchor, gravity=g)
    sim.relax(rtol=1e-10, max_iter=2_000_000)
    u_fire = sim.displacement()
    umax = np.abs(u_fire).max()
    assert 0.01 * 0.04 < umax < 0.5 * 0.04
    assert np.abs(sol.displacement - u_fire).max() < 1e-4 * umax
    # the anchor carries the weight
    assert sol.reactions["anchor"] == pytest.approx(net.mass.sum() * g, rel=1e-8)


def test_network_warm_start_reaches_the_same_equilibrium(small_network):
    """From the equilibrium without a pin, with gravity on, to the one with a pin: as a solve from rest."""
    net, tables = small_network
    anchor = np.flatnonzero(net.points[:, 0] < 1e-9)
    g = np.array([0.0, 0.0, -9.80665])
    free_end = np.flatnonzero(net.points[:, 0] > 0.04 - 1e-9)
    base = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=g, density=1.0)
    pinned = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),
                      Constraint.clamp("end", free_end)), "anchor", gravity=g, density=1.0)
    first = solve_network(base, net, tables)
    assert np.abs(first.displacement[free_end]).max() > 1e-3          # the end sags; the pin lifts it back
    warm = solve_network(pinned, net, tables, start=first, steps=2)
    cold = solve_network(pinned, net, tables)
    assert warm.info["warm_start"]
    assert np.abs(warm.displacement - cold.displacement).max() < 1e-6 * np.abs(first.displacement).max()


def test_floor_contact_is_found_along_the_load_path(small_network):
    """A cantilever sagging onto a floor just below it: the nodes that touch are pinned where they touch,
    none ends below the floor, and the pins hold (the tip sags less than without the floor)."""
    from esmm.pipeline.fidelity.validate import _on_the_floor
    from esmm.pipeline.progress import ensure

    net, tables = small_network
    anchor = np.flatnonzero(net.points[:, 0] < 1e-9)
    g = np.array([0.0, 0.0, -9.80665])
    free = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=g, density=1.0)
    sag = -solve_network(free, net, tables).displacement[:, 2].min()
    floor = Floor(np.array([0.0, 0.0, 1.0]), -0.3 * sag)
    case = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=g, density=1.0, floor=floor)
    sol, pins = _on_the_floor(case, lambda c, start: solve_network(c, net, tables, start=start, steps=1), 6,
                              ensure(None))
    z = net.points[:, 2] + sol.displacement[:, 2]
    assert pins > 0 and sol.info["floor_pins"] == pins
    assert z.min() >= floor.height - 1e-9 and -sol.displacement[:, 2].min() < 0.9 * sag


def test_validate_network_runs_both_sides_and_reports(small_network, liver, tmp_path):
    net, tables = small_network
    rep = validate_network(net, tables, liver, cases=["shear"], element="p2", out_dir=tmp_path)
    r = rep.results[0]
    assert 0 < r.l2_error < 1 and 0 <= r.max_error < 2 and np.isfinite(r.force_error)
    doc = json.loads((tmp_path / "validation.json").read_text())
    assert doc["cases"][0]["case"] == "shear" and doc["volume_term"] == "off"
    for name in ("shear.png", "shear.xdmf", "shear.h5", "validation.md"):
        assert (tmp_path / name).stat().st_size > 0
    assert "| shear |" in (tmp_path / "validation.md").read_text()


def test_volume_term_follows_the_network(small_network, liver):
    net, tables = small_network
    with_term = dataclasses.replace(net, volume_term=bulk_modulus_spec(tables))
    assert network_terms(net, tables, liver, volume_term="off") == ()
    assert network_terms(net, tables, liver) == ()                 # auto: the network has none
    assert network_terms(with_term, tables, liver, volume_term="off") == ()
    (term,) = network_terms(with_term, tables, liver)              # auto: the network's own
    assert term.bulk_modulus == with_term.volume_term.bulk_modulus
    with pytest.raises(ConfigError, match="volume_term"):
        network_terms(net, tables, liver, volume_term="on")
    with pytest.raises(ConfigError, match="volume_term"):
        network_terms(net, tables, liver, volume_term="maybe")


def test_network_newton_with_the_volume_term_is_the_simulators_equilibrium(small_network):
    net, tables = small_network
    net = dataclasses.replace(net, volume_term=bulk_modulus_spec(tables))
    anchor = np.flatnonzero(net.points[:, 0] < 1e-9)
    g = np.array([0.0, 0.0, -9.80665])
    case = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=g, density=1.0)
    free = solve_network(case, net, tables)
    sol = solve_network(case, net, tables, terms=network_terms(net, tables, None))
    vt = build_volume_term(net.points, net.tets, net.volume_term, lam_max=tables.lam_max)
    sim = Simulator(build_spring_term(net, tables), net.points, net.mass, fixed=anchor, gravity=g, volume=vt)
    sim.relax(rtol=1e-10, max_iter=2_000_000)
    u_fire = sim.displacement()
    umax = np.abs(u_fire).max()
    assert np.abs(sol.displacement - u_fire).max() < 1e-4 * umax
    # the term keeps the volume the springs alone lose
    assert abs(sol.volume_ratio - 1) < 0.5 * abs(free.volume_ratio - 1)
    assert sol.info["terms"] == ["springs", "VolumeElements"]


def test_shear_case_states_its_conditions(block):
    case = shear_case(*block, gamma=0.2)
    top = case.constraint("top")
    assert np.allclose(top.displacement[:, 0], 0.2 * L) and top.mask.all()
    assert "clamped" in case.description and "0.2" in case.description


@pytest.mark.slow
def test_cli_validates_the_specimen(tmp_path, capsys):
    out = tmp_path / "val"
    code = main(["validate", "--specimen", "--size", "5", "--cases", "tension", "shear", "--out", str(out),
                 "--json", str(tmp_path / "v.json")])
    assert code == 0
    doc = json.loads((tmp_path / "v.json").read_text())
    assert [c["case"] for c in doc["cases"]] == ["tension", "shear"]
    for c in doc["cases"]:
        assert c["inverted_network"] == 0 and c["inverted_continuum"] == 0
        assert abs(c["volume_change_continuum"]) < 1e-3
    assert "| tension |" in capsys.readouterr().out


@pytest.mark.slow
def test_cli_exit_status_says_a_case_found_no_equilibrium(tmp_path, capsys, monkeypatch):
    import esmm.pipeline.fidelity.validate as V

    def no_equilibrium(case, *args, **kw):
        raise SimulationError("continuum reference: no equilibrium (test)")

    monkeypatch.setattr(V, "solve_continuum", no_equilibrium)
    code = main(["validate", "--specimen", "--size", "5", "--cases", "shear", "--out", str(tmp_path / "val")])
    err = capsys.readouterr().err
    assert code == SimulationError.exit_code and "without an equilibrium (shear)" in err and "Traceback" not in err


def test_cli_needs_an_asset_or_the_specimen(capsys):
    assert main(["validate"]) == 2
    assert "--specimen" in capsys.readouterr().err


def test_cli_refuses_the_other_kinds_options(tmp_path, capsys):
    """The specimen's --size/--side/--material with an ASSET, and --scene with --specimen, would be ignored
    without a word: refused in one line, before the asset is even read."""
    assert main(["validate", str(tmp_path / "liver.h5"), "--size", "4", "--material", "x"]) == 2
    err = capsys.readouterr().err
    assert "--size, --material: describe the built-in specimen (--specimen), not used with an ASSET" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main(["validate", "--specimen", "--scene", "interactive"]) == 2
    assert "--scene: sets the organ cases' scene, not used with --specimen" in capsys.readouterr().err


def test_cli_json_to_stdout_is_the_json_alone(tmp_path, capsys):
    """--json -: stdout parses as JSON (the table and the paths go to stderr)."""
    code = main(["validate", "--specimen", "--size", "5", "--cases", "tension", "--out", str(tmp_path / "v"),
                 "--json", "-"])
    out, err = capsys.readouterr()
    assert code == 0
    assert [c["case"] for c in json.loads(out)["cases"]] == ["tension"]
    assert "| tension |" in err and "outputs:" in err


def test_cli_refuses_bad_sizes_and_outputs_before_any_solve(tmp_path, capsys):
    """--side/--size are in mm (the message too); --out a file, --json a folder: refused up front."""
    assert main(["validate", "--specimen", "--size", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--size: expected a positive length in mm, got -1" in err and "metres" not in err
    assert main(["validate", "--specimen", "--side", "0"]) == 2
    assert "--side: expected a positive length in mm" in capsys.readouterr().err
    (tmp_path / "file").write_text("keep")
    assert main(["validate", "--specimen", "--size", "5", "--cases", "tension", "--out", str(tmp_path / "file")]) == 2
    err = capsys.readouterr().err
    assert "--out: " in err and "is a file" in err and "Traceback" not in err
    assert (tmp_path / "file").read_text() == "keep"
    out = tmp_path / "val"
    assert main(["validate", "--specimen", "--size", "5", "--cases", "tension", "--out", str(out),
                 "--json", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--json: " in err and "is a folder" in err and not out.exists()


@pytest.mark.parametrize("stretch", [1.3, 1.36])
def test_continuum_reports_how_near_locking_it_goes(block, liver, stretch):
    """Homogeneous uniaxial: Ī1 = λ² + 2/λ at every point (to the penalty's volume change, as the stress
    test's 5e-3); the locking share is its way from 3 to 3N."""
    case = uniaxial_case(*block, stretch=stretch)
    sol = solve_continuum(case, liver, element="p2")
    share = (stretch ** 2 + 2.0 / stretch - 3.0) / (3.0 * liver.params_for(None)["N"] - 3.0)
    assert sol.info["locking_share"] == pytest.approx(share, rel=2e-3)
    assert sol.info["cells_near_locking"] == (case.tets.shape[0] if share >= 0.99 else 0)


@pytest.mark.parametrize("stretch", [1.2, 1.36])
def test_validate_warns_when_the_continuum_nears_locking(small_network, liver, stretch):
    from esmm.pipeline.fidelity.validate import LoadOptions
    from esmm.pipeline.progress import ListReporter

    net, tables = small_network
    rep = ListReporter()
    out = validate_network(net, tables, liver, cases=["tension"], loads=LoadOptions(tension=stretch), element="p2",
                           reporter=rep)
    share = (stretch ** 2 + 2.0 / stretch - 3.0) / (3.0 * liver.params_for(None)["N"] - 3.0)   # 0.33, 0.994
    assert out.results[0].figures()["continuum"]["locking_share"] == pytest.approx(share, rel=2e-3)
    near = [w for w in rep.warnings if "locking" in w]
    assert bool(near) == (share >= 0.99)


def test_a_solve_from_a_lighter_load_level_ramps_the_body_force_from_there(small_network, liver, monkeypatch):
    """From the solution at half the gravity (the floor's load level k-1) to the whole gravity (level k):
    both solvers' body force goes 0.5 -> 0.75 -> 1 over two steps (before: at 1 from the first step, an
    increment no halving could shrink), and they end where a solve from rest does."""
    from esmm.pipeline.fidelity import continuum as C
    from esmm.pipeline.fidelity import network_solve as N
    from esmm.pipeline.fidelity.cases import at_load
    from esmm.pipeline.fidelity.solution import start_scale

    net, tables = small_network
    anchor = np.flatnonzero(net.points[:, 0] < 1e-9)
    case = LoadCase("gravity", "", net.points, net.tets, (Constraint.clamp("anchor", anchor),), "anchor",
                    gravity=np.array([0.0, 0.0, -9.80665]), density=1000.0)
    half_c = solve_continuum(at_load(case, 0.5), liver, element="mini")
    half_n = solve_network(at_load(case, 0.5), net, tables)
    assert start_scale(half_c, case.gravity) == pytest.approx(0.5) == start_scale(half_n, case.gravity)
    assert start_scale(None, case.gravity) == 0.0 and start_scale(half_c, at_load(case, 0.5).gravity) == 1.0
    scales = []
    real_step = C._Stepper.step
    monkeypatch.setattr(C._Stepper, "step", lambda self, scale, ext0: scales.append(scale) or real_step(self, scale, ext0))
    warm = solve_continuum(case, liver, element="mini", start=half_c, steps=2)
    assert scales == pytest.approx([0.75, 1.0])
    cold = solve_continuum(case, liver, element="mini")
    assert np.abs(warm.displacement - cold.displacement).max() < 1e-6 * np.abs(cold.displacement).max()
    seen = []
    real_scale = N._Problem.scale
    monkeypatch.setattr(N._Problem, "scale", lambda self, t: seen.append(real_scale(self, t)) or seen[-1])
    solve_network(case, net, tables, start=half_n, steps=2)
    assert min(seen) == pytest.approx(0.75) and max(seen) == pytest.approx(1.0)   # before: 1 throughout


def test_cases_at_once_give_the_serial_figures_and_messages(small_network, liver):
    """Cases solved in forked workers (jobs 2) give the serial run's figures exactly, its messages in order."""
    from esmm.pipeline.progress import ListReporter

    net, tables = small_network
    runs = {}
    for jobs in (1, 2):
        rec = ListReporter()
        rep = validate_network(net, tables, liver, cases=["tension", "shear"], element="p2", jobs=jobs, reporter=rec)
        runs[jobs] = (rep, rec)
    (serial, rec1), (forked, rec2) = runs[1], runs[2]

    def untimed(fig):
        return {k: {kk: vv for kk, vv in v.items() if kk != "seconds"} if k in ("continuum", "network") else v
                for k, v in fig.items()}

    assert [untimed(r.figures()) for r in serial.results] == [untimed(r.figures()) for r in forked.results]
    for a, b in zip(serial.results, forked.results, strict=True):
        assert np.array_equal(a.continuum.displacement, b.continuum.displacement)
        assert np.array_equal(a.network.displacement, b.network.displacement)
    progress = [s for s in rec2.steps if s.startswith("solving 2 cases") or ": solved (" in s]
    assert len(progress) == 3                          # the start and each case as it ends, besides the replay
    assert rec1.steps == [s for s in rec2.steps if s not in progress] and rec1.warnings == rec2.warnings
    assert set(forked.info["case_seconds"]) == {"tension", "shear"}


def test_cases_at_once_raise_a_worker_error():
    """An error other than a solver's (a defect) raised in a worker is raised by the caller."""
    from esmm.pipeline.fidelity.workers import map_cases
    from esmm.pipeline.progress import ListReporter

    def fn(item, rep):
        rep.step(f"item {item}")
        if item == 2:
            raise ValueError("two")
        return item * 10

    rec = ListReporter()
    assert map_cases(fn, [1, 3], jobs=2, reporter=rec, names=["one", "three"]) == [10, 30]
    assert rec.steps[0] == "solving 2 cases in 2 processes: one, three"            # progress in a log, at once
    assert sorted(s.split(":")[0] for s in rec.steps if "solved (" in s) == ["one", "three"]
    assert [s for s in rec.steps if s.startswith("item")] == ["item 1", "item 3"]   # replayed in the cases' order
    with pytest.raises(ValueError, match="two"):
        map_cases(fn, [1, 2], jobs=2, reporter=ListReporter())


def _children(pid: int) -> list[int]:
    """The processes whose parent is *pid* (Linux's /proc)."""
    import os

    out = []
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                fields = open(f"/proc/{name}/stat").read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] not in ("Z", "X"):
                out.append(int(name))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_case_workers_end_with_a_killed_parent():
    """Workers of a killed validation do not solve on for nobody: they end with the process that forked them."""
    import os
    import signal
    import time

    from esmm.pipeline.fidelity.workers import map_cases
    from esmm.pipeline.progress import ListReporter

    def slow(item, rep):
        time.sleep(300)                              # far beyond the test's deadline
        return item

    pid = os.fork()
    if pid == 0:                                       # the "validation": forks two workers, then is killed
        try:
            map_cases(slow, [1, 2], jobs=2, reporter=ListReporter())
        finally:
            os._exit(0)
    deadline = time.monotonic() + 60
    kids = []
    while time.monotonic() < deadline and len(kids) < 2:
        time.sleep(0.2)
        kids = [k for k in _children(pid) if k != pid]
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)

    def running(k):
        try:
            return open(f"/proc/{k}/stat").read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
        except OSError:
            return False

    while time.monotonic() < deadline and any(running(k) for k in kids):
        time.sleep(0.2)
    assert len(kids) == 2 and not any(running(k) for k in kids)


def _column_lift(lift_mm: float, height: float = 0.02):
    """A 10 x 10 x *height* column held at its bottom face, its top face's centre node lifted."""
    from esmm.pipeline.fidelity.cases import lift_case
    from esmm.pipeline.simulate.scene import load_scene

    b = box_tets(2, 2, 4, (0.01, 0.01, height))
    pts = b.points
    fixed = np.flatnonzero(pts[:, 2] < 1e-9)
    top = int(np.argmin(np.linalg.norm(pts - [0.005, 0.005, height], axis=1)))
    return lift_case(pts, b.tets, scene=load_scene("default"), fixed=fixed, grasped=[top],
                     lift=[0.0, 0.0, lift_mm * 1e-3], density=1000.0, weight=1.0)


def test_lift_stretch_of_a_column_is_its_axial_stretch():
    """Lifting the top of a column held at its base by d stretches the vertical segment between them by
    (H + d)/H (the largest over every inner segment: slanted ones stretch less); the lift at which it
    reaches a given stretch s is (s - 1) H."""
    from esmm.pipeline.fidelity.cases import lift_stretch

    ls = lift_stretch(_column_lift(5.0))
    assert ls.stretch == pytest.approx(25.0 / 20.0, rel=1e-12) and ls.length == pytest.approx(0.02)
    assert ls.lift_at(1.361) == pytest.approx(0.361 * 0.02, rel=1e-9)


def test_a_lift_past_the_locking_stretch_is_refused_at_once(liver):
    """A lift that stretches an inner segment past the material's locking (1.361 on the liver) has no
    equilibrium: refused before either solver runs, with the lift that would lock that segment."""
    from esmm.pipeline.fidelity.validate import _reachable

    _reachable(_column_lift(5.0), liver)                                  # 1.25: a case the solvers try
    with pytest.raises(SimulationError, match=r"stretches at least 1\.500.*locking stretch 1\.361.*below 7\.22 mm"):
        _reachable(_column_lift(10.0), liver)
