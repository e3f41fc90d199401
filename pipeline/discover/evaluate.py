"""Predict new tensile files with a saved fit, without refitting the material.

``esmm evaluate FIT_DIR FILE...`` reads what ``esmm calibrate`` (``fit.json``
or ``params.toml``) or ``esmm calibrate --discover`` (``discover.json``) saved
in ``FIT_DIR``, predicts every file, and reports the error measures of the
discovery (RMSE, NRMSE = RMSE / range of the measured stress, max error) for

* **before** — the base model alone, as ``esmm calibrate`` fitted it, with
  no correction of the data; and
* **after** — the final model: the base model refitted with the kept material
  effects (viscoelasticity, Mullins softening, damage, ...) and strain-energy
  terms, as saved.

Nothing is refitted by default: the material as saved, and no measurement
artefact (a new file's slack, offset, specimen scale and slips are its own and
unknown, so none is applied). With ``refit_artefacts=True``
(``esmm evaluate --refit-artefacts``) the artefacts the discovery kept are
re-estimated on each new file with the material held, and the report says so
(those errors then use the new files' own data for the corrections). The JSON
document (schema ``esmm.evaluate/1``) is described in docs/reference/outputs.md.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError, InputError
from ..materials import get_model
from ..materials.composite import split_name
from ..materials.effects import ARTEFACTS, MaterialEffects
from ..materials.material import load_material
from ..progress import Reporter, ensure
from ..tensile.data import TensileTest
from .fitted import Fitted, effect_params, full_errors
from .initialise import initialise
from .model import Bounds, Problem, Spec, spec_of_effects
from .records import prepare, slack_applicable
from .statistics import Errors

JSON_SCHEMA = "esmm.evaluate/1"


@dataclass
class SavedFit:
    """A fit read back from a calibrate or discover output folder.

    Attributes
    ----------
    path : Path
        The file it was read from.
    kind : str
        ``"discover"`` (discover.json), ``"calibrate"`` (fit.json) or ``"material"`` (a params.toml).
    model : str
    spec : dict
        Effect variants (``esmm.pipeline.discover.model.Spec.to_dict``); all 0 for a plain fit.
    base, final : dict
        ``{"params": {...}, "directions": {...} or absent}`` (SI); ``final`` also has ``"effects"``.
    fixed : dict
    directions : list of str or None
    bounds : dict or None
    max_points : int
    """

    path: Path
    kind: str
    model: str
    spec: dict[str, int]
    base: dict[str, Any]
    final: dict[str, Any]
    fixed: dict[str, float] = field(default_factory=dict)
    directions: list[str] | None = None
    bounds: dict[str, float] | None = None
    max_points: int = 400

    @property
    def effects(self) -> list[str]:
        return Spec.from_dict(self.spec).names()


def load_fit(path: str | Path) -> SavedFit:
    """Read a saved fit: a folder (discover.json, else fit.json, else params.toml) or one of those files.

    Raises
    ------
    ConfigError
        Nothing usable there, or a malformed file (one line naming it).
    """
    p = Path(path)
    if p.is_dir():
        for name in ("discover.json", "fit.json", "params.toml"):
            if (p / name).is_file():
                return load_fit(p / name)
        raise ConfigError(f"{p}: no discover.json, fit.json or params.toml here; give the output folder of "
                          "a calibration or of a discovery")
    if not p.is_file():
        raise ConfigError(f"{p}: no such file or folder; give the output folder of a calibration or of a discovery")
    if p.suffix == ".toml":
        return _from_material(p)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{p}: not a JSON file written by esmm ({exc}); give the output folder of a "
                          "calibration or of a discovery") from None
    schema = str(doc.get("schema", ""))
    if schema.startswith("esmm.discover/"):
        sm = doc.get("saved_model")
        if not isinstance(sm, dict):
            raise ConfigError(f"{p}: has no saved_model section; rerun the discovery")
        try:
            return SavedFit(path=p, kind="discover", model=str(sm["model"]), spec=dict(sm["spec"]),
                            base=dict(sm["base"]), final=dict(sm["final"]), fixed=dict(sm.get("fixed") or {}),
                            directions=sm.get("directions"), bounds=sm.get("bounds"),
                            max_points=int(sm.get("max_points", 400)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{p}: saved_model is incomplete ({exc}); rerun the discovery") from None
    if schema.startswith("esmm.calibrate/"):
        mat = doc.get("material") or {}
        if "params" not in mat:
            raise ConfigError(f"{p}: has no material section; rerun the calibration")
        params = {"params": dict(mat["params"])}
        if mat.get("directions"):
            params["directions"] = dict(mat["directions"])
        base_name, terms = split_name(str(doc["model"]))
        return SavedFit(path=p, kind="calibrate", model=base_name, spec={"terms": list(terms)}, base=params,
                        final={**params, "effects": {}},
                        directions=sorted(mat["directions"]) if mat.get("directions") else None)
    raise ConfigError(f"{p}: unknown schema {schema!r}; expected a discover.json or fit.json written by esmm")


def _from_material(p: Path) -> SavedFit:
    mat = load_material(p)
    eff_table = mat.metadata.get("effects")
    effects = MaterialEffects.from_toml_table(eff_table, stress_unit=mat.stress_unit,
                                              where=f"{p}: [material.effects]")
    params = {"params": dict(mat.params)}
    dirs = None
    if mat.directions:
        full = {d: mat.params_for(d) for d in mat.directions}
        params["directions"] = full
        dirs = sorted(full)
    base_name, terms = split_name(mat.model)
    spec = spec_of_effects(effects, terms).to_dict()
    return SavedFit(path=p, kind="material", model=base_name, spec=spec, base=params,
                    final={**params, "effects": effects.to_dict()}, directions=dirs)


@dataclass
class Evaluation:
    """Errors of a saved fit on new files."""

    fit: SavedFit
    files: list[str]
    before: Errors
    after: Errors
    artefacts: dict[str, dict[str, Any]]
    warnings: list[str]
    artefacts_refitted: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": JSON_SCHEMA,
            "esmm_version": __version__,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "fit": str(self.fit.path),
            "fit_kind": self.fit.kind,
            "model": self.fit.model,
            "effects": self.fit.effects,
            "files": list(self.files),
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "artefacts_refitted": self.artefacts_refitted,
            "artefacts": self.artefacts,
            "warnings": list(self.warnings),
        }


def evaluate(fit: SavedFit | str | Path, tests: list[TensileTest], *, refit_artefacts: bool = False,
             reporter: Reporter | None = None) -> Evaluation:
    """Predict *tests* with a saved fit, refitting nothing (module docstring).

    Parameters
    ----------
    fit : SavedFit or path
        From :func:`load_fit`, or a folder/file it accepts.
    tests : list of TensileTest
    refit_artefacts : bool
        Re-estimate the kept measurement artefacts (slack, load-cell offset and
        drift, specimen scale, grip slips) on each new file, the material held.
        Off by default: the prediction is then the material's alone.

    Returns
    -------
    Evaluation
    """
    rep = ensure(reporter)
    saved = fit if isinstance(fit, SavedFit) else load_fit(fit)
    if not tests:
        raise InputError("no tensile files to evaluate; give at least one")
    _check_orientations(saved, tests)
    m = get_model(saved.model)
    records = prepare(tests, max_points=saved.max_points)
    bounds = Bounds.from_dict(saved.bounds) if saved.bounds else Bounds(records, 1.0)
    spec = Spec.from_dict(saved.spec)
    effects = MaterialEffects.from_dict(saved.final.get("effects"), where=f"{saved.path}: effects")
    warnings = _not_applied(spec, records)
    # before: the base model alone, no corrections
    # (the base of a discovery is the plain base model; a calibrated composite law keeps its terms)
    base_spec = Spec() if saved.kind == "discover" else Spec(terms=spec.terms)
    pb = Problem(m, records, base_spec, fixed=dict(saved.fixed), directions=saved.directions, bounds=bounds,
                 free_scales=True)
    before = full_errors(pb, pb.params.encode(_per_direction(saved.base)))
    # after: final material + effects; artefacts re-estimated per file only when asked
    if not refit_artefacts:
        spec = _without_artefacts(spec)
    pa = pb.derived(spec)
    za = pa.params.encode(_per_direction(saved.final), effects)
    if refit_artefacts:
        za = _artefacts_refitted(pa, za)
    after = full_errors(pa, za)
    fitted = Fitted(spec, pa, za, {}, after)
    artefacts = {n: effect_params(fitted, n) for n in ARTEFACTS if spec.variant(n)}
    for w in warnings:
        rep.warn(w)
    rep.step(f"evaluated {saved.kind} fit of {saved.model} on {len(tests)} file(s): NRMSE "
             f"{before.nrmse:.2%} (base) -> {after.nrmse:.2%} (with {', '.join(saved.effects) or 'nothing more'})")
    if not math.isfinite(after.rmse):
        warnings.append("the model cannot predict some samples (outside its admissible range)")
    return Evaluation(saved, [str(t.source) for t in tests], before, after, artefacts, warnings, refit_artefacts)


def _check_orientations(saved: SavedFit, tests: list[TensileTest]) -> None:
    """An anisotropic fit predicts only files tagged with one of its fibre directions."""
    dirs = saved.directions
    bad = [t.name for t in tests if t.orientation not in dirs] if dirs else []
    if bad:
        raise InputError(
            f"{bad[0]}: the fit is anisotropic ({', '.join(dirs)}); tag the file with orientation = "
            f"{'|'.join(dirs)} (in its sidecar, a '# orientation: x' comment or the orientation override)")


def _per_direction(block: dict[str, Any]) -> dict[str | None, dict[str, float]]:
    """``{"params", "directions"}`` of a saved fit as parameters per direction (None: shared)."""
    out = {None: dict(block["params"])}
    for d, p in (block.get("directions") or {}).items():
        out[d] = {**block["params"], **p}
    return out


def _not_applied(spec: Spec, records) -> list[str]:
    """Warnings for the effects of *spec* that cannot apply to some of the new files."""
    warnings: list[str] = []
    if spec.viscoelastic:
        warnings += [f"{r.name}: no time column, so the viscoelastic effect is not applied to it"
                     for r in records if r.t is None]
    if spec.mullins:
        warnings += [f"{r.name}: no time column (no loading history), so Mullins softening is not applied"
                     for r in records if not r.history]
    if spec.slack and not any(slack_applicable(r) for r in records):
        warnings.append("slack correction not applicable to these files (no tension test from zero displacement)")
    return warnings


def _without_artefacts(spec: Spec) -> Spec:
    """*spec* with every measurement artefact off (the material's prediction alone)."""
    for n in ARTEFACTS:
        spec = spec.with_(n, 0)
    return spec


def _artefacts_refitted(prob: Problem, z: np.ndarray) -> np.ndarray:
    """*z* with the per-file artefact parameters re-estimated, the material held."""
    own = [i for i, s in enumerate(prob.slots) if s.file is not None]
    if own:
        for name in ("specimen_scale", "grip_slip", "slack"):  # closed forms and a grid first:
            if prob.spec.variant(name):  # the slack optimum, for one, is not found from zero
                z = initialise(prob, z, name)
        z, _ = prob.solve(z, active=own)
    return z


def summary_lines(ev: Evaluation) -> list[str]:
    """Lines for the terminal: per file and overall, before and after."""
    def pct(v):
        return "–" if v is None or not math.isfinite(v) else f"{100 * v:.2f} %"

    eff = ", ".join(ev.fit.effects) or "nothing more"
    how = ("the kept artefacts re-estimated on each file (--refit-artefacts)" if ev.artefacts_refitted
           else "nothing refitted")
    lines = [f"fit: {ev.fit.path} ({ev.fit.kind}, {ev.fit.model}; effects: {eff}; {how})",
             f"{'file':<28} {'NRMSE before':>13} {'NRMSE after':>12} {'RMSE after [Pa]':>16} {'max after [Pa]':>15}"]
    for b, a in zip(ev.before.per_file, ev.after.per_file):
        lines.append(f"{Path(a['file']).name[:28]:<28} {pct(b['nrmse']):>13} {pct(a['nrmse']):>12} "
                     f"{a['rmse']:>16.4g} {a['max_abs']:>15.4g}")
    lines.append(f"{'all files':<28} {pct(ev.before.nrmse):>13} {pct(ev.after.nrmse):>12} "
                 f"{ev.after.rmse:>16.4g} {ev.after.max_abs:>15.4g}")
    return lines


__all__ = ["Evaluation", "SavedFit", "evaluate", "load_fit", "summary_lines"]
