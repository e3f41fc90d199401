"""Outputs of a calibration: parameters (TOML), JSON, the plot (PNG), report.md and report.html.

The JSON document (schema ``esmm.calibrate/1``) is described in
docs/reference/outputs.md. Every file is written atomically. The Markdown report
(:mod:`.markdown`) and the HTML report (:mod:`.html`) say the same, the verdict first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..atomicio import write_json, write_text
from ..materials import get_model
from ..tensile.data import TensileTest
from .calibration import Calibration, assess
from .fit import FitResult
from .html import write_html
from .inputs import how_read
from .markdown import markdown_report
from .plots import plot_fit

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


def result_to_dict(result: FitResult, tests: Sequence[TensileTest], *,
                   calibration: Calibration | None = None) -> dict[str, Any]:
    """The JSON-ready description of a fit (schema ``esmm.calibrate/1``).

    *tests* are the records as read; *calibration* (default: :func:`~.calibration.assess` of
    *result* on *tests*) gives the verdict and the failure tests.
    """
    cal = calibration or assess(result, tests)
    params: dict[str, Any] = {}
    for e in result.estimates:
        params[e.key] = {
            "name": e.name, "direction": e.direction, "value": e.value,
            "ci95": [e.lower, e.upper], "unit": _unit_of(e.kind), "at_bound": e.at_bound,
            "identifiable": e.identifiable, "fitted": True,
        }
    for p in get_model(result.model).parameters:
        if p.name in result.fixed:
            params[p.name] = {"name": p.name, "direction": None, "value": float(result.fixed[p.name]),
                              "ci95": None, "unit": _unit_of(p.kind), "at_bound": False, "identifiable": None,
                              "fitted": False}
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
        "verdict": cal.verdict.to_dict(),
        "failure": {"tests": [f.to_dict() for f in cal.failures], "summary": cal.failure_summary},
    }


def params_toml(result: FitResult, tests: Sequence[TensileTest], *, name: str | None = None,
                calibration: Calibration | None = None) -> str:
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
    if calibration is not None:
        header.append(f"# verdict: {calibration.verdict.short()}")
    header += [f"# warning: {w}" for w in result.warnings]
    return "\n".join(header) + "\n" + mat.to_toml()




def write_outputs(out_dir: str | Path, result: FitResult, tests: Sequence[TensileTest], *,
                  calibration: Calibration | None = None, json_path: str | Path | None = None,
                  name: str | None = None) -> dict[str, Path]:
    """Write params.toml, fit.png, report.md, report.html and fit.json into *out_dir*.

    *tests* are the records as read; *calibration* (:func:`~.calibration.calibrate`) carries
    what was fitted, the failure tests and the verdict (default: :func:`~.calibration.assess`).
    """
    cal = calibration or assess(result, tests)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {
        "params": write_text(out / "params.toml", params_toml(result, tests, name=name, calibration=cal)),
        "plot": plot_fit(out / "fit.png", cal),
        "report": write_text(out / "report.md", markdown_report(cal)),
        "html": write_html(out / "report.html", cal),
    }
    doc = result_to_dict(result, tests, calibration=cal)
    written["json"] = write_json(out / "fit.json", doc)
    if json_path is not None:
        written["json_extra"] = write_json(json_path, doc)
    return written
