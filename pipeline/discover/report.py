"""Outputs of a discovery: JSON, Markdown, residual plots, params.toml with effects, corrected data.

Files written by :func:`write_outputs` into the output folder (docs/reference/outputs.md):

``discover.json``         the full result (schema ``esmm.discover/1``), also what ``esmm evaluate`` reads
``discover.md``           the report, with the plain-language paragraph
``params.toml``           the final material: base parameters refitted with the kept effects, and
                          ``[material.effects.*]`` (see :class:`~esmm.pipeline.materials.effects.MaterialEffects`)
``params_base.toml``      the base model alone (as ``esmm calibrate`` would give it)
``residuals_before.png``  data vs base model, and its residual against time, stretch and segment
``residuals_after.png``   the same for the final model
``corrected/<file>.csv``  artefact-corrected raw data (only when an artefact was kept)
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
from ..calibrate.report import display_stress_unit
from ..materials.effects import ARTEFACTS, MATERIAL_EFFECTS, MaterialEffects
from ..materials.material import Material
from ..materials.terms import TERMS
from .covariates import thin
from .fitted import Fitted
from .search import DiscoverResult, discover
from .statistics import resolution

JSON_SCHEMA = "esmm.discover/1"
MODEL_SCHEMA = "esmm.discover-model/1"

_NICE = {
    "viscoelastic": "viscoelasticity (rate dependence and relaxation)",
    "mullins": "Mullins softening (softer below a previous maximum)",
    "damage": "damage (irreversible softening past a stretch)",
    "slack": "slack (the specimen was not taut at zero displacement)",
    "sensor_offset": "a load-cell offset and drift",
    "nonlinear_viscoelastic": "stretch-dependent relaxation",
    "cyclic_softening": "softening from cycle to cycle (preconditioning)",
    "permanent_set": "a residual strain (permanent set) that grows with the largest stretch",
    "specimen_scale": "a stress scale per specimen (cross-section error or specimen-to-specimen variation)",
    "grip_slip": "slips of the specimen in the grips",
}


# --------------------------------------------------------------------------- JSON
def _params_doc(f: Fitted) -> dict[str, Any]:
    st = f.values
    out: dict[str, Any] = {"params": dict(st.base[None])}
    if f.problem.directions:
        out["directions"] = {d: dict(st.base[d]) for d in f.problem.directions}
    return out


def _nested_nrmse(res: DiscoverResult, which: str) -> float | None:
    """The nested held-out NRMSE before or after (None when not computed)."""
    n = res.nested
    return n[which]["nrmse"] if n and n.get(which) else None


def _errors_doc(f: Fitted) -> dict[str, Any]:
    h = f.heldout
    d = f.errors.to_dict()
    if h is not None:
        d.update({"heldout_rmse": h.rmse, "heldout_nrmse": h.nrmse, "heldout_max_abs": h.max_abs,
                  "heldout_per_file": h.per_file})
    else:
        d.update({"heldout_rmse": None, "heldout_nrmse": None, "heldout_max_abs": None, "heldout_per_file": []})
    return d


def saved_model(res: DiscoverResult) -> dict[str, Any]:
    """What ``esmm evaluate`` needs to predict new files (schema ``esmm.discover-model/1``)."""
    fin = res.final
    return {
        "schema": MODEL_SCHEMA,
        "model": res.model,
        "spec": fin.spec.to_dict(),
        "fixed": dict(res.settings["fixed"]),
        "directions": res.settings["directions"],
        "bounds": res.settings["bounds"],
        "max_points": res.settings["max_points"],
        "base": _params_doc(res.base),
        "final": {**_params_doc(fin), "effects": res.material_effects.to_dict()},
        "artefacts": {n: getattr(fin.spec, n) for n in ARTEFACTS},
    }


def _noise_doc(r) -> dict[str, Any]:
    """A record's noise model for the JSON: SD, quantisation step, correlation, at rest (SI units)."""
    m = r.noise
    spacing = float(np.median(np.diff(r.fit_idx))) if r.fit_idx.size > 1 else 1.0
    pre = r.preload()
    return {"sd_Pa": r.sigma, "sd_of_range": r.sigma / r.range, "quantum_Pa": m.quantum,
            "correlation_samples": m.length,
            "correlation_time_s": m.correlation_time if math.isfinite(m.correlation_time) else None,
            "tau_at_fitting_spacing": m.tau(spacing), "separable": m.separable,
            "resolution_Pa": resolution(r.y, r.sigma), "force_lag_s": r.lag.get("seconds", 0.0),
            "at_rest": dict(zip(("mean_Pa", "sd_Pa", "samples"), pre)) if pre is not None else None}


