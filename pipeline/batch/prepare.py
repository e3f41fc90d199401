"""``esmm prepare FILES... --out DIR`` as a cached, parallel batch (one asset per organ).

Each input becomes one :class:`~esmm.pipeline.batch.jobs.Job` whose worker
calls :func:`esmm.pipeline.prepare.prepare` and writes ``<out>/<name>.h5`` and
its ``.xdmf`` sidecar. Asset names: the input's stem when the stems are
unique (``liver.stl`` -> ``liver.h5``); otherwise the inputs' folders are
mirrored below ``<out>`` from their deepest common folder
(``p01/liver.stl``, ``p02/liver.stl`` -> ``p01/liver.h5``, ``p02/liver.h5``).

The key of an organ covers the input's bytes, every option of
:func:`~esmm.pipeline.prepare.prepare` given (including ``force``, which
changes what is written below the quality floors), and the bytes of a prepare
config or material given as a file (also a material file named inside the
prepare config). Bundled presets are covered by the code version.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..prepare import input_stem, load_prepare_config, prepare
from ..progress import Reporter
from .jobs import BatchSummary, Job, JobOutput
from .runner import run_jobs

KIND = "prepare"

#: Keyword options of prepare() that are not result options (the batch sets them itself).
_NOT_OPTIONS = ("input_path", "output", "reporter", "argv")


def prepare_options() -> tuple[str, ...]:
    """The keyword options of :func:`esmm.pipeline.prepare.prepare` a batch passes through."""
    return tuple(n for n, prm in inspect.signature(prepare).parameters.items()
                 if prm.kind is inspect.Parameter.KEYWORD_ONLY and n not in _NOT_OPTIONS)


def asset_names(inputs: Sequence[str | os.PathLike]) -> dict[str, str]:
    """Input path (resolved, as text) -> asset path relative to the batch folder.

    Unique stems give ``<stem>.h5``; otherwise the folders are mirrored from
    the inputs' deepest common folder.

    Raises
    ------
    ConfigError
        The same file is given twice, or two inputs would still collide.
    """
    paths = [Path(p).resolve() for p in inputs]
    seen: set[Path] = set()
    for p in paths:
        if p in seen:
            raise ConfigError(f"{p}: given twice; give each organ once")
        seen.add(p)
    stems = [input_stem(p) for p in paths]
    if len(set(stems)) == len(stems):
        return {str(p): f"{s}.h5" for p, s in zip(paths, stems)}
    common = Path(os.path.commonpath([str(p.parent) for p in paths]))
    out = {}
    for p, s in zip(paths, stems):
        rel = p.parent.relative_to(common)
        out[str(p)] = (rel / f"{s}.h5").as_posix()
    clash = [n for n in out.values() if list(out.values()).count(n) > 1]
    if clash:  # e.g. liver.stl and liver.obj in one folder
        raise ConfigError(f"two inputs would both make {clash[0]}; rename one of them or run them separately")
    return out


def _file_option(value: Any) -> Path | None:
    """The file a config/material option names, or None for a preset name."""
    if value is None or isinstance(value, dict):
        return None
    s = str(value)
    if s.endswith(".toml") or os.sep in s or Path(s).is_file():
        return Path(s).resolve()
    return None


def prepare_one(input_path: str, asset: str, options: Mapping[str, Any], argv: Sequence[str] | None) -> JobOutput:
    """Worker function: :func:`esmm.pipeline.prepare.prepare` one organ into *asset*.

    Returns
    -------
    JobOutput
        The ``.h5`` and ``.xdmf``; summary: nodes, springs, tets, mesher,
        quality verdict, timings [s], warnings.
    """
    res = prepare(input_path, output=asset, argv=list(argv) if argv else None, **dict(options))
    net = res.network
    summary = {
        "input": input_path, "structure": getattr(net, "structure", ""), "nodes": int(net.n_nodes),
        "springs": int(net.n_springs), "tets": int(net.n_tets) if getattr(net, "tets", None) is not None else 0,
        "mesher": res.mesher, "quality_passed": bool(res.quality_passed),
        "timings": {k: float(v) for k, v in res.timings.items()}, "warnings": list(res.warnings),
    }
    outputs = [res.asset] + ([res.xdmf] if Path(res.xdmf).is_file() else [])
    return JobOutput(outputs=outputs, summary=summary)


def prepare_jobs(inputs: Sequence[str | os.PathLike], *, out_dir: str | os.PathLike,
                 options: Mapping[str, Any] | None = None, argv: Sequence[str] | None = None) -> list[Job]:
    """One job per organ.

    Parameters
    ----------
    inputs : sequence of path
        Organ surfaces or masks.
    out_dir : path
        The batch folder; assets are named by :func:`asset_names`.
    options : mapping, optional
        Keyword options of :func:`esmm.pipeline.prepare.prepare` (see
        :func:`prepare_options`); ``size`` in metres. ``None`` values are
        dropped (prepare's defaults apply).
    argv : sequence of str, optional
        The command line, recorded in each asset's provenance.

    Raises
    ------
    ConfigError
        An unknown option, a prepare config that cannot be loaded, or
        colliding asset names (these would fail every organ alike).
    """
    opts = dict(options or {})
    known = prepare_options()
    unknown = sorted(set(opts) - set(known))
    if unknown:
        raise ConfigError(f"prepare batch: unknown option(s) {', '.join(unknown)}; known: {', '.join(known)}")
    opts = {k: v for k, v in opts.items() if v is not None}
    # Files named by options: absolute (workers may run elsewhere) and part of the key.
    extra: list[Path] = []
    for k in ("config", "material"):
        f = _file_option(opts.get(k))
        if f is not None:
            opts[k] = str(f)
            extra.append(f)
    cfg, _ = load_prepare_config(opts.get("config"))
    if "material" not in opts:
        f = _file_option(cfg["prepare"].get("material"))
        if f is not None:
            extra.append(f)
    names = asset_names(inputs)
    out = Path(out_dir).resolve()
    jobs = []
    for inp, rel in names.items():
        name = rel[:-3]  # without .h5
        jobs.append(Job(name=name, kind=KIND, fn=prepare_one, args=(inp, str(out / rel), opts, list(argv or [])),
                        key_inputs=[inp, *map(str, extra)], config={"asset": rel, "options": opts}))
    return jobs


def prepare_batch(inputs: Sequence[str | os.PathLike], *, out_dir: str | os.PathLike,
                  options: Mapping[str, Any] | None = None, argv: Sequence[str] | None = None,
                  scheduler: Any = None, workers: int | None = None, force: bool = False,
                  reporter: Reporter | None = None) -> BatchSummary:
    """Prepare every organ of *inputs* into ``<out_dir>``, in parallel, with caching.

    Parameters
    ----------
    inputs, options, argv
        See :func:`prepare_jobs`.
    out_dir : path
        Batch folder: the assets, ``batch-summary.csv``, ``esmm-batch-<time>.log``,
        ``.esmm-cache/``.
    scheduler, workers, force, reporter
        See :func:`esmm.pipeline.batch.runner.run_jobs` (``force`` here means
        "recompute cached organs"; the quality override is ``options["force"]``).

    Returns
    -------
    BatchSummary
    """
    jobs = prepare_jobs(inputs, out_dir=out_dir, options=options, argv=argv)
    return run_jobs(jobs, out_dir=out_dir, scheduler=scheduler, workers=workers, force=force,
                    reporter=reporter, title="preparing")
