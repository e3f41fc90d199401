"""A seeded population of generated tests with hidden effects, and how a discovery scores on it.

Every *class* is a set of hidden candidates (none, one, or a pair) with the
protocols under which the data can show them (:mod:`.identify`): viscoelasticity
from two rates or a hold, Mullins softening and damage from cycles to rising
maxima, cyclic softening from cycles repeated to one maximum, a permanent set
from cycles at two rates, artefacts from files that start at rest, strain-energy
terms from tension and compression. :func:`population` draws random parameters
for each case (base modulus and locking, effect strengths and time scales, noise
level, samples at rest) from ranges where the effect changes the stress by
well over the noise; :func:`run_case` writes the raw files
(:mod:`.synthetic`), runs :func:`~esmm.pipeline.discover.search.discover` and
compares what it kept with the truth; :func:`confusion` tabulates.

A case is *right* when the kept names equal the hidden ones; its error is
*halved* when the final NRMSE is at most half the base model's, or the final
residual is at the noise level (an effect whose base error was already near
the noise cannot halve it). Strain-energy terms
count by family (:data:`TERM_FAMILY`): which of two terms of one family a
stretch range favours is not identifiable (a Mooney-Rivlin I2 term and a weak
exponential I2 term are the same curve up to a few percent of stretch).
"""

from __future__ import annotations

import math
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..materials import get_model
from ..materials.loading import energy_density, invariants
from ..tensile import read
from . import synthetic as syn
from .search import discover

#: strain-energy terms that the data of a population case cannot tell apart (scored as one name)
TERM_FAMILY = {"mooney": "I2 term", "i2exp": "I2 term", "i2log": "I2 term", "i1exp": "I1 stiffening",
               "yeoh": "I1 stiffening", "gent": "I1 stiffening", "fibreexp": "I1 stiffening", "toe": "toe",
               "toeweibull": "toe"}
GAUGE = 0.03  # m
AREA = 20e-6  # m2


@dataclass
class Case:
    """One generated test set: what is hidden, the protocols, the per-file artefacts, the noise."""

    name: str  # the class
    truth: syn.Truth
    protocols: list[syn.Protocol]
    vary: dict[str, list] = field(default_factory=dict)
    noise: float = 0.003
    rest: int = 0
    seed: int = 0

    @property
    def hidden(self) -> set[str]:
        names = set(self.truth.effects())
        per_file = {"slack": "slack", "offset": "sensor_offset", "scale": "specimen_scale", "slips": "grip_slip"}
        return names | {per_file[k] for k, v in self.vary.items()
                        if k in per_file and any(np.any(np.asarray(x, dtype=object)) for x in v)}


def family(names) -> set[str]:
    """Names with strain-energy terms replaced by their family."""
    return {TERM_FAMILY.get(n, n) for n in names}


# --------------------------------------------------------------------------- draws
def _base(rng) -> dict[str, float]:
    return {"mu": float(rng.uniform(5e3, 50e3)), "N": float(rng.uniform(4.0, 20.0))}


def _W(params, lam: float, model: str = "arruda-boyce") -> float:
    return float(energy_density(get_model(model), params, "uniaxial", lam))


def _lu(rng, rates=(0.02, 0.2)) -> tuple[list[syn.Protocol], float]:
    lam = float(rng.uniform(1.35, 1.8))
    return [syn.load_unload(r, lam, name=f"lu_{i}") for i, r in enumerate(rates)], lam


def _visco(rng, t_short: float, t_long: float) -> dict[str, Any]:
    return {"g": [float(rng.uniform(0.25, 0.6))], "tau": [float(math.exp(rng.uniform(math.log(t_short),
                                                                                      math.log(t_long))))]}


def _rising(rng, rate: float = 0.05) -> tuple[syn.Protocol, float]:
    top = float(rng.uniform(1.4, 1.8))
    return syn.cycles(rate, [1 + 0.4 * (top - 1), 1 + 0.7 * (top - 1), top], name="cycles"), top


def case_none(rng, i: int) -> Case:
    base = _base(rng)
    kind = i % 5
    if kind == 0:
        prs, _ = _lu(rng)
    elif kind == 1:
        prs = [_rising(rng)[0]]
    elif kind == 2:
        prs = [syn.ramp_hold(0.2, float(rng.uniform(1.3, 1.6)), 60.0, name="hold")]
    elif kind == 3:
        prs = [syn.monotonic(0.05, float(rng.uniform(1.5, 2.0)), name="ramp")]
    else:
        prs = [syn.repeated_cycles(0.1, float(rng.uniform(1.3, 1.6)), 4, name="repeat")]
    return Case("none", syn.Truth("arruda-boyce", base), prs)