def result_to_dict(res: DiscoverResult) -> dict[str, Any]:
    """The JSON document of a discovery (schema ``esmm.discover/1``, docs/reference/outputs.md)."""
    fin, base = res.final, res.base
    d0 = res.diagnoses[0] if res.diagnoses else None
    dl = res.diagnoses[-1] if res.diagnoses else None
    return {
        "schema": JSON_SCHEMA,
        "esmm_version": __version__,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "files": [str(r.test.source) for r in res.records],
        "samples": int(sum(r.test.n for r in res.records)),
        "fitting_samples": int(sum(r.fit_idx.size for r in res.records)),
        "base": {"model": res.model, **_errors_doc(base), **_params_doc(base),
                 "nested_heldout_nrmse": _nested_nrmse(res, "before"),
                 "lag1": d0.lag1 if d0 else None, "runs_z": d0.runs_z if d0 else None,
                 "chi2_per_sample": d0.chi2 if d0 else None},
        "effects": list(res.kept),
        "unclamped_files": unclamped(res),
        "noise": {r.name: _noise_doc(r) for r in res.records},
        "ruptures": res.cuts,
        "slips": {r.name: [int(k) for k in r.slips] for r in res.records if r.slips},
        "outcome": res.outcome,
        "final": {
            "model": res.final_model, "terms": res.terms, **_errors_doc(fin), **_params_doc(fin),
            "nested_heldout_nrmse": _nested_nrmse(res, "after"),
            "effects": res.material_effects.to_dict(),
            "artefacts": {n: res.candidates[n].params for n in res.kept if n in ARTEFACTS},
            "parameters": {e.key: e.to_dict() for e in fin.estimates},
            "lag1": dl.lag1 if dl else None, "runs_z": dl.runs_z if dl else None,
            "chi2_per_sample": dl.chi2 if dl else None,
        },
        "candidates": [c.to_dict() for c in res.candidates.values()],
        "not_identifiable": list(res.not_identifiable),
        "heldout": {"scheme": res.scheme, "folds": list(res.folds), "artefact_scheme": res.artefact_scheme,
                    "slip_scheme": res.slip_scheme or None,
                    "alpha": res.settings.get("alpha"), "levels": [lv.to_dict() for lv in res.levels],
                    "nested": res.nested},
        "diagnosis": [d.to_dict() for d in res.diagnoses],
        "summary": plain_language(res),
        "warnings": list(res.warnings),
        "settings": {k: v for k, v in res.settings.items() if k not in ("bounds",)},
        "saved_model": saved_model(res),
        "seconds": res.seconds,
    }


# --------------------------------------------------------------------------- words
def _pct(v: float | None) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{100 * v:.2f} %"


def _num(v: float | None, fmt: str = ".4g") -> str:
    return "–" if v is None or not math.isfinite(v) else format(v, fmt)


