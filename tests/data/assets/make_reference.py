"""Write the committed reference asset ``box_v1.h5`` and its record ``box_v1.json``.

Run from the repository root with the venv's Python (``.venv/bin/python
tests/data/assets/make_reference.py``) only when the asset format changes on
purpose (a new schema version): the point of the committed file is that an
*unintended* change of the v1 format, or of what the writer puts in it, makes
tests/test_asset_reference.py fail.

Inputs, all deterministic: a 3 x 3 x 3 Kuhn box of 20 mm (162 tetrahedra), fixed
at z = 0; the bundled paper material with a viscoelastic effect (one Prony term)
added; its stiffness tables (the default grid); fixed provenance (no time stamp,
no package versions).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import numpy as np

HERE = Path(__file__).resolve().parent


def inputs():
    """(network, material, tables, provenance) of the reference asset."""
    from esmm.pipeline.asset import Provenance
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.mesh.synthetic import box_tets
    from esmm.pipeline.network.springs import network_from_tets
    from esmm.pipeline.network.tables import build_tables

    net = network_from_tets(box_tets(3, 3, 3, (0.02, 0.02, 0.02)), density=1060.0)
    net = net.with_fixed(np.flatnonzero(net.points[:, 2] < 1e-9))
    base = load_material("porcine_liver_paper")
    material = base.to_toml() + '\n[material.effects.viscoelastic]\ng = [0.3]\ntau = ["2 s"]\n'
    tables = build_tables(base)
    prov = Provenance(input_path="box.stl", input_sha256="0" * 64, config_toml='[mesh]\nsize = "6.7 mm"\n',
                      command_line=["esmm", "prepare", "box.stl"], utc_time="2026-01-01T00:00:00+00:00",
                      host="reference", packages={"esmm": "reference"}, python="reference",
                      platform="reference")
    return net, material, tables, prov


def record(path: Path) -> dict:
    """Every object of the file: groups with their type and version, datasets with dtype,
    shape, units and sha256."""
    out = {}

    def visit(name, obj):
        a = obj.attrs
        if isinstance(obj, h5py.Group):
            out["/" + name] = {"esmm_type": str(a.get("esmm_type", "")), "esmm_version": int(a.get("esmm_version", -1))}
        else:
            out["/" + name] = {"dtype": obj.dtype.str, "shape": list(obj.shape), "units": str(a.get("units", "")),
                               "sha256": str(a.get("sha256", ""))}

    with h5py.File(path, "r") as f:
        out["/"] = {"esmm_type": str(f.attrs["esmm_type"]), "esmm_version": int(f.attrs["esmm_version"])}
        f.visititems(visit)
    return out


def write(target: Path) -> Path:
    from esmm.pipeline.asset import write_asset

    net, material, tables, prov = inputs()
    return write_asset(target, net, material=material, tables=tables, provenance=prov,
                       fixed_region="band z <= 0", xdmf=False)


if __name__ == "__main__":
    target = HERE / "box_v1.h5"
    write(target)
    (HERE / "box_v1.json").write_text(json.dumps(record(target), indent=1, sort_keys=True) + "\n")
    print(f"wrote {target} ({target.stat().st_size} bytes) and box_v1.json", file=sys.stderr)
