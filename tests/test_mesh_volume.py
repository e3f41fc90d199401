"""Volume meshing: checks, fallbacks, time limit, and every shared organ surface."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError, InputError, MeshingError
from esmm.pipeline.mesh import gmsh_worker
from esmm.pipeline.mesh import volume as volmod
from esmm.pipeline.mesh.gmsh_worker import GmshFailure, GmshTimeout, run_worker
from esmm.pipeline.mesh.quality import tet_quality
from esmm.pipeline.mesh.surface import Surface
from esmm.pipeline.mesh.volume import VolumeMesh, check_tets, mesh_volume, restore_volume


def sphere(r=0.04, nsub=4):
    import pyvista as pv

    return Surface.from_pyvista(pv.Icosphere(radius=r, nsub=nsub), source="sphere")


def assert_valid(mesh: VolumeMesh, surface: Surface):
    assert mesh.n_tets > 0
    v = mesh.tet_volumes()
    assert np.all(v > 0)
    assert abs(mesh.volume() / surface.volume() - 1) <= 0.01
    b = mesh.boundary_surface()
    assert b.is_closed()
    assert b.volume() == pytest.approx(mesh.volume(), rel=1e-9)  # outward boundary
    used = np.zeros(mesh.n_nodes, bool)
    used[mesh.tets.ravel()] = True
    assert used.all()


@pytest.mark.slow
def test_sphere_with_node_target():
    s = sphere()
    mesh = mesh_volume(s, nodes=800)
    assert mesh.path == "gmsh"
    assert_valid(mesh, s)
    assert 800 * 0.6 <= mesh.n_nodes <= 800 * 1.4
    assert mesh.volume() == pytest.approx(4 / 3 * np.pi * 0.04 ** 3, rel=0.02)
    assert tet_quality(mesh).passes()[0]


@pytest.mark.slow
def test_size_sets_the_edge_length():
    s = sphere()
    mesh = mesh_volume(s, size=0.012)
    t = mesh.tets
    p = mesh.points
    e = np.concatenate([np.linalg.norm(p[t[:, i]] - p[t[:, j]], axis=1)
                        for i in range(4) for j in range(i + 1, 4)])
    assert 0.7 * 0.012 < np.median(e) < 1.3 * 0.012


def test_open_or_inward_surface_is_refused():
    s = sphere(nsub=2)
    with pytest.raises(MeshingError, match="not closed"):
        mesh_volume(Surface(s.points, s.faces[1:]))
    with pytest.raises(MeshingError, match="inward"):
        mesh_volume(Surface(s.points, s.faces[:, ::-1]))


@pytest.mark.parametrize("kw,match", [
    (dict(size=-1.0), "size"), (dict(nodes=3), "nodes"), (dict(timeout=0), "timeout"),
    (dict(size=1.0), "larger than the organ"), (dict(size=1e-5), "nodes"),
])
def test_bad_options(kw, match):
    with pytest.raises(ConfigError, match=match):
        mesh_volume(sphere(nsub=2), **kw)


def _child_that_cannot_finish(monkeypatch, pid_file=None):
    """Put a child in the mesher's place that never finishes (a shell waiting on a sleep).

    The time limit is then tested by what it does, whatever the speed of the
    machine or of today's gmsh. The shell writes its background sleep's pid to
    *pid_file*, so the test can check that the whole process group was killed.
    """
    import shutil

    sh = shutil.which("sh")
    record = f"echo $! > '{pid_file}'; " if pid_file else ""
    monkeypatch.setattr(gmsh_worker, "child_argv", lambda folder: [sh, "-c", f"sleep 1000 & {record}wait"])


def test_worker_time_limit_kills_the_process_group(monkeypatch, tmp_path):
    import psutil

    pid_file = tmp_path / "grandchild.pid"
    _child_that_cannot_finish(monkeypatch, pid_file)
    s = sphere(nsub=2)
    with pytest.raises(GmshTimeout, match="no result after 2 s; the process was killed") as ei:
        run_worker("mesh", {"size": 2.0}, arrays={"points": s.points * 1e3, "faces": s.faces}, timeout=2.0)
    def alive(pid):
        try:
            return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
        except psutil.NoSuchProcess:
            return False

    assert ei.value.pid is not None and not alive(ei.value.pid)
    grandchild = int(pid_file.read_text())  # started by the child: killed with its group
    with contextlib.suppress(psutil.NoSuchProcess, psutil.TimeoutExpired):
        psutil.Process(grandchild).wait(timeout=10)  # SIGKILL is sent; give the kernel time to act
    assert not alive(grandchild)


def test_time_limit_gives_a_clear_error(monkeypatch):
    _child_that_cannot_finish(monkeypatch)
    with pytest.raises(MeshingError, match=r"no result within 0.3 s, killed") as ei:
        mesh_volume(sphere(nsub=3), nodes=500, timeout=0.3)
    msg = str(ei.value)
    assert "\n" not in msg and "gmsh:" in msg and "gmsh-after-repair:" in msg and "pytetwild:" in msg


def test_all_paths_failing_lists_them(monkeypatch):
    def fail(command, options, **kw):
        raise GmshFailure(f"{command} exploded")

    monkeypatch.setattr(volmod, "run_worker", fail)
    with pytest.raises(MeshingError) as ei:
        mesh_volume(sphere(nsub=3), nodes=500)
    msg = str(ei.value)
    for path in ("gmsh:", "gmsh-after-repair:", "pytetwild:"):
        assert path in msg


@pytest.mark.slow
def test_falls_back_to_pytetwild(monkeypatch, tmp_path):
    """gmsh failing twice, fTetWild meshes; the child works in its own folder, so fTetWild's scratch file
    (``__tracked_surface.stl``, written in its working directory) is not left in the user's."""
    real = volmod.run_worker
    monkeypatch.chdir(tmp_path)

    def gmsh_broken(command, options, **kw):
        if command == "mesh":
            raise GmshFailure("PLC Error: a segment and a facet intersect")
        return real(command, options, **kw)

    monkeypatch.setattr(volmod, "run_worker", gmsh_broken)
    s = sphere(nsub=3)
    mesh = mesh_volume(s, nodes=400)
    assert mesh.path == "pytetwild"
    assert_valid(mesh, s)
    assert sum("PLC Error" in line for line in mesh.log) == 2  # gmsh and gmsh-after-repair
    assert list(tmp_path.iterdir()) == []


