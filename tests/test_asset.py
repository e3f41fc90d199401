"""The HDF5 asset: round trip, schema, integrity (truncation, tampering), XDMF sidecar."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from esmm.pipeline.asset import (
    Provenance,
    collect_provenance,
    hdf5,
    read_asset,
    validate_asset,
    write_asset,
)
from esmm.pipeline.asset.xdmf import check_sidecar, referenced_datasets, sidecar_path, sidecar_paths
from esmm.pipeline.errors import AssetError, InputError
from esmm.pipeline.mesh.synthetic import box_tets  # noqa: E402
from esmm.pipeline.network.springs import network_from_skeleton, network_from_tets


def kuhn_cube(n=4, side=0.04):
    """A structured tet mesh of a cube: n^3 cells, 6 Kuhn tets each."""
    return box_tets(n, n, n, (side, side, side))


@pytest.fixture(scope="module")
def network():
    net = network_from_tets(kuhn_cube(), density=1060.0)
    return net.with_fixed(np.flatnonzero(net.points[:, 2] < 1e-9))


def make_tables():
    from esmm.pipeline.network.tables import StiffnessTables

    lam = np.linspace(0.7, 1.6, 7)
    stress = np.vstack([(lam - 1) * (1 + r) * 1e4 for r in (0.0, 0.1, 0.2)])
    energy = np.vstack([0.5 * (lam - 1) ** 2 * (1 + r) * 1e4 for r in (0.0, 0.1, 0.2)])
    values = np.vstack([np.full(7, (1 + r) * 1e4) for r in (0.0, 0.1, 0.2)])
    return StiffnessTables(lam_min=0.7, lam_max=1.6, n=7, values=values, stress=stress, energy=energy,
                           material_toml="", metadata={"material_name": "test"})


MATERIAL_TOML = """[material]
model = "esedf"
name = "test liver"
stress_unit = "MPa"

