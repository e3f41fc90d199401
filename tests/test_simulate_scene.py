"""Scenes, grasper planning, the history file and the whole `simulate` run."""

from __future__ import annotations

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest
from esmm.pipeline.config import bundled_names
from esmm.pipeline.errors import ConfigError, SimulationError
from esmm.pipeline.mesh.synthetic import box_tets  # noqa: E402  (shared structured box)
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.tables import StiffnessTables
from esmm.pipeline.progress import ListReporter
from esmm.pipeline.simulate.grasper import plan_grasp, vertex_normals
from esmm.pipeline.simulate.history import History, HistoryWriter
from esmm.pipeline.simulate.run import simulate_network
from esmm.pipeline.simulate.scene import FloorSpec, Scene, load_scene, scene_from_dict


def stiff_tables(mu0=2.0e5):
    lam = np.linspace(0.5, 2.0, 301)
    mu = np.vstack([mu0 * (1 + 4 * (lam - 1) ** 2)] * 3)
    stress = mu * (lam - 1)
    return StiffnessTables(lam_min=0.5, lam_max=2.0, n=301, values=mu, stress=stress, energy=np.zeros((3, 301)))


@pytest.fixture(scope="module")
def slab():
    """A 60 x 30 x 15 mm slab, fixed at x = 0."""
    net = network_from_tets(box_tets(8, 4, 2, (0.06, 0.03, 0.015)))
    return net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))


# ---------------------------------------------------------------------------
# scene files
# ---------------------------------------------------------------------------

def test_bundled_scenes_load():
    assert "default" in bundled_names("scenes")
    for name in bundled_names("scenes"):
        sc = load_scene(name)
        assert sc.duration > 0 and sc.frame_rate > 0


def test_default_scene_values():
    sc = load_scene()
    assert sc.duration == 3.0 and sc.frame_rate == 30
    np.testing.assert_allclose(sc.gravity, [0, 0, -9.80665])
    assert sc.dashpot == pytest.approx(0.5e-3) and sc.velocity_decay == pytest.approx(0.15)
    assert sc.mass_damping == pytest.approx(1 / 0.15)
    g = sc.grasper
    assert g.mode == "prescribed" and g.release_time == 2.0 and g.radius == "auto"
    assert sc.step == "adaptive" and sc.window == 0.05 and sc.mass_scaling == 0.001
    assert sc.start == "equilibrium"
    assert [w.time for w in g.waypoints] == [0.0, 1.0]
    # The grasper lifts the free edge 20 mm against gravity.
    assert g.direction == "up" and g.waypoints[1].distance == pytest.approx(0.020)
    # The organ lies on a rigid floor touching it from below, with sticking friction ...
    assert sc.floor is not None and sc.floor.height == "auto" and sc.floor.friction == "stick"
    # ... anchored by a thin band across the vertical, the lowest 5 % of its height.
    f = sc.fixed
    assert f.kind == "band" and f.end == "min" and f.width is None and f.width_fraction == pytest.approx(0.05)
    np.testing.assert_allclose(f.axis, -sc.gravity / np.linalg.norm(sc.gravity))
    assert sc.effects == "asset" and sc.n_frames == 90


def test_band_axis_up_follows_gravity():
    sc = scene_from_dict({"scene": {"gravity": [0, -2, 0]}, "fixed": {"kind": "band", "axis": "up"}})
    np.testing.assert_allclose(sc.fixed.axis, [0, 1, 0])
    sc = scene_from_dict({"scene": {"gravity": [3, 0, 0]}, "fixed": {"kind": "band", "axis": "down"}})
    np.testing.assert_allclose(sc.fixed.axis, [1, 0, 0])
    with pytest.raises(ConfigError, match="needs gravity"):
        scene_from_dict({"scene": {"gravity": [0, 0, 0]}, "fixed": {"kind": "band", "axis": "up"}})


@pytest.mark.parametrize("data, match", [
    ({"scene": {"duration": 3}}, "has no unit"),
    ({"scene": {"durations": "3 s"}}, "unknown key"),
    ({"scen": {}}, "unknown table"),
    ({"scene": {"frame_rate": 0}}, "frame_rate"),
    ({"scene": {"duration": "0.5 s", "frame_rate": 0.01}}, r"\[scene\] frame_rate: 0.01 frames/s leaves no whole frame"),
    ({"scene": {"gravity": [0, 0]}}, "3 numbers"),
    ({"scene": {"gravity_unit": "ft/s2"}}, "gravity_unit"),
    ({"scene": {"law": "hooke"}}, "law"),
    ({"scene": {"start": "moving"}}, "start"),
    ({"damping": {"dashpot": "-1 ms"}}, "dashpot"),
    ({"damping": {"velocity_decay": 0.2}}, "has no unit"),
    ({"integrator": {"safety": 1.5}}, "safety"),
    ({"integrator": {"threads": 0}}, "threads"),
    ({"integrator": {"step": "tiny"}}, "step"),
    ({"integrator": {"window": 0}}, "window"),
    ({"integrator": {"mass_scaling": 0.5}}, "mass_scaling"),
    ({"fixed": {"kind": "asset", "width": "3 mm"}}, "asset"),
    ({"fixed": {"kind": "band", "width": "3"}}, "no unit"),
    ({"grasper": {"mode": "magnet"}}, "mode"),
    ({"grasper": {"mode": "spring"}}, "stiffness"),
    ({"grasper": {"mode": "spring", "stiffness": "500 N"}}, "stiffness"),
    ({"grasper": {"release_time": "0 s"}}, "release_time"),
    ({"grasper": {"waypoints": [{"time": "1 s", "distance": "1 mm"}, {"time": "0.5 s", "distance": "2 mm"}]}},
     "increase"),
    ({"grasper": {"waypoints": [{"time": "1 s", "distance": "1 mm", "offset": ["0 mm"] * 3}]}}, "exactly one"),
    ({"grasper": {"grasp_time": "1 s", "waypoints": [{"time": "0.5 s", "distance": "1 mm"}]}}, "before grasp_time"),
    ({"grasper": {"direction": [0, 0, 0]}}, "zero vector"),
    ({"scene": {"duration": "1 s"}, "grasper": {"grasp_time": "2 s", "waypoints": [{"time": "2 s", "distance": "0 mm"}], "release_time": "3 s"}},
     "before the end"),
    ({"video": {"width": 10}}, "width"),
    ({"floor": {"enabled": "yes"}}, "enabled"),
    ({"floor": {"height": -0.02}}, "no unit"),
    ({"floor": {"height": "2 kg"}}, "height"),
    ({"floor": {"friction": "glue"}}, "friction"),
    ({"floor": {"level": "auto"}}, "unknown key"),
    ({"scene": {"gravity": [0, 0, 0]}, "floor": {"enabled": True}}, "needs gravity"),
    ({"video": {"colormap": "nonesuch"}}, "colormap"),
])
def test_scene_errors_are_one_line_config_errors(data, match):
    with pytest.raises(ConfigError, match=match) as exc:
        scene_from_dict(data, source="t.toml")
    assert "\n" not in str(exc.value)


