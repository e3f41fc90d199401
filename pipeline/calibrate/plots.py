"""The calibration's figures: one row of panels per loading mode, and the failure tests.

Conventions, the same in every figure of esmm's reports:

* one row per loading mode: a stretch λ and a shear strain γ never share an axis;
* the residual is **model − data** everywhere;
* stress against time beside stress against stretch for every record with a time
  column, so that a hold (relaxation) shows as a curve in time, not as a vertical
  smear at one stretch;
* the samples left out of the fit (after a failure's ultimate stress) are drawn in
  grey, with the ultimate stress and the rupture marked.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..atomicio import atomic_path
from ..htmlreport import readable_unit
from .calibration import Calibration
from .fit import predict

MODE_TITLES = {"uniaxial": "uniaxial", "equibiaxial": "equibiaxial", "pure_shear": "pure shear",
               "simple_shear": "simple shear"}
#: samples drawn per record (evenly thinned above this)
DRAWN = 3000


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def modes(cal: Calibration) -> list[str]:
    """The loading modes of the calibration's records, in the order of MODE_TITLES."""
    present = {t.mode for t in cal.tests}
    return [m for m in MODE_TITLES if m in present]


def x_label(mode: str) -> str:
    return "shear strain γ [–]" if mode == "simple_shear" else "stretch λ [–]"


def _thin(n: int) -> np.ndarray:
    return np.arange(n) if n <= DRAWN else np.linspace(0, n - 1, DRAWN).round().astype(int)


def draw_mode(axes: Sequence, cal: Calibration, mode: str, *, legend: bool = True) -> None:
    """Draw the records of *mode* on four axes: stress and residual against x, and against time."""
    plt = _pyplot()
    idx = [k for k, t in enumerate(cal.tests) if t.mode == mode]
    unit, fac = readable_unit([float(np.max(np.abs(cal.tests[k].stress))) for k in idx], "Pa")
    cmap = plt.get_cmap("tab10")
    has_time = False
    for n, k in enumerate(idx):
        full, fit, fail = cal.tests[k], cal.fitted[k], cal.failures[k]
        c = cmap(n % 10)
        pred = predict(cal.result, fit)
        res = (pred - fit.stress) / fac  # model − data
        sl = _thin(fit.n)
        label = full.name if len(idx) <= 10 else None
        axes[0].plot(fit.stretch[sl], fit.stress[sl] / fac, ".", ms=2.5, color=c, alpha=0.5, label=label)
        order = np.argsort(fit.stretch) if fit.time is None else sl
        axes[0].plot(fit.stretch[order], pred[order] / fac, "-", lw=1.2, color=c)
        axes[1].plot(fit.stretch[sl], res[sl], ".", ms=2, color=c, alpha=0.6)
        if full.n > fit.n:  # the part left out, in grey
            cut = np.arange(fit.n, full.n)[_thin(full.n - fit.n)]
            axes[0].plot(full.stretch[cut], full.stress[cut] / fac, ".", ms=2, color="0.6",
                         label="not fitted (after the ultimate stress)" if n == 0 else None)
        _mark_failure(axes[0], full, fail, fac, c)
        if full.time is not None:
            has_time = True
            axes[2].plot(full.time[_thin(full.n)], full.stress[_thin(full.n)] / fac, ".", ms=1.5, color=c, alpha=0.4)
            axes[2].plot(fit.time[sl], pred[sl] / fac, "-", lw=1.0, color=c)
            axes[3].plot(fit.time[sl], res[sl], "-", lw=0.8, color=c)
    _label_mode(axes, mode, unit, has_time, legend and len(idx) <= 10)


def _mark_failure(ax, full, fail, fac: float, c) -> None:
    if fail.ultimate_index is not None:
        ax.plot([fail.ultimate_stretch], [fail.ultimate_stress / fac], "v", ms=7, color=c, mec="k")
    if fail.rupture_stretch is not None:
        ax.axvline(fail.rupture_stretch, color=c, ls="--", lw=0.8)