[material.parameters]
mu = 2.973e-06
N = 1.1074
A1 = 3.9106
A2 = 451.9193
f = 0.0019
"""


@pytest.fixture()
def asset(tmp_path, network):
    prov = collect_provenance(None, config_toml="[mesh]\nelements = 10\n", argv=["esmm", "prepare", "x.stl"])
    path = write_asset(tmp_path / "organ.h5", network, material=MATERIAL_TOML, tables=make_tables(),
                       quality={"min_dihedral_deg": 35.3, "sicn": [0.5, 0.7, 0.9]},
                       cleaning={"steps": [{"name": "keep largest", "dropped": 2}], "volume_before": 1e-4},
                       provenance=prov, fixed_region="band z <= 0")
    return path


def test_kuhn_cube_edge_count():
    """(n+1)^3 nodes; 3n(n+1)^2 axis edges + 3n^2(n+1) face diagonals + n^3 body diagonals."""
    n = 4
    net = network_from_tets(kuhn_cube(n))
    assert net.n_nodes == (n + 1) ** 3 and net.n_tets == 6 * n**3
    assert net.n_springs == 3 * n * (n + 1) ** 2 + 3 * n**2 * (n + 1) + n**3
    assert net.volume.sum() == pytest.approx(0.04**3, rel=1e-12)


def test_round_trip(asset, network):
    a = read_asset(asset)
    net = a.network
    for name in ("points", "springs", "rest_length", "volume", "volume_weight", "cos2", "mass",
                 "surface_faces", "fixed", "tets", "node_kind", "fibre_frame"):
        np.testing.assert_array_equal(getattr(net, name), getattr(network, name), err_msg=name)
    assert net.structure == "tetra" and net.density == 1060.0
    assert a.material_toml == MATERIAL_TOML
    assert a.material is not None and a.material.name == "test liver"
    assert a.material.params["A1"] == pytest.approx(3.9106e6)
    t = a.tables
    np.testing.assert_array_equal(t.values, make_tables().values)
    assert t.lam_min == 0.7 and t.n == 7
    assert a.quality["min_dihedral_deg"] == 35.3
    assert a.cleaning["steps"][0]["dropped"] == 2
    assert a.provenance.command_line == ["esmm", "prepare", "x.stl"]
    assert a.provenance.config_toml.startswith("[mesh]")
    assert a.provenance.packages["numpy"] == np.__version__
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", a.provenance.utc_time)
    assert a.fixed_region == "band z <= 0"
    s = a.summary()
    assert s["nodes"] == network.n_nodes and s["volume_mL"] == pytest.approx(64.0)
    json.dumps(s)
    assert validate_asset(asset) == []


def test_schema_attributes_everywhere(asset):
    with h5py.File(asset, "r") as f:
        assert f.attrs["esmm_type"] == "esmm_asset" and f.attrs["esmm_version"] == 1

        def visit(name, obj):
            if isinstance(obj, h5py.Group):
                assert "esmm_type" in obj.attrs and "esmm_version" in obj.attrs, name
            else:
                assert obj.attrs["units"], name
                assert len(obj.attrs["sha256"]) == 64, name

        f.visititems(visit)
        assert f["/springs/rest_length"].attrs["units"] == "m"
        assert f["/springs/volume"].attrs["units"] == "m3"
        assert f["/nodes/mass"].attrs["units"] == "kg"
        assert f["/material/parameters/A1"].attrs["units"] == "Pa"
        assert f["/material/parameters/A1"][()] == pytest.approx(3.9106e6)
        assert f["/material/parameters/N"].attrs["units"] == "1"


def test_material_object_is_stored(tmp_path, network):
    mat_mod = pytest.importorskip("esmm.pipeline.materials.material")
    mat = mat_mod.load_material("porcine_liver_paper")
    p = write_asset(tmp_path / "m.h5", network, material=mat)
    a = read_asset(p)
    assert a.material.params == pytest.approx(mat.params)
    assert a.tables is None and a.quality is None and a.cleaning is None


def test_truncated_file_is_refused(asset):
    size = asset.stat().st_size
    with open(asset, "r+b") as fh:
        fh.truncate(size // 2)
    with pytest.raises(AssetError, match="truncated") as info:
        read_asset(asset)
    assert "\n" not in str(info.value)
    problems = validate_asset(asset)
    assert len(problems) == 1 and "truncated" in problems[0]


def test_flipped_dataset_value_is_detected(asset):
    """An edit without re-sealing: the file hash (checked before HDF5 parses the file) objects.

    The per-dataset sha256 that names the dataset is tested on a file without
    the esmm file header in test_asset_userblock.py.
    """
    with h5py.File(asset, "r+") as f:
        f["/springs/rest_length"][5] *= 1.001
    with pytest.raises(AssetError, match="damaged or modified after esmm wrote it .*file hash mismatch"):
        read_asset(asset)
    assert any("file hash mismatch" in p for p in validate_asset(asset))


def test_flipped_bit_in_the_file_is_detected(asset):
    with h5py.File(asset, "r") as f:
        offset = f["/nodes/mass"].id.get_offset()
    with open(asset, "r+b") as fh:
        fh.seek(offset + 3)
        b = fh.read(1)
        fh.seek(offset + 3)
        fh.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(AssetError, match="file hash mismatch"):
        read_asset(asset)


def test_flipped_attribute_is_detected(asset):
    """Attribute edits without re-sealing: the file hash objects (the root checksum and units
    checks behind it are tested on a file without the esmm header in test_asset_userblock.py)."""
    with h5py.File(asset, "r+") as f:
        f["/nodes"].attrs["density_kg_m3"] = 1000.0
    with pytest.raises(AssetError, match="file hash mismatch"):
        read_asset(asset)
    with h5py.File(asset, "r+") as f:
        f["/springs/rest_length"].attrs["units"] = "mm"
    problems = validate_asset(asset)
    assert len(problems) == 1 and "file hash mismatch" in problems[0]


def test_resealed_but_inconsistent_content_is_caught(asset):
    """Someone edits masses and recomputes every checksum: the physical checks still object."""
    with h5py.File(asset, "r+") as f:
        m = f["/nodes/mass"][()]
        m[0] = -m[0]
        f["/nodes/mass"][...] = m
        c = f["/springs/cos2"][()]
        c[3] *= 2
        f["/springs/cos2"][...] = c
        hdf5.seal(f)
    problems = validate_asset(asset)
    assert any("zero or negative mass" in p for p in problems)
    assert any("cos2 rows" in p for p in problems)
    with pytest.raises(AssetError, match="mass|cos2"):
        read_asset(asset)


def test_bad_tets_and_indices_are_caught(asset):
    with h5py.File(asset, "r+") as f:
        t = f["/mesh/tets"][()]
        t[0, [1, 2]] = t[0, [2, 1]]  # inverted tet
        f["/mesh/tets"][...] = t
        p = f["/springs/pairs"][()]
        p[-1, 1] = f["/mesh/points"].shape[0] + 5
        f["/springs/pairs"][...] = p
        hdf5.seal(f)
    problems = validate_asset(asset)
    assert any("spring indices outside" in p for p in problems)


def test_newer_or_foreign_schema_is_refused(asset, tmp_path):
    with h5py.File(asset, "r+") as f:
        f["/springs"].attrs["esmm_version"] = 7
        hdf5.seal(f)
    with pytest.raises(AssetError, match="springs version 7 is newer than this esmm reads \\(1\\); upgrade esmm"):
        read_asset(asset)
    with h5py.File(asset, "r+") as f:
        f.attrs["esmm_version"] = 2
        hdf5.seal(f)  # as a newer esmm would have written it: consistent checksums and file hash
    with pytest.raises(AssetError, match="schema version 2 is newer"):
        read_asset(asset)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("x", data=[1, 2])
    with pytest.raises(AssetError, match="not an esmm asset"):
        read_asset(other)
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    with pytest.raises(AssetError, match="not an HDF5 file"):
        read_asset(text)
    with pytest.raises(AssetError, match="no such file"):
        read_asset(tmp_path / "missing.h5")


def test_missing_group_and_dataset(asset):
    with h5py.File(asset, "r+") as f:
        del f["/springs/volume_weight"]
        del f["/provenance"]
        hdf5.seal(f)
    problems = validate_asset(asset)
    assert "/provenance: required group is missing" in problems
    assert "/springs/volume_weight: required dataset is missing" in problems


def test_xdmf_sidecars_refer_to_existing_datasets(asset, network):
    sides = sidecar_paths(asset)
    assert sorted(p.name for p in asset.parent.glob("*.xdmf")) == ["organ.springs.xdmf", "organ.surface.xdmf",
                                                                    "organ.xdmf"]
    paths = set()
    for side in sides.values():
        assert check_sidecar(side) == []
        refs = referenced_datasets(side)
        paths |= {r[1] for r in refs}
        assert all(r[0] == "organ.h5" for r in refs)
        with h5py.File(asset, "r") as f:
            for _, path, dims, _, _ in refs:
                assert f[path].shape == dims
    assert {"/mesh/points", "/mesh/tets", "/springs/pairs", "/nodes/mass", "/nodes/fixed_mask",
            "/springs/rest_length", "/springs/volume_weight", "/mesh/surface_faces"} <= paths
    # a sidecar pointing at a dataset that is gone is reported
    with h5py.File(asset, "r+") as f:
        del f["/springs/volume_weight"]
    assert any("volume_weight, which does not exist" in p for p in check_sidecar(sides["springs"]))


def _vtk_blocks(path):
    """The grids VTK's XDMF reader (what ParaView uses) finds in one file: name -> dataset."""
    vtk = pytest.importorskip("vtkmodules.vtkIOXdmf2")
    from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet

    r = vtk.vtkXdmfReader()
    r.SetFileName(str(path))
    r.Update()
    out = r.GetOutputDataObject(0)
    if not out.IsA("vtkCompositeDataSet"):
        return {r.GetOutputInformation(0).Get(vtkCompositeDataSet.NAME()) or "grid": out}
    blocks = {}
    it = out.NewIterator()
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        blocks[it.GetCurrentMetaData().Get(vtkCompositeDataSet.NAME())] = it.GetCurrentDataObject()
        it.GoToNextItem()
    return blocks