def test_scene_from_file_and_overrides(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[scene]\nduration = "500 ms"\ngravity = [0, -1, 0]\ngravity_unit = "g"\n'
                 '[grasper]\nenabled = false\n[fixed]\nkind = "band"\naxis = [1, 0, 0]\nend = "max"\nwidth = "5 mm"\n'
                 '[video]\nwidth = 321\n', encoding="utf-8")
    sc = load_scene(str(p))
    assert sc.duration == 0.5 and sc.grasper is None and sc.video.width == 322
    np.testing.assert_allclose(sc.gravity, [0, -9.80665, 0])
    assert sc.fixed.kind == "band" and sc.fixed.width == pytest.approx(0.005)
    sc2 = sc.with_overrides(duration=2.0, threads=2, law="energy")
    assert (sc2.duration, sc2.threads, sc2.law) == (2.0, 2, "energy")
    with pytest.raises(ConfigError, match="^duration") as exc:        # the library names its parameter
        sc.with_overrides(duration=-1.0)
    assert exc.value.parameter == "duration"
    with pytest.raises(ConfigError, match="no scenes preset"):
        load_scene("no-such-scene").source  # noqa: B018


def test_a_duration_override_shorter_than_a_frame_is_refused():
    """``--duration "10 ms"`` at 30 frames/s ran one frame, 33 ms, and reported 0.0333 s simulated: the
    override is refused as the same duration in a scene file is (it names the option)."""
    sc = load_scene("default")
    with pytest.raises(ConfigError, match=r"^duration: 30 frames/s leaves no whole frame in the duration "
                                          r"\(0\.01 s") as exc:
        sc.with_overrides(duration="10 ms")
    assert exc.value.parameter == "duration"
    assert sc.with_overrides(duration=1 / 30).n_frames == 1


def test_interactive_scene_is_the_default_on_a_slippery_bed_both_solved_implicitly():
    a, b = load_scene("default"), load_scene("interactive")
    changed = {f for f in a.__dataclass_fields__ if repr(getattr(a, f)) != repr(getattr(b, f))}
    assert changed == {"floor", "source"}
    assert (a.method, a.floor.friction) == ("implicit", "stick")
    assert (b.method, b.floor.friction, b.floor.height) == ("implicit", "slip", a.floor.height)


