"""``esmm simulate``: run a scene on an asset and write its outputs.

Outputs in the output folder (each written atomically):

* ``history.h5`` + ``history.xdmf``: displacement per frame (ParaView replay),
  grasper tip per frame and grasper force per integration step
  (:mod:`.history`);
* ``grasper_force.png``: force of the tissue on the grasper vs time (:mod:`.plots`);
* ``summary.json``: the figures of the run (:class:`~.summary.SimulationSummary`);
* ``report.html``: the run in one page, its verdict first (:mod:`.report`);
* the video, when asked for (:mod:`.render`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..asset import read_asset
from ..atomicio import output_folder, write_json
from ..errors import AssetError, ConfigError
from ..progress import ensure
from .frames import FrameSpec, RangeCheck, run_frames
from .grasper import GraspPlan
from .history import HistoryWriter
from .plots import plot_forces
from .render import render_video
from .report import write_simulation_html
from .runsetup import RunSetup, plan_grasper, plan_steps, prepare_run, settle_at_start
from .scene import Scene, load_scene
from .summary import SimulationSummary, VideoSummary, summarize

VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi")


@dataclass
class SimulationResult:
    """Files and figures of a run."""

    out_dir: Path
    history: Path
    xdmf: Path
    force_plot: Path | None
    summary_path: Path
    summary: SimulationSummary
    video: Path | None = None
    report: Path | None = None      #: report.html: the run's verdict, speed in words, the grasper's force


def simulate_network(network, tables, scene: Scene, out_dir, *, video=None, reporter=None,
                     asset_label: str = "", effects=None) -> SimulationResult:
    """Run *scene* on a network with its tables and write the outputs into *out_dir*.

    Parameters
    ----------
    network : SpringNetwork
    tables : StiffnessTables
    scene : Scene
    out_dir : path-like
    video : path-like, optional
        Also render the video there.
    reporter : Reporter, optional
    asset_label : str
        Where the network came from (recorded).
    effects : MaterialEffects, optional
        The material's effects (viscoelastic, Mullins, damage), applied per
        spring unless the scene says ``effects = "none"``.

    Raises
    ------
    ConfigError
        A scene that does not fit the network (fixed region, grasper).
    SimulationError
        Too many steps, or the run became unstable.
    """
    rep = ensure(reporter)
    with output_folder(out_dir) as out:
        return _run_into(out, network, tables, scene, video, rep, asset_label, effects)


def _run_into(out: Path, network, tables, scene: Scene, video, rep, asset_label: str, effects) -> SimulationResult:
    """:func:`simulate_network` in the folder *out*, which exists."""
    run = prepare_run(network, tables, scene, effects=effects, reporter=rep)
    settle = settle_at_start(run, scene, network, rep)
    plan = plan_grasper(run, scene, network, rep)
    plan_steps(run, scene, plan, rep)
    spec = _frame_spec(network, scene, plan)
    range_check = RangeCheck(run.sim.model.springs, rep)
    range_check(run.sim.x, "at the start")
    hist_path = out / "history.h5"
    with HistoryWriter(hist_path, **_history_layout(network, run, scene, plan, asset_label)) as writer:
        if plan is not None:
            writer.set_grasped(plan.nodes)
        writer.add_frame(0.0, run.sim.displacement(), tip=None)      # the rest shape, or the equilibrium
        log = run_frames(run.sim, run.schedule, spec, plan, writer, range_check, rep)
        summary = summarize(run, scene, log, range_check, plan=plan, settle=settle, asset_label=asset_label,
                            effects_available=effects, asset_fixed=int(np.asarray(network.fixed).size))
        writer.set_attrs(summary=summary.to_dict())
    rep.step(summary.describe())
    force_png = None if plan is None else plot_forces(hist_path, out / "grasper_force.png", plan=plan)
    stale = out / "grasper_force.png"
    if force_png is None and stale.is_file():   # an earlier run's, with a grasper: not this run's force
        stale.unlink()
        rep.step(f"removed {stale} of an earlier run (this scene has no grasper)")
    # The run's summary before the video, so that a video stopped or failed leaves this run's outputs
    # whole (history, plot, summary; no video), never a history beside an earlier run's summary.
    summary_path = write_json(out / "summary.json", summary.to_dict())
    if video is not None:
        summary.video = _render(hist_path, video, scene, rep)
        summary_path = write_json(out / "summary.json", summary.to_dict())
    report = write_simulation_html(summary, out, force_plot=force_png)
    return SimulationResult(out_dir=out, history=hist_path, xdmf=hist_path.with_suffix(".xdmf"),
                            force_plot=force_png, summary_path=summary_path, summary=summary,
                            video=None if video is None else Path(video), report=report)


def default_out_dir(asset_path) -> Path:
    """Where :func:`simulate` writes when no folder is given: ``<asset stem>-sim`` beside the asset."""
    return Path(asset_path).with_name(Path(asset_path).stem + "-sim")


def _frame_spec(network, scene: Scene, plan: GraspPlan | None) -> FrameSpec:
    events = []
    if plan is not None:
        events.append(("grasp", scene.grasper.grasp_time))
        if scene.grasper.release_time is not None:
            events.append(("release", scene.grasper.release_time))
    return FrameSpec(n_frames=scene.n_frames, frame_dt=1.0 / scene.frame_rate, events=tuple(events),
                     max_steps=scene.max_steps, organ_size=float(np.ptp(np.asarray(network.points), axis=0).max()))


def _history_layout(network, run: RunSetup, scene: Scene, plan: GraspPlan | None, asset_label: str) -> dict:
    """The :class:`~.history.HistoryWriter` arguments of a run: mesh, fixed nodes, attributes."""
    attrs = {
        "asset": asset_label, "law": run.law, "method": scene.method,
        "step_mode": "fixed" if scene.method == "implicit" else scene.step, "frame_rate": scene.frame_rate,
        "gravity": scene.gravity.tolist(), "scene_source": scene.source, "scene": scene.describe(),
        "units": "SI (m, s, N)",
    }
    if plan is not None:
        attrs["grasper_normal"] = plan.normal.tolist()
        attrs["grasper_direction"] = plan.direction.tolist()
        attrs["grasper_target"] = plan.target
    fx = run.sim.model.springs.effects
    if fx is not None:
        attrs["effects"] = fx.describe()
    tets = getattr(network, "tets", None)
    cells = tets if tets is not None and len(tets) else network.surface_faces
    return {"points": network.points, "cells": cells, "surface": network.surface_faces, "fixed": run.fixed,
            "attrs": attrs}


def _render(hist_path: Path, video, scene: Scene, reporter) -> VideoSummary:
    info = render_video(hist_path, video, video=scene.video, reporter=reporter)
    reporter.step(f"video: {info['frames']} frames in {info['seconds']:.3g} s ({info['render_fps']:.3g} frames/s)")
    return VideoSummary(path=str(Path(video)), frames=info["frames"], render_s=info["seconds"],
                        render_fps=info["render_fps"])


def read_asset_for_simulation(path, *, with_effects: bool = False):
    """(network, tables, label) of an asset file (and its MaterialEffects or None, *with_effects*)."""
    p = Path(path)
    if not p.is_file():
        raise AssetError(f"{p}: no such asset file; build one with 'esmm prepare'")
    asset = read_asset(p)
    network = getattr(asset, "network", None)
    tables = getattr(asset, "tables", None)
    if network is None or tables is None:
        raise AssetError(f"{p}: the asset has no spring network or no stiffness tables; rebuild it with "
                         "'esmm prepare'")
    if with_effects:
        return network, tables, str(p), getattr(asset, "effects", None)
    return network, tables, str(p)


def simulate(asset_path, *, scene=None, out_dir=None, video=None, duration=None, threads=None,
             law=None, effects=None, method=None, reporter=None) -> SimulationResult:
    """Run a scene on an asset file (the ``esmm simulate`` command).

    Parameters
    ----------
    asset_path : path-like
        HDF5 asset written by ``esmm prepare``.
    scene : Scene, str or path-like, optional
        A :class:`Scene`, a bundled scene name or a TOML path (default: ``"default"``).
    out_dir : path-like, optional
        Output folder (default: ``<asset stem>-sim`` beside the asset).
    video : path-like, optional
        Also render the video there (``.mp4``, ``.mkv``, ``.mov`` or ``.avi``).
    duration : float or str, optional
        Override of the scene's duration: seconds, or a time with its unit ("500 ms").
    threads : "auto", int or str, optional
    law : {"asset", "secant", "energy"}, optional
    effects : {"asset", "none"}, optional
        Override of the scene's use of the asset's material effects.
    method : {"implicit", "explicit"}, optional
        Override of the scene's integrator.
    """
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    sc = sc.with_overrides(duration=duration, threads=threads, law=law, effects=effects, method=method)
    network, tables, label, fx = read_asset_for_simulation(asset_path, with_effects=True)
    if out_dir is None:
        out_dir = default_out_dir(asset_path)
    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"video: {video} should end in .mp4 (or .mkv, .mov, .avi)", parameter="video")
    return simulate_network(network, tables, sc, out_dir, video=video, reporter=reporter,
                            asset_label=label, effects=fx)