def test_xdmf_opens_in_vtk(asset, network):
    """VTK's XDMF reader (what ParaView uses) opens each sidecar: the tets, the springs, the surface."""
    sides = sidecar_paths(asset)
    (tet,) = _vtk_blocks(sides[""]).values()
    assert tet.GetNumberOfCells() == network.n_tets and tet.GetNumberOfPoints() == network.n_nodes
    assert tet.GetCellType(0) == 10  # VTK_TETRA
    fixed = tet.GetPointData().GetArray("fixed")
    assert sum(fixed.GetValue(i) for i in range(fixed.GetNumberOfTuples())) == network.fixed.size
    (springs,) = _vtk_blocks(sides["springs"]).values()
    assert springs.GetNumberOfCells() == network.n_springs
    rl = springs.GetCellData().GetArray("rest_length")
    assert rl.GetValue(7) == pytest.approx(network.rest_length[7])
    (surface,) = _vtk_blocks(sides["surface"]).values()
    assert surface.GetNumberOfCells() == network.surface_faces.shape[0]


def test_meshio_reads_the_asset_sidecars(asset, network):
    """``meshio.read("organ.xdmf")`` gives the mesh with its node fields; each other sidecar its grid
    (meshio reads one grid per file: the three grids in one file failed with "Only supports one grid")."""
    import xml.etree.ElementTree as ET

    meshio = pytest.importorskip("meshio")
    sides = sidecar_paths(asset)
    m = meshio.read(sides[""])
    assert [c.type for c in m.cells] == ["tetra"] and m.cells[0].data.shape == (network.n_tets, 4)
    np.testing.assert_array_equal(m.cells[0].data, network.tets)
    np.testing.assert_allclose(m.points, network.points)
    np.testing.assert_array_equal(m.point_data["fixed"], network.fixed_mask().astype(np.uint8))
    np.testing.assert_allclose(m.point_data["mass"], network.mass)
    lines = meshio.read(sides["springs"])
    assert lines.cells[0].type == "line" and lines.cells[0].data.shape == (network.n_springs, 2)
    np.testing.assert_allclose(lines.cell_data["volume_weight"][0], network.volume_weight)
    assert meshio.read(sides["surface"]).cells[0].data.shape == network.surface_faces.shape
    for side in sides.values():      # valid XDMF 3: one Domain, one uniform Grid with its Topology and Geometry
        root = ET.parse(side).getroot()
        assert root.tag == "Xdmf" and root.attrib["Version"] == "3.0"
        (domain,) = list(root)
        (grid,) = list(domain)
        assert grid.tag == "Grid" and grid.attrib["GridType"] == "Uniform"
        assert [c.tag for c in grid][:2] == ["Topology", "Geometry"]


