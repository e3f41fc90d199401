"""The effects a case may carry (one per effect case), their parameter draws and how they act.

Material effects change the stress along the stretch path (:mod:`.relaxation`, :mod:`.history`).
Measurement artefacts change what the machine records: the specimen's real stretch (slack, grip
slips), the force reading (a load-cell offset and thermal drift), or the stated cross-section
(specimen scale). The class names are the ones esmm's discovery reports, so that a case's truth
can be compared with its JSON; the forms are the literature's (module docstrings), not esmm's.

Magnitudes are drawn relative to the test (the protocol's time scales, the largest energy
reached, the peak force) so that every effect is present in the data at a physical size; the
size actually reached is measured afterwards (``effect_size`` in truth.json).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from . import history, relaxation
from .draws import loguniform

MATERIAL = ("viscoelastic", "nonlinear_viscoelastic", "mullins", "damage", "cyclic_softening", "permanent_set")
ARTEFACTS = ("slack", "sensor_offset", "specimen_scale", "grip_slip")
CLASSES = MATERIAL + ARTEFACTS

#: Where each class is drawn: protocols (weights), test shapes (weights), material families.
PLAN = {
    "viscoelastic": ({"relaxation": 2, "staircase": 1, "multirate": 2, "cycles": 1, "rising": 1},
                     {"tension": 4, "compression": 1, "simple_shear": 1}),
    "nonlinear_viscoelastic": ({"staircase": 3, "multirate": 1}, {"tension": 1}),
    "mullins": ({"rising": 3, "cycles": 1}, {"tension": 1}),
    "damage": ({"rising": 3, "cycles": 1}, {"tension": 1}),
    "cyclic_softening": ({"cycles": 1}, {"tension": 1}),
    "permanent_set": ({"rising": 3, "cycles": 1}, {"tension": 1}),
    "slack": ({"ramp": 2, "failure": 1, "cycles": 1, "rising": 1, "multirate": 1, "replicates": 2}, {"tension": 1}),
    "sensor_offset": ({"ramp": 2, "failure": 1, "cycles": 1, "rising": 1, "relaxation": 1, "multirate": 1,
                       "staircase": 1}, {"tension": 4, "compression": 1, "simple_shear": 1}),
    "specimen_scale": ({"replicates": 1}, {"tension": 3, "compression": 1}),
    "grip_slip": ({"ramp": 2, "failure": 1}, {"tension": 1}),
}


class Elastic:
    """The base law along one test: ``stress(x)`` and ``energy(x)``; fibre laws (solved or
    integrated numerically) are tabulated once on the test's range with a cubic spline."""

    def __init__(self, law, mode: str, lo: float, hi: float):
        self.law, self.mode = law, mode
        self._tab = None
        if law.name in ("hgo", "toe"):
            span = hi - lo
            x = np.linspace(lo - 0.1 * span, hi + 0.1 * span, 3001)
            p, w = law.stress(x, mode), law.energy(x, mode)
            # the margin beyond the test's range only pads the spline: where the law is not defined there
            # (a fibre law below its reference) or runs away (an exponential beyond ten times its largest
            # value on the test), the table starts or ends at the last sample before
            on = (x >= lo) & (x <= hi)
            with np.errstate(invalid="ignore"):
                big_p, big_w = 10.0 * np.nanmax(np.abs(p[on])), 10.0 * np.nanmax(np.abs(w[on]))
                bad = np.flatnonzero(~(np.isfinite(p) & np.isfinite(w) & (np.abs(p) <= big_p)
                                       & (np.abs(w) <= big_w)))
            inside = np.searchsorted(x, 0.5 * (lo + hi))
            first = int(bad[bad < inside].max()) + 1 if np.any(bad < inside) else 0
            last = int(bad[bad > inside].min()) if np.any(bad > inside) else x.size
            x, p, w = x[first:last], p[first:last], w[first:last]
            self._tab = (x[0], x[-1], CubicSpline(x, p), CubicSpline(x, w))

    def stress(self, x) -> np.ndarray:
        if self._tab is None:
            return self.law.stress(x, self.mode)
        a, b, s, _ = self._tab
        return s(np.clip(x, a, b))

    def energy(self, x) -> np.ndarray:
        if self._tab is None:
            return self.law.energy(x, self.mode)
        a, b, _, e = self._tab
        return e(np.clip(x, a, b))


@dataclass
class Ctx:
    """What an effect's draw may depend on: the base law along the test and the protocol's scales."""

    elastic: Elastic
    x0: float
    hi: float
    t_move: float  # the shortest moving segment [s]
    t_long: float  # the longest hold, else the longest file [s]