def _label_mode(axes, mode: str, unit: str, has_time: bool, legend: bool) -> None:
    title = MODE_TITLES[mode]
    axes[0].set(xlabel=x_label(mode), ylabel=f"nominal stress [{unit}]", title=f"{title}: data (dots), model (lines)")
    axes[1].axhline(0, color="k", lw=0.6)
    axes[1].set(xlabel=x_label(mode), ylabel=f"model − data [{unit}]", title=f"{title}: residual")
    if has_time:
        axes[2].set(xlabel="time [s]", ylabel=f"nominal stress [{unit}]", title=f"{title}: stress vs time")
        axes[3].axhline(0, color="k", lw=0.6)
        axes[3].set(xlabel="time [s]", ylabel=f"model − data [{unit}]", title=f"{title}: residual vs time")
    else:
        for ax in axes[2:]:
            if ax is not None:
                ax.set_axis_off()
                ax.text(0.5, 0.5, "no time column", ha="center", va="center", transform=ax.transAxes, color="0.5")
    if legend:
        axes[0].legend(fontsize=7, loc="best")


def mode_figure(cal: Calibration, mode: str):
    """One figure for the records of *mode*: four panels, or two when none of them has a time column."""
    plt = _pyplot()
    timed = any(t.time is not None for t in cal.tests if t.mode == mode)
    fig, axes = plt.subplots(1, 4 if timed else 2, figsize=(17 if timed else 9, 4.2), constrained_layout=True)
    draw_mode(list(axes) + ([] if timed else [None, None]), cal, mode)
    return fig


def plot_fit(path: str | Path, cal: Calibration) -> Path:
    """fit.png: a row of four panels per loading mode (:func:`draw_mode`)."""
    plt = _pyplot()
    ms = modes(cal)
    fig, axes = plt.subplots(len(ms), 4, figsize=(17, 4.2 * len(ms)), constrained_layout=True, squeeze=False)
    for row, m in zip(axes, ms):
        draw_mode(row, cal, m)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)


def failure_figure(cal: Calibration):
    """The failure tests: each record's last loading with its ultimate stress, linear window and toe, or None."""
    plt = _pyplot()
    tests = [(k, f) for k, f in enumerate(cal.failures) if f.kind != "none"][:12]
    if not tests:
        return None
    cols = min(3, len(tests))
    rows = -(-len(tests) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.6 * cols, 4.0 * rows), constrained_layout=True, squeeze=False)
    for ax, (k, f) in zip(axes.flat, tests):
        _draw_failure(ax, cal.tests[k], f)
    for ax in list(axes.flat)[len(tests):]:
        ax.set_axis_off()
    return fig


def _draw_failure(ax, t, f) -> None:
    unit, fac = readable_unit([f.ultimate_stress], "Pa")
    s0 = f.loading_start or 0
    end = f.rupture_index + 1 if f.rupture_index is not None else t.n
    end = min(t.n, end + (end - s0) // 20 + 1)
    sl = np.arange(s0, end)[_thin(end - s0)]
    ax.plot(t.stretch[sl], t.stress[sl] / fac, ".", ms=2, color="C0", alpha=0.5, label="last loading")
    ax.plot([f.ultimate_stretch], [f.ultimate_stress / fac], "v", ms=8, color="C3", mec="k",
            label="ultimate stress" + (" (censored: a lower bound)" if f.censored else ""))
    if f.linear_modulus is not None:
        x = np.array([f.linear_from, f.linear_to])
        mid = (t.stretch[s0:end] >= x[0]) & (t.stretch[s0:end] <= x[1])
        y0 = float(np.mean(t.stress[s0:end][mid])) if np.any(mid) else 0.0
        xm = float(np.mean(t.stretch[s0:end][mid])) if np.any(mid) else x.mean()
        ax.plot(x, (y0 + f.linear_modulus * (x - xm)) / fac, "-", lw=2.2, color="C2", label="linear region")
    if f.toe_end_stretch is not None:
        ax.axvline(f.toe_end_stretch, color="C1", ls=":", lw=1.2, label="toe end")
    if f.rupture_stretch is not None:
        ax.axvline(f.rupture_stretch, color="k", ls="--", lw=0.8, label="rupture")
    ax.set(xlabel="stretch λ [–]", ylabel=f"nominal stress [{unit}]", title=f"{t.name}: {f.kind}")
    ax.legend(fontsize=7, loc="best")
