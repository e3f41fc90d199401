"""The asset's file header (HDF5 user block: SHA-256 and length of every later byte), checked before
libhdf5 parses the file; and the HDF5-level checks that remain for files without it."""

from __future__ import annotations

import hashlib
import re
import shutil
import sys
from pathlib import Path

import cloudpickle
import h5py
import numpy as np
import pytest
from esmm.pipeline.asset import collect_provenance, hdf5, read_asset, validate_asset, write_asset
from esmm.pipeline.errors import AssetError

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the sandbox runs this module's probe


from esmm.pipeline.mesh.synthetic import box_tets  # noqa: E402


def kuhn_cube(n=2, side=0.04):
    """A structured tet mesh of a cube: n^3 cells, 6 Kuhn tets each."""
    return box_tets(n, n, n, (side, side, side))


@pytest.fixture(scope="module")
def sandbox():
    from esmm.pipeline.batch.local import Sandbox

    with Sandbox() as sb:
        yield sb


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    from esmm.pipeline.network.springs import network_from_tets

    net = network_from_tets(kuhn_cube(), density=1060.0)
    net = net.with_fixed(np.flatnonzero(net.points[:, 2] < 1e-9))
    p = tmp_path_factory.mktemp("ub") / "organ.h5"
    write_asset(p, net, provenance=collect_provenance(None, config_toml="[mesh]\n", argv=["esmm"]),
                fixed_region="z = 0")
    return p


@pytest.fixture()
def asset(written, tmp_path):
    p = Path(shutil.copy(written, tmp_path / "organ.h5"))
    shutil.copy(written.with_suffix(".xdmf"), tmp_path / "organ.xdmf")
    return p


def headerless(src: Path, dst: Path) -> Path:
    """The same asset as an older esmm wrote it: no user block, dataset and root checksums only."""
    with h5py.File(src, "r") as s, h5py.File(dst, "w") as d:
        for k, v in s.attrs.items():
            d.attrs[k] = v
        for k in s:
            s.copy(s[k], d, name=k)
        hdf5.seal_content(d)
    return dst


def test_header_states_hash_and_length_of_the_hdf5_bytes(asset):
    data = asset.read_bytes()
    m = re.match(rb"ESMM-ASSET 1 sha256=([0-9a-f]{64}) length=(\d+)\n", data)
    assert m is not None
    rest = data[hdf5.USERBLOCK_SIZE:]
    assert rest.startswith(hdf5.HDF5_SIGNATURE)  # the superblock right after the user block
    assert int(m.group(2)) == len(rest) and m.group(1).decode() == hashlib.sha256(rest).hexdigest()
    assert hdf5.check_file(asset) == (True, "")
    with h5py.File(asset, "r") as f:
        assert f.userblock_size == 512 and f.attrs["esmm_type"] == "esmm_asset"
    assert validate_asset(asset) == []  # the XDMF sidecar included


@pytest.mark.parametrize("where", [0.0, 0.3, 0.77, 1.0])
def test_any_changed_byte_after_the_header_is_refused_before_parsing(asset, where):
    b = bytearray(asset.read_bytes())
    i = min(len(b) - 1, 512 + int(where * (len(b) - 512)))
    b[i] ^= 0x01
    asset.write_bytes(bytes(b))
    with pytest.raises(AssetError, match=r"damaged or modified after esmm wrote it \(file hash mismatch\); "
                                         r"re-create it with 'esmm prepare'") as info:
        read_asset(asset)
    assert str(info.value).startswith(str(asset)) and "\n" not in str(info.value)
    assert validate_asset(asset) == [str(info.value)]


def test_truncated_and_extended_files(asset):
    data = asset.read_bytes()
    asset.write_bytes(data[:3000])
    with pytest.raises(AssetError, match=f"the file is truncated \\(3000 of {len(data)} bytes\\)"):
        read_asset(asset)
    asset.write_bytes(data + b"\0" * 10)
    with pytest.raises(AssetError, match="10 bytes more than written; file hash mismatch"):
        read_asset(asset)


