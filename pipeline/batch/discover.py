"""``esmm calibrate --discover --by specimen|folder FILES...``: one discovery per group, and what they share.

Each group (:mod:`.groups`) is one job on the local pool or a Dask cluster, like a
batch of fits: :func:`esmm.pipeline.discover.discover_and_save` writes the group's
discovery into ``<out>/<group>/`` (params.toml, discover.json, discover.md, the plots)
and :func:`esmm.pipeline.discover.html.write_discover_html` its report.html. Across
the groups (:func:`effect_table`, :func:`parameter_table`), per tissue (the files'
``tissue`` metadata; one population when none is stated):

* which effects each group shows (``summary.csv``);
* how often each effect is found: in how many groups, out of those where it could be
  found at all (the data can show it: applicable and identifiable), as a count and a
  fraction (``effects.csv``): what a lab wants from twenty specimens of one tissue;
* the material effects' parameters across the groups that kept the effect and whose
  data determine the parameter: median and spread (quartiles), never a value the data
  do not determine (``effect-parameters.csv``).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..atomicio import write_text
from ..checks import choice
from ..discover import discover_and_save, result_to_dict
from ..discover.html import verdict_of, write_discover_html
from ..errors import EsmmError
from ..htmlreport import DIMENSIONLESS, Column, Document, Quantity
from ..progress import Reporter, ensure
from .calibrate import named, plain_options, read_group
from .groups import (
    GROUP_BY,
    PARAMS_TABLE,
    failed_jobs,
    group_names,
    refuse_if_nothing,
    sidecars,
    sort_files,
)
from .jobs import BatchSummary, Job, JobOutput
from .runner import run_jobs

KIND = "discover"
EFFECTS_TABLE = "effects.csv"
PARAMETERS_TABLE = "effect-parameters.csv"
#: the population of groups whose files state no tissue
NO_TISSUE = "(no tissue stated)"


def discover_group(files: Sequence[str], out_dir: str, name: str, read_kwargs: Mapping[str, Any],
                   options: Mapping[str, Any]) -> JobOutput:
    """Worker function: read *files*, discover what the model misses, write ``<out_dir>/<name>/``.

    Returns
    -------
    JobOutput
        The files written and a summary: ``effects`` kept, per ``candidates`` whether it was
        kept and could be found (applicable, identifiable), the final ``parameters``
        (value, unit, not_identifiable), the errors before and after, the verdict,
        the files and the tissue.
    """
    tests = read_group(files, read_kwargs)
    folder = Path(out_dir) / name
    try:
        res = discover_and_save(tests, out_dir=folder, **dict(options))
    except EsmmError as exc:
        raise named(exc, files) from None
    doc = result_to_dict(res)
    html = write_discover_html(folder / "report.html", res, doc)
    outputs = [p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(".")]
    level, head, _, _ = verdict_of(doc)
    kinds = {c["name"]: c.get("kind", "") for c in doc.get("candidates", [])}
    summary = {
        "effects": list(doc.get("effects", [])),
        "candidates": {c["name"]: {"kind": c.get("kind", ""), "kept": bool(c.get("kept")),
                                   "testable": bool(c.get("applicable")) and bool(c.get("identifiable"))}
                       for c in doc.get("candidates", [])},
        "parameters": {k: {"value": p.get("value"), "unit": p.get("unit") or "",
                           "not_identifiable": bool(p.get("not_identifiable"))}
                       for k, p in doc["final"].get("parameters", {}).items()
                       if kinds.get(k.split(".")[0]) == "material"},
        "base_nrmse": doc["base"].get("nrmse"), "final_nrmse": doc["final"].get("nrmse"),
        "heldout_base": doc["base"].get("heldout_nrmse"), "heldout_final": doc["final"].get("heldout_nrmse"),
        "outcome": doc.get("outcome", ""), "verdict": {"level": level, "text": head},
        "files": [str(t.source) for t in tests], "specimens": sorted({t.specimen for t in tests}),
        "tissue": sorted({str(t.metadata.get("tissue")) for t in tests if t.metadata.get("tissue")}),
    }
    return JobOutput(outputs=sorted({*outputs, html}), summary=summary)


def discover_jobs(files: Sequence[str | os.PathLike], *, by: str = "specimen", out_dir: str | os.PathLike,
                  read_kwargs: Mapping[str, Any] | None = None, options: Mapping[str, Any] | None = None,
                  reporter: Reporter | None = None) -> list[Job]:
    """Group *files* and make one discovery job per group (plus a failed job per unreadable file).

    *options* are the keyword arguments of :func:`esmm.pipeline.discover.discover`
    (plain data: model, n_starts, seed, weights, fixed, free, ...). Raises as
    :func:`esmm.pipeline.batch.calibrate.calibrate_jobs`.
    """
    choice(by, GROUP_BY, "by")
    rep = ensure(reporter)
    read_kwargs, options = plain_options(read_kwargs, options)
    groups, failed, skipped, n_files = sort_files(files, by, read_kwargs, rep)
    refuse_if_nothing(groups, failed, skipped, n_files)
    names = group_names(list(groups), by)
    jobs = failed_jobs(failed, {n.casefold() for n in names.values()}, KIND)
    for key, paths in groups.items():
        name = names[key]
        config = {"by": by, "group": key, "read": read_kwargs, "discover": options}
        jobs.append(Job(name=name, kind=KIND, fn=discover_group,
                        args=(paths, str(Path(out_dir).resolve()), name, read_kwargs, options),
                        key_inputs=[*paths, *map(str, sidecars(paths))], config=config))
    return jobs


def _done(summary: BatchSummary) -> list:
    return [o for o in summary.outcomes if o.status in ("done", "cached") and "effects" in o.summary]


def tissue_of(o) -> str:
    t = o.summary.get("tissue") or []
    return "; ".join(t) if t else NO_TISSUE


def effect_counts(summary: BatchSummary) -> list[dict[str, Any]]:
    """Per tissue and effect: found in how many groups, out of how many where it could be found."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    for o in _done(summary):
        for name, c in o.summary.get("candidates", {}).items():
            r = rows.setdefault((tissue_of(o), name), {"tissue": tissue_of(o), "effect": name, "kind": c["kind"],
                                                        "groups": 0, "testable": 0, "found": 0, "found_in": []})
            r["groups"] += 1
            r["testable"] += int(c["testable"] or c["kept"])
            if c["kept"]:
                r["found"] += 1
                r["found_in"].append(o.name)
    for r in rows.values():
        r["fraction"] = r["found"] / r["testable"] if r["testable"] else None
    return sorted(rows.values(), key=lambda r: (r["tissue"], -r["found"], r["effect"]))