def test_scene_base_overrides_key_by_key_and_refuses_loops(tmp_path):
    parent = tmp_path / "parent.toml"
    parent.write_text('base = "default"\n[scene]\nduration = "1 s"\n[fixed]\nwidth_fraction = 0.1\n', encoding="utf-8")
    child = tmp_path / "sub" / "child.toml"
    child.parent.mkdir()
    child.write_text('base = "../parent.toml"\n[damping]\ndashpot = "1 ms"\n'
                     '[fixed]\nkind = "band"\naxis = [1, 0, 0]\nend = "max"\nwidth = "5 mm"\n', encoding="utf-8")
    d, p, c = load_scene("default"), load_scene(str(parent)), load_scene(str(child))
    assert (p.duration, p.fixed.width_fraction, p.dashpot) == (1.0, 0.1, d.dashpot)
    assert p.fixed.axis is not None and p.velocity_decay == d.velocity_decay and p.grasper == d.grasper
    assert (c.duration, c.dashpot, c.fixed.width, c.fixed.width_fraction) == (1.0, 0.001, pytest.approx(0.005), None)
    loop = tmp_path / "loop.toml"
    loop.write_text('base = "loop.toml"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match="loops") as exc:
        load_scene(str(loop))
    assert "\n" not in str(exc.value)
    bad = tmp_path / "bad.toml"
    bad.write_text("base = 3\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="base: expected a scene name"):
        load_scene(str(bad))


def test_unknown_bundled_scene_lists_choices():
    with pytest.raises(ConfigError, match="choose one of .*default"):
        load_scene("nonesuch")


def test_a_base_that_cannot_be_read_names_the_scene_and_its_base_key(tmp_path):
    """A wrong ``base`` says which file names it, not only "no scenes preset named ..."."""
    child = tmp_path / "child.toml"
    child.write_text('base = "defualt"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"child\.toml: base = 'defualt': no scenes preset named 'defualt'"):
        load_scene(str(child))
    child.write_text('base = "gone.toml"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"child\.toml: base = 'gone.toml': .*gone\.toml: no such file"):
        load_scene(str(child))


# ---------------------------------------------------------------------------
# grasper planning
# ---------------------------------------------------------------------------

def test_default_scene_on_a_slab_lifts_the_top_off_its_bed(slab):
    from esmm.pipeline.network.regions import select_fixed

    sc = load_scene()
    fixed = select_fixed(slab.points, sc.fixed)
    # The anchor: the lowest 5 % of the 15 mm height is the z = 0 layer of this 2-layer slab.
    np.testing.assert_array_equal(fixed, np.flatnonzero(slab.points[:, 2] < 1e-9))
    plan = plan_grasp(sc.grasper, slab.points, slab.surface_faces, fixed, sc.gravity)
    assert slab.points[plan.target, 2] == pytest.approx(0.015)          # the top: farthest from the bed
    np.testing.assert_allclose(plan.direction, [0, 0, 1])               # "up", against gravity
    np.testing.assert_allclose(plan.offsets[-1], [0, 0, 0.020])
    assert plan.normal @ (slab.points[plan.target] - slab.points.mean(axis=0)) > 0      # outward


def test_grasp_plan_auto_target_is_farthest_from_fixed(slab):
    sc = load_scene()
    spec = replace(sc.grasper, direction="away")
    plan = plan_grasp(spec, slab.points, slab.surface_faces, slab.fixed, sc.gravity)
    assert slab.points[plan.target, 0] == pytest.approx(0.06)          # the free end
    assert plan.target in plan.nodes and not np.isin(plan.nodes, slab.fixed).any()
    d = np.linalg.norm(slab.points[plan.nodes] - slab.points[plan.target], axis=1)
    assert d.max() <= 0.006 + 1e-12
    # "away": from the fixed nodes' centroid to the target.
    ref = slab.points[slab.fixed].mean(axis=0)
    exp = (slab.points[plan.target] - ref) / np.linalg.norm(slab.points[plan.target] - ref)
    np.testing.assert_allclose(plan.direction, exp)
    np.testing.assert_allclose(plan.offsets[-1], 0.020 * exp)
    assert plan.normal @ (slab.points[plan.target] - slab.points.mean(axis=0)) > 0      # outward


def test_grasp_plan_target_point_up_and_implicit_start(slab):
    spec = scene_from_dict({"grasper": {
        "target": ["30 mm", "15 mm", "20 mm"], "radius": "0 mm", "direction": "up", "grasp_time": "0.1 s",
        "waypoints": [{"time": "0.5 s", "offset": ["0 mm", "0 mm", "4 mm"]}]}}).grasper
    plan = plan_grasp(spec, slab.points, slab.surface_faces, slab.fixed, np.array([0, 0, -9.81]))
    np.testing.assert_allclose(slab.points[plan.target], [0.03, 0.015, 0.015])
    assert plan.nodes.tolist() == [plan.target]
    np.testing.assert_allclose(plan.direction, [0, 0, 1])
    np.testing.assert_allclose(plan.times, [0.1, 0.5])
    np.testing.assert_allclose(plan.offsets, [[0, 0, 0], [0, 0, 0.004]])
    with pytest.raises(ConfigError, match="needs gravity"):
        plan_grasp(spec, slab.points, slab.surface_faces, slab.fixed, np.zeros(3))


def test_grasp_target_far_outside_the_organ_is_refused(slab):
    """A point in another frame or unit (1 m off) is refused, not moved to some surface node."""
    def spec(target):
        return scene_from_dict({"grasper": {"target": target, "direction": "up"}}).grasper

    g = np.array([0, 0, -9.81])
    with pytest.raises(ConfigError, match=r"\[grasper\] target: .* mm outside the organ \(x 0\.\.60, y 0\.\.30"):
        plan_grasp(spec(["1000 mm", "0 mm", "0 mm"]), slab.points, slab.surface_faces, slab.fixed, g)
    with pytest.raises(ConfigError, match="outside the organ"):     # metres written as millimetres
        plan_grasp(spec(["0.03 mm", "0.015 mm", "-60 mm"]), slab.points, slab.surface_faces, slab.fixed, g)
    # Near the surface (5 mm above the top) or inside: the nearest free surface node, as documented.
    plan = plan_grasp(spec(["30 mm", "15 mm", "20 mm"]), slab.points, slab.surface_faces, slab.fixed, g)
    np.testing.assert_allclose(slab.points[plan.target], [0.03, 0.015, 0.015])


def test_a_grasp_radius_that_holds_the_whole_organ_is_refused(slab):
    """A radius that reaches every free surface node would carry the organ whole (1.7 kN on the liver):
    refused, naming the farthest node's distance; one just below it holds a patch."""
    g = np.array([0, 0, -9.81])
    spec = scene_from_dict({"grasper": {"radius": "1 m", "direction": "up"}}).grasper
    with pytest.raises(ConfigError, match=r"\[grasper\] radius: 1000 mm holds every free surface node .* give a "
                                          r"radius below"):
        plan_grasp(spec, slab.points, slab.surface_faces, slab.fixed, g)
    ok = scene_from_dict({"grasper": {"radius": "20 mm", "direction": "up"}}).grasper
    plan = plan_grasp(ok, slab.points, slab.surface_faces, slab.fixed, g)
    assert 1 < plan.nodes.size < np.setdiff1d(np.unique(slab.surface_faces), slab.fixed).size


def test_waypoints_after_the_end_of_the_run_warn(slab):
    from esmm.pipeline.simulate.runsetup import plan_grasper

    run, sc, rep = _prepared(slab, {"grasper": {"waypoints": [{"time": "0.05 s", "distance": "1 mm"},
                                                               {"time": "0.5 s", "distance": "2 mm"}]}})
    plan_grasper(run, sc, slab, rep)
    assert any("1 of them come after the end of the run (0.1 s; the first at 0.5 s)" in w for w in rep.warnings)
    run, sc, rep = _prepared(slab, {"grasper": {"waypoints": [{"time": "0.05 s", "distance": "1 mm"}]}})
    plan_grasper(run, sc, slab, rep)
    assert not any("after the end" in w for w in rep.warnings)


def _prepared(slab, scene_dict):
    from esmm.pipeline.simulate.runsetup import prepare_run

    rep = ListReporter()
    sc = scene_from_dict({"scene": {"duration": "0.1 s", "start": "rest"}, "integrator": {"threads": 1,
                          "method": "explicit"}, **scene_dict}, source="test")
    return prepare_run(slab, stiff_tables(), sc, effects=None, reporter=rep), sc, rep


def test_a_floor_above_the_organ_is_refused_and_one_through_it_warns(slab):
    """The slab spans z 0..15 mm: a plane at 20 mm would start it inside the floor; at 5 mm it crushes a part."""
    with pytest.raises(ConfigError, match=r"\[floor\] height: the plane at 20 mm along up is above the whole organ"):
        _prepared(slab, {"floor": {"height": "20 mm"}, "grasper": {"enabled": False}})
    _, _, rep = _prepared(slab, {"floor": {"height": "5 mm"}, "grasper": {"enabled": False}})
    assert any(w.startswith("[floor] height: ") and "start below the plane at 5 mm" in w for w in rep.warnings)
    _, _, rep = _prepared(slab, {"floor": {"height": "auto"}, "grasper": {"enabled": False}})
    assert rep.warnings == [] and any(m.startswith("floor: stick, plane 0 mm") for m in rep.steps)


def test_an_unconverged_start_warns_with_what_the_scene_can_change(slab, monkeypatch):
    """FIRE's own advice ("raise max_iter or the tolerance") names no setting a scene or option has: the
    warning gives the residual against the organ's weight and the scene's way out (start = "rest")."""
    from esmm.pipeline.simulate.relax import RelaxNotConverged
    from esmm.pipeline.simulate.runsetup import settle_at_start
    from esmm.pipeline.simulate.simulator import Simulator

    def stuck(self, **kw):
        raise RelaxNotConverged("quasi-static relaxation did not converge in 400000 iterations (residual "
                                "0.0127 N > 1.85e-06 N)", "raise max_iter or the tolerance")

    monkeypatch.setattr(Simulator, "relax", stuck)
    run, sc, rep = _prepared(slab, {"scene": {"duration": "0.1 s", "start": "equilibrium",
                                              "gravity": [0, 0, -9.81]}, "grasper": {"enabled": False}})
    settle = settle_at_start(run, sc, slab, rep)
    assert settle["converged"] is False
    (w,) = [w for w in rep.warnings if "equilibrium under gravity was not reached" in w]
    assert "residual 0.0127 N" in w and "raise max_iter" not in w
    weight = float(np.sum(slab.mass)) * 9.81
    assert f"the organ weighs {weight:.3g} N" in w and 'start = "rest"' in w
    assert any(m.startswith("start (FIRE's closest state, not converged)") and "FIRE unconverged" in m
               for m in rep.steps)


def test_a_grasper_path_below_the_floor_warns(slab):
    """The held nodes are exempt from the floor: a path into it drags them through the bed; the run says so."""
    from esmm.pipeline.simulate.runsetup import plan_grasper

    def warnings(distance):
        run, sc, rep = _prepared(slab, {"floor": {}, "grasper": {
            "target": ["60 mm", "15 mm", "15 mm"], "direction": "up", "release_time": "never",
            "waypoints": [{"time": "0 s", "distance": "0 mm"}, {"time": "0.05 s", "distance": distance}]}})
        plan_grasper(run, sc, slab, rep)
        return [w for w in rep.warnings if w.startswith("[grasper] waypoints")]

    assert warnings("10 mm") == [] and warnings("-10 mm") == []      # the top 15 mm above the floor
    (w,) = warnings("-25 mm")
    assert "the tip 10 mm below the floor (at 0.05 s" in w


def test_vertex_normals_of_a_box_point_outward(slab):
    n = vertex_normals(slab.points, slab.surface_faces)
    surf = np.unique(slab.surface_faces)
    c = slab.points.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", n[surf], slab.points[surf] - c) > 0)


# ---------------------------------------------------------------------------
# history file
# ---------------------------------------------------------------------------

def test_history_roundtrip_and_xdmf_readable_by_vtk(tmp_path, slab):
    p = tmp_path / "h.h5"
    with HistoryWriter(p, points=slab.points, cells=slab.tets, surface=slab.surface_faces, fixed=slab.fixed,
                       attrs={"frame_rate": 30.0, "gravity": [0, 0, -9.81]}) as w:
        for k in range(3):
            w.add_frame(k / 30, np.tile([0.001 * k, 0.0, -0.0005 * k], (slab.n_nodes, 1)),
                        tip=None if k == 0 else np.array([0.06, 0.0, 0.001 * k]))
        w.add_forces(np.arange(5) * 1e-3, np.arange(15.0).reshape(5, 3))
        w.set_grasped([3, 4])
    assert sorted(x.name for x in tmp_path.iterdir()) == ["h.h5", "h.xdmf"]
    with History(p) as h:
        assert h.n_frames == 3
        np.testing.assert_allclose(h.displacement(2)[0], [0.002, 0, -0.001], rtol=1e-6)
        assert np.isnan(h.tips[0]).all() and h.tips[2, 2] == pytest.approx(0.002)
        t, f = h.forces()
        assert t.size == 5 and f[4, 2] == 14.0
        assert h.max_displacement() == pytest.approx(np.hypot(0.002, 0.001), rel=1e-6)

    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as S
    from vtkmodules.vtkIOXdmf2 import vtkXdmfReader

    r = vtkXdmfReader()
    r.SetFileName(str(tmp_path / "h.xdmf"))
    r.UpdateInformation()
    times = r.GetOutputInformation(0).Get(S.TIME_STEPS())
    np.testing.assert_allclose(times, [0, 1 / 30, 2 / 30])
    r.UpdateTimeStep(times[2])
    out = r.GetOutputDataObject(0)
    assert out.GetNumberOfCells() == slab.n_tets
    pts = vtk_to_numpy(out.GetPoints().GetData())
    np.testing.assert_allclose(pts - slab.points, np.tile([0.002, 0, -0.001], (slab.n_nodes, 1)), atol=1e-8)
    disp = vtk_to_numpy(out.GetPointData().GetArray("displacement"))
    np.testing.assert_allclose(disp[0], [0.002, 0, -0.001], rtol=1e-6)


def test_history_writer_leaves_nothing_on_error(tmp_path, slab):
    with pytest.raises(RuntimeError):
        with HistoryWriter(tmp_path / "h.h5", points=slab.points, cells=slab.tets, surface=slab.surface_faces) as w:
            w.add_frame(0.0, np.zeros((slab.n_nodes, 3)))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------
# whole runs
# ---------------------------------------------------------------------------

def short_scene(**grasper) -> Scene:
    g = {"radius": "8 mm", "release_time": "0.2 s",
         "waypoints": [{"time": "0 s", "distance": "0 mm"}, {"time": "0.1 s", "distance": "3 mm"}]}
    g.update(grasper)
    # No gravity: after the release the slab recoils towards its rest shape.
    return scene_from_dict({"scene": {"duration": "0.3 s", "frame_rate": 30, "gravity": [0, 0, 0]},
                            "damping": {"dashpot": "0.2 ms", "velocity_decay": "0.05 s"},
                            "integrator": {"threads": 1, "method": "explicit"}, "grasper": g}, source="test")


def test_simulate_network_outputs(tmp_path, slab):
    rep = ListReporter()
    res = simulate_network(slab, stiff_tables(), short_scene(), tmp_path, reporter=rep, asset_label="slab")
    names = sorted(x.name for x in tmp_path.iterdir())
    assert names == ["grasper_force.png", "history.h5", "history.xdmf", "report.html", "summary.json"]
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["springs"] == slab.n_springs and s["threads"] == 1
    assert s["step_mode"] == "adaptive" and s["dt_min_s"] >= s["dt_table_bound_s"] * s["safety"] * (1 - 1e-12)
    assert s["steps"] * s["dt_mean_s"] == pytest.approx(0.3)
    assert s["real_time_factor"] > 0 and s["grasper"]["held_nodes"] >= 1
    with History(res.history) as h:
        assert h.n_frames == 10
        np.testing.assert_allclose(h.times, np.arange(10) / 30, atol=1e-12)
        t, f = h.forces()
        # Forces recorded at every step while held: 0 .. 0.2 s, in steps of dt_min..dt_max.
        assert t[0] == 0.0 and 0.2 - s["dt_max_s"] <= t[-1] < 0.2
        assert np.all(np.diff(t) >= s["dt_min_s"] * (1 - 1e-9)) and np.all(np.diff(t) <= s["dt_max_s"] * (1 + 1e-9))
        # The tip follows the path: 3 mm away at 0.1 s, released (NaN) after 0.2 s.
        plan_dir = np.asarray(s["grasper"]["direction"])
        tip0 = h.tips[0] if np.isfinite(h.tips[0]).all() else None
        assert tip0 is None or np.isfinite(tip0).all()
        k01 = 3
        moved = h.tips[k01] - slab.points[s["grasper"]["target_node"]]
        np.testing.assert_allclose(moved @ plan_dir, 0.003, rtol=1e-9)
        assert np.isnan(h.tips[-1]).all()
        # Fixed nodes never move.
        assert np.abs(h.displacement(9)[slab.fixed]).max() == 0.0
        # The pulled end moved, and came back towards rest after release.
        tgt = s["grasper"]["target_node"]
        assert np.linalg.norm(h.displacement(6)[tgt]) > np.linalg.norm(h.displacement(9)[tgt])
    assert any("real-time factor" in m for m in rep.steps)


def test_pulling_harder_needs_more_force(tmp_path, slab):
    forces = []
    for dist in ("1 mm", "2 mm"):
        sc = short_scene(waypoints=[{"time": "0 s", "distance": "0 mm"}, {"time": "0.1 s", "distance": dist}],
                         release_time="never")
        res = simulate_network(slab, stiff_tables(), sc, tmp_path / dist.replace(" ", ""))
        with History(res.history) as h:
            t, f = h.forces()
        d = np.asarray(res.summary.grasper.direction)
        forces.append(-(f[-50:] @ d).mean())      # the tissue pulls back against the pull
    assert forces[0] > 0
    assert forces[1] > 1.8 * forces[0]            # stiffening material: more than proportional-ish


def test_spring_grasper_and_fixed_override(tmp_path, slab):
    sc = scene_from_dict({
        "scene": {"duration": "0.1 s"}, "integrator": {"threads": 1},
        "fixed": {"kind": "band", "axis": [1, 0, 0], "end": "min", "width": "1 mm"},
        "grasper": {"mode": "spring", "stiffness": "20 N/m", "release_time": "never",
                    "waypoints": [{"time": "0 s", "distance": "0 mm"}, {"time": "0.1 s", "distance": "1 mm"}]}},
        source="test")
    res = simulate_network(slab.with_fixed([]), stiff_tables(), sc, tmp_path)
    assert res.summary.fixed_nodes == int((slab.points[:, 0] < 1e-9).sum())
    assert res.summary.grasper.max_force_N > 0


def test_table_step_mode_uses_one_step(tmp_path, slab):
    sc = scene_from_dict({"scene": {"duration": "0.1 s", "gravity": [0, 0, 0]},
                          "integrator": {"threads": 1, "step": "table", "method": "explicit"}}, source="t")
    s = simulate_network(slab, stiff_tables(), sc, tmp_path).summary
    assert s.dt_min_s == s.dt_max_s <= s.dt_table_bound_s * s.safety * (1 + 1e-12)
    assert s.frames_redone == 0


def test_adaptive_redoes_frames_that_leave_the_window(tmp_path, slab):
    # A fast pull (6 mm in 0.05 s) on a narrow window: frames must be redone, and the run
    # must agree with the safe whole-table step to within the difference of their steps.
    g = {"radius": "8 mm", "release_time": "never",
         "waypoints": [{"time": "0 s", "distance": "0 mm"}, {"time": "0.05 s", "distance": "6 mm"}]}
    out = {}
    for mode in ("adaptive", "table"):
        sc = scene_from_dict({"scene": {"duration": "0.2 s", "gravity": [0, 0, 0]}, "grasper": g,
                              "damping": {"velocity_decay": "0.02 s"},
                              "integrator": {"threads": 1, "step": mode, "window": 0.002, "method": "explicit"}},
                             source="t")
        res = simulate_network(slab, stiff_tables(), sc, tmp_path / mode)
        with History(res.history) as h:
            out[mode] = (res.summary, h.displacement(h.n_frames - 1))
    assert out["adaptive"][0].frames_redone > 0
    assert out["adaptive"][0].dt_max_s > out["table"][0].dt_max_s
    u_a, u_t = out["adaptive"][1], out["table"][1]
    assert np.abs(u_a - u_t).max() < 0.02 * np.abs(u_t).max()


def test_too_many_steps_refused(tmp_path, slab):
    sc = scene_from_dict({"scene": {"duration": "10 s"}, "integrator": {"max_steps": 1000, "method": "explicit"}})
    with pytest.raises(SimulationError, match="max_steps"):
        simulate_network(slab, stiff_tables(), sc, tmp_path)


def test_a_refused_scene_leaves_no_output_folder(tmp_path, slab):
    """Nothing half-written: a scene refused before the first step leaves no (empty) --out folder behind,
    and an existing folder with an earlier run's files is left as it was."""
    sc = scene_from_dict({"grasper": {"target": ["1000 mm", "0 mm", "0 mm"], "direction": "up"}})
    out = tmp_path / "runs" / "a"
    with pytest.raises(ConfigError, match="outside the organ"):
        simulate_network(slab, stiff_tables(), sc, out)
    assert not (tmp_path / "runs").exists()
    out.mkdir(parents=True)
    (out / "summary.json").write_text("{}")
    with pytest.raises(ConfigError, match="outside the organ"):
        simulate_network(slab, stiff_tables(), sc, out)
    assert (out / "summary.json").read_text() == "{}"


def test_unstable_run_is_reported(tmp_path, slab, monkeypatch):
    # Force a step far above the bound: the run must stop with a one-line error, and
    # leave no history behind.
    from esmm.pipeline.simulate import runsetup as runmod

    real = runmod.stable_step

    def wrong(*a, **k):
        b = real(*a, **k)
        return type(b)(b.dt * 50, b.dt_critical * 50, b.omega_max, b.gamma_max, b.safety, b.node)

    monkeypatch.setattr(runmod, "stable_step", wrong)
    real_set = runmod.Simulator.set_time_step
    monkeypatch.setattr(runmod.Simulator, "set_time_step",
                        lambda self, dt, bound=None, t0=None: real_set(self, dt, bound=b_big(bound), t0=t0))

    def b_big(b):
        return None if b is None else type(b)(b.dt, b.dt_critical * 1e3, b.omega_max, b.gamma_max, b.safety, b.node)

    sc = scene_from_dict({"scene": {"duration": "0.5 s"}, "grasper": {"enabled": False},
                          "integrator": {"threads": 1, "step": "table", "method": "explicit"}})
    with pytest.raises(SimulationError, match="unstable"):
        simulate_network(slab, stiff_tables(), sc, tmp_path)
    assert not (tmp_path / "history.h5").exists()
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_history_attrs_carry_the_run(tmp_path, slab):
    res = simulate_network(slab, stiff_tables(), short_scene(), tmp_path)
    with h5py.File(res.history, "r") as f:
        assert f.attrs["esmm_type"] == "simulation_history"
        assert f.attrs["law"] == "secant"
        assert json.loads(f.attrs["summary"])["steps"] == res.summary.steps
        assert f["grasper/nodes"].shape[0] == res.summary.grasper.held_nodes


def test_cli_missing_asset(run_cli, tmp_path):
    code, out, err = run_cli("simulate", tmp_path / "none.h5")
    assert code == 2 and "no such asset file" in err and "Traceback" not in err


def test_cli_bad_options(run_cli, tmp_path):
    code, out, err = run_cli("simulate", tmp_path / "a.h5", "--threads", "zero")
    assert code == 2 and "--threads" in err
    # the library names its parameter ("duration: ..."); the command line shows the flag
    code, out, err = run_cli("simulate", tmp_path / "a.h5", "--duration", "-1")
    assert code == 2 and "--duration: " in err and "Traceback" not in err
    code, out, err = run_cli("simulate", tmp_path / "a.h5", "--law", "hooke")
    assert code == 2


def test_cli_end_to_end_on_an_asset(run_cli, tmp_path, slab):
    """esmm simulate on a real asset file: outputs, summary, exit code (video in test_render)."""
    from esmm.pipeline.asset import write_asset

    asset = write_asset(tmp_path / "slab.h5", slab, tables=stiff_tables())
    scene = tmp_path / "s.toml"
    scene.write_text('[scene]\nduration = "2 s"\n[integrator]\nthreads = 1\n'
                     '[grasper]\nrelease_time = "0.1 s"\nwaypoints = [{time = "0 s", distance = "0 mm"}, '
                     '{time = "0.1 s", distance = "2 mm"}]\n', encoding="utf-8")
    code, out, err = run_cli("simulate", asset, "--scene", scene, "--duration", "200 ms", "--law", "energy",
                             "--out", tmp_path / "run")
    assert code == 0, err
    assert "real-time factor" in out and "history:" in out
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["law"] == "energy" and s["simulated_s"] == pytest.approx(0.2, abs=1 / 30)
    assert (tmp_path / "run" / "history.xdmf").is_file() and (tmp_path / "run" / "grasper_force.png").is_file()
    # A scene that does not fit this asset: one-line error, exit code 2, no traceback.
    bad = tmp_path / "bad.toml"
    bad.write_text('[fixed]\nkind = "box"\nlower = ["1 m", "1 m", "1 m"]\nupper = ["2 m", "2 m", "2 m"]\n')
    code, out, err = run_cli("simulate", asset, "--scene", bad, "--out", tmp_path / "run2")
    assert code == 2 and "holds no" in err and "Traceback" not in err


def test_cli_refuses_unusable_outputs_up_front_and_drops_a_stale_force_plot(run_cli, tmp_path, slab):
    """--out a file, --video a folder: refused before the run; a run without a grasper into the folder of
    one with a grasper does not leave that run's grasper_force.png beside its own outputs."""
    from esmm.pipeline.asset import write_asset

    asset = write_asset(tmp_path / "slab.h5", slab, tables=stiff_tables())
    (tmp_path / "file").write_text("keep")
    code, _, err = run_cli("simulate", asset, "--out", tmp_path / "file")
    assert code == 2 and "--out: " in err and "is a file" in err and "Traceback" not in err
    assert (tmp_path / "file").read_text() == "keep"
    (tmp_path / "v.mp4").mkdir()
    code, _, err = run_cli("simulate", asset, "--out", tmp_path / "run", "--video", tmp_path / "v.mp4")
    assert code == 2 and "--video: " in err and "is a folder" in err and not (tmp_path / "run").exists()
    base = ('[scene]\nduration = "0.1 s"\ngravity = [0, 0, 0]\nstart = "rest"\n'
            '[integrator]\nthreads = 1\nmethod = "explicit"\n')
    with_grasper, without = tmp_path / "g.toml", tmp_path / "n.toml"
    with_grasper.write_text(base + '[grasper]\nwaypoints = [{time = "0 s", distance = "0 mm"}, '
                            '{time = "0.05 s", distance = "1 mm"}]\n', encoding="utf-8")
    without.write_text(base + "[grasper]\nenabled = false\n", encoding="utf-8")
    assert run_cli("simulate", asset, "--scene", with_grasper, "--out", tmp_path / "run")[0] == 0
    assert (tmp_path / "run" / "grasper_force.png").is_file()
    code, out, err = run_cli("simulate", asset, "--scene", without, "--out", tmp_path / "run")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["history.h5", "history.xdmf", "report.html",
                                                                       "summary.json"]


def test_start_at_equilibrium_has_no_transient(tmp_path, slab):
    """Started at the equilibrium under gravity, nothing moves without the grasper."""
    out = {}
    for start in ("equilibrium", "rest"):
        sc = scene_from_dict({"scene": {"duration": "0.2 s", "start": start}, "grasper": {"enabled": False},
                              "integrator": {"threads": 1}}, source="t")
        res = simulate_network(slab, stiff_tables(), sc, tmp_path / start)
        with History(res.history) as h:
            out[start] = [h.displacement(k) for k in range(h.n_frames)]
        if start == "equilibrium":
            assert res.summary.equilibrium["converged"]
    eq, rest = out["equilibrium"], out["rest"]
    sag = np.abs(eq[0]).max()
    assert sag > 1e-4 and np.abs(rest[0]).max() == 0.0
    drift = max(np.abs(u - eq[0]).max() for u in eq)
    assert drift < 1e-3 * sag                    # already at rest
    assert max(np.abs(u - rest[0]).max() for u in rest) > 0.3 * sag     # dropping from the rest shape


# ---------------------------------------------------------------------------
# the video camera (no OpenGL needed: vtkCamera's matrices)
# ---------------------------------------------------------------------------

def _box_cloud(lengths, yaw_deg, seed=0):
    rng = np.random.default_rng(seed)
    p = (rng.random((4000, 3)) - 0.5) * np.asarray(lengths)
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    return p @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + [0.1, -0.2, 0.05]


def test_auto_view_is_horizontal_with_up_against_gravity():
    from esmm.pipeline.simulate.render import auto_view

    p = _box_cloud((0.20, 0.06, 0.10), 30.0)         # widest along x rotated by 30 deg, thinnest horizontally y'
    g = np.array([0, 0, -9.81])
    thin = np.array([-np.sin(np.deg2rad(30)), np.cos(np.deg2rad(30)), 0])
    look, up = auto_view(p, np.array([0, 0, 0.02]), g, toward=p.mean(axis=0) - 0.05 * thin)
    np.testing.assert_allclose(up, [0, 0, 1])
    assert abs(look @ up) < 1e-12                       # horizontal line of sight
    assert look @ thin == pytest.approx(-1, abs=0.02)   # along the thinnest horizontal axis, grasper side
    look2, _ = auto_view(p, np.zeros(3), g, toward=p.mean(axis=0) + 0.05 * thin)
    assert look2 @ thin == pytest.approx(1, abs=0.02)
    # a motion seen end-on along that axis: look along the widest horizontal axis instead
    look3, _ = auto_view(p, 0.03 * thin, g)
    assert abs(look3 @ thin) < 0.05 and abs(look3 @ up) < 1e-12
    # gravity along -y: up is +y whatever the organ's shape
    _, up4 = auto_view(p, np.zeros(3), np.array([0, -2.0, 0]))
    np.testing.assert_allclose(up4, [0, 1, 0])


def test_fit_camera_keeps_every_frame_inside_the_box():
    import vtk
    from esmm.pipeline.simulate.render import FIT_BOX, auto_view, fit_camera

    rest = _box_cloud((0.20, 0.06, 0.10), 10.0)
    frames = [rest + [0, 0, 0.03 * k / 5] * (rest[:, [0]] > 0.15) for k in range(6)]   # a lifted end
    look, up = auto_view(rest, np.array([0, 0, 0.03]), np.array([0, 0, -9.81]))
    aspect = 960 / 720
    pos, focal = fit_camera(look, up, frames, view_angle_deg=30.0, aspect=aspect)
    cam = vtk.vtkCamera()
    cam.SetPosition(*pos)
    cam.SetFocalPoint(*focal)
    cam.SetViewUp(*up)
    cam.SetViewAngle(30.0)
    cam.SetClippingRange(1e-4, 100.0)
    m = cam.GetCompositeProjectionTransformMatrix(aspect, -1, 1)
    M = np.array([[m.GetElement(i, j) for j in range(4)] for i in range(4)])
    q = np.c_[np.concatenate(frames), np.ones(sum(len(f) for f in frames))] @ M.T
    x, y = (q[:, 0] / q[:, 3] + 1) / 2, (q[:, 1] / q[:, 3] + 1) / 2          # picture fractions
    x0, x1, y0, y1 = FIT_BOX
    assert x.min() >= x0 - 0.01 and x.max() <= x1 + 0.01 and y.min() >= y0 - 0.01 and y.max() <= y1 + 0.01
    # tight: the organ fills the box along one of its sides
    assert max((x.max() - x.min()) / (x1 - x0), (y.max() - y.min()) / (y1 - y0)) > 0.9
    np.testing.assert_allclose(np.asarray(cam.GetViewUp()), up, atol=1e-12)   # exactly against gravity


# ---------------------------------------------------------------------------
# the floor (rigid half-space contact)
# ---------------------------------------------------------------------------

def test_floor_scene_keys():
    assert scene_from_dict({}).floor is None
    assert scene_from_dict({"floor": {}}).floor == FloorSpec()       # "[floor]" alone: present, so on
    assert scene_from_dict({"floor": {"enabled": False, "height": "3 mm"}}).floor is None
    sc = scene_from_dict({"floor": {"height": "-20 mm", "friction": "slip"}})
    assert sc.floor.height == pytest.approx(-0.020) and sc.floor.friction == "slip"
    assert "floor at -20 mm (slip)" in sc.describe()


def _cube(n=3, size=0.02):
    return network_from_tets(box_tets(n, n, n, (size, size, size)))


def _sim(net, *, floor=None, gravity=(0, 0, -9.81), fixed=(), decay=0.02, **kw):
    from esmm.pipeline.simulate.simulator import Simulator
    from esmm.pipeline.simulate.springterm import build_spring_term

    m = build_spring_term(net, stiff_tables(), dashpot=kw.pop("dashpot", 1e-4))
    return Simulator(m, net.points, net.mass, fixed=fixed, gravity=gravity,
                     mass_damping=0.0 if decay is None else 1.0 / decay, floor=floor, threads=kw.pop("threads", 1))


def test_floor_geometry():
    from esmm.pipeline.simulate.model import Floor

    pts = np.array([[0.0, 0, 0.01], [0.0, 0.02, -0.003], [0.01, 0, 0.05]])
    fl = Floor.under(pts, [0, 0, -2.0])
    np.testing.assert_allclose(fl.normal, [0, 0, 1])
    assert fl.height == pytest.approx(-0.003) and fl.friction == "stick"
    fl = Floor.under(pts, [0, 9.81, 0], height=0.01, friction="slip")     # gravity along +y: "up" is -y
    np.testing.assert_allclose(fl.normal, [0, -1, 0])
    np.testing.assert_allclose(fl.distance(pts), [-0.01, -0.03, -0.01])
    with pytest.raises(ConfigError, match="gravity"):
        Floor.under(pts, [0, 0, 0])
    with pytest.raises(ConfigError, match="friction"):
        Floor.under(pts, [0, 0, -1], friction="glue")


@pytest.mark.parametrize("friction", ["stick", "slip"])
def test_block_dropped_onto_the_floor_comes_to_rest_on_it(friction):
    from esmm.pipeline.simulate.model import Floor

    net = _cube(2, 0.01)
    fl = Floor(normal=[0, 0, 1], height=-0.005, friction=friction)       # 5 mm below the block
    sim = _sim(net, floor=fl, decay=0.01)
    lowest = np.inf
    for _ in range(60):                                                  # 0.3 s: the fall takes 32 ms
        sim.advance(int(round(0.005 / sim.dt)))
        lowest = min(lowest, float(fl.distance(sim.x).min()))
    assert lowest >= -1e-9                                               # never below the plane
    bottom = net.points[:, 2] < 1e-9
    np.testing.assert_allclose(fl.distance(sim.x)[bottom], 0.0, atol=1e-9)   # lies on it ...
    top = net.points[:, 2] > 0.01 - 1e-9
    assert np.all(fl.distance(sim.x)[top] > 0.009)                       # ... not flattened
    assert np.abs(sim.v).max() < 1e-4                                    # at rest (it hit at 0.31 m/s)
    assert sim.n_contact == bottom.sum()


def test_cube_resting_on_the_floor_stays_on_it_and_matches_a_clamped_base():
    """Equilibrium (FIRE) on a sticking floor = the same cube with its base clamped; dynamics agree."""
    from esmm.pipeline.simulate.model import Floor

    net = _cube(3, 0.02)
    bottom = np.flatnonzero(net.points[:, 2] < 1e-9)
    soft = lambda: StiffnessTables(lam_min=0.5, lam_max=2.0, n=301, values=np.full((3, 301), 3e5),  # noqa: E731
                                   stress=np.zeros((3, 301)), energy=np.zeros((3, 301)))
    from esmm.pipeline.simulate.simulator import Simulator
    from esmm.pipeline.simulate.springterm import build_spring_term

    m = build_spring_term(net, soft())
    fl = Floor.under(net.points, [0, 0, -9.81])
    assert fl.height == 0.0
    on_floor = Simulator(m, net.points, net.mass, gravity=(0, 0, -9.81), floor=fl)
    clamped = Simulator(m, net.points, net.mass, gravity=(0, 0, -9.81), fixed=bottom)
    on_floor.relax(rtol=1e-9)
    clamped.relax(rtol=1e-9)
    sag = np.abs(clamped.displacement()).max()
    assert sag > 1e-6                                                    # a visible compression
    assert fl.distance(on_floor.x).min() >= -1e-12
    np.testing.assert_allclose(on_floor.x[bottom], net.points[bottom], atol=1e-12)
    assert np.abs(on_floor.x - clamped.x).max() < 1e-4 * sag
    assert on_floor.n_contact == bottom.size
    # Without the floor the same relaxation has no equilibrium: the cube falls.
    free_fall = Simulator(m, net.points, net.mass, gravity=(0, 0, -9.81))
    with pytest.raises(SimulationError):
        free_fall.relax(max_iter=2000)
    # Dynamics from the rest shape: the base never goes below the plane, the cube settles
    # at the same equilibrium.
    dyn = Simulator(m, net.points, net.mass, gravity=(0, 0, -9.81), floor=fl, mass_damping=1 / 0.01)
    for _ in range(30):
        dyn.advance(int(round(0.01 / dyn.dt)))
        assert fl.distance(dyn.x).min() >= -1e-9
    # Friction makes the end state path-dependent (base nodes may lift and re-land during the
    # bounce), so the dynamic rest state is close to, not equal to, the clamped equilibrium.
    assert np.abs(dyn.v).max() < 1e-6
    np.testing.assert_allclose(fl.distance(dyn.x)[bottom], 0.0, atol=1e-9)
    assert np.abs(dyn.x - clamped.x).max() < 0.3 * sag


@pytest.mark.parametrize("friction", ["stick", "slip"])
def test_sticking_floor_holds_a_sideways_push(friction):
    from esmm.pipeline.simulate.model import Floor

    net = _cube(2, 0.01)
    bottom = net.points[:, 2] < 1e-9
    fl = Floor(normal=[0, 0, 1], height=0.0, friction=friction)
    # Gravity tilted 20 degrees: pressed onto the floor and pushed along +x.
    sim = _sim(net, floor=fl, gravity=(9.81 * np.sin(0.35), 0, -9.81 * np.cos(0.35)), decay=0.05)
    always = bottom.copy()                       # in contact at every step
    for _ in range(int(round(0.1 / sim.dt))):
        sim.advance(1)
        always &= sim.contact > 0
    slide = sim.x[:, :2] - net.points[:, :2]
    np.testing.assert_allclose(fl.distance(sim.x)[bottom], 0.0, atol=1e-9)
    if friction == "stick":
        # The push rocks the cube: its trailing edge may lift off; what stayed down did not move.
        assert always.sum() >= 6
        assert np.abs(slide[always]).max() == 0.0                        # not a nanometre
        assert np.abs(slide[~bottom]).max() > 1e-7                       # while the cube leans
    else:
        assert slide[bottom, 0].min() > 1e-3                             # frictionless: it slides away


def test_fire_respects_a_slip_floor_and_leaves_tangential_balance_to_the_springs():
    """A cube on a frictionless floor, anchored by one edge node: it settles with its base on the plane."""
    from esmm.pipeline.simulate.model import Floor

    net = _cube(2, 0.01)
    bottom = np.flatnonzero(net.points[:, 2] < 1e-9)
    fl = Floor(normal=[0, 0, 1], height=0.0, friction="slip")
    sim = _sim(net, floor=fl, fixed=[0], gravity=(3.0, 0, -9.81))
    info = sim.relax(rtol=1e-8)
    assert info["residual"] < info["ftol"]
    np.testing.assert_allclose(fl.distance(sim.x)[bottom], 0.0, atol=1e-12)
    assert fl.distance(sim.x).min() >= -1e-12
    # The residual is the force the floor cannot take: tangential forces on the base are balanced.
    f = sim.forces()
    free = sim.free
    assert np.abs(f[free][:, :2]).max() < 1e-6 * np.abs(sim.fext).max()
    assert np.all(f[bottom[1:], 2] <= 1e-9)                             # the floor pushes up, never pulls


def test_no_floor_path_is_bit_identical_and_an_untouched_floor_changes_nothing():
    from esmm.pipeline.simulate.model import Floor, Grasp

    net = _cube(2, 0.01)
    fixed = np.flatnonzero(net.points[:, 0] < 1e-9)
    runs = []
    for floor in (None, Floor(normal=[0, 0, 1], height=-1.0, friction="stick")):
        sim = _sim(net, floor=floor, fixed=fixed, decay=0.2)
        sim.advance(150)
        tgt = int(np.argmax(net.points @ [1, 0, 1]))
        sim.attach(Grasp(nodes=np.array([tgt]), offsets=np.zeros((1, 3)), wp_t=np.array([sim.t, sim.t + 0.01]),
                         wp_x=np.array([sim.x[tgt], sim.x[tgt] + [0, 0, 0.002]])))
        r = sim.advance(200)
        sim.release()
        sim.advance(50)
        runs.append((sim.x.copy(), sim.v.copy(), r))
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)
    assert np.abs(runs[0][0] - net.points).max() > 1e-4                 # something happened


def test_grasped_nodes_are_exempt_from_the_floor():
    from esmm.pipeline.simulate.model import Floor, Grasp

    net = _cube(2, 0.01)
    fl = Floor(normal=[0, 0, 1], height=0.0, friction="stick")
    sim = _sim(net, floor=fl, fixed=np.flatnonzero(net.points[:, 0] > 0.01 - 1e-9))
    tgt = int(np.flatnonzero((net.points[:, 0] < 1e-9) & (net.points[:, 2] < 1e-9))[0])
    sim.attach(Grasp(nodes=np.array([tgt]), offsets=np.zeros((1, 3)), wp_t=np.array([0.0, 0.01]),
                     wp_x=np.array([net.points[tgt], net.points[tgt] - [0, 0, 0.002]])))
    sim.advance(int(round(0.02 / sim.dt)))
    assert fl.distance(sim.x)[tgt] == pytest.approx(-0.002, abs=1e-12)  # the tip goes where it is told
    others = np.ones(net.n_nodes, bool)
    others[tgt] = False
    assert fl.distance(sim.x)[others].min() >= -1e-9


def test_simulate_network_with_a_floor_counts_contacts(tmp_path, slab):
    sc = scene_from_dict({"scene": {"duration": "0.1 s"}, "floor": {"enabled": True},
                          "fixed": {"kind": "none"}, "grasper": {"enabled": False},
                          "integrator": {"threads": 1}}, source="t")
    res = simulate_network(slab, stiff_tables(), sc, tmp_path)
    s = res.summary
    bottom = int(np.count_nonzero(slab.points[:, 2] < 1e-9))
    assert s.equilibrium["converged"] and s.equilibrium["contact_nodes"] == bottom
    assert s.floor.friction == "stick" and s.floor.height_m == 0.0
    assert s.floor.contact_nodes_max == bottom and s.floor.min_distance_m >= -1e-9
    assert json.loads((tmp_path / "summary.json").read_text())["floor"]["height_spec"] == "auto"


def test_fire_in_chunks_takes_the_path_of_one_call_and_reports_its_progress(monkeypatch):
    """FIRE on a sticking floor (a path-dependent equilibrium), run in chunks of 7 iterations for the
    progress display: bit for bit the state and iteration count of one uninterrupted call."""
    from esmm.pipeline.progress import ListReporter
    from esmm.pipeline.simulate import relax as R
    from esmm.pipeline.simulate.model import Floor

    net = _cube(3, 0.02)

    def settle(chunk):
        monkeypatch.setattr(R, "CHUNK", chunk)
        fl = Floor(normal=[0, 0, 1], height=0.0, friction="stick")
        sim = _sim(net, floor=fl, gravity=(3.0, 0, -9.81))
        rep = ListReporter()
        return sim, sim.relax(rtol=1e-9, reporter=rep), rep

    one, info1, _ = settle(10**9)
    chunked, info7, rep = settle(7)
    assert info1["iterations"] > 50                       # many chunks
    assert info7 == info1
    np.testing.assert_array_equal(chunked.x, one.x)
    np.testing.assert_array_equal(chunked.contact, one.contact)
    assert rep.tasks == ["equilibrium under gravity (FIRE)"]


def test_a_settled_equilibrium_is_taken_from_the_cache_only_for_the_same_inputs(tmp_path, monkeypatch):
    """The second settle of the same scene takes the stored state (bit for bit FIRE's, FIRE not run);
    another gravity is a miss; an unreadable entry is a miss that is computed and stored again."""
    from esmm.pipeline.simulate import relax as R
    from esmm.pipeline.simulate.model import Floor

    net = _cube(3, 0.02)

    def settle(gravity=(3.0, 0, -9.81)):
        sim = _sim(net, floor=Floor(normal=[0, 0, 1], height=0.0, friction="stick"), gravity=gravity)
        return sim, sim.relax(rtol=1e-9, cache=tmp_path)

    first, info = settle()
    assert info["cached"] is False and len(list(tmp_path.glob("*.npz"))) == 1
    real = R.fire_relax
    monkeypatch.setattr(R, "fire_relax", lambda *a: pytest.fail("FIRE ran on a cached equilibrium"))
    again, info2 = settle()
    assert info2 == {**info, "cached": True}
    np.testing.assert_array_equal(again.x, first.x)
    np.testing.assert_array_equal(again.contact, first.contact)
    assert np.abs(again.v).max() == 0.0
    monkeypatch.setattr(R, "fire_relax", real)
    other, info3 = settle(gravity=(0.0, 3.0, -9.81))
    assert info3["cached"] is False and len(list(tmp_path.glob("*.npz"))) == 2
    assert np.abs(other.x - first.x).max() > 1e-6
    for entry in tmp_path.glob("*.npz"):
        entry.write_bytes(b"not an npz")
    spoiled, info4 = settle()
    assert info4["cached"] is False                                    # computed again ...
    np.testing.assert_array_equal(spoiled.x, first.x)
    assert settle()[1]["cached"] is True                               # ... and stored again


def test_the_cache_digest_tells_apart_types_shapes_and_dtypes():
    from esmm.pipeline.cache import digest

    a = np.arange(6, dtype=np.float64)
    assert digest(a) == digest(a.copy())
    assert digest(a) != digest(a.reshape(2, 3))
    assert digest(a) != digest(a.astype(np.float32))
    assert digest(1) != digest(1.0) != digest(True)
    assert digest("a") != digest(b"a")
    assert digest((1, 2), 3) != digest(1, (2, 3))
    assert digest({"a": 1, "b": None}) == digest({"b": None, "a": 1})
    with pytest.raises(TypeError):
        digest(object())


def test_a_video_that_fails_leaves_this_runs_outputs_whole(tmp_path, slab, monkeypatch):
    """Stopped or failed while rendering: the history, plot and summary are this run's (the summary is
    written before the video), not a new history beside an earlier run's summary."""
    from esmm.pipeline.simulate import run as R

    (tmp_path / "summary.json").write_text('{"stale": true}')           # an earlier run's
    monkeypatch.setattr(R, "_render", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        simulate_network(slab, stiff_tables(), short_scene(), tmp_path, video=tmp_path / "run.mp4", asset_label="slab")
    s = json.loads((tmp_path / "summary.json").read_text())
    assert "stale" not in s and s["springs"] == slab.n_springs and s.get("video") is None
    assert not (tmp_path / "run.mp4").exists()