def test_a_new_asset_removes_the_sidecars_an_earlier_one_left(tmp_path, network):
    write_asset(tmp_path / "organ.h5", network)
    assert (tmp_path / "organ.springs.xdmf").is_file()
    g = (1 + 5**0.5) / 2
    v = np.array([[0, 1, g], [0, -1, g], [0, 1, -g], [0, -1, -g], [1, g, 0], [-1, g, 0], [1, -g, 0],
                  [-1, -g, 0], [g, 0, 1], [-g, 0, 1], [g, 0, -1], [-g, 0, -1]], float) * 0.01
    edges = [[0, k] for k in range(1, 13)] + [[k, k + 1] for k in range(1, 12)]
    sk = network_from_skeleton(np.vstack([[0, 0, 0], v]), np.array(edges), volume=4e-6).with_fixed([0])
    write_asset(tmp_path / "organ.h5", sk)          # the skeleton: its mesh is the springs
    assert sorted(p.name for p in tmp_path.glob("*.xdmf")) == ["organ.xdmf"]
    assert validate_asset(tmp_path / "organ.h5") == []


def test_skeleton_asset_round_trip(tmp_path):
    g = (1 + 5**0.5) / 2
    v = np.array([[0, 1, g], [0, -1, g], [0, 1, -g], [0, -1, -g], [1, g, 0], [-1, g, 0], [1, -g, 0],
                  [-1, -g, 0], [g, 0, 1], [-g, 0, 1], [g, 0, -1], [-g, 0, -1]], float) * 0.01
    pts = np.vstack([[0, 0, 0], v])
    edges = [[0, k] for k in range(1, 13)] + [[k, k + 1] for k in range(1, 12)]
    net = network_from_skeleton(pts, np.array(edges), volume=4e-6).with_fixed([0])
    p = write_asset(tmp_path / "sk.h5", net)
    a = read_asset(p)
    assert a.network.structure == "skeleton" and a.network.tets is None
    np.testing.assert_array_equal(a.network.volume, net.volume)
    assert validate_asset(p) == []
    with h5py.File(p) as f:
        assert "/mesh/tets" not in f


def test_write_is_atomic_and_refuses_bad_input(tmp_path, network):
    import dataclasses

    bad = dataclasses.replace(network, mass=np.zeros(network.n_nodes))
    with pytest.raises(InputError, match="mass"):
        write_asset(tmp_path / "bad.h5", bad)
    with pytest.raises(InputError, match=r"\.h5"):
        write_asset(tmp_path / "bad.vtk", network)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises((AssetError, OSError)):
        write_asset(blocker / "sub" / "a.h5", network)

    class Exploding:  # tables that fail while the asset is being written
        def __getattr__(self, name):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        write_asset(tmp_path / "half.h5", network, tables=Exploding())
    assert sorted(os.listdir(tmp_path)) == ["file"]  # no .h5, no .xdmf, no temp file


def test_overwrite_replaces_both_files(tmp_path, network):
    p = write_asset(tmp_path / "a.h5", network)
    first = Path(p).read_bytes()
    net2 = network.with_fixed([0, 1])
    write_asset(p, net2)
    assert Path(p).read_bytes() != first
    assert read_asset(p).network.fixed.tolist() == [0, 1]
    assert check_sidecar(sidecar_path(p)) == []


