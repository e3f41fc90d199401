"""Is validate's continuum reference converged for the grasper force of a split asset?

``esmm validate`` compares a split network (``esmm prepare --split``) with felupe's P2 on the
network's *parents*, node for node (docs/design/validation.md, "Split networks"). This script
solves validate's lift case of a split asset (the same anchor, bed and grasped nodes) with
refinements of that reference, and measures the network against each level:

* ``parents``: P2 on the parent tetrahedra (validate's reference; its nodes are the split's);
* ``split``: P2 on the split tetrahedra themselves (a nested refinement, h/2: the split's nodes
  and a node on every split edge; a middle node is prescribed where both ends of its edge are,
  as validate does on the parents; the floor is checked at every P2 node);
* ``mini_split``, ``mini_split2``: MINI (first order) on the split tetrahedra and on the split
  split again (h/2, h/4): two more solutions of the problem ``split`` solves, for its order.

What the grasped nodes hold differs between the levels, and the script counts it (``patch``):
a P2 field on the parents is held on a surface face only where all six of its nodes are
grasped; the network, and every level on the split tetrahedra, hold each split surface
triangle whose three corners are grasped. Where no parent face is held whole (the grasp
patch smaller than a parent face), P2 on the parents holds isolated points and edges.

Every continuum solve is cached in ``--work`` (P2 on the split liver: tens of minutes on one
core). Run single-threaded and niced beside other jobs:

    OMP_NUM_THREADS=1 nice python scripts/reference_convergence.py       # the liver's coarse split, 5 mm lift
    python scripts/reference_convergence.py --organs liver kidney --lifts 5 20 --levels parents split
    python scripts/reference_convergence.py --table docs/figures/reference_convergence.json
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import pickle
import subprocess
import time
from pathlib import Path

import numpy as np
from esmm.pipeline.asset import read_asset
from esmm.pipeline.errors import SimulationError
from esmm.pipeline.fidelity.cases import Constraint, LoadCase, at_load, lift_case, parent_faces
from esmm.pipeline.fidelity.compare import compare
from esmm.pipeline.fidelity.continuum import solve_continuum
from esmm.pipeline.fidelity.material import DEFAULT_BULK_RATIO, bulk_modulus
from esmm.pipeline.fidelity.network_solve import solve_network
from esmm.pipeline.fidelity.solution import Solution
from esmm.pipeline.fidelity.validate import _on_the_floor, network_terms
from esmm.pipeline.mesh.refine import quadratic_tets, split_in_eight
from esmm.pipeline.simulate.grasper import plan_grasp
from esmm.pipeline.simulate.runsetup import fixed_nodes
from volume_kappa import (  # the same organs, lift and reporter
    ESMM,
    MAX_ROUNDS,
    ORGANS,
    REP,
    ROOT,
    lift_scene,
)

#: The two assets per organ: the split of a coarse parent mesh (docs/design/realtime.md) and the paper split.
ASSETS = {"coarse_split": ["--elements", "1500", "--split"], "paper_split": ["--config", "paper", "--split"]}
LEVELS = ("parents", "split", "mini_split", "mini_split2")
#: The continuum's element at each level.
ELEMENT_OF = {"parents": "p2", "split": "p2", "mini_split": "mini", "mini_split2": "mini"}
OUT = ROOT / "docs" / "figures" / "reference_convergence.json"


# ---------------------------------------------------------------------------------------------
# Assets and cases


def asset_path(organ: str, kind: str, work: Path) -> Path:
    """The organ's asset of *kind* (:data:`ASSETS`), prepared once into *work*."""
    path = work / f"{organ}-{kind}.h5"
    if not path.exists():
        subprocess.run([str(ESMM), "prepare", str(ORGANS[organ]), *ASSETS[kind], "-o", str(path)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return path


def organ_lift(net, mm: float, grasped=None) -> LoadCase:
    """validate's lift case on *net* (its anchor, bed, grasper plan), the patch *grasped* if given;
    with the network's parents as the P2 cells, as validate solves a split network."""
    scene = lift_scene(mm)
    fixed = fixed_nodes(net, scene)
    plan = plan_grasp(scene.grasper, net.points, net.surface_faces, fixed, scene.gravity, springs=net.springs)
    density = float(net.mass.sum()) / float(net.total_volume())
    weight = float(net.mass.sum() * np.linalg.norm(scene.gravity))
    case = lift_case(net.points, net.tets, scene=scene, fixed=fixed,
                     grasped=plan.nodes if grasped is None else grasped, lift=plan.offsets[-1],
                     density=density, weight=weight)
    return dataclasses.replace(case, quadratic_cells=net.quadratic_cells)


def held_faces(faces: np.ndarray, grasped: np.ndarray) -> np.ndarray:
    """The rows of *faces* (k, m) whose every node is grasped."""
    return faces[np.all(np.isin(faces, grasped), axis=1)]


def patch_figures(net, case: LoadCase) -> dict:
    """What the grasped nodes hold: the split's surface triangles and the parents' surface faces with every
    node grasped, and the held area of each [mm2]."""
    g = case.constraint("grasper").nodes
    tri = held_faces(net.surface_faces, g)
    par = held_faces(parent_faces(net.quadratic_cells), g)
    p = net.points

    def area(f):
        return 0.5e6 * float(np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1).sum())

    return {"grasped_nodes": int(g.size), "split_triangles_held": int(tri.shape[0]),
            "split_area_held_mm2": area(tri) if tri.size else 0.0,
            "parent_faces_held": int(par.shape[0]), "parent_area_held_mm2": area(par) if par.size else 0.0}


def nested_case(case: LoadCase) -> LoadCase:
    """*case* on its own tetrahedra split in eight, solved as P2 on those tetrahedra (h/2 of the parents').

    The nodes are the case's (first, in order) and a middle node on each of its edges. A middle node joins a
    constraint group where both ends of its edge are in it (their mean value, all components): what validate
    does at a P2 cell's middle nodes, so that the region held is the union of the surface triangles with
    every corner held, as the network holds it.
    """
    pts, tets, cells = split_in_eight(case.points, case.tets)
    _, _, edges = quadratic_tets(case.points, case.tets)
    n = case.n_nodes
    cons = []
    for c in case.constraints:
        member = np.zeros(n, bool)
        member[c.nodes] = True
        u, m = np.zeros((n, 3)), np.zeros((n, 3), bool)
        u[c.nodes], m[c.nodes] = c.displacement, c.mask
        mid = np.flatnonzero(member[edges[:, 0]] & member[edges[:, 1]])
        mask = m[edges[mid, 0]] & m[edges[mid, 1]]
        keep = mask.any(axis=1)
        mid, mask = mid[keep], mask[keep]
        disp = np.where(mask, 0.5 * (u[edges[mid, 0]] + u[edges[mid, 1]]), 0.0)
        cons.append(Constraint(c.name, np.concatenate([c.nodes, n + mid]), np.vstack([c.mask, mask]),
                               np.vstack([c.displacement, disp])))
    return dataclasses.replace(case, points=pts, tets=tets, constraints=tuple(cons), quadratic_cells=cells)


# ---------------------------------------------------------------------------------------------
# Solving, as esmm validate does (the floor as a sticking contact along each solver's load path)


def _key(case: LoadCase) -> str:
    h = hashlib.sha256()
    for a in (case.points, case.tets, case.gravity,
              np.zeros(0) if case.quadratic_cells is None else case.quadratic_cells):
        h.update(np.ascontiguousarray(a).tobytes())
    for c in case.constraints:
        h.update(c.name.encode())
        h.update(np.ascontiguousarray(c.nodes).tobytes())
        h.update(np.ascontiguousarray(np.asarray(c.displacement, dtype=np.float64)).tobytes())
    return h.hexdigest()[:16]


def continuum(case: LoadCase, material, work: Path, tag: str, *, element: str = "p2") -> Solution | str:
    """*element* on *case* (P2: on its quadratic cells) with the floor found along its load path, as validate
    finds it (cached in *work*); the solver's message where it finds no equilibrium."""
    f = work / f"{element}-{tag}-{_key(case)}.pkl"
    if f.exists():
        return pickle.loads(f.read_bytes())
    bulk = bulk_modulus(material, ratio=DEFAULT_BULK_RATIO)
    t = time.perf_counter()

    def solve(c, start):
        return solve_continuum(c, material, bulk=bulk, element=element, start=start, steps=1, reporter=REP)

    try:
        sol, pins = _on_the_floor(case, solve, MAX_ROUNDS, REP)
    except SimulationError as exc:
        msg = f"{exc} (after {time.perf_counter() - t:.0f} s)"
        f.write_bytes(pickle.dumps(msg))
        print(f"  {tag}: {element} found no equilibrium: {msg}", flush=True)
        return msg
    sol.state = None
    sol.info.update(seconds_total=time.perf_counter() - t, floor_pins=int(pins), nodes=case.n_nodes)
    f.write_bytes(pickle.dumps(sol))
    print(f"  {tag}: {element} {sol.info['dofs']} unknowns, {sol.info['newton_iterations']} Newton iterations, "
          f"{sol.info['seconds_total']:.0f} s", flush=True)
    return sol


def network(case: LoadCase, asset) -> Solution:
    """The asset's network (with its volume term, as validate's "auto") on *case*, the floor as validate finds it."""
    terms = network_terms(asset.network, asset.tables, asset.material)

    def solve(c, start):
        return solve_network(c, asset.network, asset.tables, terms=terms, start=start, steps=1, reporter=REP)

    sol, _ = _on_the_floor(case, solve, MAX_ROUNDS, REP)
    return sol


def restricted(sol: Solution, n: int) -> Solution:
    """*sol* with its displacement at the first *n* nodes only (a nested level on the coarser level's nodes)."""
    return dataclasses.replace(sol, displacement=sol.displacement[:n])


def figures(case: LoadCase, ref: Solution, other: Solution) -> dict:
    """*other* against *ref* on *case*'s nodes: validate's L2 and force error, and the force ratio."""
    res = compare(case, ref, other)
    g = case.force_group
    rr, ro = np.asarray(ref.reactions[g]), np.asarray(other.reactions[g])
    return {"l2": res.l2_error, "max": res.max_error, "force": res.force_error,
            "force_ratio": float(np.linalg.norm(ro) / np.linalg.norm(rr) - 1.0)}


def force_of(sol: Solution, group: str = "grasper") -> dict:
    r = np.asarray(sol.reactions[group], dtype=float)
    return {"force_N": r.tolist(), "magnitude_N": float(np.linalg.norm(r)),
            "max_displacement_mm": 1e3 * float(np.linalg.norm(sol.displacement, axis=1).max()),
            "floor_pins": int(sol.info.get("floor_pins", 0)), "dofs": sol.info.get("dofs"),
            "newton_iterations": sol.info.get("newton_iterations"), "seconds": sol.info.get("seconds_total"),
            "cells_near_locking": int(sol.info.get("cells_near_locking", 0) or 0),
            "locking_share": sol.info.get("locking_share")}


# ---------------------------------------------------------------------------------------------
# The study


def cell_size_mm(case: LoadCase) -> float:
    """The continuum's cells' size: the edge of the regular tetrahedron of their mean volume [mm]."""
    cells = case.quadratic_cells.shape[0] if case.quadratic_cells is not None else case.tets.shape[0]
    vol = float(case.node_volumes().sum()) / cells
    return 1e3 * (6.0 * np.sqrt(2.0) * vol) ** (1.0 / 3.0)


def level_case(case0: LoadCase, level: str) -> tuple[LoadCase, str]:
    """The case and element of *level* (:data:`LEVELS`) made from validate's case *case0* on a split network."""
    if level == "parents":
        return case0, "p2"
    if level == "split":
        return nested_case(case0), "p2"
    if level == "mini_split":
        return dataclasses.replace(case0, quadratic_cells=None), "mini"
    return dataclasses.replace(nested_case(case0), quadratic_cells=None), "mini"


def references(organ: str, kind: str, mm: float, levels, work: Path, load: float = 1.0) -> dict:
    """The continuum's lift of *mm* at each of *levels* on the asset *kind*'s own case (validate's), gravity and
    the lift scaled by *load*."""
    a = read_asset(asset_path(organ, kind, work))
    case0 = organ_lift(a.network, mm)
    case0 = case0 if load == 1.0 else at_load(case0, load)
    out = {"asset": a, "case": case0, "solutions": {}, "cases": {}, "failed": {}}
    tag = (f"{organ}-{mm:g}mm" if kind == "coarse_split" else f"{organ}-{kind}-{mm:g}mm") + (
        "" if load == 1.0 else f"-x{load:g}")
    for level in levels:
        c, element = level_case(case0, level)
        out["cases"][level] = c
        sol = continuum(c, a.material, work, f"{tag}-{level}", element=element)
        out["failed" if isinstance(sol, str) else "solutions"][level] = sol
    return out


def level_rows(refs: dict) -> dict:
    """Per level: its mesh, its force and field, and its difference from P2 on the split (at the split's nodes)."""
    rows = {}
    n = refs["case"].n_nodes
    sols = refs["solutions"]
    for level, sol in sols.items():
        c = refs["cases"][level]
        rows[level] = {"element": ELEMENT_OF[level], "cells": int(c.tets.shape[0] if c.quadratic_cells is None
                                                                 else c.quadratic_cells.shape[0]),
                       "cell_size_mm": cell_size_mm(c), "nodes": c.n_nodes,
                       "grasped_nodes": int(c.constraint("grasper").nodes.size), **force_of(sol)}
        if level != "split" and "split" in sols:
            rows[level]["against_split"] = figures(refs["case"], restricted(sols["split"], n), restricted(sol, n))
    return rows


def network_rows(refs: dict) -> dict:
    """The asset's network against every level, at its own nodes."""
    case0, n = refs["case"], refs["case"].n_nodes
    nw = network(case0, refs["asset"])
    f = np.asarray(nw.reactions["grasper"])
    return {"force_N": f.tolist(), "magnitude_N": float(np.linalg.norm(f)),
            "max_displacement_mm": 1e3 * float(np.linalg.norm(nw.displacement, axis=1).max()),
            "inverted": nw.inverted, "volume_change": nw.volume_ratio - 1.0,
            "against": {lv: figures(case0, restricted(sol, n), nw) for lv, sol in refs["solutions"].items()}}


def study(organ: str, kind: str, mm: float, levels, work: Path, load: float = 1.0) -> dict:
    t = time.perf_counter()
    refs = references(organ, kind, mm, levels, work, load)
    a = refs["asset"]
    return {"lift_mm": mm, "load_factor": load, "nodes": a.network.n_nodes, "springs": a.network.n_springs,
            "parents": int(a.network.quadratic_cells.shape[0]), "patch": patch_figures(a.network, refs["case"]),
            "levels": level_rows(refs), "failed": refs["failed"], "network": network_rows(refs),
            "seconds": time.perf_counter() - t}


# ---------------------------------------------------------------------------------------------
# Output


def pct(x) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def table(doc: dict) -> str:
    """Markdown: per organ, asset and lift, each level's force and its difference from P2 on the split, and the
    asset's network against each level (L2 / force, %)."""
    lines = ["| organ, asset, lift | level | cells (size mm) | grasped nodes | force N | level vs P2 on split: "
             "L2 / force % | network vs level: L2 / force % |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for organ, runs in doc["organs"].items():
        for key, s in runs.items():
            nw = s["network"]["against"]
            for lv, r in s["levels"].items():
                d = r.get("against_split")
                diff = "–" if d is None else f"{pct(d['l2'])} / {pct(d['force'])}"
                lock = f" ({r['cells_near_locking']} at locking)" if r["cells_near_locking"] else ""
                lines.append(f"| {organ} {key} | {r['element']} on {lv.removeprefix('mini_')} | {r['cells']} "
                             f"({r['cell_size_mm']:.1f}) | {r['grasped_nodes']} | {r['magnitude_N']:.4f}{lock} | {diff} | "
                             f"{pct(nw[lv]['l2'])} / {pct(nw[lv]['force'])} |")
            for lv, msg in s.get("failed", {}).items():
                lines.append(f"| {organ} {key} | {ELEMENT_OF[lv]} on {lv.removeprefix('mini_')} | no equilibrium: "
                             f"{msg[:80]} | | | | |")
            lines.append(f"| {organ} {key} | network | | {s['patch']['grasped_nodes']} | "
                         f"{s['network']['magnitude_N']:.4f} | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--organs", nargs="+", default=["liver"], choices=sorted(ORGANS))
    ap.add_argument("--assets", nargs="+", default=["coarse_split"], choices=sorted(ASSETS))
    ap.add_argument("--lifts", nargs="+", type=float, default=[5.0], help="last waypoint [mm] (default 5)")
    ap.add_argument("--load", type=float, default=1.0, help="gravity and the lift scaled by this factor (default 1: "
                    "validate's case)")
    ap.add_argument("--levels", nargs="+", default=list(LEVELS), choices=LEVELS)
    ap.add_argument("--work", type=Path, default=Path.home() / ".cache" / "esmm" / "reference_convergence",
                    help="assets and cached solutions (default ~/.cache/esmm/reference_convergence)")
    ap.add_argument("--json", type=Path, default=OUT, help="read and extended (one entry per organ, asset, lift)")
    ap.add_argument("--table", type=Path, help="print the table of a written JSON and exit")
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    doc = json.loads(args.json.read_text()) if args.json.exists() else {"organs": {}}
    for organ in args.organs:
        for kind in args.assets:
            for mm in args.lifts:
                key = f"{kind} lift {mm:g} mm" + ("" if args.load == 1.0 else f" at load {args.load:g}")
                print(f"{organ}, {key}", flush=True)
                doc["organs"].setdefault(organ, {})[key] = study(organ, kind, mm, args.levels, args.work, args.load)
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps(doc, indent=1) + "\n")
    print(table(doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
