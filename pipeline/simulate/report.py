"""``report.html`` of ``esmm simulate``: one self-contained page, the run's verdict in plain words first.

From the run's :class:`~.summary.SimulationSummary` and its force plot: whether the run
kept up with real time (in words: "0.27x real time: 3.7 times slower than real time"),
whether every spring stayed on the tables' grid and the organ kept its volume without
inverted tetrahedra, then the grasper's force (the plot, embedded), the steps and their
timings, the fixed nodes and the floor. Every number has its unit.

The verdict: "good" when the run was at least as fast as real time and nothing below
happened; "poor" when it was slower than real time (a user's interactive simulator
would lag), when springs left the tables' grid (their stiffness was held at the grid's
end), when tetrahedra inverted, or when the volume changed by more than
:data:`VOLUME_POOR` (a nearly incompressible tissue keeps it within a fraction of a
percent with the volume term: docs/guide/prepare.md, "How far to trust it").
"""

from __future__ import annotations

from pathlib import Path

from .. import __version__
from ..htmlreport import DIMENSIONLESS, Document
from .summary import SimulationSummary

#: Largest relative volume change of a run judged "good" (a fraction; module docstring).
VOLUME_POOR = 0.01


def _reasons(s: SimulationSummary) -> list[tuple[str, str]]:
    """(reason, what to do) of a "poor" run."""
    out = []
    if s.real_time_factor < 1.0:
        out.append((f"slower than real time: {s.real_time}", "a coarser asset (--config coarse), the implicit "
                    "stepper, or more threads; speeds per preset: docs/guide/simulate.md"))
    if (s.outside_table or {}).get("frames"):
        o = s.outside_table
        out.append((f"springs left the tables' grid in {o['frames']} of {o['of_frames']} frames (stretch "
                    f"{o.get('stretch_min') or 0:.3g} to {o.get('stretch_max') or 0:.3g}, the grid "
                    f"{s.table_range[0]:.3g} to {s.table_range[1]:.3g}): their stiffness was held at its end",
                    "a gentler scene, or tables over a wider grid ([tables] lam_min, lam_max)"))
    final = (s.volume or {}).get("final") or {}
    if final.get("inverted_tets"):
        out.append((f"{final['inverted_tets']} tetrahedra inverted at the end", "an asset with its volume term"))
    ratio = final.get("volume_ratio")
    if ratio is not None and abs(ratio - 1.0) > VOLUME_POOR:
        out.append((f"the organ's volume changed by {100 * (ratio - 1):.3g} % (above {100 * VOLUME_POOR:g} %)",
                    "an asset with its volume term (esmm prepare without --no-volume)"))
    return out


def simulation_document(s: SimulationSummary, *, force_plot: Path | None = None) -> Document:
    """The report of a run as a :class:`~esmm.pipeline.htmlreport.Document`."""
    doc = Document(f"Simulation: {Path(s.asset).name or 'network'}", producer=f"esmm {__version__} simulate",
                   subtitle=f"{s.scene_source}; {s.simulated_s:g} s simulated, {s.method} stepper")
    reasons = _reasons(s)
    force = f"; the largest force on the grasper {s.grasper.max_force_N:.3g} N" if s.grasper else ""
    doc.verdict("poor" if reasons else "good", f"The run was {s.real_time}{force}.",
                reasons=[r for r, _ in reasons], advice=list(dict.fromkeys(a for _, a in reasons)))
    doc.section("Speed")
    doc.facts([("simulated time", s.simulated_s, "s"), ("stepping time (wall clock)", s.stepping_wall_s, "s"),
               ("real-time factor (simulated over stepping time)", s.real_time_factor, DIMENSIONLESS),
               ("in words", s.real_time, None), ("steps", str(s.steps), None),
               ("step size", s.dt_max_s, "s"), ("wall time per step", s.wall_per_step_us * 1e-6, "s"),
               ("threads", str(s.threads), None), ("springs", str(s.springs), None), ("nodes", str(s.nodes), None)])
    if s.grasper is not None:
        doc.section("The grasper")
        if force_plot is not None and Path(force_plot).is_file():
            doc.figure(Path(force_plot).read_bytes(), alt="the force of the tissue on the grasper in newtons "
                       "(x, y, z and magnitude) against time in seconds", caption="Force of the tissue on the grasper")
        doc.facts([("largest force", s.grasper.max_force_N, "N"), ("nodes held", str(s.grasper.held_nodes), None),
                   ("mode", s.grasper.mode, None)])
    _shape(doc, s)
    doc.section("Scene and settings", collapsed=True)
    doc.facts([("scene", s.scene, None), ("fixed nodes", s.fixed_words(), None), ("force law", s.law, None),
               ("material effects", ", ".join(s.effect_names) or "none", None),
               ("start", s.start + (" (cached)" if (s.equilibrium or {}).get("cached") else ""), None)])
    return doc


def _shape(doc: Document, s: SimulationSummary) -> None:
    doc.section("The organ's shape and the springs' stretch")
    final = (s.volume or {}).get("final") or {}
    facts = [("springs' stretch, smallest", s.stretch_min, DIMENSIONLESS),
             ("springs' stretch, largest", s.stretch_max, DIMENSIONLESS),
             ("tables' grid", f"{s.table_range[0]:.4g} to {s.table_range[1]:.4g} (dimensionless)", None),
             ("largest displacement at the end", s.final_max_displacement_m, "m")]
    if final.get("volume_ratio") is not None:
        facts += [("volume change at the end", final["volume_ratio"] - 1.0, "%"),
                  ("inverted tetrahedra at the end", str(final.get("inverted_tets")), None)]
    if s.floor is not None:
        facts.append(("nodes on the floor at the end", str(s.floor.contact_nodes_final), None))
    doc.facts(facts)


def write_simulation_html(s: SimulationSummary, out: str | Path, *, force_plot: Path | None = None) -> Path:
    """Write ``report.html`` into the run's folder *out* (atomically)."""
    return simulation_document(s, force_plot=force_plot).write(Path(out) / "report.html")
