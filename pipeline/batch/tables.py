"""The tables of a batch of fits: one row per group, and statistics only where they mean something.

``summary.csv`` has one row per group: its status, its verdict and why, each
parameter with whether the data determine it, the errors, and the failure tests
(the group's mean over its tests that failed). Then three rows across groups:
``mean``, ``sd`` and ``n``. A statistic uses only

* groups whose fit is usable (verdict good or poor): an unusable fit is listed with
  its reason, never averaged;
* parameter values the data determine in that group (``<key> determined`` = yes): a
  value the data do not determine is an arbitrary point of a valley, and averaging
  it with measurements would be averaging noise with data;
* for the failure tests, groups whose specimens failed: a censored strength is a
  lower bound, not a value.

``n`` says how many groups each column's statistics rest on.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from typing import Any

from ..htmlreport import DIMENSIONLESS, Column, Document, Quantity
from .jobs import BatchSummary

#: failure columns: (summary key, title, SI unit)
FAILURE_COLUMNS = (("ultimate_stress", "ultimate stress", "Pa"), ("ultimate_stretch", "stretch at ultimate", "1"),
                   ("rupture_stretch", "stretch at rupture", "1"), ("toe_end_stretch", "toe end stretch", "1"),
                   ("toe_modulus", "toe modulus", "Pa"), ("linear_modulus", "linear modulus", "Pa"))
USABLE = ("good", "poor")


def _unit(kind: str) -> str:
    return "Pa" if kind == "stress" else "1"


def _fitted(o) -> bool:
    return o.status in ("done", "cached") and "estimates" in o.summary


def parameter_keys(summary: BatchSummary) -> list[tuple[str, str]]:
    """(key, SI unit) of every parameter fitted in some group, in order of appearance."""
    keys: dict[str, str] = {}
    for o in summary.outcomes:
        for e in o.summary.get("estimates", []) if _fitted(o) else []:
            keys.setdefault(e["key"], _unit(e.get("kind", "")))
    return list(keys.items())


def group_values(o, keys: list[tuple[str, str]]) -> dict[str, Any]:
    """The numbers of one fitted group: parameters (None where not determined, for the statistics), errors,
    failure metrics (the mean over its failed tests)."""
    s = o.summary
    est = {e["key"]: e for e in s.get("estimates", [])}
    out: dict[str, Any] = {}
    for k, _ in keys:
        e = est.get(k)
        out[k] = None if e is None else float(e["value"])
        out[f"{k}:determined"] = None if e is None else bool(e.get("identifiable", True))
    for k in ("rmse", "nrmse", "r2", "noise_ratio"):
        v = s.get(k)
        out[k] = None if v is None else float(v)
    stats = (s.get("failure") or {}).get("summary", {}).get("stats", {})
    for k, _, _ in FAILURE_COLUMNS:
        out[k] = (stats.get(k) or {}).get("mean")
    fs = (s.get("failure") or {}).get("summary", {})
    out["failed"], out["censored"] = fs.get("failed", 0), fs.get("censored", 0)
    cens = fs.get("censored_at") or []
    out["censored_at"] = min(cens) if cens else None
    return out


def _num(v, digits: int = 8) -> str:
    return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}g}"


def _header(keys) -> list[str]:
    cols = ["group", "status", "verdict", "reason", "files"]
    for k, u in keys:
        cols += [f"{k} [{u}]", f"{k} determined"]
    cols += ["rmse [Pa]", "nrmse [%]", "r2 [1]", "rmse/resolution [1]", "failed tests", "censored tests",
             "censored at [Pa]"]
    cols += [f"{title} [{u}]" for _, title, u in FAILURE_COLUMNS]
    return cols + ["seconds [s]", "cached"]


def _row(o, vals: dict[str, Any] | None, keys) -> list[str]:
    s = o.summary
    status = {"done": "ok", "cached": "ok"}.get(o.status, o.status)
    if o.status == "failed" and s.get("unreadable"):
        status = "unreadable"
    verdict = (s.get("verdict") or {}).get("level", "") if vals is not None else ""
    reason = (s.get("verdict") or {}).get("text", "") if vals is not None else o.reason
    row = [o.name, status, verdict, reason, str(len(s.get("files", [])) or "")]
    if vals is None:
        return row + [""] * (len(_header(keys)) - 7) + [f"{o.seconds:.2f}", ""]
    for k, _ in keys:
        det = vals[f"{k}:determined"]
        row += [_num(vals[k]), "" if det is None else ("yes" if det else "no")]
    nrmse = vals["nrmse"]
    row += [_num(vals["rmse"], 6), _num(None if nrmse is None else 100 * nrmse, 4), _num(vals["r2"], 6),
            _num(vals["noise_ratio"], 4), str(vals["failed"]), str(vals["censored"]), _num(vals["censored_at"])]
    row += [_num(vals[k]) for k, _, _ in FAILURE_COLUMNS]
    return row + [f"{o.seconds:.2f}", "yes" if o.status == "cached" else ""]


def statistics_rows(fitted: list[tuple[Any, dict[str, Any]]], keys) -> dict[str, dict[str, Any]]:
    """mean, sd and n per column over the usable groups (determined parameters only; failed specimens only)."""
    usable = [(o, v) for o, v in fitted if (o.summary.get("verdict") or {}).get("level", "good") in USABLE]
    cols: dict[str, list[float]] = {}
    for _, v in usable:
        for k, _u in keys:
            if v[k] is not None and v[f"{k}:determined"]:
                cols.setdefault(k, []).append(v[k])
        for k in ("rmse", "nrmse", "r2", "noise_ratio", *(c for c, _, _ in FAILURE_COLUMNS)):
            if v[k] is not None and math.isfinite(v[k]):
                cols.setdefault(k, []).append(v[k])
    out: dict[str, dict[str, Any]] = {}
    for k, vals in cols.items():
        out[k] = {"mean": statistics.fmean(vals), "sd": statistics.stdev(vals) if len(vals) > 1 else None,
                  "n": len(vals)}
    return {"columns": out, "usable": [o.name for o, _ in usable],
            "excluded": [(o.name, (o.summary.get("verdict") or {}).get("text", "")) for o, v in fitted
                         if (o, v) not in usable]}


def params_table(summary: BatchSummary) -> str:
    """summary.csv of a batch of fits (module docstring)."""
    keys = parameter_keys(summary)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_header(keys))
    fitted = []
    for o in summary.outcomes:
        vals = group_values(o, keys) if _fitted(o) else None
        if vals is not None:
            fitted.append((o, vals))
        w.writerow(_row(o, vals, keys))
    if fitted:
        st = statistics_rows(fitted, keys)
        excluded = "; ".join(f"{n} ({why})" for n, why in st["excluded"])
        label = f"{len(st['usable'])} usable group(s)" + (f"; not averaged: {excluded}" if excluded else "")
        for stat in ("mean", "sd", "n"):
            row = [stat, label, "", "only parameters the data determine, of usable fits", ""]
            for k, _ in keys:
                row += [_stat(st, k, stat), ""]
            nr = _stat(st, "nrmse", stat, scale=100.0) if stat != "n" else _stat(st, "nrmse", "n")
            row += [_stat(st, "rmse", stat), nr, _stat(st, "r2", stat), _stat(st, "noise_ratio", stat), "", "", ""]
            row += [_stat(st, k, stat) for k, _, _ in FAILURE_COLUMNS]
            w.writerow(row + ["", ""])
    return buf.getvalue()


def _stat(st, key: str, stat: str, scale: float = 1.0) -> str:
    c = st["columns"].get(key)
    if stat == "n":
        return str(c["n"] if c else 0)
    v = None if c is None else c[stat]
    return _num(None if v is None else v * scale)


def batch_html(summary: BatchSummary, *, by: str) -> Document:
    """report.html of a batch of fits: how many groups are usable, then the groups' table and the statistics."""
    keys = parameter_keys(summary)
    fitted = [(o, group_values(o, keys)) for o in summary.outcomes if _fitted(o)]
    levels = [(o.summary.get("verdict") or {}).get("level", "") for o, _ in fitted]
    failed = [o for o in summary.outcomes if not _fitted(o)]
    n_use = sum(lvl in USABLE for lvl in levels)
    doc = Document(f"Batch of fits by {by}", producer="esmm calibrate --by",
                   subtitle=f"{len(summary.outcomes)} group(s) in {summary.out_dir}")
    head = (f"{n_use} of {len(summary.outcomes)} group(s) give a usable fit ({levels.count('good')} good, "
            f"{levels.count('poor')} poor); {levels.count('unusable')} unusable; {len(failed)} failed.")
    doc.verdict("info", head, reasons=[f"{o.name}: {(o.summary.get('verdict') or {}).get('text', '')}"
                                       for o, _ in fitted if (o.summary.get('verdict') or {}).get('level') != 'good']
                + [f"{o.name}: {o.status}: {o.reason}" for o in failed],
                advice=["open each group's report.html for its plots and reasons"])
    doc.section("Groups")
    cols = [Column("group"), Column("verdict")] + [Column(f"{k}") for k, _ in keys] + [
        Column("NRMSE", unit="%", digits=3), Column("R²", unit=DIMENSIONLESS), Column("ultimate stress"),
        Column("linear modulus")]
    rows = []
    for o, v in fitted:
        rows.append([o.name, (o.summary.get("verdict") or {}).get("level", "")]
                    + [Quantity(v[k], u, note="" if v[f"{k}:determined"] else "(not determined)")
                       for k, u in keys]
                    + [v["nrmse"], v["r2"], Quantity(v["ultimate_stress"], "Pa"), Quantity(v["linear_modulus"], "Pa")])
    doc.table(cols, rows, caption="A value the data do not determine is shown but never averaged.")
    if fitted:
        st = statistics_rows(fitted, keys)
        doc.section("Across groups")
        doc.text("Mean ± SD over the usable fits only, and only over the values the data determine; n: the groups "
                 "each statistic rests on." + (" Not averaged: " + "; ".join(f"{n} ({w})" for n, w in st["excluded"])
                                               if st["excluded"] else ""))
        units = dict(keys) | {"rmse": "Pa", "r2": DIMENSIONLESS, "noise_ratio": DIMENSIONLESS}
        units |= {k: u for k, _, u in FAILURE_COLUMNS}
        srows = [[k, Quantity(c["mean"], units.get(k, DIMENSIONLESS)), Quantity(c["sd"], units.get(k, DIMENSIONLESS)),
                  c["n"]] for k, c in st["columns"].items() if k != "nrmse"]
        doc.table([Column("quantity"), Column("mean"), Column("SD"), Column("n", unit="1", digits=6)], srows)
    return doc
