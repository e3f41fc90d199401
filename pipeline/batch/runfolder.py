"""What an output folder holds from an earlier run, and how to clear it before a new one writes there.

A run of ``esmm calibrate`` (one fit, a discovery, a batch of either) records what it
wrote in ``<out>/.esmm-run.json`` (:func:`record_run`). Before a new run writes into the
same folder, :func:`previous_run` says what is there (from that record, or, for a
folder written without one, from esmm's own output names), so that the command line
can refuse to mix two runs' files, and :func:`clear_run` removes exactly the earlier
run's files: the new run's outputs never stand beside stale ones (a ``fit.json`` of an
old fit beside a new discovery's ``params.toml``). Files esmm did not write are never
removed.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..atomicio import write_json
from .cache import CACHE_DIR
from .jobs import SUMMARY_CSV

#: The record of a run in its output folder.
RUN_FILE = ".esmm-run.json"
RUN_SCHEMA = "esmm.run/1"

#: Output names of each kind of run, for folders written without a record.
KNOWN: dict[str, tuple[str, ...]] = {
    "calibrate": ("params.toml", "fit.png", "report.md", "report.html", "fit.json"),
    "discover": ("params.toml", "params_base.toml", "discover.json", "discover.md", "report.html",
                 "residuals_before.png", "residuals_after.png", "corrected"),
    "calibrate-batch": ("summary.csv", SUMMARY_CSV, "report.html", CACHE_DIR),
    "discover-batch": ("summary.csv", SUMMARY_CSV, "report.html", "effects.csv", "effect-parameters.csv",
                       CACHE_DIR),
}

DESCRIPTIONS = {"calibrate": "fit", "discover": "discovery", "calibrate-batch": "batch of fits",
                "discover-batch": "batch of discoveries"}


@dataclass
class PreviousRun:
    """An earlier run found in a folder: its kind and the files it wrote that are still there."""

    kind: str
    files: list[Path] = field(default_factory=list)

    def describe(self) -> str:
        names = sorted({p.name for p in self.files})
        shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        return f"an earlier esmm {DESCRIPTIONS.get(self.kind, self.kind)} ({shown})"


def _record(folder: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads((folder / RUN_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("schema") == RUN_SCHEMA else None


def _batch_outputs(folder: Path) -> tuple[str | None, list[Path]]:
    """The kind and the outputs of the jobs a batch's cache lists."""
    kind, out = None, []
    cache = folder / CACHE_DIR
    for m in sorted(cache.glob("*.json")) if cache.is_dir() else []:
        try:
            doc = json.loads(m.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        kind = kind or doc.get("kind")
        out += [folder / o["path"] for o in doc.get("outputs", []) if isinstance(o, dict) and "path" in o]
    return kind, out


def previous_run(folder: str | os.PathLike) -> PreviousRun | None:
    """The earlier run in *folder*, or None (no folder, an empty one, or only files esmm did not write)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    rec = _record(folder)
    batch_kind, batch_files = _batch_outputs(folder)
    if rec is not None:
        kind = str(rec.get("kind", "calibrate"))
        files = [folder / p for p in rec.get("outputs", [])]
    elif (folder / CACHE_DIR).is_dir() or (folder / SUMMARY_CSV).exists():
        kind = "discover-batch" if batch_kind == "discover" else "calibrate-batch"
        files = []
    elif (folder / "discover.json").exists() or (folder / "discover.md").exists():
        kind, files = "discover", []
    else:
        kind, files = "calibrate", []
    # every name esmm's runs write, whatever the kind recorded: a folder written by several runs (or by the
    # library, without a record) is cleared of all of them
    files += batch_files + [folder / n for names in KNOWN.values() for n in names]
    files += [p for p in folder.glob("esmm-batch-*.log")]
    seen, existing = set(), []
    for p in files:
        if p not in seen and (p.exists() or p.is_symlink()):
            seen.add(p)
            existing.append(p)
    if rec is None and not existing:
        return None
    return PreviousRun(kind, existing)


def clear_run(folder: str | os.PathLike, run: PreviousRun) -> list[Path]:
    """Remove the files of *run* from *folder* (and the folders that leaves empty); the paths removed."""
    folder = Path(folder)
    removed = []
    for p in run.files + [folder / RUN_FILE]:
        if p.is_dir() and not p.is_symlink():
            if p.name in (CACHE_DIR, "corrected"):
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p)
            continue
        try:
            p.unlink()
            removed.append(p)
        except FileNotFoundError:
            continue
    for d in sorted({p.parent for p in removed if p.parent != folder}, key=lambda q: -len(q.parts)):
        try:
            d.rmdir()  # only when empty: a file esmm did not write stays, with its folder
        except OSError:
            pass
    return removed


def record_run(folder: str | os.PathLike, *, kind: str, outputs: list[str | os.PathLike]) -> Path:
    """Write ``<folder>/.esmm-run.json``: the run's kind and its outputs (relative to *folder*)."""
    folder = Path(folder)
    rel = []
    for p in outputs:
        q = Path(p)
        try:
            rel.append(q.resolve().relative_to(folder.resolve()).as_posix())
        except ValueError:
            continue  # written elsewhere (--json PATH): not this folder's
    return write_json(folder / RUN_FILE, {"schema": RUN_SCHEMA, "kind": kind, "outputs": sorted(set(rel))})
