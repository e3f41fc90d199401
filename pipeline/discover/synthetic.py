"""Synthetic raw tensile tests with hidden effects, for testing and demonstrating the discovery.

The generator writes what a testing machine writes — (time, displacement,
force) CSV files with the specimen geometry in ``# key: value`` comment lines
or in a TOML sidecar, in the formats of the tensile-data contract
(docs/reference/tensile-input.md) — for a hyperelastic base material plus
one or more hidden effects, with realistic noise and quantisation.

Its physics is written independently of the fitting code in
:mod:`esmm.pipeline.discover.model` where a choice exists: the Prony
internal variables are integrated with the trapezoidal (Crank-Nicolson) rule
on a grid at least four times finer than the shortest relaxation time, not
with the exact exponential recursion the fit uses.

Protocols (stretch histories, :class:`Protocol`): :func:`load_unload`,
:func:`cycles` (to rising maxima), :func:`ramp_hold`, :func:`monotonic`.
Effects (:class:`Truth`): ``viscoelastic`` (g, tau), ``mullins`` (r, m, beta),
``damage`` (onset, scale, shape), ``slack`` (length [m]) and
``sensor_offset`` (force [N], drift [N/s]).

Example
-------
>>> from esmm.pipeline.discover import synthetic as syn
>>> truth = syn.Truth("arruda-boyce", {"mu": 20e3, "N": 4.0},
...                   viscoelastic={"g": [0.4], "tau": [2.0]})
>>> paths = syn.write_set(tmp_path, [syn.load_unload(0.05, 1.6), syn.load_unload(0.5, 1.6)],
...                       truth, seed=1)                                      # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from scipy.special import erf

from ..atomicio import write_text
from ..errors import ConfigError
from ..materials import get_model
from ..materials.composite import split_name
from ..materials.effects import equivalent_stretch
from ..materials.loading import energy_density, nominal_stress

__all__ = ["Protocol", "Truth", "load_unload", "cycles", "repeated_cycles", "ramp_hold", "ramp_holds",
           "tension_compression", "monotonic", "simulate",
           "write_csv", "write_set"]


@dataclass
class Protocol:
    """A prescribed stretch history (uniaxial tension).

    Attributes
    ----------
    name : str
        File stem.
    t : ndarray, shape (n,)
        Time [s], uniform step.
    lam : ndarray, shape (n,)
        Crosshead stretch (1 + displacement / gauge length).
    notes : str
    """

    name: str
    t: np.ndarray
    lam: np.ndarray
    notes: str = ""


def _path(name: str, knots_t: Sequence[float], knots_lam: Sequence[float], dt: float, notes: str) -> Protocol:
    t = np.arange(0.0, knots_t[-1] + 0.5 * dt, dt)
    lam = np.interp(t, knots_t, knots_lam)
    return Protocol(name, t, lam, notes)


def _dt(rate: float, span: float, dt: float | None, n_target: int = 400) -> float:
    if dt is not None:
        return float(dt)
    return max(span / rate / n_target, 1e-3)


def load_unload(rate: float, lam_max: float, *, dt: float | None = None, name: str | None = None) -> Protocol:
    """Load at *rate* [1/s] to *lam_max*, unload at the same rate to 1."""
    T = (lam_max - 1.0) / rate
    d = _dt(rate, 2 * (lam_max - 1.0), dt)
    return _path(name or f"lu_{rate:g}_{lam_max:g}", [0, T, 2 * T], [1, lam_max, 1], d,
                 f"load-unload at {rate:g} /s to {lam_max:g}")


def cycles(rate: float, maxima: Sequence[float], *, dt: float | None = None, name: str | None = None) -> Protocol:
    """Load-unload cycles to the rising *maxima* at *rate* [1/s], back to stretch 1 each time."""
    kt, kl, t = [0.0], [1.0], 0.0
    for mx in maxima:
        t += (mx - 1.0) / rate
        kt.append(t)
        kl.append(mx)
        t += (mx - 1.0) / rate
        kt.append(t)
        kl.append(1.0)
    span = 2 * sum(mx - 1.0 for mx in maxima)
    d = _dt(rate, span, dt, 600)
    return _path(name or f"cycles_{rate:g}", kt, kl, d, f"cycles at {rate:g} /s to {', '.join(f'{m:g}' for m in maxima)}")


def ramp_hold(rate: float, lam_hold: float, hold: float, *, dt: float | None = None,
              name: str | None = None) -> Protocol:
    """Ramp at *rate* to *lam_hold*, then hold for *hold* seconds."""
    T = (lam_hold - 1.0) / rate
    d = dt if dt is not None else max(min(T / 100, hold / 300), 1e-3)
    return _path(name or f"hold_{lam_hold:g}", [0, T, T + hold], [1, lam_hold, lam_hold], d,
                 f"ramp at {rate:g} /s to {lam_hold:g}, hold {hold:g} s")


def repeated_cycles(rate: float, lam_max: float, n: int, *, dt: float | None = None,
                    name: str | None = None) -> Protocol:
    """*n* load-unload cycles at *rate* to the same *lam_max* (preconditioning)."""
    return cycles(rate, [lam_max] * n, dt=dt, name=name or f"repeat_{lam_max:g}x{n}")


def tension_compression(rate: float, lam_min: float, lam_max: float, *, dt: float | None = None,
                        name: str | None = None) -> Protocol:
    """Stretch from 1 to *lam_max*, back through 1 to *lam_min* (compression), and back to 1, at *rate*."""
    a, b = lam_max - 1.0, 1.0 - lam_min
    T = [0.0, a / rate, 2 * a / rate, (2 * a + b) / rate, 2 * (a + b) / rate]
    d = _dt(rate, 2 * (a + b), dt)
    return _path(name or f"tc_{lam_min:g}_{lam_max:g}", T, [1, lam_max, 1, lam_min, 1], d,
                 f"tension to {lam_max:g} and compression to {lam_min:g} at {rate:g} /s")


def ramp_holds(rate: float, levels: Sequence[float], hold: float, *, dt: float | None = None,
               name: str | None = None) -> Protocol:
    """Ramps at *rate* to each stretch of *levels* in turn, each held for *hold* seconds."""
    kt, kl, t, lam = [0.0], [1.0], 0.0, 1.0
    for v in levels:
        t += abs(v - lam) / rate
        kt.append(t)
        kl.append(v)
        t += hold
        kt.append(t)
        kl.append(v)
        lam = v
    d = dt if dt is not None else max(min(t / 1500, hold / 300), 1e-3)
    return _path(name or f"holds_{'_'.join(f'{v:g}' for v in levels)}", kt, kl, d,
                 f"ramps at {rate:g} /s to {', '.join(f'{v:g}' for v in levels)}, each held {hold:g} s")


def monotonic(rate: float, lam_max: float, *, dt: float | None = None, name: str | None = None) -> Protocol:
    """One monotonic ramp at *rate* to *lam_max* (e.g. to failure)."""
    T = (lam_max - 1.0) / rate
    d = _dt(rate, lam_max - 1.0, dt)
    return _path(name or f"ramp_{lam_max:g}", [0, T], [1, lam_max], d, f"monotonic ramp at {rate:g} /s to {lam_max:g}")


@dataclass
class Truth:
    """The hidden material and artefacts.

    Attributes
    ----------
    model : str
        Base model name (``arruda-boyce``, ``esedf``).
    params : dict
        Base parameters (SI). With ``viscoelastic`` they are the instantaneous response.
    viscoelastic : dict, optional
        ``{"g": [...], "tau": [... s]}``, optionally ``"kappa"`` (stretch-dependent relaxed amount).
    mullins : dict, optional
        ``{"r": > 1, "m": Pa, "beta": >= 0}``.
    damage : dict, optional
        ``{"onset": stretch, "scale": stretch, "shape": >= 1}``.
    slack : float, optional
        Slack length [m]: the specimen becomes taut after this displacement.
    sensor_offset : dict, optional
        ``{"force": N, "drift": N/s}``.
    cyclic_softening : dict, optional
        ``{"d_inf": < 1, "eta": Pa}`` (softening with the accumulated |dW|).
    permanent_set : dict, optional
        ``{"fraction": < 1}`` (set stretch ``1 + fraction (lam_max - 1)``).
    specimen_scale : float, optional
        True cross-section / stated one (varied per file with ``vary``).
    grip_slip : sequence of (time fraction, extension lost [m]), optional
    """

    model: str
    params: dict[str, float]
    viscoelastic: dict[str, Any] | None = None
    mullins: dict[str, float] | None = None
    damage: dict[str, float] | None = None
    slack: float | None = None
    sensor_offset: dict[str, float] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    cyclic_softening: dict[str, float] | None = None
    permanent_set: dict[str, float] | None = None
    specimen_scale: float | None = None
    grip_slip: tuple[tuple[float, float], ...] | None = None

    def effects(self) -> list[str]:
        """The names a discovery should find: effects and artefacts present, and the strain-energy terms."""
        names = [n for n in ("viscoelastic", "mullins", "damage", "cyclic_softening", "permanent_set", "slack",
                             "sensor_offset", "specimen_scale", "grip_slip") if getattr(self, n)]
        if self.viscoelastic and self.viscoelastic.get("kappa"):
            names.append("nonlinear_viscoelastic")
        if self.specimen_scale == 1.0:
            names.remove("specimen_scale")
        return names + list(split_name(self.model)[1])


def prony_trapezoid(t: np.ndarray, p: np.ndarray, g: Sequence[float], tau: Sequence[float]) -> np.ndarray:
    r"""Quasi-linear viscoelastic stress by the trapezoidal rule (the generator's own integration).

    .. math::

        P(t) = g_\infty P_e(t) + \sum_i g_i h_i(t), \qquad
        \dot h_i = \dot P_e - h_i / \tau_i, \quad h_i(0) = P_e(0),

    with :math:`g_\infty = 1 - \sum_i g_i`, integrated by Crank-Nicolson on a grid
    refined to Δt <= min(τ)/8 (P_e linear between samples). Independent of the
    fit's exact recursion (:func:`esmm.pipeline.materials.effects.qlv_stress`), so
    the test that compares them checks both.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Sample times [s], increasing.
    p : ndarray, shape (n,)
        Elastic (instantaneous) stress P_e [Pa].
    g, tau : sequence of float, shape (m,)
        Prony weights and relaxation times [s].

    Returns
    -------
    ndarray, shape (n,)
        P [Pa] at the sample times.
    """
    dt = float(np.min(np.diff(t))) if t.size > 1 else 1.0
    sub = max(1, int(math.ceil(8 * dt / min(tau))))
    if sub > 1:
        tf = np.linspace(t[0], t[-1], (t.size - 1) * sub + 1)
        pf = np.interp(tf, t, p)
    else:
        tf, pf = t, p
    out = (1.0 - sum(g)) * pf
    for gi, ti in zip(g, tau):
        h = np.empty_like(pf)
        h[0] = pf[0]
        d = np.diff(tf)
        a = 0.5 * d / ti
        dp = np.diff(pf)
        for k in range(pf.size - 1):
            h[k + 1] = (h[k] * (1.0 - a[k]) + dp[k]) / (1.0 + a[k])
        out = out + gi * h
    return out[::sub] if sub > 1 else out


def simulate(protocol: Protocol, truth: Truth, *, gauge_length: float = 0.03, area: float = 20e-6,
             noise: float = 0.003, seed: int = 0, rest: int = 0) -> dict[str, np.ndarray]:
    """The machine channels of one test.

    Parameters
    ----------
    protocol : Protocol
    truth : Truth
    gauge_length : float
        Nominal gauge length [m] (the clamp distance at zero displacement).
    area : float
        Cross-section [m2] as stated in the file (a ``specimen_scale`` c makes
        the true one c times larger: the stress the file implies is c times the true).
    noise : float
        Standard deviation of the force noise as a fraction of the largest
        true force (white), plus quantisation: displacement 0.1 µm, force 0.1 mN.
    seed : int
    rest : int
        Samples recorded at rest before the crosshead moves.

    Returns
    -------
    dict with ``time`` [s], ``displacement`` [m], ``force`` [N], ``true_force`` [N]
    """
    m = get_model(truth.model)
    rng = np.random.default_rng(seed)
    t, lam_c = _with_rest(protocol, rest)
    u = gauge_length * (lam_c - 1.0)
    lam = _specimen_stretch(t, u, truth, gauge_length)
    p = _material_stress(m, truth, t, lam)
    p = np.maximum(p, 0.0) if np.min(lam_c) >= 1.0 else p  # a pulled strip buckles instead of carrying compression
    f_true = p * area * float(truth.specimen_scale or 1.0)
    f = f_true.copy()
    if truth.sensor_offset:
        f = f + truth.sensor_offset.get("force", 0.0) + truth.sensor_offset.get("drift", 0.0) * (t - t[0])
    f = f + noise * float(np.max(np.abs(f_true))) * rng.standard_normal(f.size)
    f = np.round(f / 1e-4) * 1e-4
    u = np.round(u / 1e-7) * 1e-7
    return {"time": t, "displacement": u, "force": f, "true_force": f_true}


def _with_rest(protocol: Protocol, rest: int) -> tuple[np.ndarray, np.ndarray]:
    """Time and crosshead stretch with *rest* samples at stretch 1 before the protocol."""
    t, lam = protocol.t, protocol.lam
    if rest <= 0 or t.size < 2:
        return t, lam
    dt = float(t[1] - t[0])
    return np.concatenate([np.arange(rest) * dt, t + rest * dt]), np.concatenate([np.ones(rest), lam])


def _specimen_stretch(t: np.ndarray, u: np.ndarray, truth: Truth, gauge: float) -> np.ndarray:
    """The specimen's stretch: extension lost at each grip slip, then slack (taut once u > slack)."""
    for when, loss in truth.grip_slip or ():
        u = u - loss * (t >= when * t[-1])
    s = float(truth.slack or 0.0)
    lam = (gauge + u) / (gauge + s)
    return np.maximum(lam, 1.0) if s > 0 else lam


def _material_stress(m, truth: Truth, t: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Nominal stress of the hidden material along the stretch history *lam* (the generator's own physics)."""
    lam_s = np.ones_like(lam)
    if truth.permanent_set:
        lam_s = 1.0 + truth.permanent_set["fraction"] * np.maximum(np.maximum.accumulate(lam) - 1.0, 0.0)
    le = lam / lam_s
    p = np.asarray(nominal_stress(m, truth.params, "uniaxial", le), float) / lam_s
    W = np.asarray(energy_density(m, truth.params, "uniaxial", le), float)
    if truth.damage:
        d = truth.damage
        xi = equivalent_stretch(lam * lam + 2.0 / lam)
        x = np.maximum(np.maximum.accumulate(xi) - d["onset"], 0.0) / d["scale"]
        p = p * np.exp(-(x ** d.get("shape", 1.0)))
    if truth.mullins:
        mu = truth.mullins
        Wm = np.maximum.accumulate(W)
        p = p * (1.0 - erf((Wm - W) / (mu["m"] + mu.get("beta", 0.0) * Wm)) / mu["r"])
    if truth.cyclic_softening:
        c = truth.cyclic_softening
        alpha = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(W)))])
        p = p * (1.0 - c["d_inf"] * (1.0 - np.exp(-alpha / c["eta"])))
    if truth.viscoelastic:
        v = truth.viscoelastic
        q = prony_trapezoid(t, p, v["g"], v["tau"])
        kappa = float(v.get("kappa", 0.0))
        if kappa:
            xi = np.maximum(lam, 1.0)  # uniaxial tension: the equivalent stretch is the stretch
            s_k = np.minimum(np.exp(kappa * (xi - 1.0)), 1.0 / sum(v["g"]))
            q = p - s_k * (p - q)
        p = q
    return p