def case_viscoelastic(rng, i: int) -> Case:
    base = _base(rng)
    if i % 2:
        prs, lam = _lu(rng)
        v = _visco(rng, 1.0, 0.5 * (lam - 1) / 0.02)
    else:
        prs = [syn.ramp_hold(0.2, float(rng.uniform(1.3, 1.6)), 60.0, name="hold")]
        v = _visco(rng, 1.0, 20.0)
    return Case("viscoelastic", syn.Truth("arruda-boyce", base, viscoelastic=v), prs)


def case_nonlinear_viscoelastic(rng, i: int) -> Case:
    base = _base(rng)
    top = float(rng.uniform(1.4, 1.7))
    prs = [syn.ramp_holds(0.2, [1 + 0.5 * (top - 1), top], 40.0, name="holds"),
           syn.load_unload(0.02, top, name="lu_slow")]
    v = {"g": [float(rng.uniform(0.3, 0.5))], "tau": [float(math.exp(rng.uniform(0.0, math.log(15.0))))]}
    v["kappa"] = float(rng.choice([-1, 1]) * rng.uniform(0.7, 1.0) / (top - 1))
    return Case("nonlinear_viscoelastic", syn.Truth("arruda-boyce", base, viscoelastic=v), prs)


def case_mullins(rng, i: int) -> Case:
    base = _base(rng)
    pr, top = _rising(rng)
    m = {"r": float(rng.uniform(1.5, 4.0)), "m": float(rng.uniform(0.05, 0.4)) * _W(base, top),
         "beta": float(rng.choice([0.0, 0.1]))}
    return Case("mullins", syn.Truth("arruda-boyce", base, mullins=m), [pr])


def case_damage(rng, i: int) -> Case:
    base = _base(rng)
    pr, top = _rising(rng)
    span = top - 1.0
    d = {"onset": 1.0 + float(rng.uniform(0.2, 0.5)) * span, "scale": float(rng.uniform(0.2, 0.5)) * span,
         "shape": float(rng.uniform(1.0, 3.0))}
    return Case("damage", syn.Truth("arruda-boyce", base, damage=d), [pr])


def case_cyclic(rng, i: int) -> Case:
    base = _base(rng)
    top = float(rng.uniform(1.3, 1.6))
    c = {"d_inf": float(rng.uniform(0.15, 0.35)), "eta": float(rng.uniform(1.0, 4.0)) * _W(base, top)}
    return Case("cyclic_softening", syn.Truth("arruda-boyce", base, cyclic_softening=c),
                [syn.repeated_cycles(0.1, top, 5, name="repeat")])


def case_set(rng, i: int) -> Case:
    base = _base(rng)
    pr, top = _rising(rng, 0.05)
    prs = [pr, syn.load_unload(0.25, top, name="lu_fast")]
    return Case("permanent_set", syn.Truth("arruda-boyce", base, permanent_set={"fraction": float(
        rng.uniform(0.06, 0.2))}), prs)


def case_slack(rng, i: int) -> Case:
    base = _base(rng)
    lam = float(rng.uniform(1.4, 1.8))
    prs = [syn.load_unload(0.05, lam, name="a"), syn.load_unload(0.05, 1 + 0.8 * (lam - 1), name="b")]
    hi = 0.25 * (lam - 1) * GAUGE
    return Case("slack", syn.Truth("arruda-boyce", base), prs,
                vary={"slack": [float(rng.uniform(0.3, 1.0)) * hi, float(rng.uniform(0.3, 1.0)) * hi]})


def case_offset(rng, i: int) -> Case:
    base = _base(rng)
    lam = float(rng.uniform(1.4, 1.8))
    prs = [syn.load_unload(0.05, lam, name="a"), syn.load_unload(0.05, 1 + 0.8 * (lam - 1), name="b")]
    f_max = float(np.max(np.abs(syn.simulate(prs[0], syn.Truth("arruda-boyce", base))["true_force"])))
    off = [float(rng.choice([-1, 1]) * rng.uniform(0.03, 0.1) * f_max) for _ in prs]
    so = {"force": 0.0, "drift": float(rng.choice([0.0, 1.0]) * rng.uniform(0.02, 0.05) * f_max / prs[0].t[-1])}
    return Case("sensor_offset", syn.Truth("arruda-boyce", base, sensor_offset=so), prs, vary={"offset": off},
                rest=int(rng.integers(5, 30)))


def case_scale(rng, i: int) -> Case:
    base = _base(rng)
    lam = float(rng.uniform(1.4, 1.8))
    n = 2 + i % 2
    prs = [syn.load_unload(0.05, 1 + (0.7 + 0.3 * j / n) * (lam - 1), name=f"s{j + 1}") for j in range(n)]
    scales = list(np.exp(rng.uniform(-0.35, 0.35, n)))
    scales = [float(s / np.exp(np.mean(np.log(scales)))) for s in scales]
    return Case("specimen_scale", syn.Truth("arruda-boyce", base), prs, vary={"scale": scales})