def torus_with_dent():
    """A closed torus whose outer wall is pushed through its inner wall (self-intersecting)."""
    nu, nv, R, r = 60, 30, 0.04, 0.015
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    x = (R + r * np.cos(V)) * np.cos(U)
    y = (R + r * np.cos(V)) * np.sin(U)
    z = r * np.sin(V)
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(nu * nv).reshape(nu, nv)
    i1, j1 = np.roll(idx, -1, 0), np.roll(idx, -1, 1)
    ij = np.roll(i1, -1, 1)
    f = np.vstack([np.column_stack([idx.ravel(), i1.ravel(), ij.ravel()]),
                   np.column_stack([idx.ravel(), ij.ravel(), j1.ravel()])])
    ang = np.arctan2(pts[:, 1], pts[:, 0])
    sel = (np.abs(ang) < 0.3) & (np.hypot(pts[:, 0], pts[:, 1]) > 0.045)
    pts[sel, 0] -= 0.035 * np.cos(ang[sel] / 0.3 * np.pi / 2) ** 2
    s = Surface(pts, f, "dented torus")
    return s if s.volume() > 0 else Surface(pts, f[:, ::-1], "dented torus")


@pytest.mark.slow
def test_self_intersecting_surface_is_repaired_and_meshed():
    s = torus_with_dent()
    assert s.is_closed()
    mesh = mesh_volume(s, nodes=1000)
    assert mesh.path == "gmsh-after-repair"
    assert any("segment and a facet intersect" in line for line in mesh.log)
    assert mesh.n_tets > 0 and np.all(mesh.tet_volumes() > 0)


def test_check_tets_catches_empty_and_inverted():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    ok, msg, _ = check_tets(pts, np.zeros((0, 4), np.int64), 1.0)
    assert not ok and "0 tetrahedra" in msg
    t = np.array([[0, 1, 2, 3], [1, 3, 2, 4]])
    # (0,1,2,3) is positive, (1,3,2,4) negative: one of them is inverted
    ok, msg, _ = check_tets(pts, t, 1.0)
    assert not ok and "inverted" in msg
    # consistently negative meshes are just reoriented
    ok, msg, mesh = check_tets(pts, np.array([[0, 1, 3, 2]]), 1 / 6)
    assert ok and mesh.tet_volumes()[0] == pytest.approx(1 / 6)


def kuhn_block(n=4, a=0.04):
    """A cube of side a cut into n^3 cells of 6 positive tetrahedra each."""
    import itertools

    g = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    ax = np.linspace(0, a, n + 1)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            c = np.array([i, j, k])
            path = [c.copy()]
            for axis in perm:
                c = c.copy()
                c[axis] += 1
                path.append(c)
            tets.append([g[tuple(v)] for v in path])
    tets = np.array(tets)
    d = VolumeMesh(pts, tets, np.zeros((0, 3), int)).tet_volumes()
    tets[d < 0] = tets[d < 0][:, [0, 1, 3, 2]]  # odd permutations are negative
    ok, _, mesh = check_tets(pts, tets, a ** 3)
    assert ok
    return mesh