def write_csv(path: str | Path, channels: Mapping[str, np.ndarray], *, gauge_length: float, area: float,
              style: str = "comments", specimen: str = "synthetic", notes: str = "",
              extra: Mapping[str, str] | None = None) -> Path:
    """Write one raw test file in a format of the tensile-data contract.

    Parameters
    ----------
    path : path
        The CSV to write (a sidecar ``.toml`` beside it for ``style="sidecar"``).
    channels : mapping
        ``time`` [s], ``displacement`` [m], ``force`` [N] arrays.
    gauge_length, area : float
        Geometry [m], [m2].
    style : {"comments", "sidecar", "units_row"}
        ``comments``: ``# key: value`` lines and bracketed units in the header;
        ``sidecar``: geometry in ``<stem>.toml``, units in parentheses;
        ``units_row``: geometry in comments, a units row under the header,
        ``;`` delimiter with decimal commas.
    specimen, notes : str
    extra : mapping, optional
        More ``key: value`` metadata.
    """
    path = Path(path)
    t = np.asarray(channels["time"], float)
    u = np.asarray(channels["displacement"], float) * 1e3  # mm
    f = np.asarray(channels["force"], float)
    meta = {"specimen": specimen, "gauge_length": f"{gauge_length * 1e3:g} mm",
            "area": f"{area * 1e6:g} mm2", "tissue": "synthetic", "notes": notes}
    meta.update(extra or {})
    if style == "comments":
        lines = [f"# {k}: {v}" for k, v in meta.items() if v]
        lines.append("time [s],displacement [mm],force [N]")
        lines += [f"{a:.4f},{b:.5f},{c:.5f}" for a, b, c in zip(t, u, f)]
    elif style == "sidecar":
        write_text(path.with_suffix(".toml"), tomli_w.dumps({k: v for k, v in meta.items() if v}))
        lines = ["Time (s),Extension (mm),Load (N)"]
        lines += [f"{a:.4f},{b:.5f},{c:.5f}" for a, b, c in zip(t, u, f)]
    elif style == "units_row":
        lines = [f"# {k}: {v}" for k, v in meta.items() if v]
        lines += ["Time;Extension;Load", "(s);(mm);(N)"]
        lines += [f"{a:.4f};{b:.5f};{c:.5f}".replace(".", ",") for a, b, c in zip(t, u, f)]
    else:
        raise ConfigError(f"style must be comments, sidecar or units_row, got {style!r}")
    return write_text(path, "\n".join(lines) + "\n")