def _kernel(rng, ctx: Ctx) -> tuple[dict, object]:
    kind = str(rng.choice(["prony", "fung", "power"]))
    if kind == "prony":
        m = int(rng.integers(1, 4))
        tau = np.sort([loguniform(rng, 0.05 * ctx.t_move, 2.0 * ctx.t_long) for _ in range(m)])
        g = rng.dirichlet(np.ones(m)) * rng.uniform(0.1, 0.6)
        k = relaxation.Prony(g, tau)
    elif kind == "fung":
        tau1 = loguniform(rng, 1e-3, 0.1) * ctx.t_move
        tau2 = loguniform(rng, 0.3, 3.0) * ctx.t_long
        target = rng.uniform(0.15, 0.7)  # 1 - G(inf)
        k = relaxation.FungSpectrum(target / (1 - target) / np.log(tau2 / tau1), tau1, tau2)
    else:
        k = relaxation.PowerLaw(rng.uniform(0.3, 0.85), loguniform(rng, 0.01, 1.0) * ctx.t_move, rng.uniform(0.1, 0.5))
    return k.describe(), k


def kernel_from(d: dict):
    if d["kernel"] == "prony":
        return relaxation.Prony(d["g"], d["tau_s"])
    if d["kernel"] == "fung":
        return relaxation.FungSpectrum(d["C"], d["tau1_s"], d["tau2_s"])
    return relaxation.PowerLaw(d["g_inf"], d["t0_s"], d["n"])


def draw(name: str, rng: np.random.Generator, ctx: Ctx) -> dict:
    """The parameters of effect ``name`` (JSON-able; ``variant`` names the published form)."""
    span = ctx.hi - ctx.x0
    w_max = float(ctx.elastic.energy(np.array([ctx.hi]))[0])
    if name == "viscoelastic":
        d, _ = _kernel(rng, ctx)
        return {"variant": "qlv", **d}
    if name == "nonlinear_viscoelastic":
        if rng.uniform() < 0.5:
            d, _ = _kernel(rng, ctx)
            return {"variant": "schapery", "c": float(np.log(rng.uniform(1.5, 4.0)) / span), **d}
        m = int(rng.integers(1, 3))
        tau = np.sort([loguniform(rng, 0.1 * ctx.t_move, 2.0 * ctx.t_long) for _ in range(m)])
        g = rng.dirichlet(np.ones(m)) * rng.uniform(0.2, 0.6)
        return {"variant": "strain_dependent_rate", "g": g.tolist(), "tau_s": tau.tolist(),
                "c": float(np.log(rng.uniform(3.0, 30.0)) / span)}
    if name == "mullins":
        if rng.uniform() < 0.5:
            return {"variant": "discontinuous_damage", "d_inf": rng.uniform(0.2, 0.6), "eta_Pa": w_max * rng.uniform(0.3, 2.0)}
        return {"variant": "ogden_roxburgh", "r": rng.uniform(1.1, 2.5), "m_Pa": w_max * rng.uniform(0.05, 0.5),
                "beta": rng.uniform(0.0, 0.3)}
    if name == "damage":
        x_on = ctx.x0 + rng.uniform(0.3, 0.6) * span
        xi0 = float(np.sqrt(2.0 * ctx.elastic.energy(np.array([x_on]))[0]))
        xi_max = np.sqrt(2.0 * w_max)
        return {"variant": "simo1987", "onset_x": x_on, "xi0_sqrtPa": xi0,
                "a_sqrtPa": (xi_max - xi0) * rng.uniform(0.2, 1.5), "b": rng.uniform(0.2, 0.7)}
    if name == "cyclic_softening":
        n_sat = rng.uniform(3.0, 10.0)
        return {"variant": "miehe_continuous", "d_inf": rng.uniform(0.1, 0.4), "eta_Pa": 2.0 * w_max * n_sat / 3.0,
                "cycles_to_95pc": n_sat}
    if name == "permanent_set":
        return {"variant": "multiplicative_residual_stretch", "f": rng.uniform(0.05, 0.2), "q": rng.uniform(1.0, 2.0)}
    return draw_artefact(name, rng, span)