def test_restore_volume_after_chord_loss():
    """A 2 % volume deficit is undone by a uniform normal offset of the boundary nodes."""
    mesh = kuhn_block()
    assert mesh.volume() == pytest.approx(0.04 ** 3)
    target = mesh.volume() * 1.02
    new, delta = restore_volume(mesh.points, mesh.tets, mesh.boundary_faces, target)
    assert VolumeMesh(new, mesh.tets, mesh.boundary_faces).volume() == pytest.approx(target, rel=1e-3)
    # first order delta = dV / A = 0.02 a^3 / (6 a^2); a little more on a cube, whose edge and
    # corner nodes move along averaged (diagonal) normals
    assert 1.0 <= delta / (0.02 * 0.04 / 6) < 1.2
    interior = np.setdiff1d(np.arange(mesh.n_nodes), np.unique(mesh.boundary_faces))
    np.testing.assert_array_equal(new[interior], mesh.points[interior])


def test_check_tets_restores_a_coarse_mesh_volume():
    mesh = kuhn_block()
    ok, msg, fixed = check_tets(mesh.points, mesh.tets, mesh.volume() * 1.015)
    assert ok and "restore the volume" in msg
    assert fixed.volume() == pytest.approx(mesh.volume() * 1.015, rel=1e-3)


# -------------------------------------------------------- real and synthetic organs
def _shared_cases():
    return [("sofa_liver.stl", {}), ("sofa_liver.vtk", {}), ("ts_liver_3mm_closed.stl", {}),
            ("ts_liver_3mm_open.stl", {}), ("ts_liver_selfintersecting.stl", {}),
            ("ts_liver_partial_1mm.stl", {}), ("ts_example_seg.nii.gz", {"label": 5}),
            ("sofa_liver_smooth_ascii.stl", {"unit": "cm"}), ("sofa_liver_v1.msh", {"unit": "cm"})]


@pytest.mark.slow
@pytest.mark.parametrize("name,kw", _shared_cases(), ids=[c[0] for c in _shared_cases()])
def test_shared_organ_gives_a_valid_mesh(shared_data, name, kw):
    from esmm.pipeline.mesh.cleaning import clean_surface
    from esmm.pipeline.mesh.readers import read_surface

    raw = read_surface(shared_data / "meshes" / name, **kw)
    clean, report = clean_surface(raw)
    assert abs(report.relative_volume_change) <= 0.02
    mesh = mesh_volume(clean, nodes=1500, timeout=60)
    assert_valid(mesh, clean)
    q = tet_quality(mesh)
    ok, problems = q.passes()
    assert ok, problems


@pytest.mark.parametrize("name,kw,match", [
    ("sofa_liver_broken.vtk", {}, "corrupt or truncated"),
    ("sofa_liver_smooth_ascii.stl", {}, "unit cm"),
])
def test_shared_bad_inputs_fail_clearly(shared_data, name, kw, match):
    from esmm.pipeline.mesh.readers import read_surface

    with pytest.raises(InputError, match=match):
        read_surface(shared_data / "meshes" / name, **kw)


@pytest.mark.slow
def test_invesalius_like_input_end_to_end(tmp_path):
    from esmm.pipeline.mesh.cleaning import clean_surface
    from esmm.pipeline.mesh.readers import read_surface
    from esmm.pipeline.mesh.synthetic import invesalius_like_surface

    path = tmp_path / "organ.stl"
    invesalius_like_surface(shape="kidney", voxel=(1.0, 1.0, 2.0), second_body=True, path=path, seed=4)
    raw = read_surface(path)
    clean, report = clean_surface(raw)
    assert clean.is_closed()
    assert abs(clean.volume() / report.volume_before - 1) <= 0.02
    assert report.bodies_found >= 6  # organ, second body, 4 specks
    mesh = mesh_volume(clean, nodes=1000)
    assert_valid(mesh, clean)


@pytest.mark.slow
def test_two_bodies_are_meshed_separately():
    a = sphere(0.04, 3)
    b = Surface(sphere(0.02, 3).points + [0.1, 0.0, 0.0], sphere(0.02, 3).faces)
    both = Surface(np.vstack([a.points, b.points]), np.vstack([a.faces, b.faces + a.n_points]), "two")
    mesh = mesh_volume(both, nodes=900)
    assert_valid(mesh, both)
    assert any("2 bodies" in line for line in mesh.log)
    from esmm.pipeline.mesh.cleaning import face_components

    assert face_components(mesh.n_nodes, mesh.boundary_faces)[0] == 2