def write_set(folder: str | Path, protocols: Sequence[Protocol], truth: Truth, *, seed: int = 0,
              gauge_length: float = 0.03, area: float = 20e-6, noise: float = 0.003,
              styles: Sequence[str] = ("comments", "sidecar", "units_row"),
              vary: Mapping[str, Sequence] | None = None, rest: int = 0) -> list[Path]:
    """Simulate and write one file per protocol; returns the CSV paths.

    Parameters
    ----------
    folder : path
    protocols : sequence of Protocol
    truth : Truth
    seed : int
        File *i* uses ``seed + i``.
    gauge_length, area, noise
        As :func:`simulate`.
    styles : sequence of str
        File formats, cycled over the files.
    vary : mapping, optional
        Per-file values of the artefacts, e.g. ``{"slack": [1e-3, 2e-3]}``,
        ``{"offset": [0.01, -0.02]}`` (force offsets [N]), ``{"scale": [0.8, 1.25]}``
        (specimen scales: every file is then its own specimen, unless ``"specimen"``
        gives the ids) or ``{"slips": [((0.4, 2e-4),), ()]}``; cycled over files.
    rest : int
        Samples recorded at rest before each protocol starts.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, pr in enumerate(protocols):
        tr = _varied(truth, vary, i) if vary else truth
        ch = simulate(pr, tr, gauge_length=gauge_length, area=area, noise=noise, seed=seed + i, rest=rest)
        specimen = "synthetic"
        if vary and "specimen" in vary:
            specimen = str(vary["specimen"][i % len(vary["specimen"])])
        elif vary and "scale" in vary:
            specimen = f"specimen-{i + 1}"
        out.append(write_csv(folder / f"{pr.name}.csv", ch, gauge_length=gauge_length, area=area,
                             style=styles[i % len(styles)], notes=pr.notes, specimen=specimen))
    return out


def _varied(truth: Truth, vary: Mapping[str, Sequence], i: int) -> Truth:
    """*truth* with file *i*'s values of the per-test quantities in *vary*."""
    kw = dict(vars(truth))

    def pick(key):
        return vary[key][i % len(vary[key])]

    if "slack" in vary:
        kw["slack"] = pick("slack")
    if "offset" in vary:
        kw["sensor_offset"] = {**(truth.sensor_offset or {}), "force": pick("offset")}
    if "scale" in vary:
        kw["specimen_scale"] = pick("scale")
    if "slips" in vary:
        kw["grip_slip"] = pick("slips")
    return Truth(**kw)
