"""``esmm simulate``: replay an asset in a scripted scene (history, force plot, video)."""

from __future__ import annotations

import argparse

EPILOG = """\
outputs (in --out DIR, default ASSET-sim/ beside the asset):
  history.h5, history.xdmf   displacement per frame (open the .xdmf in ParaView), grasper
                             tip per frame and grasper force per integration step
  grasper_force.png          force of the tissue on the grasper vs time
  summary.json               time step, stability bound, timings, real-time factor
  report.html                the run in one page: its verdict, the speed in words, the grasper force
  --video OUT.mp4            off-screen rendering (no display or GPU needed)

scenes: 'default' (bundled: the organ lies on a sticking bed, its lowest 5 % held; a grasper
lifts the free edge 20 mm in 1 s, holds, releases at 2 s; implicit stepper, grasper force at
1 kHz), 'interactive' (the default on a frictionless bed) or a TOML file, which
may start from a bundled one (base = "default"); see docs/reference/configuration.md for the schema.

material effects: an asset made from a discovery's params.toml carries its kept effects
(viscoelastic, Mullins, damage; 'esmm info' lists them); they are applied per spring
unless --effects none (or [scene] effects = "none").

examples:
  esmm simulate liver.h5
  esmm simulate liver.h5 --video liver.mp4 --duration 2
  esmm simulate liver.h5 --scene interactive
  esmm simulate liver.h5 --scene myscene.toml --law energy --threads 2 --out runs/a
"""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "simulate", help="run an asset in a scripted scene (history, force plot, video)",
        description="Simulate a spring-network asset in real time in a scripted scene: gravity, a fixed "
                    "region and a grasper that pulls, holds and releases the organ. Writes the "
                    "displacement history (HDF5 + XDMF), the grasper force and optionally a video.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("asset", metavar="ASSET.h5", help="asset written by 'esmm prepare'")
    p.add_argument("--scene", metavar="C", default=None,
                   help="bundled scene name or .toml file (default: 'default')")
    p.add_argument("--video", metavar="OUT.mp4", default=None, help="also render a video (off-screen)")
    p.add_argument("--duration", metavar="S", default=None,
                   help="simulated time in seconds (or with a unit, '500 ms'); overrides the scene")
    p.add_argument("--threads", metavar="N", default=None,
                   help="'auto' (measure and pick) or a number of threads; overrides the scene")
    p.add_argument("--law", choices=("asset", "secant", "energy"), default=None,
                   help="force law: the asset's default, secant (paper Eq. 9) or energy-consistent")
    p.add_argument("--effects", choices=("asset", "none"), default=None,
                   help="apply the asset's material effects (default, when it has any) or none "
                        "(instantaneous elastic response only); overrides the scene")
    p.add_argument("--method", choices=("implicit", "explicit"), default=None,
                   help="integrator: implicit (backward Euler, stable at the frame step, grasper force at 1 kHz; "
                        "the default scene's) or explicit (symplectic Euler under the stiffest spring's bound; "
                        "the accuracy reference); overrides the scene")
    p.add_argument("--out", metavar="DIR", default=None, help="output folder (default: ASSET-sim/)")
    p.set_defaults(func=run)
    return p


def run(args, ui) -> int:
    from esmm.cli.outputs import check_out_dir, check_out_file
    from esmm.pipeline.simulate.run import default_out_dir, simulate
    from esmm.pipeline.simulate.summary import iterations_per_step

    check_out_dir(args.out if args.out is not None else default_out_dir(args.asset), "--out")
    if args.video is not None:
        check_out_file(args.video, "--video", "run.mp4")
    res = simulate(args.asset, scene=args.scene, out_dir=args.out, video=args.video,
                   duration=args.duration, threads=args.threads, law=args.law, effects=args.effects,
                   method=args.method, reporter=ui)
    s = res.summary
    if s.method == "implicit":
        it = s.integrator
        ui.info(f"simulated {s.simulated_s:g} s: {s.springs} springs, implicit, {s.steps} steps of "
                f"{s.dt_max_s * 1e3:.4g} ms ({iterations_per_step(it)} per step, "
                f"{it['factorizations']} factorizations), grasper force at {it['haptic_rate_hz']:g} Hz")
    else:
        ui.info(f"simulated {s.simulated_s:g} s: {s.springs} springs, explicit, {s.steps} steps of "
                f"{s.dt_min_s * 1e6:.4g}..{s.dt_max_s * 1e6:.4g} us ({s.threads} thread(s))")
    ui.info(f"speed: {s.real_time} (real-time factor {s.real_time_factor:.3g}: simulated over stepping time)")
    ui.info(f"fixed: {s.fixed_words()}")
    if s.effects:
        ui.info("material effects: " + ", ".join(s.effect_names))
    ui.info(f"history: {res.xdmf}")
    if res.force_plot is not None:
        ui.info(f"grasper force: {res.force_plot} (max {s.grasper.max_force_N if s.grasper else 0.0:.3g} N)")
    if res.video is not None:
        ui.info(f"video: {res.video}")
    ui.info(f"summary: {res.summary_path}")
    if res.report is not None:
        ui.info(f"report: {res.report} (the run in one page, in a browser)")
    return 0
