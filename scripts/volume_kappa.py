"""The volume term's bulk modulus against the continuum: the sweep.

The paper preset's organs are stiff against the P2 continuum, and at small strain most
of the excess is the nodal volume term's (docs/design/realtime.md, "Per-spring
corrections against the continuum"), whose bulk modulus is sized on the material's
stiffest tangent (docs/design/model.md, "The volume term (nearly incompressible
network)"). This script measures what a smaller bulk modulus gives, setting by setting:
each organ's asset (``esmm prepare MESH --config paper``) gets the setting's volume term
and its tables compensated again *with that term* (the compensation's own cache), then

* validate's cases on the organ: gravity, the default scene's 20 mm lift and a 5 mm
  lift (the same scene with its last waypoint at 5 mm), P2 (MINI where P2 finds no
  equilibrium, as ``esmm validate`` does), the floor found along the load path exactly
  as ``esmm validate`` finds it;
* the specimen's tension, compression and shear (``esmm validate --specimen``: the
  20 mm cube at 2.5 mm elements, its volume term and compensation made for the setting);
* the default scene (``esmm simulate``, implicit) on each organ: the real-time factor,
  the child process's CPU time and the implicit stepper's counts.

The continuum does not depend on the network's volume term, so each case's continuum
is solved once and cached (``--work``); the network is solved for every setting.

``--split-parents N`` takes the accurate assets instead of the paper preset: each organ
prepared as ``esmm prepare MESH --config paper --elements N --split`` (every parent tet
split in eight; the meshes and options of ``bench_splits`` in
benchmarks/bench_simulate.py), the continuum P2 on the parents node for node as
``esmm validate`` solves it. Their variants get their own names in ``--work``, so a
paper-preset sweep and a split sweep can share one work folder (and its continuum cache).

    python scripts/volume_kappa.py                  # everything; writes docs/figures/volume_kappa.json
    python scripts/volume_kappa.py --organs liver --settings t0.45 s0.49 --no-simulate --json out.json
    python scripts/volume_kappa.py --table docs/figures/volume_kappa.json     # the table of a written run
    python scripts/volume_kappa.py --split-parents 1500 --settings t0.45 t0.25 --no-simulate \
        --json docs/figures/volume_kappa_splits.json                           # the split assets
    python scripts/volume_kappa.py --split-parents 1500 --settings t0.45 t0.25 --speed 3 \
        --json docs/figures/volume_kappa_splits.json                           # their speed, in turn
    python scripts/volume_kappa.py --merge A.json B.json --settings t0.45 t0.25 --json out.json
                                       # sweeps run apart (organs in parallel, settings in phases) joined

Settings (``--settings``): ``tNU`` sizes kappa on the material's largest tangent over the
calibration range with Poisson ratio NU there (``t0.45`` is the default of
``esmm prepare``); ``sNU`` sizes it on the small-strain shear modulus mu0 with Poisson
ratio NU at small strain; ``off`` is no volume term (the tables compensated without one,
as ``esmm prepare --no-volume`` makes them); ``A/B`` is the term of A on the tables
compensated for the term of B (a diagnosis, not an asset ``esmm prepare`` makes; no
scene run).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import pickle
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from esmm.pipeline.asset import read_asset, write_asset
from esmm.pipeline.compensation.calibration import calibration_stretches, compensate
from esmm.pipeline.fidelity.cases import SPECIMEN_CASES
from esmm.pipeline.fidelity.compare import compare
from esmm.pipeline.fidelity.continuum import solve_continuum
from esmm.pipeline.fidelity.material import DEFAULT_BULK_RATIO
from esmm.pipeline.fidelity.material import bulk_modulus as continuum_bulk
from esmm.pipeline.fidelity.network_solve import solve_network
from esmm.pipeline.fidelity.specimen import cube_specimen
from esmm.pipeline.fidelity.validate import LoadOptions, _cases_for, _on_the_floor
from esmm.pipeline.network.tables import build_tables
from esmm.pipeline.network.volume import (
    VolumeSpec,
    bulk_modulus,
    bulk_ratio,
    tangent_shear_modulus,
    volume_elements,
)
from esmm.pipeline.progress import SILENT
from esmm.pipeline.simulate.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data" / "meshes"
ORGANS = {"liver": ROOT / "data" / "meshes" / "ts_liver_3mm_closed.stl",
          "kidney": SHARED / "openhelp_Kidney_left.stl", "spleen": SHARED / "openhelp_Spleen.stl"}
SETTINGS = ("t0.45", "t0.40", "t0.35", "t0.30", "t0.25", "s0.49", "s0.45", "off",
            "t0.25/t0.45", "s0.45/t0.45", "off/t0.45")
OUT = ROOT / "docs" / "figures" / "volume_kappa.json"
ESMM = Path(sys.executable).with_name("esmm")
MAX_ROUNDS = 10          # validate's default rounds of floor pins per load level


class _Quiet:
    """A reporter that prints warnings only (the solvers' progress is not needed here)."""

    def step(self, message: str) -> None:
        pass

    def warn(self, message: str) -> None:
        print(f"  warning: {message}", flush=True)

    def task(self, description: str, total: float | None = None):
        return SILENT.task(description, total)


REP = _Quiet()


# ---------------------------------------------------------------------------------------------
# Settings


def volume_spec(raw, setting: str) -> VolumeSpec | None:
    """The volume term of *setting* on the uncompensated tables *raw* (None: ``off``)."""
    if setting == "off":
        return None
    kind, nu = setting[0], float(setting[1:])
    if kind == "t":
        return bulk_modulus(raw, poisson=nu, calibration_range=calibration_stretches(raw))
    if kind != "s":
        raise SystemExit(f"--settings: unknown {setting!r}; use tNU, sNU or off")
    mu0, at = tangent_shear_modulus(raw, 1.0, 1.0)
    ratio = bulk_ratio(nu)
    return VolumeSpec(bulk_modulus=ratio * mu0, formulation="nodal", poisson_ratio=nu, shear_modulus=mu0,
                      at_stretch=at, rule=f"kappa = {ratio:.4g} * mu0 = {ratio * mu0:.4g} Pa (small strain, nu {nu:g})")


def with_setting(network, raw, material, setting: str):
    """(network with the setting's volume term, its tables compensated with it, the spec).

    ``KAPPA/TABLES`` (e.g. ``s0.45/t0.45``): the volume term of KAPPA on the tables compensated for
    the term of TABLES: not an asset ``esmm prepare`` makes (its compensation is calibrated with the
    term it carries), the diagnosis of what the compensation's shift does.
    """
    kappa_of, _, tables_of = setting.partition("/")
    spec = volume_spec(raw, kappa_of)
    net = dataclasses.replace(network, volume_term=spec)
    spec_c = volume_spec(raw, tables_of) if tables_of else spec
    tables = compensate(raw, dataclasses.replace(network, volume_term=spec_c), material=material, volume=spec_c,
                        reporter=REP).tables
    return net, tables, spec


def raw_tables(tables, material):
    """The material's uncompensated tables on the grid of *tables* (an asset's)."""
    return build_tables(material, n=tables.n, lam_min=tables.lam_min, lam_max=tables.lam_max,
                        law=tables.default_law)


# ---------------------------------------------------------------------------------------------
# Solving a case: the continuum (cached) and the network, as esmm validate does


def _key(case) -> str:
    h = hashlib.sha256()
    for a in (case.points, case.tets, case.gravity):
        h.update(np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
    for c in case.constraints:
        h.update(c.name.encode())
        h.update(np.ascontiguousarray(c.nodes).tobytes())
        h.update(np.ascontiguousarray(np.asarray(c.displacement, dtype=np.float64)).tobytes())
    return h.hexdigest()[:16]


def _with_floor(case, solve):
    if case.floor is None:
        return solve(case, None), 0
    return _on_the_floor(case, lambda c, start: solve(c, start), MAX_ROUNDS, REP)


def continuum(case, material, cache: Path):
    """``(Solution, pins)`` of the continuum on *case*: P2, MINI where P2 finds no equilibrium (cached)."""
    f = cache / f"continuum-{case.name}-{_key(case)}.pkl"
    if f.exists():
        return pickle.loads(f.read_bytes())
    bulk = continuum_bulk(material, ratio=DEFAULT_BULK_RATIO)
    t = time.perf_counter()
    for element in ("p2", "mini"):
        def solve(c, start, element=element):
            return solve_continuum(c, material, bulk=bulk, element=element, start=start,
                                   steps=1 if c.floor is not None else 8, reporter=REP)
        try:
            sol, pins = _with_floor(case, solve)
            break
        except Exception as exc:   # noqa: BLE001 - SimulationError: the next element
            if element == "mini":
                raise
            print(f"  {case.name}: P2 found no equilibrium ({exc}); MINI", flush=True)
    sol.state = None
    sol.info["element_used"] = element
    sol.info["seconds_total"] = time.perf_counter() - t
    f.write_bytes(pickle.dumps((sol, pins)))
    return sol, pins


def network(case, net, tables):
    """``(Solution, pins)`` of the network (with its volume term, if it has one) on *case*."""
    terms = () if net.volume_term is None else (volume_elements(net.points, net.tets, net.volume_term),)

    def solve(c, start):
        return solve_network(c, net, tables, terms=terms, start=start, steps=1 if c.floor is not None else 8,
                             reporter=REP)
    return _with_floor(case, solve)


def row(case, fe, pins_c, nw, pins_n) -> dict:
    res = compare(case, fe, nw, pins=max(pins_c, pins_n))
    fig = res.figures()
    return {"l2": res.l2_error, "force": res.force_error, "max_error": res.max_error,
            "volume_change": fig["volume_change_network"],
            "max_local_volume_change": fig["max_local_volume_change_network"],
            "inverted": int(fig["inverted_network"]), "element": fe.info.get("element_used", "p2"),
            "locking_cells": int(fe.info.get("cells_near_locking", 0) or 0),
            "max_displacement_mm": 1e3 * res.max_displacement_m,
            "force_ratio": float(np.linalg.norm(fig["reaction_network_N"]) / np.linalg.norm(fig["reaction_continuum_N"]))
            - 1.0}


# ---------------------------------------------------------------------------------------------
# The organs, the specimen, the scene


def lift_scene(mm: float):
    """The default scene with its last waypoint at *mm* (a scene file with ``base = "default"``)."""
    import tempfile

    text = ('base = "default"\n[grasper]\nwaypoints = [{ time = "0 s", distance = "0 mm" }, '
            f'{{ time = "1 s", distance = "{mm:g} mm" }}]\n')
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as fh:
        fh.write(text)
    try:
        return load_scene(fh.name)
    finally:
        os.unlink(fh.name)


def organ_cases(net) -> dict:
    """validate's gravity and 20 mm lift (the default scene) and the 5 mm lift, on *net*'s nodes."""
    g, l20 = _cases_for(net, ["gravity", "lift"], LoadOptions())
    (l5,) = _cases_for(net, ["lift"], LoadOptions(scene=lift_scene(5.0)))
    return {"gravity": g, "lift20": l20, "lift5": l5}


def stem(organ: str, *, split_parents: int | None) -> str:
    """The file stem of the organ's assets in ``--work``: ``liver`` (paper preset) or ``liver-split1500``,
    so that the two kinds of asset and their variants never overwrite each other."""
    return organ if split_parents is None else f"{organ}-split{split_parents}"


def prepare_command(organ: str, *, split_parents: int | None) -> list[str]:
    """The ``esmm prepare`` arguments (after the mesh) of the organ's base asset: the paper preset, or its
    split of about *split_parents* parents (``--elements N --split``, as ``bench_splits`` prepares them)."""
    args = ["--config", "paper"]
    return args if split_parents is None else [*args, "--elements", str(split_parents), "--split"]


def base_asset(organ: str, work: Path, *, split_parents: int | None = None) -> Path:
    """The organ's base asset (prepared once into *work*): the paper preset, or its split (*split_parents*)."""
    path = work / f"{stem(organ, split_parents=split_parents)}.h5"
    if not path.exists():
        subprocess.run([str(ESMM), "prepare", str(ORGANS[organ]), *prepare_command(organ, split_parents=split_parents),
                        "-o", str(path)], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return path


def run_scene(path: Path, out: Path) -> dict:
    """One ``esmm simulate`` of the default scene on *path*: the summary's speed, the process's CPU time,
    the implicit stepper's counts."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([str(ESMM), "simulate", str(path), "--out", str(out)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    s = json.loads((out / "summary.json").read_text())
    integ = {k: v for k, v in (s.get("integrator") or {}).items() if isinstance(v, int | float)}
    return {"real_time_factor": s["real_time_factor"], "stepping_wall_s": s["stepping_wall_s"],
            "process_cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "integrator": integ, "volume": s.get("volume"), "load_average": os.getloadavg()[0]}


def simulate(net, tables, material, path: Path, runs: int) -> dict:
    """The default scene on the asset of *net* and *tables*, *runs* times: medians and the last run's counts."""
    write_asset(path, net, material=material, tables=tables, xdmf=False)
    rs = [run_scene(path, path.with_suffix(f".sim{k}")) for k in range(runs)]
    return {"real_time_factor": statistics.median(r["real_time_factor"] for r in rs),
            "real_time_factor_runs": [r["real_time_factor"] for r in rs],
            "stepping_wall_s": statistics.median(r["stepping_wall_s"] for r in rs),
            "process_cpu_s": statistics.median(r["process_cpu_s"] for r in rs),
            "integrator": rs[-1]["integrator"], "volume": rs[-1]["volume"], "load_average": rs[-1]["load_average"]}


def variant_asset(organ: str, setting: str, work: Path, *, split_parents: int | None = None) -> Path:
    """The organ's asset with *setting*'s volume term and its tables compensated with it, in *work*: the
    sweep's (written beside its cases), or made here from the base asset where it is missing (the
    compensation's cache makes that quick), so that ``--speed`` needs no network solve."""
    path = work / f"{stem(organ, split_parents=split_parents)}-{setting}.h5"
    if not path.exists():
        asset = read_asset(base_asset(organ, work, split_parents=split_parents))
        net, tables, _ = with_setting(asset.network, raw_tables(asset.tables, asset.material), asset.material, setting)
        write_asset(path, net, material=asset.material, tables=tables, xdmf=False)
    return path


def speed(organ: str, settings, work: Path, rounds: int, *, split_parents: int | None = None) -> dict:
    """The default scene on the variant assets of a sweep (in *work*; the splits' with *split_parents*), the
    settings taken in turn *rounds* times, so that a change of the machine's load falls on all of them alike."""
    runs = {s: [] for s in settings}
    paths = {s: variant_asset(organ, s, work, split_parents=split_parents) for s in settings}
    for k in range(rounds):
        for s in settings:
            runs[s].append(run_scene(paths[s], paths[s].with_suffix(f".speed{k}")))
    out = {}
    for s, rs in runs.items():
        out[s] = {"real_time_factor": statistics.median(r["real_time_factor"] for r in rs),
                  "real_time_factor_runs": [r["real_time_factor"] for r in rs],
                  "process_cpu_s": statistics.median(r["process_cpu_s"] for r in rs),
                  "solves": statistics.median(r["integrator"].get("solves", 0) for r in rs),
                  "factorizations": statistics.median(r["integrator"].get("factorizations", 0) for r in rs),
                  "load_average": [r["load_average"] for r in rs]}
        print(f"speed {organ} {s:6s} real time {out[s]['real_time_factor']:.2f} "
              f"({', '.join(f'{v:.2f}' for v in out[s]['real_time_factor_runs'])}), CPU {out[s]['process_cpu_s']:.2f} s, "
              f"solves {out[s]['solves']:.0f}, factorizations {out[s]['factorizations']:.0f}", flush=True)
    return out


def sweep_organ(organ: str, settings, work: Path, *, sim_runs: int, split_parents: int | None = None) -> dict:
    """Validate's organ cases (and the scene, *sim_runs* times) per setting on the organ's base asset:
    the paper preset, or its split of about *split_parents* parents; each setting's variant written to
    *work* (for ``--speed``)."""
    variants = stem(organ, split_parents=split_parents)
    asset = read_asset(base_asset(organ, work, split_parents=split_parents))
    material = asset.material
    raw = raw_tables(asset.tables, material)
    cases = organ_cases(asset.network)
    qc = asset.network.quadratic_cells
    out = {"asset": "esmm prepare " + ORGANS[organ].name + " " + " ".join(prepare_command(organ, split_parents=split_parents)),
           "parents": None if qc is None else int(qc.shape[0]),
           "nodes": asset.network.n_nodes, "springs": asset.network.n_springs, "tets": asset.network.n_tets,
           "grasp_hold": {n: c.load.get("grasp_hold") for n, c in cases.items() if "grasp_hold" in c.load},
           "asset_bulk_modulus_pa": asset.network.volume_term.bulk_modulus,
           "asset_volume_factor": float(asset.tables.volume_factor), "settings": {}}
    refs = {}
    for name, case in cases.items():
        t = time.perf_counter()
        refs[name] = continuum(case, material, work)
        print(f"{organ} {name}: continuum ({refs[name][0].info.get('element_used')}, "
              f"{time.perf_counter() - t:.0f} s)", flush=True)
    for setting in settings:
        net, tables, spec = with_setting(asset.network, raw, material, setting)
        r = {"bulk_modulus_pa": 0.0 if spec is None else spec.bulk_modulus,
             "kappa_over_mu0": 0.0 if spec is None else spec.bulk_modulus / tangent_shear_modulus(raw, 1.0, 1.0)[0],
             "volume_factor": float(tables.volume_factor), "cases": {}}
        for name, case in cases.items():
            nw, pins = network(case, net, tables)
            r["cases"][name] = row(case, *refs[name], nw, pins)
        if "/" not in setting:    # the variant, for the scene here or for --speed later
            write_asset(work / f"{variants}-{setting}.h5", net, material=material, tables=tables, xdmf=False)
        if sim_runs and "/" not in setting:
            r["simulate"] = simulate(net, tables, material, work / f"{variants}-{setting}.h5", sim_runs)
        out["settings"][setting] = r
        print(line(organ, setting, r), flush=True)
    return out


def sweep_specimen(settings, work: Path) -> dict:
    from esmm.pipeline.materials.material import DEFAULT_MATERIAL, load_material

    material = load_material(DEFAULT_MATERIAL)
    spec0 = cube_specimen(material, volume=False, compensated=False, reporter=REP)
    raw, cases = spec0.tables, _cases_for(spec0.network, list(SPECIMEN_CASES), LoadOptions())
    refs = {c.name: continuum(c, material, work) for c in cases}
    out = {"label": spec0.label, "nodes": spec0.network.n_nodes, "tets": spec0.network.n_tets, "settings": {}}
    for setting in settings:
        net, tables, spec = with_setting(spec0.network, raw, material, setting)
        r = {"bulk_modulus_pa": 0.0 if spec is None else spec.bulk_modulus,
             "volume_factor": float(tables.volume_factor), "cases": {}}
        for case in cases:
            nw, pins = network(case, net, tables)
            r["cases"][case.name] = row(case, *refs[case.name], nw, pins)
        out["settings"][setting] = r
        print(line("specimen", setting, r), flush=True)
    return out


# ---------------------------------------------------------------------------------------------
# Output


#: The figures of a case in the JSON, in this order (one list per case; fractions, counts, mm).
COLUMNS = ("l2", "force", "volume_change", "max_local_volume_change", "inverted", "locking_cells",
           "max_displacement_mm", "max_error", "force_ratio")
SIM_KEYS = ("real_time_factor", "real_time_factor_runs", "stepping_wall_s", "process_cpu_s", "load_average")


def _settings(doc: dict):
    for o in doc.get("organs", {}).values():
        yield from o["settings"].values()
    yield from doc.get("specimen", {}).get("settings", {}).values()


def compact(doc: dict) -> dict:
    """*doc* as written: each case a list in :data:`COLUMNS` order, the scene's run its speed and counts."""
    for r in _settings(doc):
        for n, c in r["cases"].items():
            if isinstance(c, dict):
                if c.get("element", "p2") != "p2":
                    r.setdefault("mini_cases", []).append(n)
                r["cases"][n] = [c[k] for k in COLUMNS]
        sim = r.get("simulate")
        if sim and "integrator" in sim:
            r["simulate"] = {**{k: sim[k] for k in SIM_KEYS if k in sim},
                             **{k: sim["integrator"].get(k) for k in ("solves", "factorizations")}}
    return doc


def expand(doc: dict) -> dict:
    """The inverse of :func:`compact` for the cases (each a dict again)."""
    for r in _settings(doc):
        r["cases"] = {n: dict(zip(COLUMNS, c, strict=False)) if isinstance(c, list) else c
                      for n, c in r["cases"].items()}
    return doc


def line(organ: str, setting: str, r: dict) -> str:
    cells = " | ".join(f"{n} {100 * c['l2']:.2f}/{100 * c['force']:.2f} vol {100 * c['volume_change']:+.3f} "
                       f"inv {c['inverted']}" for n, c in r["cases"].items())
    sim = r.get("simulate")
    rt = "" if not sim else f" | rtf {sim['real_time_factor']:.2f} cpu {sim['process_cpu_s']:.1f} s"
    return f"{organ:8s} {setting:6s} kappa {r['bulk_modulus_pa'] / 1e3:8.1f} kPa c {r['volume_factor']:.3f} | {cells}{rt}"


def _cell(c) -> str:
    return "–" if c is None else f"{100 * c['l2']:.2f} / {100 * c['force']:.2f}"


def _ok(c) -> bool:
    return c["l2"] <= 0.05 and c["force"] <= 0.05


def table(doc: dict) -> str:
    """Two markdown tables: L2 / force [%] per organ case and setting; then per setting the specimen, the
    largest whole-body volume change, inversions, the cases outside 5 %, and the speed."""
    spec = doc.get("specimen", {}).get("settings", {})
    settings = list(dict.fromkeys([*(st for o in doc["organs"].values() for st in o["settings"]), *spec]))
    empty = {"kappa_over_mu0": float("nan"), "volume_factor": float("nan"), "cases": {}}
    organs = {n: {"settings": {st: o["settings"].get(st, empty) for st in settings}}   # a partial sweep: blanks
              for n, o in doc["organs"].items()}
    names = {"gravity": "gravity", "lift20": "lift 20 mm", "lift5": "lift 5 mm"}
    head = ["setting", "kappa / mu0"] + [f"{o}: {n}" if i == 0 else n for o in organs
                                          for i, n in enumerate(names.values())]
    out = ["| " + " | ".join(head) + " |", "| --- " * len(head) + "|"]
    for st in settings if organs else ():      # the specimen alone: its table only
        r0 = next(iter(organs.values()))["settings"][st]
        out.append(f"| {st} | {r0['kappa_over_mu0']:.3g} | " + " | ".join(
            _cell(o["settings"][st]["cases"].get(n)) for o in organs.values() for n in names) + " |")
    speed = doc.get("speed", {}).get("organs", {})
    head = ["setting", "c", "tension", "compression", "shear", "volume change, organs / specimen",
            "inverted", "cases outside 5 %", "real time (" + ", ".join(speed) + ")",
            "solves / factorizations, " + next(iter(organs), "")]
    out += ["", "| " + " | ".join(head) + " |", "| --- " * len(head) + "|"]
    for st in settings:
        org = [c for o in organs.values() for c in o["settings"][st]["cases"].values()]
        sp = list(spec.get(st, {}).get("cases", {}).values())
        vo = max((abs(c["volume_change"]) for c in org), default=float("nan"))
        vs = max((abs(c["volume_change"]) for c in sp), default=float("nan"))
        bad = sum(not _ok(c) for c in org + sp)
        rt = ", ".join(f"{speed[o][st]['real_time_factor']:.2f}" for o in speed if st in speed[o]) or "–"
        sim = next(iter(organs.values()))["settings"][st].get("simulate", {}) if organs else {}
        sf = sim.get("integrator", sim)
        if speed:
            first = next(iter(speed.values()))
            sf = {"solves": first[st]["solves"], "factorizations": first[st]["factorizations"]} if st in first else sf
        sc = spec.get(st, {}).get("cases", {})
        vf = next(iter(organs.values()))["settings"][st]["volume_factor"] if organs else spec.get(st, empty)["volume_factor"]
        out.append(f"| {st} | {vf:.3f} | " + " | ".join(_cell(sc.get(n)) for n in SPECIMEN_CASES)
                   + f" | {100 * vo:.2f} / {100 * vs:.2f} % | {sum(c['inverted'] for c in org + sp)} | "
                   f"{bad} of {len(org) + len(sp)} | {rt} | "
                   + (f"{sf['solves']:.0f} / {sf['factorizations']:.0f} |" if "solves" in sf else "– |"))
    return "\n".join(out)


def merge(parts, *, settings) -> dict:
    """One document of several sweeps' JSONs *parts* (the organs run as separate processes, the settings in
    phases, the specimen apart): their organs' settings, the specimen's and the speed's joined, in the order
    of *settings*; every part must have swept the same assets (``--split-parents``)."""
    docs = [expand(json.loads(Path(p).read_text())) for p in parts]
    split = {d.get("assets", {}).get("split_parents") for d in docs}
    if len(split) != 1:
        raise SystemExit(f"--merge: the parts swept different assets (split_parents {sorted(split, key=str)})")
    out = {**{k: v for k, v in docs[0].items() if k not in ("organs", "specimen", "speed", "command")},
           "commands": list(dict.fromkeys(c for d in docs for c in [*d.get("commands", [d.get("command")]),
                                                                   d.get("speed", {}).get("command")] if c)),
           "merged_from": [str(p) for p in parts], "organs": {}}
    order = {st: k for k, st in enumerate(settings)}

    def join(into: dict, part: dict) -> dict:
        keep = {k: v for k, v in part.items() if k != "settings"}
        into.update(keep)
        both = {**into.get("settings", {}), **part["settings"]}
        into["settings"] = dict(sorted(both.items(), key=lambda kv: order.get(kv[0], len(order))))
        return into
    for d in docs:
        for organ, o in d.get("organs", {}).items():
            out["organs"][organ] = join(out["organs"].get(organ, {}), o)
        if "specimen" in d:
            out["specimen"] = join(out.get("specimen", {}), d["specimen"])
        if "speed" in d:      # each organ's settings were alternated within one run: never mixed across runs
            out.setdefault("speed", {"rounds": d["speed"]["rounds"], "organs": {}})["organs"].update(d["speed"]["organs"])
    return out


def write_doc(doc: dict, path) -> None:
    """*doc* written compact to *path*, *doc* itself left expanded (it is written again as it grows)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(compact(json.loads(json.dumps(doc))), indent=1) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--organs", nargs="*", default=list(ORGANS), choices=list(ORGANS))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS))
    ap.add_argument("--no-specimen", action="store_true")
    ap.add_argument("--no-simulate", action="store_true")
    ap.add_argument("--sim-runs", type=int, default=3, help="default-scene runs per setting (median)")
    ap.add_argument("--work", default=str(Path(os.environ.get("TMPDIR", "/tmp")) / "esmm-volume-kappa"),
                    help="base assets, variant assets and the continuum cache")
    ap.add_argument("--json", default=str(OUT))
    ap.add_argument("--table", metavar="JSON", help="print the table of a written run and stop")
    ap.add_argument("--speed", type=int, metavar="ROUNDS", default=0,
                    help="after a sweep (its assets in --work, its JSON at --json): the default scene on each "
                         "organ's variants in turn, ROUNDS times, added to the JSON under 'speed'; no sweep")
    ap.add_argument("--merge", nargs="+", metavar="JSON",
                    help="join the JSONs of sweeps run apart (same assets) into --json, in --settings order; no sweep")
    ap.add_argument("--split-parents", type=int, metavar="N",
                    help="the organs as split assets (esmm prepare MESH --config paper --elements N --split, "
                         "as bench_splits prepares them) instead of the paper preset; the specimen is unchanged")
    args = ap.parse_args(argv)
    if args.table:
        print(table(expand(json.loads(Path(args.table).read_text()))))
        return 0
    if args.merge:
        doc = merge(args.merge, settings=args.settings)
        write_doc(doc, args.json)
        print(table(expand(doc)))
        return 0
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.speed:
        doc = expand(json.loads(Path(args.json).read_text()))
        if doc.get("assets", {}).get("split_parents") != args.split_parents:
            raise SystemExit(f"--speed: {args.json} was swept with split_parents "
                             f"{doc.get('assets', {}).get('split_parents')}, not {args.split_parents}")
        runnable = [st for st in args.settings if "/" not in st]
        doc["speed"] = {"rounds": args.speed, "command": "python scripts/volume_kappa.py " + " ".join(
                            argv if argv is not None else sys.argv[1:]), "load_average_at_start": os.getloadavg(),
                        "organs": {o: speed(o, runnable, work, args.speed, split_parents=args.split_parents)
                                   for o in args.organs}}
        write_doc(doc, args.json)
        print(table(doc))
        return 0
    doc = {"command": "python scripts/volume_kappa.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "settings": {"tNU": "kappa = 2(1+NU)/(3(1-2NU)) * the material's largest tangent shear modulus "
                                "over the calibration range (esmm prepare's rule; t0.45 the default)",
                        "sNU": "kappa = 2(1+NU)/(3(1-2NU)) * the small-strain shear modulus mu0",
                        "off": "no volume term, the tables compensated without one",
                        "A/B": "the volume term of A on the tables compensated for the term of B (a diagnosis: "
                               "esmm prepare compensates for the term the asset carries)"},
           "columns": list(COLUMNS),
           "cases": "validate's gravity and lift (20 mm, the default scene) and a 5 mm lift (the default scene, "
                    "last waypoint at 5 mm); the specimen's tension 1.2, compression 0.9, shear 0.3 "
                    "(20 mm cube, 2.5 mm elements); L2 and force errors against P2 (MINI where P2 found "
                    "no equilibrium: 'element'); volume_change: the network's whole-body volume ratio - 1; force_ratio: |R_network| / "
                    "|R_continuum| - 1 of the case's reaction (positive: the network's is larger)",
           "assets": {"split_parents": args.split_parents,
                      "organs": "paper preset (esmm prepare MESH --config paper)" if args.split_parents is None else
                      f"split assets (esmm prepare MESH --config paper --elements {args.split_parents} --split: every "
                      "parent tet split in eight; the continuum P2 on the parents, node for node)",
                      "specimen": "the 20 mm cube at 2.5 mm elements (unsplit), as esmm validate --specimen"},
           "load_average_at_start": os.getloadavg(), "organs": {}}
    if not args.no_specimen:
        doc["specimen"] = sweep_specimen(args.settings, work)
    for organ in args.organs:
        doc["organs"][organ] = sweep_organ(organ, args.settings, work, sim_runs=0 if args.no_simulate else args.sim_runs,
                                           split_parents=args.split_parents)
        write_doc(doc, args.json)       # after every organ: a long sweep's finished organs kept
    write_doc(doc, args.json)           # (and the specimen's, where no organ is swept)
    print(table(expand(doc)))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