def _effect_sentence(res: DiscoverResult, name: str) -> str:
    me = res.material_effects
    p = res.candidates[name].params or {}
    if name == "viscoelastic" and me.viscoelastic is not None:
        v = me.viscoelastic
        taus = ", ".join(f"{t:.3g} s" for t in v.tau)
        return (f"the material is viscoelastic: its stress relaxes with time constant{'s' if len(v.tau) > 1 else ''} "
                f"{taus}, and after a long hold {100 * v.g_inf:.0f} % of the instantaneous stress remains")
    if name == "mullins" and me.mullins is not None:
        m = me.mullins
        return (f"it softens after the first loading to a new maximum (Mullins effect): below a previous maximum "
                f"the stress drops by up to {100 / m.r:.0f} % of the first-loading curve")
    if name == "damage" and me.damage is not None:
        d = me.damage
        xm = max(float(np.max(r.cov.drive)) for r in res.records)
        lost = 1.0 - float(d.factor(np.array([xm]))[0])
        left = (f"; however far it is stretched, {100 * d.floor:.0f} % of the undamaged stress remains"
                if d.floor else "")
        if d.onset - 1.0 <= 0.05 * max(xm - 1.0, 1e-9):
            return (f"it softens irreversibly with the largest stretch reached, from the first loading on (a "
                    f"gradual, stretch-dependent softening rather than tearing at a threshold): at the largest "
                    f"stretch reached ({xm:.3g}) the stress is {100 * lost:.0f} % below the unsoftened curve{left}")
        return (f"it is damaged irreversibly beyond a stretch of about {d.onset:.3g}: at the largest stretch "
                f"reached ({xm:.3g}) the stress is {100 * lost:.0f} % below the undamaged curve{left}")
    if name in TERMS:
        return f"its elastic law needs the strain-energy term {name} ({TERMS[name].equation}), for {TERMS[name].addresses}"
    if name == "nonlinear_viscoelastic" and me.viscoelastic is not None and me.viscoelastic.kappa_tau:
        k = me.viscoelastic.kappa_tau
        return (f"it relaxes {'faster' if k > 0 else 'slower'} at larger stretch (kappa_tau {k:.3g}: relaxation "
                f"times x{math.exp(-k * (res.final.problem.bounds.xi_span)):.2g} over the stretches tested)")
    if name == "nonlinear_viscoelastic" and me.viscoelastic is not None:
        k = me.viscoelastic.kappa
        return (f"the amount that relaxes {'grows' if k > 0 else 'falls'} with stretch (kappa {k:.3g}: "
                f"x{math.exp(k * (res.final.problem.bounds.xi_span)):.2g} over the stretches tested)")
    if name == "cyclic_softening" and me.cyclic_softening is not None:
        return (f"it softens from cycle to cycle at the same amplitude, up to {100 * me.cyclic_softening.d_inf:.0f} % "
                "when cycled long enough (preconditioning)")
    if name == "permanent_set" and me.permanent_set is not None:
        ps = me.permanent_set
        power = "" if ps.exponent == 1.0 else f"^{ps.exponent:.3g}"
        return (f"it keeps a residual strain: after a stretch λ it is stress-free only at "
                f"1 + {ps.fraction:.3g}(λ - 1){power}")
    if name == "specimen_scale":
        f = sorted(v["scale"] for v in p.values())
        return (f"the specimens differ in stiffness by factors {f[0]:.3g}–{f[-1]:.3g} (a cross-section measured "
                "wrong or specimen-to-specimen variation); the material is their geometric mean")
    if name == "grip_slip":
        n = sum(len(v) for v in p.values())
        return f"the specimen slipped in the grips {n} time(s); the stretch after each slip has been corrected"
    if name == "slack":
        mm = [v["length_m"] * 1e3 for v in p.values() if v.get("length_m") is not None]
        if mm:
            return (f"the specimens were slack at the start: they became taut only after "
                    f"{min(mm):.3g}–{max(mm):.3g} mm of crosshead travel; the stretch has been corrected")
        dl = [v["delta"] for v in p.values()]
        return (f"the specimens were slack at the start ({100 * min(dl):.2g}–{100 * max(dl):.2g} % of the gauge "
                "length); the stretch has been corrected")
    if name == "sensor_offset":
        f = [v["force_N"] for v in p.values() if v.get("force_N") is not None]
        if f:
            dr = [abs(v["drift_N_per_s"]) for v in p.values() if v.get("drift_N_per_s")]
            s = f"the load cell was not at zero: offsets of {min(f):+.3g} to {max(f):+.3g} N"
            if dr:
                s += f" and drifts up to {max(dr):.3g} N/s"
            return s + " were removed from the force"
        o = [v["stress_Pa"] for v in p.values()]
        return f"the stress reading had offsets of {min(o):+.3g} to {max(o):+.3g} Pa, which were removed"
    return _NICE.get(name, name)


def _kinds_sentences(res: DiscoverResult) -> list[str]:
    """What each kind of kept candidate means: artefacts corrected, material effects and terms travel."""
    out = []
    arte = [n for n in res.kept if n in ARTEFACTS]
    mat = [n for n in res.kept if n in MATERIAL_EFFECTS + ("nonlinear_viscoelastic",)]
    terms = res.terms
    if arte:
        out.append("The " + " and ".join(arte).replace("_", " ") + " correction" + ("s are" if len(arte) > 1 else " is")
                   + " a flaw of the measurement, not of the material: it is removed from the data, "
                   "and the material is fitted to the corrected data.")
    if mat:
        out.append("The " + ", ".join(mat).replace("_", " ") + (" effects are" if len(mat) > 1 else " effect is")
                   + " part of the material and travel with it into params.toml"
                   + (" (the elastic parameters are then the instantaneous response)" if "viscoelastic" in mat
                      else "") + ".")
    if terms:
        out.append(f"The elastic law is now {res.final_model}: the ESEDF plus {', '.join(terms)}; its stiffness "
                   "tables for the network follow from its energy as for the ESEDF.")
    return out