def draw_artefact(name: str, rng: np.random.Generator, span: float) -> dict:
    """An artefact's parameters; ``span`` = the test's peak minus its reference."""
    if name == "slack":
        return {"variant": "uneven_fibre_lengths" if rng.uniform() < 0.5 else "sharp",
                "delta": rng.uniform(0.1, 0.5) * span, "spread": rng.uniform(0.2, 0.8)}
    if name == "sensor_offset":
        v = str(rng.choice(["offset", "drift", "offset_drift"]))
        return {"variant": v, "offset_of_peak": (rng.choice([-1, 1]) * rng.uniform(0.01, 0.1)) if "offset" in v else 0.0,
                "drift_of_peak": (rng.choice([-1, 1]) * rng.uniform(0.01, 0.08)) if "drift" in v else 0.0,
                "drift_tau_of_duration": rng.uniform(0.3, 3.0)}
    if name == "grip_slip":
        k = int(rng.integers(1, 5))
        return {"variant": "friction_limited", "at_force_of_peak": np.sort(rng.uniform(0.25, 0.9, k)).tolist(),
                "loss_of_extension": rng.uniform(0.05, 0.3, k).tolist(), "duration_s": rng.uniform(0.005, 0.05)}
    if name == "specimen_scale":
        return {"variant": "cross_section_misstated", "errors": [], "magnitude": (0.1, 0.4)}
    raise ValueError(f"effect {name!r}: use one of {', '.join(CLASSES)}")


def material_stress(name: str | None, p: dict, el: Elastic, x: np.ndarray, dt: float) -> np.ndarray:
    """Nominal stress along the path ``x`` (n,) with material effect ``name`` (None: elastic)."""
    if name is None or name not in MATERIAL:
        return el.stress(x)
    if name == "permanent_set":
        return history.permanent_set(x, el.stress, f=p["f"], q=p["q"])
    pe = el.stress(x)
    if name == "viscoelastic":
        return relaxation.hereditary(kernel_from(p), dt, pe)
    if name == "nonlinear_viscoelastic":
        if p["variant"] == "schapery":
            return relaxation.schapery(kernel_from(p), dt, pe, x, p["c"])
        return relaxation.strain_dependent_rate(p["g"], p["tau_s"], dt, pe, x, p["c"])
    w0 = el.energy(x)
    if name == "mullins" and p["variant"] == "discontinuous_damage":
        return history.mullins_discontinuous(pe, w0, d_inf=p["d_inf"], eta=p["eta_Pa"])
    if name == "mullins":
        return history.mullins_pseudo_elastic(pe, w0, r=p["r"], m=p["m_Pa"], beta=p["beta"])
    if name == "damage":
        return history.simo_damage(pe, w0, xi0=p["xi0_sqrtPa"], a=p["a_sqrtPa"], b=p["b"])
    return history.continuous_softening(pe, w0, d_inf=p["d_inf"], eta=p["eta_Pa"])


def slack_stress(p: dict, el: Elastic, x: np.ndarray) -> np.ndarray:
    """A slack specimen (tension): fibres of slack ``delta (1 + spread u)``, u over [-1, 1]
    (Gauss-Legendre), each taut once ``x`` passes ``1 + its slack``; one node when sharp."""
    if p["variant"] == "sharp":
        nodes, weights = np.array([0.0]), np.array([2.0])
    else:
        nodes, weights = np.polynomial.legendre.leggauss(12)
    out = np.zeros_like(x)
    for u, w in zip(nodes, weights):
        xf = x / (1.0 + p["delta"] * (1.0 + p["spread"] * u))
        taut = xf > 1.0
        out[taut] += 0.5 * w * el.stress(xf[taut])
    return out


def slipped(p: dict, el: Elastic, x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """The specimen's stretch with friction-limited grip slips: each slip happens when the
    force (elastic, with the earlier slips) first reaches its level while loading, and gives
    back a fraction of the extension then reached over ``duration_s``. Returns (x, slip times)."""
    peak = float(np.max(el.stress(x)))
    lost = np.zeros_like(x)
    loading = np.concatenate(([False], np.diff(x) > 0))
    times, start = [], 0
    for level, frac in zip(p["at_force_of_peak"], p["loss_of_extension"]):
        xs = x - lost
        hit = np.flatnonzero(loading[start:] & (el.stress(xs[start:]) >= level * peak))
        if hit.size == 0:
            break
        i = start + int(hit[0])
        s = np.clip((t - t[i]) / p["duration_s"], 0.0, 1.0)
        lost = lost + frac * (xs[i] - 1.0) * (3 * s ** 2 - 2 * s ** 3)
        times.append(float(t[i]))
        start = i + max(1, int(round(2 * p["duration_s"] / (t[1] - t[0]))))
    return x - lost, times


def offset_force(p: dict, t: np.ndarray, peak_force: float) -> np.ndarray:
    """Load-cell offset and thermal drift (an exponential warm-up toward its level) [N]."""
    tau = p["drift_tau_of_duration"] * max(float(t[-1]), 1e-9)
    return peak_force * (p["offset_of_peak"] + p["drift_of_peak"] * -np.expm1(-t / tau))
