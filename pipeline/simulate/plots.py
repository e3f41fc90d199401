"""Figures of a run: the force of the tissue on the grasper (``grasper_force.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomicio import atomic_path
from .grasper import GraspPlan
from .history import History


def plot_forces(history_path, png_path, *, plan: GraspPlan | None = None) -> Path:
    """Plot the grasper force (components and magnitude) vs time into *png_path*."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    with History(history_path) as h:
        t, f = h.forces()
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    if t.size:
        step = max(1, t.size // 20000)          # plot at most ~20 000 points per curve
        ts, fs = t[::step], f[::step]
        for k, (name, col) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"))):
            ax.plot(ts, fs[:, k], color=col, lw=0.8, label=f"F{name}")
        ax.plot(ts, np.linalg.norm(fs, axis=1), color="black", lw=1.2, label="|F|")
        ax.legend(loc="best", fontsize=8)
    else:
        ax.text(0.5, 0.5, "the grasper held nothing", ha="center", va="center", transform=ax.transAxes)
    if plan is not None:
        for tt, lab in ((plan.spec.grasp_time, "grasp"), (plan.spec.release_time, "release")):
            if tt is not None:
                ax.axvline(tt, color="gray", ls=":", lw=0.8)
                ax.text(tt, ax.get_ylim()[1], f" {lab}", va="top", fontsize=7, color="gray")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("force of the tissue on the grasper [N]")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(png_path)