def plain_language(res: DiscoverResult) -> str:
    """A paragraph a lab technician can read."""
    b, f = res.base, res.final
    n_files = len(res.records)
    words = [
        f"The {res.model} model fitted on its own to your {n_files} file{'s' if n_files > 1 else ''} leaves an "
        f"error of {_pct(b.errors.nrmse)} of the measured stress range ({_pct(b.heldout.nrmse if b.heldout else None)} "
        f"on data held out of the fit: {res.scheme})."
    ]
    for name, cut in res.cuts.items():
        words.append(f"{name} ruptured at stretch {cut['stretch']:.4g}; the {cut['dropped']} samples after the "
                     "rupture are not the material's response and were left out.")
    for r in res.records:
        if r.lag:
            words.append(f"In {r.name} the force lags the stretch by {r.lag['seconds']:.3g} s where the loading "
                         "turns (the acquisition's filters; a material's stress never peaks after its strain): the "
                         "force was advanced by that much.")
    d0 = res.diagnoses[0] if res.diagnoses else None
    if d0 is not None:
        if d0.white:
            words.append("Its residual is at the level of the measurement noise (estimated from the records "
                         "themselves): nothing systematic is missing.")
        else:
            words.append(f"Its residual is {math.sqrt(max(d0.chi2, 0.0)):.3g} times the measurement noise and not "
                         f"random (neighbouring samples correlate at {d0.lag1:.2f}): the model misses something "
                         "systematic.")
    if res.kept:
        parts = [_effect_sentence(res, n) for n in res.kept]
        na = _nested_nrmse(res, "after")
        held = (f"{_pct(na)} on data held out of the whole selection, {_pct(_nested_nrmse(res, 'before'))} "
                "before" if na is not None and res.nested.get("selection_rerun")
                else f"{_pct(f.heldout.nrmse if f.heldout else None)} held out")
        words.append("Adding what the data show — " + "; ".join(parts) + " — brings the error to "
                     f"{_pct(f.errors.nrmse)} ({held}).")
        words += _kinds_sentences(res)
        words += _compression_sentences(res)
    elif d0 is not None and d0.white:
        words.append("Nothing more to add: what is left is noise.")
    if res.outcome:
        words.append(res.outcome[0].upper() + res.outcome[1:])
    rejected = [n for n, c in res.candidates.items() if not c.kept and c.applicable and c.identifiable]
    if rejected:
        words.append("Tried and not kept: " + ", ".join(rejected).replace("_", " ") + ".")
    if res.not_identifiable:
        words.append("Not identifiable from these data: " + ", ".join(res.not_identifiable).replace("_", " ")
                     + " (see the reasons below; a different test would be needed to tell).")
    for n in res.kept:
        if "caution" in res.candidates[n].reason:
            words.append("Caution: " + res.candidates[n].reason.split("caution: ", 1)[1] + ".")
    return " ".join(words)


def unclamped(res: DiscoverResult) -> list[str]:
    """The files whose prediction the final model does not clamp at zero force (``Spec.compression``)."""
    clamp = res.final.problem.forward.clamp
    return [r.name for r, c in zip(res.records, clamp) if r.tension_only and not c]


def _compression_sentences(res: DiscoverResult) -> list[str]:
    names = unclamped(res)
    if not names:
        return []
    return [f"{', '.join(names)} read{'s' if len(names) == 1 else ''} a compressive force on the way down, and the "
            "relaxation fits it better as the specimen's own (carried, not buckled): the model is not clamped at "
            "zero force there."]


def summary_lines(res: DiscoverResult) -> list[str]:
    """Short lines for the terminal."""
    b, f = res.base, res.final
    lines = [
        f"discover: {len(res.records)} file(s), {sum(r.test.n for r in res.records)} samples, "
        f"{res.seconds:.1f} s; held-out scheme: {res.scheme}",
        f"  base {res.model}:  RMSE {b.errors.rmse:.4g} Pa  NRMSE {_pct(b.errors.nrmse)}  "
        f"max {b.errors.max_abs:.4g} Pa  held-out NRMSE {_pct(b.heldout.nrmse if b.heldout else None)}",
        f"  final (+{', '.join(res.kept) or 'nothing'}):  RMSE {f.errors.rmse:.4g} Pa  NRMSE {_pct(f.errors.nrmse)}  "
        f"max {f.errors.max_abs:.4g} Pa  held-out NRMSE {_pct(f.heldout.nrmse if f.heldout else None)}",
    ]
    nb, na = _nested_nrmse(res, "before"), _nested_nrmse(res, "after")
    if nb is not None and res.nested.get("selection_rerun"):
        lines.append(f"  nested held-out NRMSE (the selection run again inside each fold): {_pct(nb)} -> {_pct(na)}")
    for c in res.candidates.values():
        lines.append(f"  {'+' if c.kept else '-'} {c.name:<22} {c.reason}")
    if res.outcome:
        lines.append("  left: " + res.outcome)
    return lines


def markdown(res: DiscoverResult, *, plots: bool = True) -> str:
    """The discovery report (Markdown)."""
    L = [f"# What the {res.model} model is missing", "",
         f"esmm {__version__}; {len(res.records)} file(s), {sum(r.test.n for r in res.records)} samples "
         f"({sum(r.fit_idx.size for r in res.records)} used for fitting); {res.seconds:.1f} s.", "",
         "## In plain words", "", plain_language(res), ""]
    L += _md_errors(res) + _md_candidates(res) + _md_parameters(res) + _md_noise(res)
    L += ["## Residual structure by round", ""]
    for i, d in enumerate(res.diagnoses, start=1):
        L.append(f"Round {i}: {d.chi2:.3g} noise variances per sample, lag-1 autocorrelation {d.lag1:.2f}, "
                 f"runs-test z {d.runs_z:.1f}{' (at the noise level)' if d.white else ''}.")
        for n in d.ranking:
            L.append(f"- {n}: {d.why.get(n, '')}")
        L.append("")
    if res.warnings:
        L += ["## Warnings", ""] + [f"- {w}" for w in res.warnings] + [""]
    if plots:
        L += ["## Plots", "", "Top: stress against stretch (moving samples) and against time; bottom: the residual "
              "model − data against time and stretch.", "", "![residuals before](residuals_before.png)", "",
              "![residuals after](residuals_after.png)", ""]
    return "\n".join(L)


