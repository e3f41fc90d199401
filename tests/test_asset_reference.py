"""The committed reference asset (tests/data/assets/box_v1.h5): the v1 format does not drift.

``box_v1.json`` records every object of the file as written when it was made:
groups with their ``esmm_type`` and ``esmm_version``, datasets with dtype, shape,
units and the SHA-256 of their content. Two directions are checked:

* reading: today's reader opens the committed file, validates it and returns
  what it holds (an asset written by an earlier esmm stays readable);
* writing: today's writer, given the same deterministic inputs
  (``make_reference.inputs()``), writes the same objects with the same content
  hashes (floating-point contents that differ in their last bits from machine to
  machine, a BLAS product summed in another order: to 1e-12 of the committed
  file's values). A change of the writer's output is then either a bug or a new schema
  version: re-make the file on purpose (``make_reference.py``), never by accident.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from esmm.pipeline.asset import read_asset, validate_asset

HERE = Path(__file__).resolve().parent / "data" / "assets"
REFERENCE = HERE / "box_v1.h5"
RECORD = json.loads((HERE / "box_v1.json").read_text())


def _maker():
    spec = importlib.util.spec_from_file_location("make_reference", HERE / "make_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_committed_asset_reads_and_validates():
    assert validate_asset(REFERENCE) == []  # written without an XDMF sidecar, which is optional
    a = read_asset(REFERENCE)
    assert a.network.n_nodes == 64 and a.network.n_tets == 162 and a.network.n_springs == 279
    assert a.network.volume.sum() == pytest.approx(0.02 ** 3, rel=1e-12)
    assert len(a.network.fixed) == 16 and np.all(a.network.points[a.network.fixed, 2] == 0)
    assert a.tables is not None and a.tables.n == 1024


def test_the_committed_record_is_the_file():
    assert _maker().record(REFERENCE) == RECORD


def _same(key: str, recorded: dict, written: dict, made: Path) -> bool:
    """Whether the object *key* is written as recorded: groups, dtypes, shapes and units exactly; contents
    by their hash, or, for floating-point data whose last bits depend on the machine (a BLAS product's
    summation order on another CPU), to 1e-12 of the committed file's values."""
    if recorded == written:
        return True
    if recorded.get("sha256") is None or {**recorded, "sha256": ""} != {**written, "sha256": ""}:
        return False
    with h5py.File(REFERENCE, "r") as ref, h5py.File(made, "r") as new:
        a, b = ref[key][()], new[key][()]                 # the same dtype and shape (checked above)
    return bool(np.issubdtype(a.dtype, np.floating) and np.allclose(b, a, rtol=1e-12, atol=0.0, equal_nan=True))


def test_the_writer_still_writes_the_same_v1_file(tmp_path):
    made = _maker().write(tmp_path / "box.h5")
    got = _maker().record(made)
    missing = sorted(set(RECORD) - set(got))
    added = sorted(set(got) - set(RECORD))
    changed = sorted(k for k in set(RECORD) & set(got) if not _same(k, RECORD[k], got[k], made))
    assert not (missing or added or changed), (
        f"the v1 asset changed: missing {missing}, added {added}, changed {changed}; if on purpose, bump the "
        f"schema version and re-make tests/data/assets/box_v1.* with make_reference.py")
