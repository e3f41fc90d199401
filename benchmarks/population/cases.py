"""A case: one folder of 1-6 files of one material, and its truth.json.

``make_case`` draws a material family, a test shape and protocol, a base law, the effect of the
case (none for a clean case), the specimens and the machine, simulates every file on the
converter's fine grid, records it through the acquisition chain and writes it in one export
format. Everything comes from one seed, so a case is reproduced bit for bit.

A clean case is the base law alone (no history effect, no artefact): the machine's acquisition
chain (filters, converter, noise, encoder) is still there, as in every real record, and its
parameters are in truth.json. A failure test ruptures in clean cases too: the force falls to the
residual of broken fibres and then to the tared zero.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import effects as E
from .acquisition import record_force, record_position
from .draws import (
    FAMILIES,
    SHAPES,
    draw_law,
    draw_range,
    draw_specimen,
    loguniform,
    pick,
    replicate,
)
from .exports import allowed, measured_area, measured_length, write
from .machine import draw_levels, draw_timing
from .protocols import KINDS, Protocol, build, command, motion
from .relaxation import Prony, hereditary

GENERATOR_VERSION = "2.9"  # records bit for bit as "2"; truth.json adds the effect's detectability (2.1) and
#                             its identifiability (2.2; 2.3 in stress, one function for specimens of other areas);
#                             2.4: a slack is drawn on replicates too, each specimen with its own mounting's slack;
#                             2.5 (records as 2.4): a slack's d_id against the case's own slacked curve;
#                             2.6 (records as 2.4): d_id against the neighbouring class (NEIGHBOURS) too;
#                             2.7 (records as 2.4): a Mullins softening's d_id against damage too;
#                             2.8 (records as 2.4): a relaxation's d_id over the files written with time only;
#                             2.9 (records as 2.4): a damage's d_id against a Mullins softening too
MAX_DURATION, MIN_DURATION = 6000.0, 15.0


def _choose(rng, cls: str, kind: str | None) -> tuple[str, str, str]:
    """(family, shape, protocol kind) of a case."""
    if cls == "clean":
        family = pick(rng, {f: 1.0 for f in FAMILIES})
        shapes = dict(FAMILIES[family]["shapes"])
        if kind == "failure":
            shapes = {"tension": 1.0}
        return family, pick(rng, shapes), kind
    kinds, shapes = E.PLAN[cls]
    shape = pick(rng, shapes)
    family = pick(rng, {f: 1.0 for f, v in FAMILIES.items() if shape in v["shapes"]})
    if kind is not None:  # a protocol asked for (a population draws it: :func:`plan` asks for clean cases only)
        if kind not in kinds:
            raise ValueError(f"protocol {kind!r} is not drawn for {cls}: use one of {', '.join(kinds)}")
        return family, shape, kind
    return family, shape, pick(rng, kinds)


def _protocol(rng, kind: str, x0: float, hi: float, lo, rate: float, gauge: float) -> Protocol:
    """Build the protocol at a crosshead speed of 0.05-1000 mm/min and 15-6000 s per file."""
    speed = rate * gauge * 6e4  # mm/min
    rate *= float(np.clip(speed, 0.05, 1000.0) / speed)
    for _ in range(8):
        state = rng.bit_generator.state
        p = build(kind, rng, x0=x0, hi=hi, lo=lo, rate=rate)
        longest = max(p.duration(k) for k in range(len(p.files)))
        shortest = min(p.duration(k) for k in range(len(p.files)))
        if longest > MAX_DURATION:
            rate *= longest / (0.8 * MAX_DURATION)
        elif shortest < MIN_DURATION and longest < MAX_DURATION / 4:
            rate *= shortest / (1.5 * MIN_DURATION)
        else:
            return p
        rng.bit_generator.state = state
    return p


def _times(p: Protocol) -> tuple[float, float]:
    """(shortest moving segment, longest hold or else longest file) [s]."""
    holds = [t1 - t0 for wp in p.files for (t0, x0), (t1, x1) in zip(wp[:-1], wp[1:]) if x1 == x0]
    longest_file = max(p.duration(k) for k in range(len(p.files)))
    long_hold = max(holds) if holds else 0.0
    return p.shortest_segment(), long_hold if long_hold > 0.1 * longest_file else longest_file


def _rupture(rng, kind: str, p: Protocol) -> dict | None:
    if kind != "failure":
        return None
    return {"x": p.info["rupture_x"], "fall_s": loguniform(rng, 0.002, 0.03),
            "residual_of_peak": float(rng.uniform(0.0, 0.05)), "residual_tau_s": loguniform(rng, 0.05, 0.5)}


def _survival(t: np.ndarray, x: np.ndarray, r: dict) -> tuple[np.ndarray, np.ndarray]:
    """(factor on the stress, residual fraction of the peak stress) after a rupture at x = r['x']."""
    hit = np.flatnonzero(x >= r["x"])
    if hit.size == 0:
        return np.ones_like(t), np.zeros_like(t)
    tr = t[hit[0]]
    s = np.clip(1.0 - (t - tr) / r["fall_s"], 0.0, 1.0)
    after = t > tr
    res = np.where(after, r["residual_of_peak"] * np.exp(-np.maximum(t - tr, 0.0) / r["residual_tau_s"]), 0.0)
    res = res * (1.0 - s)
    return s, res


def _true_force(rng, wp, ch, el: E.Elastic, spec: dict, x0: float, cls: str, prm: dict, rup: dict | None,
                mounting: float = 1.0) -> dict:
    """The true force [N] (and the effect-free reference) on the fine grid of one file; a slack's is the
    case's ``delta`` times the specimen's *mounting* factor, and ``common`` the law at the case's slack
    (the function of the stretch that the specimens' curves share, :func:`_detectability`)."""
    fs = ch.fs
    n = int(np.ceil(wp[-1][0] * fs / ch.ratio)) * ch.ratio
    x = motion(command(wp, fs, n), fs, accel_s=ch.accel_s, ripple=ch.velocity_ripple, ripple_hz=ch.ripple_Hz,
               noise=ch.velocity_noise, rng=rng)
    t = np.arange(n) / fs
    xs, slips = (E.slipped(prm, el, x, t) if cls == "grip_slip" else (x, []))
    cap = (lambda v: np.minimum(v, rup["x"])) if rup else (lambda v: v)
    common = shared = None
    if cls == "slack":
        p = E.slack_stress({**prm, "delta": prm["delta"] * mounting}, el, cap(xs))
        ref = el.stress(cap(x / (1.0 + prm["delta"] * mounting)))
        common = el.stress(cap(x / (1.0 + prm["delta"])))
        shared = E.slack_stress(prm, el, cap(xs))
    else:
        p = E.material_stress(cls, prm, el, cap(xs), 1.0 / fs)
        ref = el.stress(cap(x))
    if rup:
        s, res = _survival(t, x, rup)
        p = p * s + res * np.max(p)
        ref = ref * s + res * np.max(ref)
        common = None if common is None else common * s + res * np.max(common)
        shared = None if shared is None else shared * s + res * np.max(shared)
    area = spec["area"]
    return {"t": t, "x": x, "force": p * area, "ref": ref * area, "slips_s": slips, "n": n,
            "common": ref * area if common is None else common * area,
            "shared": p * area if shared is None else shared * area,
            **({"energy": el.energy(cap(xs))} if NEIGHBOURS.get(cls) in ("damage", "mullins") else {})}


def _stated(spec: dict, error: float) -> tuple[dict, float]:
    """The geometry the lab writes (its chosen keys, as measured: :func:`measured_length`) and the
    area it gives; a misstated cross-section (``error``) goes into the thickness, the diameter or
    the area."""
    how, f = spec["stated"], 1.0 + error
    if how == "diameter":
        d = measured_length(spec["diameter"] * np.sqrt(f))
        return {"diameter": d}, np.pi * d * d / 4
    if how == "width x thickness":
        w, th = measured_length(spec["width"]), measured_length(spec["thickness"] * f)
        return {"width": w, "thickness": th}, w * th
    a = measured_area(spec["area"] * f)
    return {"area": a}, a


def _plain(v):
    """JSON for numpy values."""
    if isinstance(v, dict):
        return {str(k): _plain(u) for k, u in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(u) for u in v]
    if isinstance(v, np.ndarray):
        return [_plain(u) for u in v.tolist()]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _scale_errors(rng, cls: str, m: int) -> list[float]:
    if cls != "specimen_scale":
        return [0.0] * m
    wrong = rng.permutation(m)[: int(rng.integers(1, m))]
    return [float(rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) if k in wrong else 0.0 for k in range(m)]


def _draw_material(rng, cls: str, family: str, shape: str, kind: str):
    """Mode, reference, peak(s), the base law and the slack (drawn first: the crosshead then goes
    further, ``hi (1 + delta)``, so that the specimen still reaches the peak). Replicates are mounted
    one by one, each with its own slack: the case's ``delta`` times a factor of 0.5-1.5 per specimen
    (``mounting``); the files of one specimen share its mounting."""
    mode, x0 = SHAPES[shape]
    hi, lo = draw_range(rng, family, shape)
    if kind not in ("cycles", "rising", "multirate", "replicates"):
        lo = None
    pre = E.draw_artefact("slack", rng, hi - x0) if cls == "slack" else {}
    if pre and kind == "replicates":
        pre["mounting"] = rng.uniform(0.5, 1.5, 3).tolist()
    top = hi * (1.0 + pre["delta"] * max(pre.get("mounting", [1.0]))) if pre else hi
    lo_all, hi_all = min(x0, top, lo if lo is not None else x0), max(x0, top, lo if lo is not None else x0)
    law = draw_law(rng, family, mode, x0, lo_all, hi_all)
    return mode, x0, hi, lo, law, pre, (lo_all, hi_all)


def make_case(seq: np.random.SeedSequence, cls: str, folder: Path, *, kind: str | None = None) -> dict:
    """Draw, simulate, record and write one case into ``folder``; returns its truth."""
    rng = np.random.default_rng(seq)
    family, shape, kind = _choose(rng, cls, kind)
    mode, x0, hi, lo, law, pre, (lo_all, hi_all) = _draw_material(rng, cls, family, shape, kind)
    hi_cmd = hi * (1.0 + pre["delta"] * max(pre.get("mounting", [1.0]))) if cls == "slack" else hi
    specs = [draw_specimen(rng, family, shape)]
    proto = _protocol(rng, kind, x0, hi_cmd, lo, loguniform(rng, *FAMILIES[family]["rate"]), specs[0]["gauge_length"])
    specs += [replicate(rng, specs[0]) for _ in range(1, len(proto.files) if kind == "replicates" else 1)]
    el = E.Elastic(law, mode, lo_all, hi_all)
    t_move, t_long = _times(proto)
    prm = pre or (E.draw(cls, rng, E.Ctx(el, x0, hi, t_move, t_long)) if cls != "clean" else {})
    rup = _rupture(rng, kind, proto)
    chains = draw_timing(rng, [proto.duration(k) for k in range(len(proto.files))], t_move)
    spec_of = [specs[k] if kind == "replicates" else specs[0] for k in range(len(proto.files))]
    mounting = [prm.get("mounting", [1.0] * 3)[k] if kind == "replicates" else 1.0 for k in range(len(proto.files))]
    sims = [_true_force(rng, wp, ch, el, sp, x0, cls, prm, rup, m)
            for wp, ch, sp, m in zip(proto.files, chains, spec_of, mounting)]
    peak = max(float(np.max(np.abs(s["force"]))) for s in sims)
    chains = draw_levels(rng, chains, peak)
    errors = _scale_errors(rng, cls, len(specs))
    if cls == "specimen_scale":
        prm["errors"] = errors
    fmt = pick(rng, allowed(mode))
    folder.mkdir(parents=True, exist_ok=True)
    ks = [k if kind == "replicates" else 0 for k in range(len(sims))]
    files = [_record_file(rng, folder, k, s, ch, sp, ks[k], errors[ks[k]], fmt, mode, x0, family, proto, cls,
                          prm, peak) for k, (s, ch, sp) in enumerate(zip(sims, chains, spec_of))]
    size = _effect_size(cls, prm, sims, peak)
    detect, ident, beside = _detectability(seq, cls, prm, sims, chains, peak, [errors[k] for k in ks], x0,
                                           [sp["area"] for sp in spec_of], times=(t_move, t_long),
                                           timed=[f["export"].get("time", True) for f in files])
    truth = {"schema": "population-case/1", "generator_version": GENERATOR_VERSION, "case": folder.name,
             "seed": {"entropy": seq.entropy, "spawn_key": list(seq.spawn_key)}, "class": cls,
             "effect": None if cls == "clean" else {"name": cls, **prm, "size": size, "detectability": detect,
                                                     "identifiability": ident, **beside},
             "family": family, "shape": shape, "mode": mode, "base_law": law.describe(),
             "protocol": {"kind": kind, **proto.info, "shortest_segment_s": t_move, "longest_hold_s": t_long},
             "rupture": rup, "format": fmt,
             "specimens": specs, "files": files}
    truth = _plain(truth)
    (folder / "truth.json").write_text(json.dumps(truth, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return truth


def _effect_size(cls: str, prm: dict, sims: list[dict], peak: float) -> float | None:
    """How large the effect is in the true signals: the RMS change of the force it makes, over the
    force range (offset: the RMS offset; specimen scale: the largest area error)."""
    if cls == "clean":
        return None
    if cls == "specimen_scale":
        return float(max(abs(e) for e in prm["errors"]))
    ref = np.concatenate([s["ref"] for s in sims])
    span = float(np.ptp(ref)) or 1.0
    if cls == "sensor_offset":
        off = np.concatenate([E.offset_force(prm, s["t"], peak) for s in sims])
        return float(np.sqrt(np.mean(off ** 2)) / span)
    f = np.concatenate([s["force"] for s in sims])
    return float(np.sqrt(np.mean((f - ref) ** 2)) / span)


def _detectability(seq, cls: str, prm: dict, sims: list[dict], chains: list, peak: float,
                   errors: list[float], x0: float, areas: list[float], *,
                   times: tuple[float, float], timed: list[bool]) -> tuple[float | None, float | None, dict]:
    """How far the effect stands out of the acquisition noise in the recorded force, (d, d_id, beside).

    **d** is the signal-to-noise ratio of the best test there is for the effect (the effect known
    exactly, its absence the alternative),

        d = sqrt( sum_files sum_i Delta_i^2 / (sigma^2 tau) ),

    with ``Delta`` the recorded (noise-free) force with the effect minus without it, ``sigma`` the
    standard deviation of the recorded acquisition error (noise, hum, quantization) and ``tau`` its
    integrated autocorrelation time in samples (:func:`integrated_time`), so that filtered, correlated
    noise counts as the fewer independent samples it is. An effect with d below 2-3 cannot be told
    from the noise by any method, whatever its size over the force range.

    **d_id** is the same ratio for the part of the record that no elastic law can take: ``Delta``
    minus its weighted least-squares fit by a smooth function of the stretch alone that vanishes at
    the reference stretch (a cubic spline of :data:`IDENTIFY_INTERVALS` intervals over the case's
    stretch range, less its value at the reference; one function of the stress shared by every file
    of the case, the material being one, each file's force its specimen's area times it; each basis
    function put through the force channel's filters and
    decimation as a force would be, so that their delay is not read as a path dependence). For a
    slack, ``Delta`` is taken against the case's own slacked curve (the specimen taut fibre by fibre),
    itself such a function: a slack in one mounting is nothing an elastic law cannot take, sharp or
    smooth (d_id 0; generator 2.4 and earlier took it against the sharp slack, so a smooth pick-up's
    curvature counted as identifiable), and replicates' own slacks differ around it, which no one
    function takes. A relaxation on one monotone ramp, a slack,
    a gradual slip or a drift during one ramp is such a function (d_id near 0 however large d is): a
    record of that protocol cannot tell the effect from another elastic law, by any method that does
    not know the law. What remains is what the protocol makes identifiable: a hold, an unloading, a
    second rate, a reading at rest, a second specimen, and features sharper than the spline's
    intervals (a sudden slip: no smooth law drops while it is stretched).

    **beside** holds, for a class with a neighbour (:data:`NEIGHBOURS`), ``identifiability_from``:
    {neighbour: d_id against it}, the same ratio for what neither an elastic law nor the neighbour
    takes (:func:`_relaxation_atoms`, :func:`_damage_atoms`, :func:`_mullins_atoms`). A stretch-dependent
    relaxation whose change with the stretch stays below the noise is a plain relaxation to any method, a
    Mullins softening that scales the primary loading too (Miehe's discontinuous damage) is a damage, and a
    damage whose primary loading an elastic law takes, seen only where the reloadings fall below the
    largest energy, is a Mullins softening; d_id alone counts them identifiable.

    A relaxation (:data:`RATE_CLASSES`) is a change in time, which a file written without its time
    column (*timed* False) cannot show: d_id and the neighbour's ratio count the files with time only.

    The noise is a fresh realization from the case's seed (spawn key extended), so the case's own
    files are unchanged. (*times*: the protocol's shortest moving segment and longest hold or file.)
    """
    if cls == "clean":
        return None, None, {}
    rng = np.random.default_rng(np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, 2 ** 30)))
    lo, hi = min(x0, *(float(np.min(s["x"])) for s in sims)), max(x0, *(float(np.max(s["x"])) for s in sims))
    d2 = 0.0
    parts, atoms = [], []
    for s, ch, err, area, with_time in zip(sims, chains, errors, areas, timed):
        force = s["force"] + (E.offset_force(prm, s["t"], peak) if cls == "sensor_offset" else 0.0)
        rec = record_force(force, ch, None)
        delta = rec * err if cls == "specimen_scale" else rec - record_force(s["common"], ch, None)
        noise = record_force(force, ch, rng) - rec
        var = float(np.var(noise))
        if var <= 0.0:
            continue
        w = 1.0 / (var * integrated_time(noise))
        d2 += float(np.sum(delta ** 2)) * w
        if cls in RATE_CLASSES and not with_time:
            continue
        if cls == "slack":  # against the case's own slacked curve: a function of the stretch the files share
            delta = rec - record_force(s["shared"], ch, None)
        parts.append((delta / area, _elastic_basis(s["x"], x0, lo, hi, ch), w * area ** 2))  # in stress
        if cls in NEIGHBOURS:
            atoms.append(NEIGHBOUR_ATOMS[NEIGHBOURS[cls]](s, ch, area, times))
    if not parts:
        return float(np.sqrt(d2)), 0.0, {}
    beside = {}
    if atoms:
        extended = [(y, np.hstack([b, a]), w) for (y, b, w), a in zip(parts, atoms)]
        d_nb = float(np.sqrt(_not_elastic(extended, signed=parts[0][1].shape[1])))
        beside = {"identifiability_from": {NEIGHBOURS[cls]: d_nb}}
    return float(np.sqrt(d2)), float(np.sqrt(_not_elastic(parts))), beside


#: cubic B-spline intervals over a case's stretch range for the elastic functions of :func:`_not_elastic`
IDENTIFY_INTERVALS = 24


def _elastic_basis(x: np.ndarray, x0: float, lo: float, hi: float, ch) -> np.ndarray:
    """The recorded force of each elastic basis function of the stretch history *x* (fine grid), shape
    (recorded samples, functions): cubic B-splines of :data:`IDENTIFY_INTERVALS` intervals over [lo, hi],
    less their value at the reference *x0* (every function vanishes there), each put through the force
    channel's filters and decimation as a force would be."""
    from scipy.interpolate import BSpline

    k = 3
    if hi - lo <= 0.0:
        return np.zeros((record_force(x, ch, None).size, 0))
    knots = np.concatenate([[lo] * k, np.linspace(lo, hi, IDENTIFY_INTERVALS + 1), [hi] * k])
    fine = BSpline.design_matrix(np.clip(x, lo, hi), knots, k).tocsc()
    at0 = BSpline.design_matrix(np.array([x0]), knots, k).toarray()[0]
    return np.stack([record_force(fine[:, j].toarray().ravel() - at0[j], ch, None)
                     for j in range(fine.shape[1])], axis=1)


def _not_elastic(parts: list, *, signed: int | None = None) -> float:
    """sum_i w_i r_i^2 of the residual r of the files' changes after the weighted least-squares fit of
    one elastic function shared by all files; *parts*: (change, recorded basis, weight) per file
    (:func:`_detectability`). With *signed*, only the first *signed* columns take either sign, the
    others (a neighbour's relaxation strengths) are non-negative."""
    y = np.concatenate([p[0] for p in parts])
    basis = np.concatenate([p[1] for p in parts])
    w = np.concatenate([np.full(p[0].size, p[2]) for p in parts])
    if basis.shape[1] == 0:
        return float(np.sum(w * y ** 2))
    sw = np.sqrt(w)
    if signed is None or signed >= basis.shape[1]:
        coef, *_ = np.linalg.lstsq(basis * sw[:, None], y * sw, rcond=None)
    else:
        from scipy.optimize import lsq_linear

        a = basis * sw[:, None]
        norm = np.linalg.norm(a, axis=0)
        norm[norm == 0.0] = 1.0  # columns of unit length: the atoms' scales span many decades
        lo = np.r_[np.full(signed, -np.inf), np.zeros(basis.shape[1] - signed)]
        coef = lsq_linear(a / norm, y * sw, bounds=(lo, np.inf), method="bvls").x / norm
    r = y - basis @ coef
    return float(np.sum(w * r ** 2))


#: the class a generated effect is nearest to in the vocabulary of a fitter, when it can look like it:
#: a stretch-dependent relaxation whose dependence is small is a plain relaxation, a load cell's
#: drift over a record's holds is a slow relaxation, and a Mullins softening that scales the primary
#: loading as well as the reloadings (a discontinuous damage in the largest energy) is a damage, and a
#: damage whose reloadings below the largest energy carry most of its change is a Mullins softening
NEIGHBOURS = {"nonlinear_viscoelastic": "viscoelastic", "sensor_offset": "viscoelastic", "mullins": "damage",
              "damage": "mullins"}
#: the classes whose effect is a change in time, which a file without its time column cannot show
RATE_CLASSES = ("viscoelastic", "nonlinear_viscoelastic")
#: relaxation times of the neighbour's atoms: this many, log-spaced from a tenth of the protocol's shortest
#: moving segment to five times its longest hold or file
RELAX_TIMES = 24


def _relaxation_atoms(sim: dict, ch, area: float, times: tuple[float, float]) -> np.ndarray:
    """The recorded stress of one unit Prony term per relaxation time (quasi-linear viscoelasticity of
    the file's elastic force, :func:`.relaxation.hereditary`), less the elastic stress, shape (recorded
    samples, :data:`RELAX_TIMES`): a plain relaxation of strengths g_j >= 0 is ``sum_j g_j atom_j``."""
    t_move, t_long = times
    t = sim["t"]
    dt = float(t[1] - t[0]) if t.size > 1 else 1.0
    pe = sim["common"]
    taus = np.geomspace(0.1 * t_move, 5.0 * max(t_long, float(t[-1])), RELAX_TIMES)
    return np.stack([record_force(hereditary(Prony([1.0], [tau]), dt, pe) - pe, ch, None) / area
                     for tau in taus], axis=1)


#: knots of the neighbour's damage function, equally spaced in sqrt(2 W_max) from 0 to its largest value
DAMAGE_KNOTS = 24


def _damage_atoms(sim: dict, ch, area: float, times=None) -> np.ndarray:
    """The recorded stress of the elastic stress times each ramp of a damage function, negated, shape
    (recorded samples, :data:`DAMAGE_KNOTS`): a damage, the stress ``g(xi) P_e`` with ``g`` any
    non-increasing function from 1 of ``xi = sqrt(2 max_past W)`` (Simo 1987; Miehe's 1995 discontinuous
    damage is one), piecewise linear on the knots, is ``P_e + sum_j c_j atom_j`` with ``c_j >= 0``
    (``g = 1 - sum_j c_j h_j``, ``h_j`` rising from 0 to 1 between knots j and j + 1). *sim* carries the
    elastic energy along the path (:func:`_true_force` keeps it where the neighbour is damage)."""
    pe = sim["common"]
    xi = np.maximum.accumulate(np.sqrt(2.0 * np.maximum(sim["energy"], 0.0)))
    edges = np.linspace(0.0, max(float(xi[-1]), 1e-300), DAMAGE_KNOTS + 1)
    ramps = np.clip((xi[:, None] - edges[:-1]) / np.diff(edges), 0.0, 1.0)
    return np.stack([record_force(-pe * ramps[:, j], ch, None) / area for j in range(DAMAGE_KNOTS)], axis=1)


#: knots of the Mullins neighbour's softening function, equally spaced in sqrt(2 (W_max - W)) from 0 to its
#: largest value
MULLINS_KNOTS = 24


def _mullins_atoms(sim: dict, ch, area: float, times=None) -> np.ndarray:
    """The recorded stress of the elastic stress times each ramp of a softening function, negated, shape
    (recorded samples, :data:`MULLINS_KNOTS`): a Mullins softening, the stress ``(1 - f(u)) P_e`` with ``f``
    any non-decreasing function from 0 of ``u = sqrt(2 (max_past W - W))`` (Ogden & Roxburgh 1999 with
    beta = 0, ``f = erf(u^2 / 2m) / r``, is one; the primary loading, where ``W = max_past W``, is
    elastic), piecewise linear on the knots, is ``P_e + sum_j c_j atom_j`` with ``c_j >= 0``. Beta > 0
    makes ``f`` depend on the largest energy too, which this family does not hold: against a Mullins
    softening with beta, the ratio counts more as identifiable than it is."""
    pe = sim["common"]
    w = np.maximum(sim["energy"], 0.0)
    u = np.sqrt(2.0 * np.maximum(np.maximum.accumulate(w) - w, 0.0))
    edges = np.linspace(0.0, max(float(np.max(u)), 1e-300), MULLINS_KNOTS + 1)
    ramps = np.clip((u[:, None] - edges[:-1]) / np.diff(edges), 0.0, 1.0)
    return np.stack([record_force(-pe * ramps[:, j], ch, None) / area for j in range(MULLINS_KNOTS)], axis=1)


#: the atoms of each neighbouring class (:data:`NEIGHBOURS`), by its name
NEIGHBOUR_ATOMS = {"viscoelastic": _relaxation_atoms, "damage": _damage_atoms, "mullins": _mullins_atoms}


def integrated_time(v: np.ndarray, c: float = 5.0) -> float:
    """Integrated autocorrelation time of a series in samples, ``1 + 2 sum_k rho_k``, summed up to the
    smallest window ``M >= c tau(M)`` (Sokal 1997, "Monte Carlo methods in statistical mechanics",
    automatic windowing); 1 for white noise."""
    v = np.asarray(v, dtype=float) - float(np.mean(v))
    n = v.size
    f = np.fft.rfft(v, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    if acf[0] <= 0.0:
        return 1.0
    tau = 2.0 * np.cumsum(acf / acf[0]) - 1.0
    ok = np.arange(n) >= c * tau
    m = int(np.argmax(ok)) if ok.any() else n - 1
    return float(max(tau[m], 1.0))


def _record_file(rng, folder: Path, k: int, sim: dict, ch, spec: dict, ks: int, error: float, fmt: str, mode: str,
                 x0: float, family: str, proto: Protocol, cls: str, prm: dict, peak: float) -> dict:
    """Record one file through the chain and write it; returns its part of truth.json."""
    force = sim["force"] + (E.offset_force(prm, sim["t"], peak) if cls == "sensor_offset" else 0.0)
    gauge = spec["gauge_length"]
    pos = (sim["x"] - x0) * gauge
    f_out = record_force(force, ch, rng)
    f_clean = record_force(force, ch, None)
    d_out = record_position(pos, ch)
    t_out = sim["t"][ch.ratio - 1:: ch.ratio] - sim["t"][ch.ratio - 1]  # the controller's clock starts at 0
    t_start = float(np.round(rng.uniform(0.0, 30.0), 2)) if rng.uniform() < 0.3 else 0.0
    stated, area_stated = _stated(spec, error)
    name = f"{folder.name}_s{ks + 1}_{k + 1}" if proto.kind == "replicates" else f"{folder.name}_{k + 1}"
    gauge_stated = measured_length(gauge)
    lsb = ch.span_N / 2.0 ** ch.bits
    rec = {"time_s": t_out + t_start, "disp_m": d_out, "force_N": f_out, "mode": mode,
           "specimen": f"{folder.name}-{ks + 1}", "gauge_length": gauge_stated, "stated": stated,
           "area_stated_m2": area_stated, "tissue": family.replace("_", " "),
           "notes": f"{proto.kind} test", "time_step_s": 1.0 / ch.f_out,
           "disp_step_m": ch.encoder_step_m, "force_step_N": min(lsb, ch.noise_sd_of_capacity * ch.capacity_N),
           "speed_mm_per_min": abs(proto.info.get("rate_per_s", proto.info.get("rates_per_s", [0.0])[0])) * gauge * 6e4}
    path = folder / f"{name}.csv"
    info = write(fmt, path, rec, rng)
    return {"file": path.name, "specimen": rec["specimen"], "gauge_length_m": gauge, "gauge_length_stated_m": gauge_stated,
            "area_m2": spec["area"], "area_stated_m2": area_stated, "area_error": error, "stated": stated,
            "samples": int(t_out.size), "duration_s": float(sim["t"][-1]), "fine_samples": sim["n"],
            "acquisition_error_sd_N": float(np.std(f_out - f_clean)),
            "acquisition_error_of_range": float(np.std(f_out - f_clean) / (np.ptp(f_clean) or 1.0)),
            "time_start_s": t_start, "slips_s": sim["slips_s"], "chain": _lag(ch.describe(), proto), "export": info}


def _lag(chain: dict, proto: Protocol) -> dict:
    """The chain plus the force's lag behind the position [s] (the analog filter's delay, and the
    decimator's when the position is latched rather than averaged alike), and that lag over the
    shortest loading segment: a lag makes an elastic record's loops open."""
    lag = chain["filter_delay_s"] + (chain["decimator_delay_s"] if chain["position"] == "latched" else 0.0)
    return {**chain, "force_lag_s": lag, "force_lag_of_segment": lag / proto.shortest_segment()}


def plan(seed: int, n_cases: int, clean_fraction: float = 0.5) -> list[tuple[str, str | None]]:
    """(class, protocol kind of a clean case) of every case of a population.

    At least half the cases are clean (``clean_fraction`` >= 0.5); clean protocols are taken in
    turn from every kind, the effect classes in turn (a shuffled order), so the population is
    balanced; the order of the cases is shuffled.
    """
    if not 0.5 <= clean_fraction <= 1.0:
        raise ValueError(f"clean_fraction {clean_fraction}: at least half of a population must be clean (0.5-1)")
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2 ** 31,)))
    n_clean = int(np.ceil(clean_fraction * n_cases - 1e-9))
    order = [str(c) for c in rng.permutation(E.CLASSES)]
    classes = ["clean"] * n_clean + [order[i % len(order)] for i in range(n_cases - n_clean)]
    classes = [classes[i] for i in rng.permutation(n_cases)]
    kinds = [str(k) for k in rng.permutation(KINDS)]
    out, c = [], 0
    for cls in classes:
        if cls == "clean":
            out.append((cls, kinds[c % len(kinds)]))
            c += 1
        else:
            out.append((cls, None))
    return out


def generate(seed: int, n_cases: int, out_dir, *, clean_fraction: float = 0.5, only=None) -> list[dict]:
    """Write ``n_cases`` case folders (``case_0000`` ...) under ``out_dir`` and ``index.json``;
    returns the index. Case i depends only on (seed, i) and its line of :func:`plan`, so a
    population is reproduced exactly from its seed (*only*: the indices of the cases to write, the
    index listing those; default every case)."""
    todo = plan(seed, n_cases, clean_fraction)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seqs = np.random.SeedSequence(seed).spawn(n_cases)
    keep = None if only is None else set(only)
    index = []
    for i, ((cls, kind), seq) in enumerate(zip(todo, seqs)):
        if keep is not None and i not in keep:
            continue
        truth = make_case(seq, cls, out / f"case_{i:04d}", kind=kind)
        index.append({"case": truth["case"], "class": truth["class"], "protocol": truth["protocol"]["kind"],
                      "files": [f["file"] for f in truth["files"]]})
    doc = {"schema": "population/1", "generator_version": GENERATOR_VERSION, "seed": seed, "n_cases": n_cases,
           "clean_fraction": clean_fraction, "cases": index}
    (out / "index.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return index
