#!/usr/bin/env python3
"""Plot the equivalent spring modulus mu_e(lambda) of a material (the ESMM paper's Fig. 5a analogue).

Usage::

    .venv/bin/python scripts/plot_mu_e.py [--material porcine_liver_paper] \
        [--out docs/figures/mu_e_porcine_liver.png]

mu_e(lambda) = 2 W(lambda) / (lambda - 1)^2 for incompressible uniaxial stretch
(docs/design/model.md), from compression to just below locking, in MPa.
"""

from __future__ import annotations

import argparse
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from esmm.pipeline.atomicio import atomic_path  # noqa: E402
from esmm.pipeline.errors import EsmmError  # noqa: E402
from esmm.pipeline.materials.material import DIRECTIONS, load_material  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", default="porcine_liver_paper", help="preset name or .toml path")
    ap.add_argument("--out", default="docs/figures/mu_e_porcine_liver.png")
    ap.add_argument("--lo", type=float, default=0.75, help="smallest stretch plotted")
    ap.add_argument("--hi", type=float, default=None, help="largest stretch (default: near locking)")
    args = ap.parse_args(argv)
    try:
        mat = load_material(args.material)
    except EsmmError as exc:
        print(f"plot_mu_e: error: {exc}", file=sys.stderr)
        return 2

    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=150)
    dirs = [None] if mat.is_isotropic else list(DIRECTIONS)
    for d in dirs:
        lo_adm, hi_adm = mat.stretch_range(d)
        lo = max(args.lo, lo_adm + 1e-3 * (1 - lo_adm))
        hi = args.hi if args.hi is not None else hi_adm - 2e-3 * (hi_adm - 1)
        hi = min(hi, hi_adm - 1e-6 * (hi_adm - 1)) if np.isfinite(hi_adm) else hi
        lam = np.linspace(lo, hi, 600)
        label = "μ_e(λ)" if d is None else f"μ_e, direction {d}"
        ax.plot(lam, mat.mu_e(lam, d) / 1e6, lw=2, label=label)
        if np.isfinite(hi_adm):
            ax.axvline(hi_adm, color="0.5", ls=":", lw=1)
            ax.text(hi_adm, 0.35, f"locking λ = {hi_adm:.4f} ", rotation=90,
                    transform=ax.get_xaxis_transform(), va="bottom", ha="right", fontsize=7,
                    color="0.35")
    e = mat.youngs_modulus() / 1e6
    ax.plot([1.0], [e], "o", color="k", ms=4, label=f"λ = 1: μ_e = E = {e:.4g} MPa")
    marks = np.array([0.9, 1.1, 1.2, 1.3])
    marks = marks[(marks > ax.get_xlim()[0]) & (marks < ax.get_xlim()[1])]
    for v, m in zip(marks, mat.mu_e(marks) / 1e6):
        ax.annotate(f"{m:.4f}", (v, m), textcoords="offset points", xytext=(-28, 6), fontsize=7)
        ax.plot([v], [m], "s", color="C3", ms=3)
    ax.set_xlabel("uniaxial stretch λ")
    ax.set_ylabel("equivalent spring modulus μ_e [MPa]")
    ax.set_title(f"{mat.name}: μ_e = 2W(λ)/(λ−1)²  ({mat.model})", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    with atomic_path(args.out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