@pytest.mark.parametrize("edit,match", [
    (lambda b: b.__setitem__(slice(0, 1), b"X"), "its esmm file header is unreadable"),        # magic
    (lambda b: b.__setitem__(slice(30, 31), b"g"), "its esmm file header is unreadable"),      # not hex
    (lambda b: b.__setitem__(slice(30, 31), b"0" if b[30:31] != b"0" else b"1"), "file hash mismatch"),
    (lambda b: b.__setitem__(slice(0, 0), b"\0" * 7), "its esmm file header is unreadable"),   # shifted
    (lambda b: b.__setitem__(slice(11, 12), b"7"), "newer esmm \\(file header version 7"),
])
def test_damaged_header(asset, edit, match):
    b = bytearray(asset.read_bytes())
    edit(b)
    asset.write_bytes(bytes(b))
    with pytest.raises(AssetError, match=match):
        read_asset(asset)
    assert len(validate_asset(asset)) == 1


def test_padding_after_the_header_line_is_not_checked(asset):
    b = bytearray(asset.read_bytes())
    b[400:410] = b"anything.."
    asset.write_bytes(bytes(b))
    assert validate_asset(asset) == []


def test_seal_rewrites_the_header_when_the_file_is_closed(asset):
    with h5py.File(asset, "r+") as f:
        f["/nodes/mass"][0] = -1.0
        hdf5.seal(f)
    assert hdf5.check_file(asset) == (True, "")
    problems = validate_asset(asset)
    assert problems and all("hash" not in p for p in problems) and any("mass" in p for p in problems)
    # an explicit close() (no with-block) seals too
    f = h5py.File(asset, "r+")
    f["/nodes/mass"][0] = f["/nodes/mass"][1]
    hdf5.seal(f)
    f.close()
    assert hdf5.check_file(asset) == (True, "") and validate_asset(asset) == []