def effect_parameters(summary: BatchSummary) -> list[dict[str, Any]]:
    """Per tissue and material-effect parameter: median and quartiles over the groups that kept the effect and
    whose data determine the parameter; how many groups kept it without determining it."""
    vals: dict[tuple[str, str], dict[str, Any]] = {}
    for o in _done(summary):
        kept = set(o.summary.get("effects", []))
        for key, p in o.summary.get("parameters", {}).items():
            if key.split(".")[0] not in kept or p.get("value") is None:
                continue
            v = vals.setdefault((tissue_of(o), key), {"tissue": tissue_of(o), "parameter": key,
                                                      "unit": p.get("unit") or "", "values": [], "undetermined": 0})
            if p.get("not_identifiable"):
                v["undetermined"] += 1
            else:
                v["values"].append(float(p["value"]))
    out = []
    for v in vals.values():
        x = np.asarray(v["values"], float)
        q = np.percentile(x, [25, 50, 75]) if x.size else [None] * 3
        out.append({**v, "n": int(x.size), "q1": q[0], "median": q[1], "q3": q[2]})
    return sorted(out, key=lambda r: (r["tissue"], r["parameter"]))


def _csv(rows: list[list[Any]]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue()


def _n(v, digits: int = 6) -> str:
    return "" if v is None else f"{float(v):.{digits}g}"


def groups_table(summary: BatchSummary) -> str:
    """summary.csv of a batch of discoveries: one row per group (the effects it shows, errors before/after)."""
    rows = [["group", "status", "tissue", "files", "verdict", "effects found", "base nrmse [%]", "final nrmse [%]",
             "held-out base nrmse [%]", "held-out final nrmse [%]", "left unexplained", "seconds [s]", "cached",
             "reason"]]
    for o in summary.outcomes:
        s = o.summary
        status = {"done": "ok", "cached": "ok"}.get(o.status, o.status)
        if "effects" not in s:
            rows.append([o.name, "unreadable" if s.get("unreadable") else status, "", len(s.get("files", [])) or "",
                         "", "", "", "", "", "", "", f"{o.seconds:.2f}", "", o.reason])
            continue
        pct = [None if s.get(k) is None else 100 * s[k] for k in ("base_nrmse", "final_nrmse", "heldout_base",
                                                                  "heldout_final")]
        rows.append([o.name, status, tissue_of(o), len(s.get("files", [])), s["verdict"]["level"],
                     " ".join(s["effects"]) or "none", *[_n(v, 4) for v in pct], s.get("outcome", ""),
                     f"{o.seconds:.2f}", "yes" if o.status == "cached" else "", ""])
    return _csv(rows)


def effects_table(summary: BatchSummary) -> str:
    """effects.csv: per tissue and effect, found in how many groups of those where it could be found."""
    rows = [["tissue", "effect", "kind", "groups", "groups where it can be found", "found", "fraction found [1]",
             "found in"]]
    rows += [[r["tissue"], r["effect"], r["kind"], r["groups"], r["testable"], r["found"], _n(r["fraction"], 3),
              " ".join(r["found_in"])] for r in effect_counts(summary)]
    return _csv(rows)


def parameters_table(summary: BatchSummary) -> str:
    """effect-parameters.csv: median and quartiles of each kept material effect's determined parameters."""
    rows = [["tissue", "parameter", "unit", "groups determined", "median", "q1 (25 %)", "q3 (75 %)",
             "groups kept but not determined"]]
    rows += [[r["tissue"], r["parameter"], r["unit"] or "1", r["n"], _n(r["median"]), _n(r["q1"]), _n(r["q3"]),
              r["undetermined"]] for r in effect_parameters(summary)]
    return _csv(rows)


def discover_batch_html(summary: BatchSummary, *, by: str) -> Document:
    """report.html of a batch of discoveries: the effects found across groups, per tissue, first."""
    done = _done(summary)
    counts = [r for r in effect_counts(summary) if r["found"]]
    head = (f"{len(done)} of {len(summary.outcomes)} group(s) analysed. "
            + ("; ".join(f"{r['effect'].replace('_', ' ')} in {r['found']} of {r['testable']}"
                         + (f" ({r['tissue']})" if r["tissue"] != NO_TISSUE else "") for r in counts)
               if counts else "No effect found in any group."))
    failed = [o for o in summary.outcomes if o not in done]
    doc = Document(f"Discovery by {by}: what the groups share", producer="esmm calibrate --discover --by",
                   subtitle=f"{len(summary.outcomes)} group(s) in {summary.out_dir}")
    doc.verdict("info", head, reasons=[f"{o.name}: {o.status}: {o.reason}" for o in failed],
                advice=["open each group's report.html for its plots; an effect found in few groups may be a "
                        "property of those specimens, or of how they were tested"])
    doc.section("Effects per group")
    doc.table([Column("group"), Column("tissue"), Column("effects found"), Column("NRMSE before", unit="%", digits=3),
               Column("NRMSE after", unit="%", digits=3), Column("verdict")],
              [[o.name, tissue_of(o), ", ".join(o.summary["effects"]) or "none", o.summary.get("base_nrmse"),
                o.summary.get("final_nrmse"), o.summary["verdict"]["level"]] for o in done])
    doc.section("How often each effect is found")
    doc.table([Column("tissue"), Column("effect"), Column("found in", unit="groups", digits=6),
               Column("could be found in", unit="groups", digits=6), Column("fraction", unit="%", digits=3)],
              [[r["tissue"], r["effect"].replace("_", " "), r["found"], r["testable"], r["fraction"]]
               for r in effect_counts(summary)],
              caption="Could be found: the group's data can show the effect (applicable and identifiable).")
    params = effect_parameters(summary)
    if params:
        doc.section("Material effects' parameters across groups")
        doc.table([Column("tissue"), Column("parameter"), Column("median"), Column("25 %"), Column("75 %"),
                   Column("groups", unit="1", digits=6), Column("kept, not determined", unit="1", digits=6)],
                  [[r["tissue"], r["parameter"], Quantity(r["median"], r["unit"] or DIMENSIONLESS),
                    Quantity(r["q1"], r["unit"] or DIMENSIONLESS), Quantity(r["q3"], r["unit"] or DIMENSIONLESS),
                    r["n"], r["undetermined"]] for r in params],
                  caption="Over the groups that kept the effect and whose data determine the parameter.")
    return doc


def discover_batch(files: Sequence[str | os.PathLike], *, out_dir: str | os.PathLike, by: str = "specimen",
                   read_kwargs: Mapping[str, Any] | None = None, options: Mapping[str, Any] | None = None,
                   scheduler: Any = None, workers: int | None = None, force: bool = False,
                   reporter: Reporter | None = None) -> BatchSummary:
    """One discovery per group of *files*, in parallel, cached; the summary across groups.

    Writes ``<out>/<group>/`` (each discovery), ``summary.csv`` (per group), ``effects.csv``
    (how often each effect is found, per tissue), ``effect-parameters.csv`` (median and
    quartiles of the material effects' determined parameters), ``report.html``, and the
    batch's own ``batch-summary.csv``, log and cache (:func:`~esmm.pipeline.batch.runner.run_jobs`).

    Returns
    -------
    BatchSummary
        ``exit_code`` 0, 5 (a file or group failed) or 130 (interrupted).
    """
    jobs = discover_jobs(files, by=by, out_dir=out_dir, read_kwargs=read_kwargs, options=options,
                         reporter=reporter)
    summary = run_jobs(jobs, out_dir=out_dir, scheduler=scheduler, workers=workers, force=force,
                       reporter=reporter, title="discovering")
    write_tables(summary, by=by)
    return summary


def write_tables(summary: BatchSummary, *, by: str) -> None:
    """summary.csv, effects.csv, effect-parameters.csv and report.html of a batch of discoveries."""
    write_text(summary.out_dir / PARAMS_TABLE, groups_table(summary))
    write_text(summary.out_dir / EFFECTS_TABLE, effects_table(summary))
    write_text(summary.out_dir / PARAMETERS_TABLE, parameters_table(summary))
    discover_batch_html(summary, by=by).write(summary.out_dir / "report.html")
