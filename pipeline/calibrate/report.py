"""Outputs of a calibration: parameters (TOML), JSON, plots (PNG) and a Markdown report.

The JSON document (schema ``esmm.calibrate/1``) is described in
docs/reference/outputs.md. Every file is written atomically.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..atomicio import atomic_path, write_json, write_text
from ..materials import get_model
from ..tensile.data import TensileTest
from .fit import FitResult, predict

JSON_SCHEMA = "esmm.calibrate/1"


def _unit_of(kind: str) -> str:
    return "Pa" if kind == "stress" else ""


def display_stress_unit(values_pa: Sequence[float]) -> tuple[str, float]:
    """A readable stress unit for values in Pa: (name, factor to divide by)."""
    vmax = max((abs(v) for v in values_pa if math.isfinite(v)), default=1.0)
    if vmax >= 1e5:
        return "MPa", 1e6
    if vmax >= 1e2:
        return "kPa", 1e3
    return "Pa", 1.0


def result_to_dict(result: FitResult, tests: Sequence[TensileTest]) -> dict[str, Any]:
    """The JSON-ready description of a fit (schema ``esmm.calibrate/1``)."""
    params: dict[str, Any] = {}
    for e in result.estimates:
        params[e.key] = {
            "name": e.name, "direction": e.direction, "value": e.value,
            "ci95": [e.lower, e.upper], "unit": _unit_of(e.kind), "at_bound": e.at_bound,
            "fitted": True,
        }
    for p in get_model(result.model).parameters:
        if p.name in result.fixed:
            params[p.name] = {"name": p.name, "direction": None, "value": float(result.fixed[p.name]),
                              "ci95": None, "unit": _unit_of(p.kind), "at_bound": False, "fitted": False}
    return {
        "schema": JSON_SCHEMA,
        "esmm_version": __version__,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "model": result.model,
        "loss": result.loss,
        "n_starts": result.n_starts,
        "parameters": params,
        "material": {"params": result.params, "directions": result.directions},
        "errors": {
            "rmse": result.rmse, "nrmse": result.nrmse, "r2": result.r2, "unit": "Pa",
            "per_file": [vars(f) for f in result.files],
        },
        "files": [str(t.source) for t in tests],
        "inputs": [how_read(t) for t in tests],
        "specimens": sorted({t.specimen for t in tests}),
        "warnings": list(result.warnings),
        "correlation": {"keys": result.free_keys, "matrix": np.round(result.correlation, 6).tolist()},
        "drucker": result.drucker,
        "seconds": result.seconds,
    }


def how_read(test: TensileTest) -> dict[str, Any]:
    """How the reader took *test* from its file: the columns used (index, header, unit, factor to SI),
    where stretch and stress came from (and the conversions made, e.g. true to nominal stress), the
    cross-checks against derived columns and the reader's warnings (docs/reference/tensile-input.md: say which
    columns were used, say so in the outputs)."""
    md = test.metadata
    return {"file": str(test.source), "stretch_from": md.get("stretch_from"), "stress_from": md.get("stress_from"),
            "used_columns": md.get("used_columns", {}), "cross_checks": md.get("cross_checks", {}),
            "warnings": list(md.get("warnings", []))}


def _inputs_section(tests: Sequence[TensileTest]) -> list[str]:
    lines = ["", "## How each file was read", "", "| file | stretch from | stress from | columns used |",
             "| --- | --- | --- | --- |"]
    for t in tests:
        h = how_read(t)
        cols = ", ".join(f"{c['index']} '{c['header'] or q}'" + (f" [{c['unit']}]" if c.get("unit") else "")
                         for q, c in h["used_columns"].items())
        lines.append(f"| {Path(t.source).name} | {h['stretch_from'] or '–'} | {h['stress_from'] or '–'} | "
                     f"{cols or '–'} |")
    notes = [f"- {w}" for t in tests for w in how_read(t)["warnings"]]     # each names its file
    return lines + (["", "Reader warnings:", ""] + notes if notes else [])


def params_toml(result: FitResult, tests: Sequence[TensileTest], *, name: str | None = None) -> str:
    """The fitted material as a material file (:func:`~esmm.pipeline.materials.material.load_material` reads it)."""
    mat = result.material(
        name=name or f"fit of {', '.join(sorted({t.specimen for t in tests}))}",
        source="esmm calibrate " + " ".join(t.source.name for t in tests),
    )
    header = [
        f"# Written by esmm {__version__} calibrate on {datetime.now(UTC).isoformat(timespec='seconds')}",
        f"# model {result.model}; RMSE {result.rmse:.6g} Pa; NRMSE {result.nrmse:.4%}; R2 {result.r2:.5f}",
        "# files: " + ", ".join(t.source.name for t in tests),
    ]
    header += [f"# warning: {w}" for w in result.warnings]
    return "\n".join(header) + "\n" + mat.to_toml()


def plot_fit(path: str | Path, result: FitResult, tests: Sequence[TensileTest], *, title: str = "") -> Path:
    """Data vs model, residuals vs stretch and residuals vs time (one PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unit, fac = display_stress_unit([float(np.max(np.abs(t.stress))) for t in tests])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), constrained_layout=True)
    cmap = plt.get_cmap("tab10")
    for k, t in enumerate(tests):
        c = cmap(k % 10)
        pred = predict(result, t)
        xlabel = "shear strain γ" if t.mode == "simple_shear" else "stretch λ"
        thin = slice(None, None, max(1, t.n // 2000))
        label = t.source.name if len(tests) <= 10 else None
        axes[0].plot(t.stretch[thin], t.stress[thin] / fac, ".", ms=2.5, color=c, alpha=0.5, label=label)
        order = np.argsort(t.stretch) if t.time is None else slice(None)
        axes[0].plot(t.stretch[order], pred[order] / fac, "-", lw=1.2, color=c)
        res = (pred - t.stress) / fac
        axes[1].plot(t.stretch[thin], res[thin], ".", ms=2, color=c, alpha=0.6)
        tt = t.time if t.time is not None else np.arange(t.n, dtype=float)
        axes[2].plot(tt[thin], res[thin], "-", lw=0.8, color=c)
    axes[0].set(xlabel="stretch λ (γ for shear)", ylabel=f"nominal stress [{unit}]",
                title=title or f"{result.model}: data (dots) vs model (lines)")
    axes[1].axhline(0, color="k", lw=0.6)
    axes[1].set(xlabel=xlabel, ylabel=f"model − data [{unit}]", title="residual vs stretch")
    axes[2].axhline(0, color="k", lw=0.6)
    has_time = any(t.time is not None for t in tests)
    axes[2].set(xlabel="time [s]" if has_time else "sample", ylabel=f"model − data [{unit}]",
                title="residual vs time" if has_time else "residual vs sample (no time column)")
    if len(tests) <= 10:
        axes[0].legend(fontsize=7, loc="best")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)


def markdown_report(result: FitResult, tests: Sequence[TensileTest], *, plot_name: str | None = "fit.png") -> str:
    """A short human-readable report."""
    unit, fac = display_stress_unit([abs(e.value) for e in result.estimates if e.kind == "stress"] or [1.0])
    sunit, sfac = display_stress_unit([float(np.max(np.abs(t.stress))) for t in tests])
    lines = [
        f"# Calibration report: {result.model}",
        "",
        f"esmm {__version__}; {len(tests)} file(s), {sum(t.n for t in tests)} samples; "
        f"loss `{result.loss}`; {result.n_starts} starts; {result.seconds:.2f} s.",
        "",
        "## Parameters (95 % confidence intervals)",
        "",
        "| parameter | value | 95 % interval | unit |",
        "| --- | --- | --- | --- |",
    ]
    for e in result.estimates:
        f = fac if e.kind == "stress" else 1.0
        u = unit if e.kind == "stress" else "–"
        flag = " (at bound)" if e.at_bound else ""
        lines.append(f"| {e.key} | {e.value / f:.6g}{flag} | [{e.lower / f:.4g}, {e.upper / f:.4g}] | {u} |")
    for k, v in result.fixed.items():
        lines.append(f"| {k} | {v:.6g} (fixed) | – | SI |")
    lines += [
        "",
        "## Errors",
        "",
        f"Overall: RMSE {result.rmse / sfac:.4g} {sunit}, normalised RMSE (RMSE / range of measured "
        f"stress) {result.nrmse:.2%}, R² {result.r2:.4f}.",
        "",
        "| file | mode | orientation | samples | RMSE [" + sunit + "] | NRMSE | R² | max |error| [" + sunit + "] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for fe in result.files:
        lines.append(
            f"| {Path(fe.path).name} | {fe.mode} | {fe.orientation or '–'} | {fe.n} | "
            f"{fe.rmse / sfac:.4g} | {fe.nrmse:.2%} | {fe.r2:.4f} | {fe.max_abs / sfac:.4g} |"
        )
    lines += _inputs_section(tests)
    if result.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings]
    if result.drucker:
        stable = result.drucker.get("stable", True)
        rng = result.drucker.get("range")
        lines += ["", "## Stability", "",
                  f"Drucker stability over λ ∈ [{rng[0]:.3g}, {rng[1]:.3g}]: "
                  f"{'stable' if stable else 'NOT stable: ' + str(result.drucker.get('detail', ''))}."
                  if rng else ""]
    if plot_name:
        lines += ["", "## Plots", "", f"![data vs model and residuals]({plot_name})"]
    return "\n".join(lines) + "\n"


def write_outputs(out_dir: str | Path, result: FitResult, tests: Sequence[TensileTest],
                  *, json_path: str | Path | None = None, name: str | None = None) -> dict[str, Path]:
    """Write params.toml, fit.png, report.md and fit.json into *out_dir*."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {
        "params": write_text(out / "params.toml", params_toml(result, tests, name=name)),
        "plot": plot_fit(out / "fit.png", result, tests),
        "report": write_text(out / "report.md", markdown_report(result, tests)),
    }
    doc = result_to_dict(result, tests)
    written["json"] = write_json(out / "fit.json", doc)
    if json_path is not None:
        written["json_extra"] = write_json(json_path, doc)
    return written
