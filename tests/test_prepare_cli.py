"""`esmm prepare` and `esmm info`: configs, bad input, the quality gate, end to end."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from esmm.pipeline.config import bundled_names
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.mesh.targets import size_for_elements
from esmm.pipeline.prepare import DEFAULTS, load_prepare_config, parse_prepare_config


def icosphere(radius=0.03, levels=3):
    """A closed, outward triangulated sphere (20 * 4**levels faces)."""
    g = (1 + 5**0.5) / 2
    v = [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g],
         [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    pts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(levels):
        cache: dict[tuple[int, int], int] = {}
        new = []
        for tri in faces:
            mids = []
            for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                key = (min(a, b), max(a, b))
                if key not in cache:
                    m = pts[a] + pts[b]
                    pts.append(m / np.linalg.norm(m))
                    cache[key] = len(pts) - 1
                mids.append(cache[key])
            ab, bc, ca = mids
            a, b, c = tri
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    from esmm.pipeline.mesh.surface import Surface

    return Surface(np.array(pts) * radius, np.array(faces))


@pytest.fixture(scope="module")
def sphere_stl(tmp_path_factory):
    from esmm.pipeline.mesh.readers import write_stl

    surf = icosphere()
    assert surf.volume() > 0
    path = tmp_path_factory.mktemp("in") / "ball.stl"
    write_stl(surf, path, unit="mm")
    return path


# -- configs ---------------------------------------------------------------------------------

def test_bundled_presets_are_complete_and_valid():
    names = bundled_names("prepare")
    assert {"coarse", "paper", "fine"} <= set(names)
    targets = {}
    for name in names:
        cfg, source = load_prepare_config(name)
        s = parse_prepare_config(cfg, source)
        targets[name] = s.target.elements
    assert targets["coarse"] < targets["paper"] == 5000 < targets["fine"]


@pytest.mark.parametrize("config, match", [
    ({"meshing": {}}, "unknown section \\[meshing\\]"),
    ({"mesh": {"sise": "8 mm"}}, "unknown key\\(s\\) sise in \\[mesh\\]"),
    ({"mesh": {"size": 8}}, "has no unit"),
    ({"mesh": {"size": "8 mm", "nodes": 100}}, "one of size, nodes or elements"),
    ({"mesh": {"timeout": "-1 s"}}, "timeout"),
    ({"prepare": {"density": "1.06 g/mm3"}}, "not plausible"),
    ({"prepare": {"structure": "hex"}}, "structure"),
    ({"prepare": {"reorder": "metis"}}, "reorder"),
    ({"input": {"unit": "furlong"}}, "unit"),
    ({"cleaning": {"keep": "biggest"}}, "keep"),
    ({"fibres": {"frame": [[1, 0, 0], [1, 1, 0], [0, 0, 1]]}}, "perpendicular"),
    ({"fixed": {"kind": "box"}}, "lower"),
    ({"tables": {"law": "spline"}}, "law"),
    ({"tables": {"n": 2}}, "\\[tables\\] n"),
    ({"quality": {"min_dihedral": 3}}, "unknown figure"),
    ({"quality": {"sicn_p1": "high"}}, "expected a number"),
])
def test_bad_config_values_are_one_line_errors(config, match):
    with pytest.raises(ConfigError, match=match) as info:
        cfg, src = load_prepare_config(config)
        parse_prepare_config(cfg, src)
    assert "\n" not in str(info.value)


def test_config_file_overrides_and_keeps_defaults(tmp_path):
    p = tmp_path / "my.toml"
    p.write_text('[mesh]\nsize = "6 mm"\n[fixed]\nkind = "none"\n')
    cfg, src = load_prepare_config(p)
    s = parse_prepare_config(cfg, src)
    assert s.target.size == pytest.approx(0.006) and s.target.elements is None and s.target.nodes is None
    assert s.fixed.kind == "none"
    assert s.density == 1060.0 and s.structure == "tetra"
    assert set(cfg) == set(DEFAULTS)


def test_size_for_elements_matches_its_definition():
    # a regular tet of edge h has volume h^3/(6 sqrt 2); the mesher's average r times that
    from esmm.pipeline.mesh.targets import MESHER_VOLUME_RATIO as r

    h = size_for_elements(1e-3, 5000)
    assert 5000 * r * h**3 / (6 * 2**0.5) == pytest.approx(1e-3, rel=1e-12)


# -- bad command lines: one line, nonzero exit, nothing written -------------------------------

@pytest.mark.parametrize("args, code, match", [
    (["missing.stl"], 2, "no such file"),
    (["{stl}", "--size", "abc"], 2, "--size"),
    (["{stl}", "--size", "-3"], 2, "positive"),
    (["{stl}", "--size", "5", "--nodes", "100"], 2, "not several"),
    (["{stl}", "--nodes", "1.5"], 2, "whole number"),
    (["{stl}", "-o", "out.vtk"], 2, "must end in .h5"),
    (["{stl}", "--config", "ultra"], 2, "no prepare preset named 'ultra'"),
    (["{stl}", "--structure", "hex"], 2, "--structure"),
    (["{stl}", "--density", "1.06"], 2, "not plausible"),
    (["{stl}", "--keep-all", "--body", "1"], 2, "not both"),
    (["{stl}", "--material", "no_such_material"], 2, "no_such_material"),
    (["{stl}", "--unit", "furlong"], 2, "unit"),
    (["{stl}", "-o", "{stl}"], 2, "must end in .h5"),
    (["{stl}", "--structure", "skeleton", "--nodes", "300"], 2, "[skeleton] n_surface"),
])
def test_bad_prepare_input(run_cli, tmp_path, monkeypatch, sphere_stl, args, code, match):
    monkeypatch.chdir(tmp_path)
    argv = [a.replace("{stl}", str(sphere_stl)) for a in args]
    rc, out, err = run_cli("prepare", *argv)
    assert rc == code
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("esmm: error:"), err
    assert match in lines[0]
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("make, output, match", [
    ("dir:organ.h5", "organ.h5", "organ.h5 is a folder"),
    ("file:notes", "notes/organ.h5", "cannot be written"),
    ("file:notes", "notes/deeper/organ.h5", "notes is a file"),
    ("dir:organ.xdmf", "organ.h5", "ParaView sidecar organ.xdmf is a folder"),
])
def test_unwritable_output_is_refused_before_any_work(run_cli, tmp_path, monkeypatch, sphere_stl, make,
                                                      output, match):
    """Found at the end of the run before (after meshing and compensation, minutes on a real organ)."""
    monkeypatch.chdir(tmp_path)
    kind, name = make.split(":")
    (tmp_path / name).mkdir() if kind == "dir" else (tmp_path / name).write_text("x")
    rc, out, err = run_cli("prepare", sphere_stl, "-o", output)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("esmm: error: --output: "), err
    assert match in lines[0]
    assert sorted(os.listdir(tmp_path)) == [name]


def test_bad_config_file_names_file_and_key(run_cli, tmp_path, monkeypatch, sphere_stl):
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[mesh]\nsise = 3\n")
    rc, out, err = run_cli("prepare", sphere_stl, "--config", cfg)
    assert rc == 2 and "sise" in err and str(cfg) in err and len(err.strip().splitlines()) == 1
    assert sorted(os.listdir(tmp_path)) == ["c.toml"]


def test_hollow_organ_is_refused_with_the_body_flag(run_cli, tmp_path, monkeypatch):
    """A hollow organ (outer wall + inner cavity surface in one STL) is not filled silently."""
    from esmm.pipeline.mesh.readers import write_stl
    from esmm.pipeline.mesh.surface import Surface

    monkeypatch.chdir(tmp_path)
    a, b = icosphere(0.03, 3), icosphere(0.025, 3)
    wall = Surface(np.vstack([a.points, b.points]), np.vstack([a.faces, b.faces[:, ::-1] + a.n_points]))
    write_stl(wall, tmp_path / "bladder.stl", unit="mm")
    rc, out, err = run_cli("prepare", "bladder.stl", "-o", "bladder.h5")
    lines = [ln for ln in err.splitlines() if ln.startswith("esmm: error:")]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith("esmm: error: --body: bladder.stl") and "hollow" in lines[0]
    assert sorted(os.listdir(tmp_path)) == ["bladder.stl"]


# -- esmm info -------------------------------------------------------------------------------

@pytest.fixture()
def small_asset(tmp_path):
    from types import SimpleNamespace

    from esmm.pipeline.asset import write_asset
    from esmm.pipeline.network.springs import network_from_tets

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]]) * 0.01
    net = network_from_tets(SimpleNamespace(points=pts, tets=np.array([[0, 1, 2, 3], [1, 3, 2, 4]])))
    return write_asset(tmp_path / "small.h5", net.with_fixed([0]), fixed_region="node 0")


def test_info_on_a_good_asset(run_cli, small_asset):
    rc, out, err = run_cli("info", small_asset)
    assert rc == 0, err
    assert "nodes        5 (1 fixed: node 0)" in out and "springs      9" in out and "valid        yes" in out
    rc, out, err = run_cli("info", small_asset, "--json")
    data = json.loads(out)
    assert rc == 0 and data["valid"] is True and data["summary"]["tets"] == 2


def test_info_on_bad_assets(run_cli, small_asset, tmp_path):
    from esmm.pipeline.asset.hdf5 import seal

    with h5py.File(small_asset, "r+") as f:
        f["/nodes/mass"][0] = 0.0
        f["/springs/rest_length"].attrs["units"] = "mm"
        seal(f)  # consistent checksums and file hash: the content checks list each problem
    rc, out, err = run_cli("info", small_asset)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) >= 3
    assert all(ln.startswith(f"esmm: error: {small_asset}") for ln in lines)
    assert any("mass" in ln for ln in lines) and any("units are 'mm'" in ln for ln in lines)
    rc, out, err = run_cli("info", small_asset, "--json")
    data = json.loads(out)
    assert rc == 2 and data["valid"] is False and len(data["problems"]) == len(lines)
    cut = tmp_path / "cut.h5"
    cut.write_bytes(small_asset.read_bytes()[:2000])
    rc, out, err = run_cli("info", cut)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "truncated" in err
    rc, out, err = run_cli("info", tmp_path / "none.h5")
    assert rc == 2 and "no such file" in err


# -- end to end ------------------------------------------------------------------------------

@pytest.mark.slow
def test_prepare_sphere_end_to_end(run_cli, tmp_path, monkeypatch, sphere_stl):
    """A 30 mm ball through the whole pipeline with the coarse preset (default output name)."""
    monkeypatch.chdir(tmp_path)
    rc, out, err = run_cli("prepare", sphere_stl, "--config", "coarse")
    assert rc == 0, err
    asset = tmp_path / "ball.h5"
    assert asset.exists() and (tmp_path / "ball.xdmf").exists()
    assert "wrote" in out and "nodes" in out and "tets" in out
    from esmm.pipeline.asset import read_asset, validate_asset

    assert validate_asset(asset) == []
    a = read_asset(asset)
    net = a.network
    v_ball = 4 / 3 * np.pi * 0.03**3
    assert net.total_volume() == pytest.approx(v_ball, rel=0.1)  # smoothing + faceting shrink a little
    assert net.total_mass() == pytest.approx(1060 * net.total_volume(), rel=1e-9)
    assert 600 < net.n_tets < 3750  # coarse: ~1 500; the mesher's size fidelity is its own business
    assert a.provenance.input_sha256 and "prepare" in a.provenance.command_line
    assert a.quality_passes is True
    assert net.fixed.size > 0
    rc, out, err = run_cli("info", asset)
    assert rc == 0 and "valid        yes" in out


@pytest.mark.slow
def test_quality_gate_and_force(run_cli, tmp_path, monkeypatch, sphere_stl):
    from esmm.pipeline.mesh.quality import QUALITY_FLOORS

    assert "min_dihedral_deg" in QUALITY_FLOORS
    key = "min_dihedral_deg"
    cfg = tmp_path / "strict.toml"
    cfg.write_text(f'[mesh]\nelements = 800\n[quality]\n{key} = 1e9\n')
    monkeypatch.chdir(tmp_path)
    rc, out, err = run_cli("prepare", sphere_stl, "--config", cfg, "-o", "strict.h5")
    assert rc == 4 and "below the floors" in err and "--force" in err
    assert sorted(os.listdir(tmp_path)) == ["strict.toml"]
    rc, out, err = run_cli("prepare", sphere_stl, "--config", cfg, "-o", "strict.h5", "--force")
    assert rc == 0 and "warning" in err
    from esmm.pipeline.asset import read_asset

    a = read_asset(tmp_path / "strict.h5")
    assert a.quality_passes is False


@pytest.mark.slow
def test_prepare_liver_paper(run_cli, tmp_path, bundled_data):
    """The bundled InVesalius-style liver (1.04 L, genus 1) with the paper preset (~5 000 tets)."""
    stl = bundled_data / "meshes" / "ts_liver_3mm_closed.stl"
    rc, out, err = run_cli("prepare", stl, "-o", tmp_path / "liver.h5")
    assert rc == 0, err
    from esmm.pipeline.asset import read_asset, validate_asset

    assert validate_asset(tmp_path / "liver.h5") == []
    net = read_asset(tmp_path / "liver.h5").network
    assert 3500 < net.n_tets < 6500
    assert net.total_volume() == pytest.approx(1.04e-3, rel=0.1)
    assert Path(tmp_path / "liver.xdmf").exists()


@pytest.mark.slow
def test_prepare_skeleton_structure(run_cli, tmp_path, sphere_stl):
    """The surface + skeleton structure: no tets, the organ volume shared over the springs."""
    out = tmp_path / "sk.h5"
    rc, stdout, err = run_cli("prepare", sphere_stl, "--structure", "skeleton", "--config", "coarse", "-o", out)
    assert rc == 0, err
    from esmm.pipeline.asset import read_asset, validate_asset

    assert validate_asset(out) == []
    a = read_asset(out)
    net = a.network
    assert net.structure == "skeleton" and net.tets is None and a.quality is None
    v = float(a.cleaning["volume_after"])
    assert net.volume.sum() == pytest.approx(v, rel=1e-9)
    assert net.total_mass() == pytest.approx(1060 * v, rel=1e-9)
    np.testing.assert_allclose(net.volume_weight, net.volume_weight[0], rtol=1e-12)  # p = 2


def test_batch_out_empty_or_a_file_is_refused_before_any_work(run_cli, tmp_path):
    """Adversarial sweep: --out "" ran a single prepare into the current folder; --out FILE failed
    with "cannot create the output folder (File exists)" and no flag."""
    surface = tmp_path / "organ.stl"
    surface.write_text("solid x\nendsolid x\n")
    code, _out, err = run_cli("prepare", surface, "--out", "")
    assert code == 2 and "esmm: error: --out: empty" in err
    code, _out, err = run_cli("prepare", surface, "--out", surface)
    assert code == 2 and "esmm: error: --out:" in err and "is a file" in err
    assert not (tmp_path / "organ.h5").exists() and not list(tmp_path.glob("esmm-batch-*"))