def _md_errors(res: DiscoverResult) -> list[str]:
    """The error table: fitted, held out (the material scheme) and nested."""
    b, f = res.base, res.final
    n = res.nested or {}
    L = ["## Error before and after", "",
         f"Held-out scheme: {res.scheme} ({len(res.folds)} folds: {'; '.join(res.folds)}); per-file artefacts "
         f"judged on: {res.artefact_scheme}"
         + (f"; grip slips on: {res.slip_scheme}" if res.slip_scheme else "") + ". NRMSE = RMSE / range of the measured stress; every file counts "
         "equally; errors on all samples. *Nested*: the whole selection run again inside each fold on its "
         "training samples, the model it chose predicting the fold's held-out samples"
         + (" (not computed, `--no-nested`: the held-out errors chose the model and are optimistic)"
            if res.nested is None else "" if n.get("selection_rerun")
            else " (nothing was kept: the base model's held-out error)") + ".", "",
         "| model | RMSE [Pa] | NRMSE | max error [Pa] | held-out NRMSE | nested held-out RMSE [Pa] | "
         "nested held-out NRMSE |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, m, key in ((f"base ({res.model})", b, "before"), (f"final (+{', '.join(res.kept) or 'nothing'})", f,
                                                                   "after")):
        h, nd = m.heldout, n.get(key) or {}
        L.append(f"| {label} | {m.errors.rmse:.4g} | {_pct(m.errors.nrmse)} | {m.errors.max_abs:.4g} | "
                 f"{_pct(h.nrmse if h else None)} | {_num(nd.get('rmse'))} | {_pct(nd.get('nrmse'))} |")
    if n.get("selection_rerun"):
        L += ["", "Kept inside each outer fold: " + "; ".join(
            f"{name}: {', '.join(k) or 'nothing'}" for name, k in zip(res.folds, n["kept_per_fold"])) + "."]
    L += ["", "Per file (fit data):", "", "| file | NRMSE before | NRMSE after | held-out before | held-out after |",
          "| --- | --- | --- | --- | --- |"]
    hb = {e["file"]: e for e in (b.heldout.per_file if b.heldout else [])}
    hf = {e["file"]: e for e in (f.heldout.per_file if f.heldout else [])}
    for e0, e1 in zip(b.errors.per_file, f.errors.per_file):
        name = e0["file"]
        L.append(f"| {name} | {_pct(e0['nrmse'])} | {_pct(e1['nrmse'])} | {_pct(hb.get(name, {}).get('nrmse'))} | "
                 f"{_pct(hf.get(name, {}).get('nrmse'))} |")
    return L + [""]


