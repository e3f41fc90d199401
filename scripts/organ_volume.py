"""The organ under gravity with and without the volume term (docs/design/model.md, "The volume term (nearly incompressible network)").

For each organ surface: ``esmm prepare`` with its defaults (the volume term on)
and with ``--no-volume`` (each compensated for what it carries), then
``esmm simulate --method explicit`` in the default scene (bed held, floor,
gravity, a grasper that lifts 20 mm and releases: the explicit stepper, whose
step the term shortens, so that the cost columns measure that; the equilibrium
is FIRE's and the same with either stepper). From each ``summary.json``: the equilibrium under
gravity (volume change, inverted tets, sag median / p90 / max, FIRE iterations)
and the end of the run, the time step and the real-time factor. Written to
``docs/figures/organ_volume.json``::

    python scripts/organ_volume.py                    # the bundled liver
    python scripts/organ_volume.py --openhelp         # + OpenHELP kidney, spleen and the SOFA liver

Run from the checkout (``../shared/data`` must resolve). Minutes per organ.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "figures" / "organ_volume.json"
ESMM = Path(sys.executable).with_name("esmm")
BUNDLED = {"ts_liver": ROOT / "data" / "meshes" / "ts_liver_3mm_closed.stl"}
SHARED = ROOT.parent / "shared" / "data" / "meshes"
OPENHELP = {"kidney": SHARED / "openhelp_Kidney_left.stl", "spleen": SHARED / "openhelp_Spleen.stl",
            "sofa_liver": SHARED / "sofa_liver.stl"}


def _run(args: list, log: Path) -> float:
    t = time.time()
    with log.open("w") as fh:
        subprocess.run([str(ESMM), *map(str, args)], check=True, stdout=fh, stderr=subprocess.STDOUT)
    return time.time() - t


def _shape(d: dict) -> dict:
    return {"volume_change_pct": 100 * (d["volume_ratio"] - 1), "inverted_tets": d["inverted_tets"],
            "sag_median_mm": 1e3 * d["sag_median_m"], "sag_p90_mm": 1e3 * d["sag_p90_m"],
            "sag_max_mm": 1e3 * d["sag_max_m"]}


def organ(name: str, surface: Path, work: Path) -> dict:
    """Both variants of one organ: prepare, simulate, the figures of the summaries."""
    out = {}
    for variant, flags in (("volume", []), ("no_volume", ["--no-volume"])):
        asset = work / f"{name}_{variant}.h5"
        t_prep = _run(["prepare", surface, "-o", asset, *flags], work / f"prepare_{name}_{variant}.log")
        t_sim = _run(["simulate", asset, "--method", "explicit", "--out", work / f"{name}_{variant}-sim"],
                     work / f"sim_{name}_{variant}.log")
        s = json.loads((work / f"{name}_{variant}-sim" / "summary.json").read_text())
        eq = s["equilibrium"]
        info = json.loads(subprocess.run([str(ESMM), "info", asset, "--json"], check=True,
                                         capture_output=True, text=True).stdout)["summary"]
        out[variant] = {
            "nodes": s.get("nodes"), "springs": s.get("springs"), "tets": info.get("tets"),
            "min_dihedral_deg": (info.get("quality") or {}).get("min_dihedral_deg"),
            "volume_factor": info.get("tables", {}).get("volume_factor"),
            "gravity": {**_shape(eq["shape"]), "fire_iterations": eq["iterations"], "fire_seconds": eq["seconds"]},
            "end_of_run": _shape((s.get("volume") or {}).get("final") or eq["shape"]),
            "dt_mean_us": 1e6 * s["dt_mean_s"], "real_time_factor": s["real_time_factor"],
            "ns_per_spring_step": s["ns_per_spring_step"],
            "grasper_max_force_N": (s.get("grasper") or {}).get("max_force_N"),
            "prepare_seconds": t_prep, "simulate_seconds": t_sim}
        print(name, variant, json.dumps(out[variant]["gravity"]), flush=True)
    on, off = out["volume"], out["no_volume"]
    out["cost_ratio_rtf"] = off["real_time_factor"] / on["real_time_factor"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--openhelp", action="store_true", help="also the OpenHELP kidney, spleen and the SOFA liver")
    ap.add_argument("--only", nargs="+", default=None, help="organ names to run (default all selected)")
    ap.add_argument("--work", default=None, help="folder for the assets and runs (default: a temporary one)")
    args = ap.parse_args(argv)
    organs = {**BUNDLED, **(OPENHELP if args.openhelp else {})}
    if args.only:
        organs = {k: v for k, v in organs.items() if k in args.only}
    data = json.loads(OUT.read_text()) if OUT.exists() else {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for name, surface in organs.items():
            data[name] = organ(name, surface, work)
            data[name]["surface"] = os.path.relpath(surface, ROOT)
            OUT.parent.mkdir(parents=True, exist_ok=True)
            OUT.write_text(json.dumps(data, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
