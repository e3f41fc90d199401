"""The default and the interactive scene on every shared organ: implicit against explicit (docs/design/simulator.md, "What it achieves").

For each organ surface: ``esmm prepare --config paper`` (the volume term on),
then, for each of the two scenes (the default's sticking bed, the interactive
one's frictionless bed), ``esmm simulate --scene S --method implicit``
(backward Euler at the frame step, grasper force at 1 kHz) and the same scene
with ``--method explicit`` (the accuracy reference), one after the other. From each
``summary.json``: the real-time factor and the stepping time; from the two
histories (``implicit_accuracy`` of benchmarks/bench_simulate.py, over the lift
t <= 1 s): the grasper force error (max and rms over the largest force) and the
displacement error (over the largest displacement). Written to
``docs/figures/implicit_organs.json``::

    python scripts/implicit_organs.py

Run from the checkout (``../shared/data`` must resolve). Minutes per organ.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "figures" / "implicit_organs.json"
ESMM = Path(sys.executable).with_name("esmm")
SHARED = ROOT.parent / "shared" / "data" / "meshes"
ORGANS = {"ts_liver": ROOT / "data" / "meshes" / "ts_liver_3mm_closed.stl", "sofa_liver": SHARED / "sofa_liver.stl",
          "kidney": SHARED / "openhelp_Kidney_left.stl", "spleen": SHARED / "openhelp_Spleen.stl"}
KEYS = ("springs", "nodes", "steps", "stepping_wall_s", "real_time_factor")
SCENES = ("default", "interactive")
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_simulate import implicit_accuracy  # noqa: E402


def _esmm(*args) -> None:
    subprocess.run([str(ESMM), *map(str, args)], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def scene(asset: Path, name: str, work: Path) -> dict:
    """Both steppers in scene *name*, compared."""
    row = {}
    for method in ("implicit", "explicit"):
        _esmm("simulate", asset, "--scene", name, "--method", method, "--out", work / method)
        summary = json.loads((work / method / "summary.json").read_text())
        row[method] = {k: summary[k] for k in KEYS}
    row["speedup_implicit_over_explicit"] = row["explicit"]["stepping_wall_s"] / row["implicit"]["stepping_wall_s"]
    row["accuracy_over_lift"] = implicit_accuracy(work / "implicit" / "history.h5", work / "explicit" / "history.h5",
                                                  1.0, 1.0 / 30.0)
    row["load_average_after"] = os.getloadavg()
    return row


def organ(surface: Path, work: Path) -> dict:
    """Prepare, then every scene of :data:`SCENES`."""
    asset = work / "organ.h5"
    _esmm("prepare", surface, "--config", "paper", "-o", asset)
    return {name: scene(asset, name, work / name) for name in SCENES}


def main() -> int:
    out = {"command": "python scripts/implicit_organs.py", "load_average_at_start": os.getloadavg(), "organs": {}}
    for name, surface in ORGANS.items():
        with tempfile.TemporaryDirectory() as d:
            out["organs"][name] = organ(surface, Path(d))
        for sc, r in out["organs"][name].items():
            a = r["accuracy_over_lift"]
            print(f"{name}, {sc}: implicit {r['implicit']['real_time_factor']:.3g}x real time, explicit "
                  f"{r['explicit']['real_time_factor']:.3g}x ({r['speedup_implicit_over_explicit']:.2f}x); force "
                  f"{100 * a['force_err_max_frac']:.2g} % max, displacement "
                  f"{100 * a['displacement_err_frac_of_largest']:.2g} %")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