def _md_candidates(res: DiscoverResult) -> list[str]:
    """Every candidate's statistics and verdict, with the search-wide levels."""
    alpha = res.settings.get("alpha")
    L = ["## Candidates", "",
         f"A candidate is kept when its held-out one-sided p-value is at most its level (the search adds anything to "
         f"records the model already explains with probability at most α = {alpha:g}: α/2^r in round r, split "
         "equally over every candidate, variant and pair that round could test) and it lowers the held-out mean "
         "squared error by at least one squared resolution per sample (the larger of the noise and 0.5 % of the "
         "reading). Fitted Δχ²: the pre-screen, the fit's improvement in noise variances (the noise's correlation "
         "counted; penalty ln N per parameter); it decides nothing, nor does ΔAICc. docs/design/discovery.md.", "",
         "| candidate | kind | kept | variant | fitted Δχ² | held-out NRMSE | t | p | level | ΔAICc | reason |",
         "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in res.candidates.values():
        L.append(f"| {c.name} | {c.kind} | {'yes' if c.kept else 'no'} | {c.variant or '–'} | {_num(c.dchi2)} | "
                 f"{_pct(c.heldout_nrmse)} | {_num(c.heldout_z, '+.2f')} | {_num(c.heldout_p, '.2g')} | "
                 f"{_num(c.heldout_level, '.2g')} | {_num(c.delta_aicc, '+.1f')} | {c.reason} |")
    if res.levels:
        L += ["", "Levels by round: " + "; ".join(
            f"round {lv.round}: α_r {lv.round_alpha:.3g} over {lv.singles} candidates"
            + (f" and {lv.pairs} pairs" if lv.pairs else "") + f" (each {lv.single:.2g})" for lv in res.levels) + "."]
    return L + [""]


def _md_parameters(res: DiscoverResult) -> list[str]:
    L = ["## Final parameters (95 % confidence intervals)", "", "| parameter | value | 95 % interval | unit |",
         "| --- | --- | --- | --- |"]
    for e in res.final.estimates:
        flag = " (not identifiable)" if e.wide else ""
        L.append(f"| {e.key} | {e.value:.6g}{flag} | [{e.lower:.4g}, {e.upper:.4g}] | {e.unit or '–'} |")
    for k, v in res.settings["fixed"].items():
        L.append(f"| {k} | {v:.6g} (held) | – | – |")
    return L + [""]


def _md_noise(res: DiscoverResult) -> list[str]:
    L = ["## Measurement noise (from each record alone)", "",
         "| file | noise sd | of the range | quantisation step | correlation time | τ at the fitting spacing | "
         "force lag (taken off) | at rest before loading |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in res.records:
        d = _noise_doc(r)
        pre = d["at_rest"]
        ct = d["correlation_time_s"]
        rest = "–" if pre is None else f"{pre['mean_Pa']:.4g} ± {pre['sd_Pa']:.3g} Pa ({pre['samples']} samples)"
        L.append(f"| {r.name} | {r.sigma:.4g} Pa{'' if d['separable'] else ' (noise and signal not separable)'} | "
                 f"{100 * r.sigma / r.range:.3g} % | {d['quantum_Pa']:.3g} Pa | "
                 f"{'–' if ct is None else f'{ct:.3g} s'} ({d['correlation_samples']:.3g} samples) | "
                 f"{d['tau_at_fitting_spacing']:.3g} | {d['force_lag_s']:.3g} s | {rest} |")
    return L + [""]


# --------------------------------------------------------------------------- TOML
def params_toml(res: DiscoverResult, *, which: str = "final", stress_unit: str | None = None) -> str:
    """A material file (:func:`~esmm.pipeline.materials.material.load_material`) for the final model,
    with ``[material.effects.*]``.

    ``which="base"`` gives the base model alone.
    """
    f = res.final if which == "final" else res.base
    st = f.values
    directions = None
    if f.problem.directions:
        dirp = [p.name for p in f.problem.model.parameters if p.directional]
        directions = {d: {k: st.base[d][k] for k in dirp if k in st.base[d]} for d in f.problem.directions}
    unit = stress_unit or display_stress_unit([abs(v) for v in st.base[None].values()])[0]
    meta: dict[str, Any] = {}
    me = res.material_effects if which == "final" else MaterialEffects()
    if me:
        meta["effects"] = me.to_toml_table(stress_unit=unit)
    model = f.problem.model.name
    mat = Material(model=model, params=dict(st.base[None]), directions=directions,
                   name=f"{model}{' with ' + ', '.join(me.names) if me else ''} from esmm discover"
                        + ("" if which == "final" else " (base model alone)"),
                   source="esmm calibrate --discover " + " ".join(r.name for r in res.records),
                   metadata=meta, stress_unit=unit)
    e = f.errors
    head = [f"# Written by esmm {__version__} calibrate --discover on {datetime.now(UTC).isoformat(timespec='seconds')}",
            f"# {'final' if which == 'final' else 'base'} model: NRMSE {_pct(e.nrmse)}, held-out NRMSE "
            f"{_pct(f.heldout.nrmse if f.heldout else None)}"]
    if which == "final" and me:
        head.append("# [material.effects.*]: see docs/reference/configuration.md, 'Material file'; with viscoelastic, the parameters above are the "
                    "instantaneous response")
    arte = [n for n in res.kept if n in ARTEFACTS]
    if which == "final" and arte:
        head.append(f"# measurement artefacts corrected in the data (not part of the material): {', '.join(arte)}")
    return "\n".join(head) + "\n" + mat.to_toml()


# --------------------------------------------------------------------------- plots
def plot_residuals(path: str | Path, res: DiscoverResult, *, which: str = "base") -> Path:
    """Data and model, and the residual (model − data, as calibrate's fit.png), against stretch and time.

    Top: stress against stretch over the moving samples (loading and
    unloading), and stress against time over every sample (a hold is a
    relaxation in time, not a vertical smear at one stretch). Bottom: the
    residual model − data against time and against stretch (moving samples).
    Files follow one another on the time axis; a file without a time column
    is drawn against its sample index.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = res.base if which == "base" else res.final
    unit, fac = display_stress_unit([r.scale for r in res.records])
    fig, ax = plt.subplots(2, 2, figsize=(13, 8.5), constrained_layout=True)
    timed = _draw_records(ax, res, f, fac, plt.get_cmap("tab10"))
    what = "base " + res.model if which == "base" else "final: +" + (", ".join(res.kept) or "nothing")
    tlabel = "time [s] (files one after another)" if timed else "sample index (no time column)"
    ax[0, 0].set(xlabel="stretch λ [-] (γ for shear), moving samples", ylabel=f"nominal stress [{unit}]")
    ax[0, 0].set_title(f"{what}: data (dots) and model (lines)", fontsize=9 if len(what) > 40 else None, wrap=True)
    if len(res.records) <= 12:
        ax[0, 0].legend(fontsize=6, loc="best")
    ax[0, 1].set(xlabel=tlabel, ylabel=f"nominal stress [{unit}]", title="stress against time (holds included)")
    for a in (ax[1, 0], ax[1, 1]):
        a.axhline(0, color="k", lw=0.5)
    ax[1, 0].set(xlabel=tlabel, ylabel=f"model − data [{unit}]",
                 title=f"residual: RMSE {f.errors.rmse / fac:.4g} {unit}, NRMSE {_pct(f.errors.nrmse)} of the range")
    ax[1, 1].set(xlabel="stretch λ [-] (γ for shear), moving samples", ylabel=f"model − data [{unit}]",
                 title="residual against stretch")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)


def _draw_records(ax, res: DiscoverResult, f: Fitted, fac: float, cmap) -> bool:
    """Draw every record's data, model and residual (model − data); True when the records have time."""
    prob = f.problem
    coefs = prob.offsets(f.z)
    offset, timed = 0.0, all(r.t is not None for r in res.records)
    for k, r in enumerate(res.records):
        c = cmap(k % 10)
        p = prob.full_prediction(k, f.z, coefs[k])
        e = (p - r.y) / fac
        sl = thin(r.test, 3000, cov=r.cov)  # arc-length thinning: ramps and holds both drawn
        moving = sl[r.cov.direction[sl] != 0] if r.history else sl
        label = r.name if len(res.records) <= 12 else None
        ax[0, 0].plot(r.x[moving], r.y[moving] / fac, ".", ms=1.5, color=c, alpha=0.35, label=label)
        ax[0, 0].plot(r.x[moving], p[moving] / fac, "-", lw=1.0, color=c)
        tt = (r.t - r.t[0]) if (timed and r.t is not None) else np.arange(r.test.n, dtype=float)
        tt = tt + offset
        offset = float(tt[-1]) + 0.02 * (float(tt[-1] - tt[0]) or 1.0)
        ax[0, 1].plot(tt[sl], r.y[sl] / fac, ".", ms=1.5, color=c, alpha=0.35)
        ax[0, 1].plot(tt[sl], p[sl] / fac, "-", lw=1.0, color=c)
        ax[1, 0].plot(tt[sl], e[sl], "-", lw=0.7, color=c)
        ax[1, 1].plot(r.x[moving], e[moving], ".", ms=1.2, color=c, alpha=0.5)
    return timed


# --------------------------------------------------------------------------- corrected data
def write_corrected(folder: str | Path, res: DiscoverResult) -> list[Path]:
    """Artefact-corrected copies of the raw files (time, displacement, force; or stretch, stress).

    Slack: the displacement is shifted so that zero is where the specimen
    became taut, and the gauge length is the taut length (``L0 + s``). Slips:
    the extension lost at each slip is taken off the displacement from then on.
    Offset: the estimated offset and drift are subtracted from the force.
    Specimen scale: the cross-section becomes ``c`` times the stated one (the
    force is what was measured). A record cut at a rupture is written up to it.
    """
    folder = Path(folder)
    if not any(n in ARTEFACTS for n in res.kept):
        return []
    f = res.final
    st = f.values
    coefs = f.problem.offsets(f.z)
    return [_write_one(folder, res, k, r, st, coefs[k]) for k, r in enumerate(res.records)]


def _corrections(f: Fitted, k: int, st, coef) -> tuple[float, np.ndarray, np.ndarray, float]:
    """(slack δ, stretch lost to slips per sample, offset per sample [Pa], scale) of record k."""
    r = f.problem.records[k]
    n = r.test.n
    delta = float(st.slack[k]) if st.slack is not None else 0.0
    lost = np.zeros(n)
    if st.slips and st.slips[k].size:
        for e, d in zip(r.slips, st.slips[k]):
            lost[e:] += d
    X = f.problem.forward.offset_columns(k, np.arange(n))
    off = X @ coef if (X is not None and coef is not None) else np.zeros(n)
    scale = float(st.scale[k]) if st.scale is not None else 1.0
    return delta, lost, off, scale


def _write_one(folder: Path, res: DiscoverResult, k: int, r, st, coef) -> Path:
    """The corrected copy of record k (see :func:`write_corrected`)."""
    f = res.final
    t = r.test
    delta, lost, off, scale = _corrections(f, k, st, coef)
    meta = [f"# corrected by esmm calibrate --discover from {t.source.name}"]
    done = _done(res, f, k, r, delta, lost, off, scale)
    if t.force is not None and t.displacement is not None and r.gauge and r.area:
        L0 = float(r.gauge)
        s = delta * L0
        meta += [f"# specimen: {t.specimen}", f"# gauge_length: {(L0 + s) * 1e3:.6g} mm",
                 f"# area: {r.area * scale * 1e6:.6g} mm2", f"# mode: {t.mode}",
                 f"# notes: {'; '.join(done) or 'nothing to correct in this file'}"]
        tt = t.time if t.time is not None else np.arange(t.n, dtype=float)
        rows = ["time [s],displacement [mm],force [N]"]
        rows += [f"{a:.6g},{b * 1e3:.6g},{c:.6g}" for a, b, c in
                 zip(tt, t.displacement - lost * L0 - s, t.force - off * r.area)]
    else:
        x = (t.stretch - lost) / (1.0 + delta) if delta else t.stretch - lost
        y = (t.stress - off) / scale
        meta += [f"# specimen: {t.specimen}", f"# mode: {t.mode}",
                 f"# notes: {'; '.join(done) or 'nothing to correct in this file'}"]
        head = "shear strain,shear stress [Pa]" if t.mode == "simple_shear" else "stretch,nominal stress [Pa]"
        if t.time is not None:
            rows = ["time [s]," + head] + [f"{a:.6g},{b:.8g},{c:.6g}" for a, b, c in zip(t.time, x, y)]
        else:
            rows = [head] + [f"{b:.8g},{c:.6g}" for b, c in zip(x, y)]
    return write_text(folder / f"{t.source.stem}.csv", "\n".join(meta + rows) + "\n")


def _done(res: DiscoverResult, f: Fitted, k: int, r, delta, lost, off, scale) -> list[str]:
    """What was corrected in record k, in words."""
    done = []
    L0 = float(r.gauge) if r.gauge else None
    if "slack" in res.kept and delta:
        done.append(f"slack {delta * L0 * 1e3:.4g} mm removed (gauge length is the taut length)" if L0
                    else f"slack {100 * delta:.3g} % of the stretch removed")
    if "grip_slip" in res.kept and lost[-1] > 0:
        done.append(f"{len(r.slips)} grip slip(s), {lost[-1] * (L0 * 1e3 if L0 else 1):.4g} "
                    f"{'mm' if L0 else '(stretch)'} of extension in all, taken off")
    if "sensor_offset" in res.kept and f.problem.forward.n_offset[k]:
        done.append(f"load-cell offset {off[0] * (r.area or 1):+.4g} {'N' if r.area else 'Pa'}"
                    + (" and its drift" if f.problem.forward.n_offset[k] == 2 else "") + " removed")
    if "specimen_scale" in res.kept and scale != 1.0:
        done.append(f"specimen stress scale {scale:.4g}: the cross-section is {scale:.4g} times the stated one")
    if r.cut:
        done.append(f"record ends at the rupture (stretch {r.cut['stretch']:.4g})")
    return done


def _remove_stale_corrected(folder: Path, res: DiscoverResult) -> None:
    """Delete corrected files an earlier discovery wrote here that this one does not rewrite."""
    if not folder.is_dir():
        return
    keep = {f"{r.test.source.stem}.csv" for r in res.records} if any(n in ARTEFACTS for n in res.kept) else set()
    for p in folder.glob("*.csv"):
        if p.name in keep:
            continue
        try:
            with open(p, encoding="utf-8") as fh:
                first = fh.readline()
        except (OSError, UnicodeDecodeError):
            continue
        if first.startswith("# corrected by esmm calibrate --discover"):
            p.unlink(missing_ok=True)
    if not any(folder.iterdir()):
        folder.rmdir()


# --------------------------------------------------------------------------- all outputs
def write_outputs(out_dir: str | Path | None, res: DiscoverResult, *,
                  json_path: str | Path | None = None) -> dict[str, Path]:
    """Write every output of a discovery (see the module docstring); returns name -> path."""
    written: dict[str, Path] = {}
    doc = result_to_dict(res)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written["params"] = write_text(out / "params.toml", params_toml(res, which="final"))
        written["params_base"] = write_text(out / "params_base.toml", params_toml(res, which="base"))
        written["plot_before"] = plot_residuals(out / "residuals_before.png", res, which="base")
        written["plot_after"] = plot_residuals(out / "residuals_after.png", res, which="final")
        written["report"] = write_text(out / "discover.md", markdown(res))
        _remove_stale_corrected(out / "corrected", res)
        corrected = write_corrected(out / "corrected", res)
        if corrected:
            written["corrected"] = out / "corrected"
        written["json"] = write_json(out / "discover.json", doc)
    if json_path is not None:
        written["json_extra"] = write_json(json_path, doc)
    return written


def discover_and_save(tests: Sequence, *, out_dir: str | Path | None = None, json_path: str | Path | None = None,
                      reporter=None, **options) -> DiscoverResult:
    """Run :func:`~esmm.pipeline.discover.search.discover` and write its outputs (the CLI's one call).

    Parameters
    ----------
    tests : sequence of TensileTest
    out_dir : path, optional
        Folder for every output (module docstring).
    json_path : path, optional
        Also write ``discover.json`` here.
    reporter : Reporter, optional
    **options
        Passed to :func:`~esmm.pipeline.discover.search.discover` (``model``,
        ``fixed``, ``weights``, ``n_starts``, ``seed``, ...).

    Returns
    -------
    DiscoverResult
        Its :func:`summary_lines` are what the CLI prints.
    """
    res = discover(tests, reporter=reporter, **options)
    write_outputs(out_dir, res, json_path=json_path)
    return res