def test_provenance_hashes_the_input(tmp_path):
    src = tmp_path / "in.stl"
    src.write_bytes(b"solid x\nendsolid x\n")
    prov = collect_provenance(src, argv=["esmm", "prepare", str(src)])
    import hashlib

    assert prov.input_sha256 == hashlib.sha256(src.read_bytes()).hexdigest()
    assert prov.input_path == str(src.resolve())
    assert isinstance(Provenance().packages, dict)


# -- the optional /volume group (the volume term) -----------------------------------------

@pytest.fixture()
def volume_asset(tmp_path, network):
    import dataclasses

    from esmm.pipeline.network.volume import VolumeSpec

    spec = VolumeSpec(2.5e5, "nodal", poisson_ratio=0.49, shear_modulus=5.0e3, at_stretch=1.3, rule="test rule")
    net = dataclasses.replace(network, volume_term=spec)
    return write_asset(tmp_path / "vol.h5", net, material=MATERIAL_TOML, tables=make_tables()), spec


def test_volume_group_round_trip(volume_asset, network):
    from esmm.pipeline.network.volume import nodal_volumes

    path, spec = volume_asset
    assert validate_asset(path) == []
    a = read_asset(path)
    assert a.network.volume_term == spec
    assert a.summary()["volume_term"]["bulk_modulus_pa"] == 2.5e5
    with h5py.File(path, "r") as f:
        g = f["/volume"]
        assert hdf5.attr_str(g.attrs["esmm_type"]) == "volume_term" and int(g.attrs["esmm_version"]) == 1
        assert hdf5.attr_str(g["bulk_modulus"].attrs["units"]) == "Pa"
        np.testing.assert_allclose(g["rest_volume"][()], nodal_volumes(network.points, network.tets), rtol=1e-15)
        assert g["rest_volume"][()].sum() == pytest.approx(network.total_volume(), rel=1e-12)
        assert int(f.attrs["esmm_version"]) == 1        # an optional group: the schema version is unchanged


def test_asset_without_volume_group_reads_as_before(asset):
    a = read_asset(asset)
    assert a.network.volume_term is None and a.summary()["volume_term"] is None
    with h5py.File(asset, "r") as f:
        assert "/volume" not in f


def test_edited_volume_group_is_caught(volume_asset):
    path, _ = volume_asset
    with h5py.File(path, "r+") as f:
        v = f["/volume/rest_volume"][()]
        v[3] *= 1.01
        f["/volume/rest_volume"][...] = v
        hdf5.seal(f)
    problems = validate_asset(path)
    assert any("/volume/rest_volume: differs" in p for p in problems)
    with pytest.raises(AssetError, match="rest_volume"):
        read_asset(path)
    with h5py.File(path, "r+") as f:
        f["/volume"].attrs["formulation"] = "hexahedra"
        hdf5.seal(f)
    assert any("formulation" in p for p in validate_asset(path))


def test_volume_term_needs_tets(tmp_path):
    import dataclasses

    from esmm.pipeline.network.volume import VolumeSpec

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]]) * 0.01
    net = network_from_skeleton(pts, [[0, 1], [0, 2], [0, 3], [1, 4], [2, 4], [3, 4]], volume=1e-7,
                                surface_faces=[[0, 1, 2]])
    with pytest.raises(InputError, match="tetrahedra"):
        write_asset(tmp_path / "sk.h5", dataclasses.replace(net, volume_term=VolumeSpec(1e5)))


@pytest.mark.parametrize("version", [1.5, True, "1", np.array([1, 2])])
def test_root_schema_version_must_be_a_whole_number(asset, version, run_cli):
    """A float 1.5 (or True) passed for schema version 1 and the asset for valid (adversarial sweep)."""
    with h5py.File(asset, "r+") as f:
        f.attrs["esmm_version"] = version
        hdf5.seal(f)
    with pytest.raises(AssetError, match="is not a schema version; re-create it"):
        read_asset(asset)
    code, _out, err = run_cli("info", asset)
    assert code == 2 and "is not a schema version" in err and "Traceback" not in err


def test_a_simulation_history_is_named_as_such(tmp_path, run_cli):
    """'esmm info history.h5' said only "not an esmm asset"; it now says what the file is and what to give."""
    hist = tmp_path / "history.h5"
    with h5py.File(hist, "w") as f:
        f.attrs["esmm_type"] = "simulation_history"
        f.attrs["esmm_version"] = 1
    code, _out, err = run_cli("info", hist)
    lines = [ln for ln in err.splitlines() if ln.startswith("esmm: error:")]
    assert code == 2 and len(lines) == 1
    assert "simulation history" in lines[0] and "'esmm prepare'" in lines[0]
    with pytest.raises(AssetError, match="simulation history .*; give the .h5 written by 'esmm prepare'$"):
        read_asset(hist)
