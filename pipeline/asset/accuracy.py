"""How far to trust an asset: the ``/accuracy`` group and its reading in plain words.

Three errors stack between the tissue and a simulation of the asset, and the asset
states each it knows (docs/reference/asset-format.md, "Accuracy"):

* **the fit**: how well the material follows its tensile data (RMSE, NRMSE, R² and
  calibrate's verdict), stored in ``/accuracy/fit`` by ``esmm prepare`` when the
  material is a ``params.toml`` that calibrate wrote (read from its ``fit.json``
  beside it when that is the same fit, else from the file's header line);
* **the compensation**: how well the network follows the material in the virtual
  load tests over the calibration range (uniaxial and simple shear), kept in the
  ``/tables`` metadata where the calibration records it, and read from there (one
  source: ``esmm tables`` rewrites both at once);
* **the validation**: how far the network is from a finite-element continuum of
  the same organ, per load case, stored in ``/accuracy/validation`` by
  ``esmm validate ASSET`` (each case's latest run, with its settings).

:class:`Accuracy` gathers them (``Asset.accuracy``) and says them in words
(:meth:`Accuracy.lines`, what ``esmm info`` prints).
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import h5py

from . import hdf5
from .schema import GROUPS

#: Schemas of the JSON records.
FIT_SCHEMA = "esmm.asset-fit/1"
VALIDATION_SCHEMA = "esmm.asset-validation/1"

#: Figures a validated case keeps (fractions, except the count of inverted elements).
CASE_FIGURES = ("l2_error", "max_error", "force_error", "volume_change_network", "volume_change_continuum",
                "inverted_network")

_HEADER = re.compile(r"#\s*model\s+(\S+);\s*RMSE\s+([-+0-9.eE]+)\s*Pa;\s*NRMSE\s+([-+0-9.eE]+)%;\s*R2\s+([-+0-9.eE]+)")
_VERDICT = re.compile(r"#\s*verdict\s*[:=]?\s*([A-Za-z]+)\s*[:;,(-]?\s*(.*)")


# -- the fit, from a params.toml -------------------------------------------------------------

def fit_record(material: str | os.PathLike, *, loaded=None) -> dict[str, Any] | None:
    """The fit's error of a material file that ``esmm calibrate`` wrote, or None.

    Parameters
    ----------
    material : str or path
        A ``params.toml`` (or a preset name: None, a preset records no fit).
    loaded : Material, optional
        The material read from it: a ``fit.json`` beside the file is used only when
        its parameters are these (the same fit), else the file's header line.

    Returns
    -------
    dict or None
        ``schema``, ``source`` (the file's name), ``model``, ``rmse_pa``, ``nrmse``
        (a fraction), ``r2``, ``verdict`` ("" when calibrate gave none), ``reasons``,
        ``files`` (the test files) and ``read_from``.
    """
    p = Path(material)
    if p.suffix.lower() != ".toml" or not p.is_file():
        return None
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    rec = _from_fit_json(p.with_name("fit.json"), loaded) or _from_header(text)
    if rec is None:
        return None
    verdict, reasons = _verdict_of(text, rec.pop("_verdict", None), loaded)
    source = f"{p.parent.name}/{p.name}" if p.parent.name else p.name
    return {"schema": FIT_SCHEMA, "source": source, **rec, "verdict": verdict, "reasons": reasons}


def _from_header(text: str) -> dict[str, Any] | None:
    """RMSE, NRMSE and R² from the header line calibrate writes (``# model esedf; RMSE 102.5 Pa; ...``)."""
    m = _HEADER.search(text)
    if m is None:
        return None
    files = next((ln.split(":", 1)[1] for ln in text.splitlines() if ln.startswith("# files:")), "")
    return {"model": m.group(1), "rmse_pa": float(m.group(2)), "nrmse": float(m.group(3)) / 100,
            "r2": float(m.group(4)), "files": [f.strip() for f in files.split(",") if f.strip()],
            "read_from": "the params.toml header"}


def _from_fit_json(path: Path, loaded) -> dict[str, Any] | None:
    """The errors of calibrate's ``fit.json`` beside the params.toml, if it is the same fit."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        errors, params = doc["errors"], doc["material"]["params"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    mine = getattr(loaded, "params", None)
    if not isinstance(mine, dict) or not isinstance(params, dict) or set(mine) != set(params) or not all(
            math.isclose(float(mine[k]), float(params[k]), rel_tol=1e-9) for k in mine):
        return None
    try:
        rec = {"model": str(doc.get("model", "")), "rmse_pa": float(errors["rmse"]), "nrmse": float(errors["nrmse"]),
               "r2": float(errors["r2"]), "files": [Path(f).name for f in doc.get("files", [])],
               "read_from": "fit.json beside the params.toml"}
    except (KeyError, TypeError, ValueError):
        return None
    rec["_verdict"] = doc.get("verdict")
    return rec


def _verdict_of(text: str, from_json, loaded) -> tuple[str, list[str]]:
    """Calibrate's verdict on the fit (good / poor / unusable) and its reasons, where calibrate states one:
    in fit.json, in the material's ``[material.fit]`` table, or on a ``# verdict:`` header line."""
    meta = getattr(loaded, "metadata", None)
    for v in (from_json, meta.get("fit", {}).get("verdict") if isinstance(meta, dict) and
              isinstance(meta.get("fit"), dict) else None):
        if isinstance(v, str) and v:
            return v, []
        if isinstance(v, dict):
            level = v.get("level") or v.get("verdict") or v.get("status") or ""
            reasons = v.get("reasons") or v.get("reason") or []
            reasons = [reasons] if isinstance(reasons, (str, dict)) else list(reasons)
            return str(level), [str(r.get("text", "")) if isinstance(r, dict) else str(r) for r in reasons]
    m = next((_VERDICT.match(ln) for ln in text.splitlines() if _VERDICT.match(ln)), None)
    if m is None:
        return "", []
    return m.group(1).lower(), [r.strip() for r in m.group(2).split("; ") if r.strip()]


# -- the /accuracy group ------------------------------------------------------------------------

def _group(f: h5py.File, name: str) -> h5py.Group:
    """``/accuracy`` (created when missing) or its subgroup *name*, replaced."""
    top = f["accuracy"] if "accuracy" in f else hdf5.typed_group(f, "accuracy", *GROUPS["/accuracy"][:2])
    if name in top:
        del top[name]
    return hdf5.typed_group(top, name, *GROUPS[f"/accuracy/{name}"][:2])


def write_fit(f: h5py.File, record: dict[str, Any]) -> None:
    """``/accuracy/fit`` of an asset open for writing (its ``record`` dataset holds *record* as JSON)."""
    g = _group(f, "fit")
    for key in ("verdict", "model", "source"):
        g.attrs[key] = str(record.get(key, ""))
    hdf5.put_text(g, "record", json.dumps(record, sort_keys=True, allow_nan=False),
                  description="the material fit's error (JSON: rmse_pa, nrmse, r2, verdict, reasons, files)")


def write_validation(f: h5py.File, record: dict[str, Any]) -> None:
    """``/accuracy/validation`` of an asset open for writing."""
    g = _group(f, "validation")
    g.attrs["cases"] = ",".join(sorted(record["cases"]))
    hdf5.put_text(g, "record", json.dumps(record, sort_keys=True, allow_nan=False),
                  description="esmm validate's figures per load case (JSON; fractions, settings, time)")


def validation_record(figures: dict[str, Any], *, old: dict[str, Any] | None, scene: str, utc_time: str,
                      version: str) -> dict[str, Any]:
    """The validation record of an asset: each case of *figures* (``esmm validate``'s JSON document)
    replaces that case of *old*; the other cases of *old* stay."""
    cases = dict((old or {}).get("cases", {}))
    settings = {"law": figures.get("law"), "volume_term": figures.get("volume_term"),
                "element": figures.get("element"), "scene": scene, "utc_time": utc_time, "esmm_version": version}
    for c in figures.get("cases", []):
        cases[c["case"]] = {**{k: _finite(c.get(k)) for k in CASE_FIGURES}, "load": str(c.get("load", "")),
                            "failed": None, **settings}
    for name, why in (figures.get("failed") or {}).items():
        cases[name] = {**{k: None for k in CASE_FIGURES}, "load": "", "failed": str(why), **settings}
    return {"schema": VALIDATION_SCHEMA, "cases": cases}


def _finite(v):
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


# -- reading and checking -----------------------------------------------------------------------

def _record(f: h5py.File, name: str) -> dict[str, Any] | None:
    path = f"/accuracy/{name}/record"
    return json.loads(hdf5.get_text(f[path])) if path in f else None


def read_records(f: h5py.File) -> tuple[dict | None, dict | None]:
    """The fit and validation records of an open asset (None where absent); :func:`accuracy_problems` first."""
    return _record(f, "fit"), _record(f, "validation")


def accuracy_problems(f: h5py.File) -> list[str]:
    """Problems of ``/accuracy``: records that are not JSON of their schema, figures that are not numbers."""
    out = []
    for name, schema, check in (("fit", FIT_SCHEMA, _fit_problem), ("validation", VALIDATION_SCHEMA,
                                                                       _validation_problem)):
        path = f"/accuracy/{name}/record"
        if path not in f:
            continue
        try:
            rec = json.loads(hdf5.get_text(f[path]))
        except (ValueError, TypeError) as exc:
            out.append(f"{path}: not JSON ({exc})")
            continue
        if not isinstance(rec, dict) or rec.get("schema") != schema:
            out.append(f"{path}: not a {schema} record")
            continue
        problem = check(rec)
        if problem:
            out.append(f"{path}: {problem}")
    return out


def _number_or_null(v) -> bool:
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))