def case_slip(rng, i: int) -> Case:
    base = _base(rng)
    lam = float(rng.uniform(1.5, 1.9))
    loss = float(rng.uniform(0.04, 0.08)) * (lam - 1) * GAUGE
    return Case("grip_slip", syn.Truth("arruda-boyce", base), [syn.monotonic(0.05, lam, name="ramp")],
                vary={"slips": [((float(rng.uniform(0.35, 0.65)), loss),)]})


def case_term(rng, i: int) -> Case:
    base = _base(rng)
    kinds = ["mooney", "i2exp", "toe"]
    term = kinds[i % len(kinds)]
    if term == "toe":
        lam = float(rng.uniform(1.15, 1.3))
        params = {**base, "mu": base["mu"] * 0.1, "toe_E": float(rng.uniform(5.0, 15.0)) * base["mu"],
                  "toe_delta": float(rng.uniform(0.3, 0.6)) * (lam - 1)}
        prs = [syn.load_unload(0.05, lam, name="lu")]
    else:
        lo, hi = float(rng.uniform(0.75, 0.85)), float(rng.uniform(1.25, 1.4))
        prs = [syn.tension_compression(0.05, lo, hi, name="tc")]
        if term == "mooney":
            params = {**base, "c2": float(rng.uniform(0.5, 1.5)) * base["mu"]}
        else:
            i2 = float(invariants("uniaxial", np.array([lo]))[1][0]) - 3.0
            params = {**base, "i2exp_a": float(rng.uniform(0.3, 1.0)) * base["mu"],
                      "i2exp_b": float(rng.uniform(2.0, 5.0)) / i2}
    return Case(f"elastic term ({term})", syn.Truth(f"arruda-boyce+{term}", params), prs)


def _pair(a: Callable, b_apply: Callable, label: str) -> Callable:
    def make(rng, i: int) -> Case:
        c = a(rng, i)
        b_apply(rng, c)
        c.name = label
        return c
    return make


def _add_visco(rng, c: Case) -> None:
    c.truth.viscoelastic = _visco(rng, 1.0, 15.0)


def _add_offset(rng, c: Case) -> None:
    f_max = float(np.max(np.abs(syn.simulate(c.protocols[0], c.truth)["true_force"])))
    c.vary["offset"] = [float(rng.choice([-1, 1]) * rng.uniform(0.03, 0.1) * f_max) for _ in c.protocols]
    c.rest = int(rng.integers(5, 30))


def _add_mullins(rng, c: Case) -> None:
    top = max(float(np.max(p.lam)) for p in c.protocols)
    c.truth.mullins = {"r": float(rng.uniform(1.5, 4.0)), "m": float(rng.uniform(0.05, 0.4)) * _W(c.truth.params, top),
                       "beta": 0.0}


#: class name -> builder(rng, index)
CLASSES: dict[str, Callable[[Any, int], Case]] = {
    "none": case_none,
    "viscoelastic": case_viscoelastic,
    "nonlinear_viscoelastic": case_nonlinear_viscoelastic,
    "mullins": case_mullins,
    "damage": case_damage,
    "cyclic_softening": case_cyclic,
    "permanent_set": case_set,
    "slack": case_slack,
    "sensor_offset": case_offset,
    "specimen_scale": case_scale,
    "grip_slip": case_slip,
    "elastic term": case_term,
    "viscoelastic + slack": _pair(lambda r, i: case_slack(r, i), _add_visco, "viscoelastic + slack"),
    "viscoelastic + sensor_offset": _pair(lambda r, i: case_viscoelastic(r, 1), _add_offset,
                                          "viscoelastic + sensor_offset"),
    "mullins + viscoelastic": _pair(case_mullins, _add_visco, "mullins + viscoelastic"),
    "mullins + permanent_set": _pair(case_set, _add_mullins, "mullins + permanent_set"),
    "cyclic_softening + mullins": _pair(lambda r, i: _with_rising_then_repeat(r), _add_mullins,
                                        "cyclic_softening + mullins"),
    "specimen_scale + viscoelastic": _pair(lambda r, i: _scale_two_rates(r), _add_visco,
                                           "specimen_scale + viscoelastic"),
    "damage + sensor_offset": _pair(case_damage, _add_offset, "damage + sensor_offset"),
}


def _with_rising_then_repeat(rng) -> Case:
    base = _base(rng)
    top = float(rng.uniform(1.35, 1.6))
    c = {"d_inf": float(rng.uniform(0.15, 0.35)), "eta": float(rng.uniform(1.0, 4.0)) * _W(base, top)}
    pr = syn.cycles(0.1, [1 + 0.5 * (top - 1), top, top, top, top], name="precondition")
    return Case("cyclic_softening + mullins", syn.Truth("arruda-boyce", base, cyclic_softening=c), [pr])