def test_esmm_info_on_a_modified_file(asset, capsys):
    from esmm.cli.main import main

    with h5py.File(asset, "r+") as f:
        f["/springs/rest_length"][0] *= 2
    assert main(["info", str(asset)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("esmm: error: ") and "file hash mismatch" in err[0]


# -- files without the header: the HDF5-level checks (and their messages) -----------------------

def test_headerless_file_gets_the_content_checks(asset, tmp_path):
    old = headerless(asset, tmp_path / "old.h5")
    assert hdf5.check_file(old) == (False, "") and validate_asset(old) == []
    with h5py.File(old, "r+") as f:
        f["/springs/rest_length"][5] *= 1.001
    with pytest.raises(AssetError, match="rest_length: content does not match its sha256"):
        read_asset(old)
    headerless(asset, old)
    with h5py.File(old, "r+") as f:
        f["/nodes"].attrs["density_kg_m3"] = 1000.0
        f["/springs/rest_length"].attrs["units"] = "mm"
    problems = validate_asset(old)
    assert any("root checksum" in p for p in problems)
    assert any("units are 'mm', expected 'm'" in p for p in problems)


def test_headerless_infinite_version_is_refused(asset, tmp_path):
    old = headerless(asset, tmp_path / "old.h5")
    with h5py.File(old, "r+") as f:
        f.attrs["esmm_version"] = np.inf
    assert any("is not a schema version" in p for p in validate_asset(old))
    with pytest.raises(AssetError, match="is not a schema version"):
        read_asset(old)


def test_headerless_damage_seen_byhdf5py_is_an_asset_error(asset, tmp_path, sandbox):
    """libhdf5's RuntimeError on damaged metadata (in a sandbox: such files can also crash it)."""
    old = headerless(asset, tmp_path / "old.h5")
    b = bytearray(old.read_bytes())
    for n in (6, 35, 63):
        i = len(b) // 2
        b[i:i] = bytes(n)
    old.write_bytes(bytes(b))
    kind, value = sandbox.call(_read_and_validate, str(old), timeout=60)
    assert kind == "result", value
    read_outcome, problems = value
    assert read_outcome.startswith("AssetError:") and problems and all("\n" not in p for p in problems)


def _read_and_validate(path: str):
    from esmm.pipeline.asset import read_asset, validate_asset
    from esmm.pipeline.errors import AssetError

    try:
        read_asset(path)
        outcome = "accepted"
    except AssetError as exc:
        outcome = f"AssetError: {exc}"
    return outcome, validate_asset(path)


def test_bugs_in_esmm_are_not_reported_as_damage(asset, monkeypatch):
    """An AttributeError raised by esmm's own code is a bug: it is not turned into 'damaged asset'."""
    from esmm.pipeline.asset import read as asset_read

    def broken(f):
        raise AttributeError("a bug")

    monkeypatch.setattr(asset_read, "_network", broken)
    with pytest.raises(AttributeError, match="a bug"):
        read_asset(asset)


def test_seal_file_gives_a_headerless_file_its_header(asset, tmp_path):
    old = headerless(asset, tmp_path / "old.h5")
    with h5py.File(old, "r") as f:
        before = {k: f[k][()] for k in ("/mesh/points", "/springs/pairs")}
    assert hdf5.seal_file(old) is True
    assert hdf5.check_file(old) == (True, "") and validate_asset(old) == []
    with h5py.File(old, "r") as f:
        assert f.userblock_size == 512
        for k, v in before.items():
            np.testing.assert_array_equal(f[k][()], v)
    data = old.read_bytes()
    with h5py.File(old, "r+"):
        pass  # opening for writing without a change leaves the bytes as they are
    assert old.read_bytes() == data


def test_foreign_user_block_is_left_alone(tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w", userblock_size=512) as f:
        f.create_dataset("x", data=[1, 2])
    with open(p, "r+b") as fh:
        fh.write(b"somebody else's user block")
    assert hdf5.seal_file(p) is False
    assert hdf5.check_file(p) == (False, "")
    with pytest.raises(AssetError, match="not an esmm asset"):
        read_asset(p)


def test_rewritten_tables_are_sealed(asset):
    from esmm.pipeline.asset import update_asset_tables
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.network.tables import build_tables

    mat = load_material("porcine_liver_paper")
    update_asset_tables(asset, build_tables(mat, n=12), material=mat)
    assert hdf5.check_file(asset) == (True, "")
    a = read_asset(asset)
    assert a.tables.n == 12 and validate_asset(asset) == []


@pytest.fixture(scope="module")
def full_asset(tmp_path_factory):
    """The fuzzer's base asset (material, tables, reports): the byte offsets below refer to its layout."""
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.network.tables import build_tables

    net = network_from_tets(kuhn_cube(), density=1060.0)
    net = net.with_fixed(np.flatnonzero(net.points[:, 2] < 1e-9))
    mat = load_material("porcine_liver_paper")
    p = tmp_path_factory.mktemp("full") / "organ.h5"
    write_asset(p, net, material=mat, tables=build_tables(mat, n=16), quality={"min_dihedral_deg": 35.0},
                cleaning={"steps": []}, provenance=collect_provenance(None, config_toml="[mesh]\n", argv=["esmm"]),
                xdmf=False)
    return p


@pytest.mark.parametrize("obj,offset,n,value", [
    ("/springs/cos2", 169, 1, 203),          # an attribute's datatype message: libhdf5 segfaults
    ("/provenance/packages", 2807, 35, 0),   # zeroed metadata: libhdf5 never returns
])
def test_bytes_that_crash_libhdf5_are_refused_before_parsing(full_asset, tmp_path, sandbox, obj, offset, n,
                                                             value):
    """The fuzzer's reproducers at the same place in the HDF5 structure (addresses are relative to
    the end of the user block), read in a sandbox so that a regression cannot end the session."""
    p = Path(shutil.copy(full_asset, tmp_path / "organ.h5"))
    with h5py.File(p, "r") as f:
        at = h5py.h5o.get_info(f[obj].id).addr + f.userblock_size + offset
    b = bytearray(p.read_bytes())
    b[at:at + n] = bytes([value]) * n
    p.write_bytes(bytes(b))
    kind, value = sandbox.call(_read_and_validate, str(p), timeout=30)
    assert kind == "result", value
    outcome, problems = value
    assert "file hash mismatch" in outcome and problems == [outcome.removeprefix("AssetError: ")]