def _fit_problem(rec: dict) -> str:
    for k in ("rmse_pa", "nrmse", "r2"):
        if not _number_or_null(rec.get(k)):
            return f"{k} is not a number ({rec.get(k)!r})"
    if not isinstance(rec.get("verdict", ""), str) or not isinstance(rec.get("reasons", []), list):
        return "verdict must be text and reasons a list"
    return ""


def _validation_problem(rec: dict) -> str:
    cases = rec.get("cases")
    if not isinstance(cases, dict):
        return "cases must be a table of load cases"
    for name, c in cases.items():
        if not isinstance(c, dict):
            return f"case {name!r} is not a table"
        bad = [k for k in CASE_FIGURES if not _number_or_null(c.get(k))]
        if bad:
            return f"case {name!r}: {bad[0]} is not a number ({c.get(bad[0])!r})"
    return ""


def compensation_summary(tables) -> dict[str, Any] | None:
    """The compensation's errors of *tables*' default law from their metadata (None: not compensated)."""
    comp = tables.metadata.get("compensation") if tables is not None else None
    rec = comp.get("laws", {}).get(tables.default_law) if isinstance(comp, dict) else None
    if not isinstance(rec, dict) or "errors_after" not in rec:
        return None
    shear = {k.replace("shear_", ""): v.get("max_abs_rel_error") for k, v in (rec.get("checks") or {}).items()
             if isinstance(v, dict)}
    return {"law": tables.default_law, "volume_factor": tables.volume_factor,
            "uniaxial_max": rec["errors_after"].get("max_abs_rel_error"),
            "uniaxial_rms": rec["errors_after"].get("rms_rel_error"),
            "raw_max": (rec.get("errors_before") or {}).get("max_abs_rel_error"),
            "shear_max": shear, "stretch_range": rec.get("stretch_range")}
