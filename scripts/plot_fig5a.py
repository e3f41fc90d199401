#!/usr/bin/env python3
"""Reproduce the ESMM paper's Fig. 5a (mu_e vs stretch) from the stiffness tables, and compare the force laws.

Usage::

    .venv/bin/python scripts/plot_fig5a.py [--material porcine_liver_paper] [--out docs/figures]

Writes ``fig5a_mu_e.png``: mu_e(lambda) as tabulated by
:func:`esmm.pipeline.network.tables.build_tables` (what an asset stores; line),
the material evaluated directly (dots) and the paper's reference values; and
``fig5a_force_laws.png``: the spring force per unit c V / L0 of the secant
(paper Eq. 9) and energy-consistent laws, and their ratio. Prints the values
quoted in docs/design/tables.md.
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
from esmm.pipeline.materials.material import load_material  # noqa: E402
from esmm.pipeline.network.tables import build_tables  # noqa: E402

#: Values read off the paper's Fig. 5a for its porcine-liver fit (docs/design/tables.md) [MPa].
PAPER_POINTS = {1.1: 0.029, 1.3: 0.123}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", default="porcine_liver_paper", help="preset name or .toml path")
    ap.add_argument("--out", default="docs/figures")
    args = ap.parse_args(argv)
    try:
        mat = load_material(args.material)
        tables = build_tables(mat)
    except EsmmError as exc:
        print(f"plot_fig5a: error: {exc}", file=sys.stderr)
        return 2
    lo_adm, hi_adm = mat.stretch_range(None)

    # --- Fig. 5a --------------------------------------------------------------
    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=150)
    lam = np.linspace(tables.lam_min, tables.lam_max, 800)
    ax.plot(lam, tables.mu_e(lam)[0] / 1e6, lw=2, label=f"table ({tables.n} points, linear)")
    pts = np.linspace(tables.lam_min, tables.lam_max, 41)
    ax.plot(pts, mat.mu_e(pts) / 1e6, "k.", ms=4, label="material, direct")
    for lam_p, mu_p in PAPER_POINTS.items():
        ax.plot([lam_p], [mu_p], "s", mfc="none", mec="C3", ms=8)
    ax.plot([], [], "s", mfc="none", mec="C3", label="paper, Fig. 5a")
    for edge in (lo_adm, hi_adm):
        ax.axvline(edge, color="0.5", ls=":", lw=1)
    ax.axvspan(tables.lam_min, tables.lam_max, color="C0", alpha=0.05, lw=0)
    ax.set_xlabel("stretch λ")
    ax.set_ylabel("μ_e [MPa]")
    ax.set_title(f"Equivalent modulus μ_e = 2 W_T / (λ−1)² — {mat.name}", fontsize=9)
    ax.text(hi_adm, 0.98, " locking ", rotation=90, transform=ax.get_xaxis_transform(), va="top",
            ha="right", fontsize=7, color="0.35")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper center")
    fig.tight_layout()
    with atomic_path(f"{args.out}/fig5a_mu_e.png") as tmp:
        fig.savefig(tmp)
    plt.close(fig)

    # --- force laws -------------------------------------------------------------
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4), dpi=150)
    fs = tables.force_function(lam, law="secant")[0]
    fe = tables.force_function(lam, law="energy")[0]
    a1.plot(lam, fs / 1e3, label="secant (paper Eq. 9): μ_e(λ)(λ−1)")
    a1.plot(lam, fe / 1e3, label="energy: W_T'(λ)")
    a1.set_xlabel("spring stretch λ")
    a1.set_ylabel("F L0 / (c V)  [kPa]")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.abs(lam - 1) > 1e-9, fs / fe, np.nan)
    a2.plot(lam, ratio, "k")
    a2.axhline(1, color="0.6", lw=1)
    a2.set_xlabel("spring stretch λ")
    a2.set_ylabel("secant / energy force")
    a2.set_ylim(0, 1.1)
    a2.grid(alpha=0.3)
    fig.suptitle(f"Spring force laws on the same tables — {mat.name}", fontsize=9)
    fig.tight_layout()
    with atomic_path(f"{args.out}/fig5a_force_laws.png") as tmp:
        fig.savefig(tmp)
    plt.close(fig)

    marks = np.array([0.75, 0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2, 1.3, 1.35])
    marks = marks[(marks >= tables.lam_min) & (marks <= tables.lam_max)]
    mu = tables.mu_e(marks)[0]
    fs = tables.force_function(marks, law="secant")[0]
    fe = tables.force_function(marks, law="energy")[0]
    print(f"grid: lam {tables.lam_min:.6g} .. {tables.lam_max:.6g}, n = {tables.n}, "
          f"dlam = {tables.dlam:.4g}; admissible ({lo_adm:.6g}, {hi_adm:.6g})")
    print("lam     mu_e [MPa]   secant f [kPa]  energy f [kPa]  secant/energy")
    for lam_m, m, s, e in zip(marks, mu, fs, fe):
        r = s / e if abs(lam_m - 1) > 1e-12 else 1.0
        print(f"{lam_m:5.2f}  {m / 1e6:10.6f}  {s / 1e3:14.4f}  {e / 1e3:14.4f}  {r:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