def _scale_two_rates(rng) -> Case:
    """Two specimens, each tested at two rates (a design that separates the specimens from the rates)."""
    base = _base(rng)
    lam = float(rng.uniform(1.4, 1.7))
    prs = [syn.load_unload(r, lam * (1 - 0.05 * j), name=f"s{j + 1}_{r:g}") for j in range(2) for r in (0.02, 0.2)]
    c = Case("specimen_scale + viscoelastic", syn.Truth("arruda-boyce", base), prs)
    s = float(np.exp(rng.uniform(0.15, 0.35)))
    c.vary = {"scale": [s, s, 1 / s, 1 / s], "specimen": ["A", "A", "B", "B"]}
    return c


def population(n: int = 114, seed: int = 0) -> list[Case]:
    """*n* cases, the classes in turn, each drawn with its own seeded generator (reproducible, order-independent)."""
    out = []
    names = list(CLASSES)
    for i in range(n):
        cls = names[i % len(names)]
        rng = np.random.default_rng([seed, i])
        c = CLASSES[cls](rng, i // len(names))
        c.noise = float(rng.uniform(0.001, 0.005))
        c.seed = int(rng.integers(0, 2**31))
        out.append(c)
    return out


# --------------------------------------------------------------------------- running and scoring
def run_case(case: Case, folder: str | Path | None = None, **options) -> dict[str, Any]:
    """Write *case*'s files, discover, and compare with the truth (``options`` go to ``discover``)."""
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(folder) if folder is not None else Path(tmp)
        paths = syn.write_set(where, case.protocols, case.truth, seed=case.seed, noise=case.noise,
                              vary=case.vary or None, rest=case.rest, gauge_length=GAUGE, area=AREA)
        tests = [read(p) for p in paths]
        kw = {"model": "arruda-boyce", "n_starts": 2, "max_points": 200, **options}
        res = discover(tests, **kw)
    hidden, kept = case.hidden, set(res.kept)
    b, f = res.base, res.final
    return {"class": case.name, "hidden": sorted(hidden), "kept": sorted(kept),
            "right": family(kept) == family(hidden), "exact": kept == hidden,
            "nrmse_before": b.errors.nrmse, "nrmse_after": f.errors.nrmse,
            "heldout_before": b.heldout.nrmse, "heldout_after": f.heldout.nrmse,
            "halved": (not hidden) or f.errors.nrmse <= 0.5 * b.errors.nrmse or res.diagnoses[-1].white,
            "seconds": res.seconds}


def score(n: int = 114, seed: int = 0, **options) -> dict[str, Any]:
    """Run the population of *n* cases drawn with *seed* and tabulate it (:func:`confusion`).

    Returns the confusion table with the run's ``seed``, its wall time ``seconds`` and the
    ``wrong`` cases (class, hidden names, kept names); ``options`` go to ``discover``.
    """
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results = [run_case(case, **options) for case in population(n, seed)]
    table = confusion(results)
    table["seconds"], table["seed"] = round(time.perf_counter() - t0, 1), seed
    table["wrong"] = [{k: r[k] for k in ("class", "hidden", "kept")} for r in results if not r["right"]]
    table["not_halved"] = [{k: r[k] for k in ("class", "hidden", "kept", "nrmse_before", "nrmse_after")}
                           for r in results if not r["halved"]]
    return table


def confusion(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Right-name rate, per-class rates, and per hidden candidate: found, missed, and what was added wrongly."""
    per_class: dict[str, list[int]] = {}
    per_name: dict[str, dict[str, int]] = {}
    for r in results:
        c = per_class.setdefault(r["class"], [0, 0])
        c[0] += int(r["right"])
        c[1] += 1
        h, k = family(r["hidden"]), family(r["kept"])
        for n in h | k:
            d = per_name.setdefault(n, {"hidden": 0, "found": 0, "missed": 0, "added_wrongly": 0})
            d["hidden"] += int(n in h)
            d["found"] += int(n in h and n in k)
            d["missed"] += int(n in h and n not in k)
            d["added_wrongly"] += int(n in k and n not in h)
    with_effect = [r for r in results if r["hidden"]]
    return {"cases": len(results), "right": sum(r["right"] for r in results),
            "right_rate": sum(r["right"] for r in results) / max(len(results), 1),
            "exact_rate": sum(r["exact"] for r in results) / max(len(results), 1),
            "halved_rate": sum(r["halved"] for r in with_effect) / max(len(with_effect), 1),
            "per_class": {k: {"right": v[0], "cases": v[1]} for k, v in per_class.items()},
            "per_name": per_name}
