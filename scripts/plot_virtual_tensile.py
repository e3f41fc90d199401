#!/usr/bin/env python3
"""Virtual tensile test study: network vs tissue before/after compensation, three mesh sizes.

Usage::

    .venv/bin/python scripts/plot_virtual_tensile.py [--material porcine_liver_paper] \
        [--sizes 2.5 1.6 1.1] [--out docs/figures]

Writes ``virtual_tensile_curves.png`` (nominal stress vs stretch), ``virtual_tensile_errors.png``
(relative error vs stretch, per mesh size and law), ``virtual_tensile_correction.png`` (the
stretch correction g) and ``virtual_tensile_study.json`` (every number quoted in
docs/design/tables.md). Takes minutes (the finest mesh dominates).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from esmm.pipeline.atomicio import atomic_path, write_text  # noqa: E402
from esmm.pipeline.compensation.calibration import calibrate_compensation  # noqa: E402
from esmm.pipeline.compensation.virtual_tensile import (  # noqa: E402
    continuum_stress,
    cylinder_specimen,
    virtual_tensile_test,
)
from esmm.pipeline.errors import EsmmError, SimulationError  # noqa: E402
from esmm.pipeline.materials.material import load_material  # noqa: E402
from esmm.pipeline.network.tables import LAWS, build_tables  # noqa: E402


def _errs(r) -> dict:
    return {"max": r.max_abs_rel_error, "rms": r.rms_rel_error}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", default="porcine_liver_paper")
    ap.add_argument("--sizes", type=float, nargs="+", default=[2.5, 1.6, 1.1], help="element sizes [mm]")
    ap.add_argument("--radius", type=float, default=5.0, help="[mm]")
    ap.add_argument("--length", type=float, default=20.0, help="[mm]")
    ap.add_argument("--out", default="docs/figures")
    args = ap.parse_args(argv)
    try:
        mat = load_material(args.material)
    except EsmmError as exc:
        print(f"plot_virtual_tensile: error: {exc}", file=sys.stderr)
        return 2
    tables = build_tables(mat)
    study: dict = {"material": args.material, "radius_mm": args.radius, "length_mm": args.length,
                   "sizes": []}
    calibrated: dict = {}
    check_t = np.round(np.arange(1.01, 1.301, 0.01), 4)
    check_c = np.round(np.arange(0.99, 0.899, -0.01), 4)
    beyond_c = np.array([0.88, 0.85])
    for size in args.sizes:
        t0 = time.perf_counter()
        spec = cylinder_specimen(radius=args.radius * 1e-3, length=args.length * 1e-3, size=size * 1e-3)
        entry = {"size_mm": size, **spec.describe(), "laws": {}}
        for law in LAWS:
            t1 = time.perf_counter()
            comp, res = calibrate_compensation(tables, spec, law=law, material=mat)
            cal_time = time.perf_counter() - t1
            # independent check at every hundredth of stretch, both sides
            vt = virtual_tensile_test(spec, comp, stretch=check_t, law=law, material=mat)
            vc = virtual_tensile_test(spec, comp, stretch=check_c, law=law, material=mat)
            try:
                vb = virtual_tensile_test(spec, comp, stretch=beyond_c, law=law, material=mat, max_iter=25)
                beyond = {str(k): float(v) for k, v in zip(beyond_c, vb.rel_error)}
            except SimulationError as exc:  # the compensated network can lose stability there
                beyond = {"failed": str(exc)}
            entry["laws"][law] = {
                "volume_factor": res.factor, "iterations": res.iterations, "converged": res.converged,
                "calibration_time_s": cal_time,
                "before": _errs(res.before), "scalar": _errs(res.scalar), "after": _errs(res.after),
                "check_tension": _errs(vt), "check_compression": _errs(vc),
                "beyond_compression": beyond,
                "knots": res.knots.tolist(), "g": res.g.tolist(),
                "curve": {"stretch": res.after.stretch.tolist(), "reference": res.after.reference.tolist(),
                          "before": res.before.stress.tolist(), "scalar": res.scalar.stress.tolist(),
                          "after": res.after.stress.tolist(),
                          "lateral": res.after.lateral_stretch.tolist()},
                "error_curve": {"stretch": np.concatenate([check_c, check_t]).tolist(),
                                "after": np.concatenate([vc.rel_error, vt.rel_error]).tolist()},
            }
            calibrated[(size, law)] = comp
        entry["time_s"] = time.perf_counter() - t0
        study["sizes"].append(entry)
        write_text(f"{args.out}/virtual_tensile_study.json", json.dumps(study, indent=1) + "\n")
        print(f"size {size} mm: {entry['nodes']} nodes, {entry['time_s']:.0f} s", file=sys.stderr)
    # transfer: the coarsest mesh's compensation applied to the others
    coarse = args.sizes[0]
    study["transfer"] = {}
    for entry in study["sizes"][1:]:
        spec = cylinder_specimen(radius=args.radius * 1e-3, length=args.length * 1e-3,
                                 size=entry["size_mm"] * 1e-3)
        for law in LAWS:
            vt = virtual_tensile_test(spec, calibrated[(coarse, law)], stretch=check_t, law=law, material=mat)
            study["transfer"][f"{coarse}->{entry['size_mm']}:{law}"] = _errs(vt)

    out = args.out
    write_text(f"{out}/virtual_tensile_study.json", json.dumps(study, indent=1) + "\n")
    _plot_curves(study, f"{out}/virtual_tensile_curves.png", mat, tables)
    _plot_errors(study, f"{out}/virtual_tensile_errors.png")
    _plot_g(study, f"{out}/virtual_tensile_correction.png")
    return 0


def _plot_curves(study, path, mat, tables):
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), dpi=150)
    for ax, law in zip(axes, LAWS):
        lam = np.linspace(0.9, 1.3, 200)
        ax.plot(lam, continuum_stress(mat, lam) / 1e3, "k-", lw=2, label="tissue (ESEDF, uniaxial)")
        for entry, col in zip(study["sizes"], ("C0", "C1", "C2")):
            d = entry["laws"][law]["curve"]
            s = np.asarray(d["stretch"])
            o = np.argsort(s)
            lbl = f"{entry['size_mm']:g} mm ({entry['nodes']} nodes)"
            ax.plot(s[o], np.asarray(d["before"])[o] / 1e3, ":", color=col, label=f"{lbl}: c = 1")
            ax.plot(s[o], np.asarray(d["scalar"])[o] / 1e3, "--", color=col,
                    label=f"c = {entry['laws'][law]['volume_factor']:.2f}")
            ax.plot(s[o], np.asarray(d["after"])[o] / 1e3, "o", ms=2.5, color=col, label="c and g(λ)")
        ax.set_title(f"{law} law")
        ax.set_xlabel("stretch λ")
        ax.set_ylabel("nominal stress [kPa]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6, ncol=2)
    fig.suptitle("Virtual tensile test of a cylinder R = 5 mm, H = 20 mm (porcine liver)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def _plot_errors(study, path):
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=150, sharey=True)
    for ax, law in zip(axes, LAWS):
        for entry, col in zip(study["sizes"], ("C0", "C1", "C2")):
            d = entry["laws"][law]["error_curve"]
            s = np.asarray(d["stretch"])
            o = np.argsort(s)
            ax.plot(s[o], 100 * np.asarray(d["after"])[o], "-o", ms=2, color=col,
                    label=f"{entry['size_mm']:g} mm, compensated")
        ax.axhspan(-5, 5, color="0.9", zorder=0)
        ax.set_ylim(-6, 6)
        ax.set_title(f"{law} law: (network − tissue) / |tissue|")
        ax.set_xlabel("stretch λ")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("relative stress error [%]")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def _plot_g(study, path):
    fig, ax = plt.subplots(figsize=(6, 4), dpi=150)
    for entry, col in zip(study["sizes"], ("C0", "C1", "C2")):
        for law, ls in zip(LAWS, ("-", "--")):
            d = entry["laws"][law]
            ax.plot(d["knots"], d["g"], ls, color=col, marker=".",
                    label=f"{entry['size_mm']:g} mm, {law} (c = {d['volume_factor']:.2f})")
    ax.set_xlabel("spring stretch λ")
    ax.set_ylabel("stretch correction g(λ)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
