r"""The extended model: a hyperelastic base plus effects, and its least-squares fit.

The objective is the one of :func:`esmm.pipeline.calibrate.fit.fit_material`
(docs/calibrate.md), so that a base model fitted here and there agree:

.. math::

    r_{f,k} = \sqrt{w_f / n_f}\;\frac{\hat P_{f,k}(\theta, \phi, \psi_f) - P_{f,k}}{s_f},
    \qquad s_f = \max_k |P_{f,k}|,

with θ the base parameters (laid out, bounded and log-transformed exactly as
the calibrate fit does: :class:`esmm.pipeline.calibrate.problem.ParameterLayout`
provides the slots, and the weights, scales and NaN penalty are those of
:mod:`esmm.pipeline.calibrate.problem`), φ the material
effects' parameters (shared by all files) and ψ_f the artefact parameters of
file *f* (slack, load-cell offset and drift). The sum runs over the thinned
fitting samples of each file (:func:`~esmm.pipeline.discover.covariates.thin`);
reported errors use every sample.

Prediction of one file, in this order (docs/discover.md):

1. slack: ``x_true = max(x / (1 + δ_f), 1)`` (tension tests only);
2. ``P_e = nominal_stress(base, x_true)``;
3. damage: ``P_e *= 1 - D(ξ_max)``; Mullins: ``P_e *= η(W, W_max)``;
4. viscoelastic: ``P = QLV[P_e]``;
5. a tension-only specimen (a test that never goes below its reference
   state) cannot carry compression: ``P = max(P, 0)`` — it buckles;
6. load-cell offset and drift: ``P + o_f + d_f (t - t_0)/T_f``. These enter
   linearly and are eliminated in closed form (variable projection) at every
   evaluation; their intervals come from the full Jacobian at the end.

The Jacobian is by forward differences, evaluated per block: a file's own
parameters perturb only that file's residuals, and perturbing an effect
parameter reuses the cached base stresses.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize

from ..blas import single_threaded_blas
from ..calibrate.problem import NAN_PENALTY, layout_for, stress_scale
from ..errors import FitError
from ..materials.effects import (
    ARTEFACTS,
    MATERIAL_EFFECTS,
    DamageEffect,
    MaterialEffects,
    MullinsEffect,
    ViscoelasticEffect,
    damage_factor,
    equivalent_stretch,
    mullins_factor,
    qlv_stress,
)
from ..materials.loading import energy_density, invariants, nominal_stress
from ..tensile.data import TensileTest
from .covariates import Covariates, covariates, thin

#: variants of each effect: name -> allowed variant numbers (0 = off)
VARIANTS = {
    "viscoelastic": (1, 2, 3),  # Prony terms
    "mullins": (2, 3),  # (r, m) or (r, m, beta)
    "damage": (3,),  # (onset, scale, shape)
    "slack": (1,),  # one slack length per file
    "sensor_offset": (1, 2),  # offset, or offset + linear drift, per file
}
#: Prony weights are stick-broken fractions u_i in [0, U_MAX]
U_MAX = 0.995


@dataclass(frozen=True)
class Spec:
    """Which effects a model has, and in which variant (0 = absent)."""

    viscoelastic: int = 0
    mullins: int = 0
    damage: int = 0
    slack: int = 0
    sensor_offset: int = 0

    def names(self) -> list[str]:
        return [n for n in MATERIAL_EFFECTS + ARTEFACTS if getattr(self, n)]

    def with_(self, name: str, variant: int) -> Spec:
        return replace(self, **{name: int(variant)})

    def variant_text(self, name: str) -> str:
        v = getattr(self, name)
        if name == "viscoelastic":
            return f"{v} Prony term{'s' if v != 1 else ''}"
        if name == "mullins":
            return "r, m, beta" if v == 3 else "r, m (beta = 0)"
        if name == "sensor_offset":
            return "offset and drift" if v == 2 else "offset"
        if name == "slack":
            return "one slack length per file"
        if name == "damage":
            return "onset, scale, shape"
        return str(v)

    def to_dict(self) -> dict[str, int]:
        return {n: getattr(self, n) for n in MATERIAL_EFFECTS + ARTEFACTS}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Spec:
        return cls(**{n: int(d.get(n, 0)) for n in MATERIAL_EFFECTS + ARTEFACTS})


# --------------------------------------------------------------------------- records
@dataclass
class Record:
    """One test prepared for fitting: covariates, thinned indices, scales."""

    test: TensileTest
    cov: Covariates
    fit_idx: np.ndarray  # (m,) thinned sample indices
    weight: float = 1.0

    def __post_init__(self):
        t = self.test
        self.x = np.asarray(t.stretch, float)
        self.y = np.asarray(t.stress, float)
        self.t = None if not self.cov.has_time else np.asarray(t.time, float)
        self.scale = stress_scale(self.y)
        self.range = float(np.ptp(self.y)) or self.scale
        ref = 0.0 if t.mode == "simple_shear" else 1.0
        x0 = float(np.min(self.x)) if t.mode != "simple_shear" else -1.0
        #: a test that never goes below its reference state (tension only)
        self.tension_only = t.mode != "simple_shear" and x0 >= ref - 1e-3 * (float(np.ptp(self.x)) or 1.0)
        self.area = t.metadata.get("area")
        self.gauge = t.metadata.get("gauge_length")
        self.T = float(self.t[-1] - self.t[0]) if self.t is not None else 0.0

    @property
    def name(self) -> str:
        return self.test.source.name

    @property
    def key(self) -> str | None:
        return self.test.orientation

    @property
    def history(self) -> bool:
        return self.cov.has_time


def prepare(tests: Sequence[TensileTest], *, max_points: int = 600,
            weights: Sequence[float] | None = None) -> list[Record]:
    """Covariates and thinned fitting samples of every test."""
    out = []
    for i, t in enumerate(tests):
        cov = covariates(t)
        idx = thin(t, max_points, cov=cov)
        out.append(Record(t, cov, idx, 1.0 if weights is None else float(weights[i])))
    return out


def view_test(rec: Record, idx: np.ndarray | None = None) -> TensileTest:
    """A TensileTest restricted to *idx* (default: the fitting samples)."""
    idx = rec.fit_idx if idx is None else idx
    t = rec.test

    def sub(a):
        return None if a is None else np.asarray(a)[idx]

    return TensileTest(source=t.source, mode=t.mode, stretch=sub(t.stretch), stress=sub(t.stress),
                       time=sub(t.time), displacement=sub(t.displacement), force=sub(t.force),
                       metadata=t.metadata)


# --------------------------------------------------------------------------- slots
@dataclass
class Slot:
    """One optimiser coordinate."""

    name: str  # reported name, e.g. "mu", "tau[1]", "slack"
    effect: str | None  # None: base parameter
    file: int | None  # None: shared; else record index
    log: bool
    lo: float
    hi: float
    kind: str = "dimensionless"  # "stress", "time", "dimensionless"
    direction: str | None = None

    @property
    def key(self) -> str:
        k = self.name if self.effect is None else f"{self.effect}.{self.name}"
        if self.direction:
            k += f"[{self.direction}]"
        return k


@dataclass
class State:
    """Parameter values decoded from an optimiser vector (SI)."""

    base: dict[str | None, dict[str, float]]
    g: np.ndarray | None = None
    tau: np.ndarray | None = None
    mullins: tuple[float, float, float] | None = None  # (r, m, beta)
    damage: tuple[float, float, float] | None = None  # (onset, scale, shape)
    slack: np.ndarray | None = None  # (n_files,) relative slack delta = s / L0
    offsets: list[np.ndarray] = field(default_factory=list)  # per file: [o] or [o, d] (Pa)

    def material_effects(self) -> MaterialEffects:
        v = m = d = None
        if self.g is not None:
            v = ViscoelasticEffect(tuple(self.g), tuple(self.tau))
        if self.mullins is not None:
            r, mm, b = self.mullins
            m = MullinsEffect(r, mm, b)
        if self.damage is not None:
            d = DamageEffect(*self.damage)
        return MaterialEffects(v, m, d)


class Bounds:
    """Data-derived bounds of the effect parameters (fixed for a whole discovery)."""

    def __init__(self, records: Sequence[Record], w_ref: float):
        dts = [float(np.median(np.diff(r.t))) for r in records if r.t is not None and r.t.size > 1]
        Ts = [r.T for r in records if r.t is not None]
        self.tau_min = max(min(dts) * 0.5, 1e-4) if dts else 1e-3
        self.tau_max = max(Ts) * 10.0 if Ts else 1e3
        self.w_ref = max(w_ref, 1e-12)  # largest base strain energy in the data [Pa]
        xi = [float(np.max(r.cov.drive)) for r in records]
        self.xi_max = max(xi) if xi else 1.0
        self.xi_span = max(self.xi_max - 1.0, 1e-3)

    def to_dict(self) -> dict[str, float]:
        return dict(tau_min=self.tau_min, tau_max=self.tau_max, w_ref=self.w_ref,
                    xi_max=self.xi_max)

    @classmethod
    def from_dict(cls, d: Mapping[str, float]) -> Bounds:
        b = cls.__new__(cls)
        b.tau_min, b.tau_max, b.w_ref = float(d["tau_min"]), float(d["tau_max"]), float(d["w_ref"])
        b.xi_max = float(d["xi_max"])
        b.xi_span = max(b.xi_max - 1.0, 1e-3)
        return b


def slack_applicable(rec: Record) -> bool:
    """Slack is a tension-test artefact whose record starts at the reference state."""
    if not rec.tension_only or rec.test.mode == "simple_shear":
        return False
    span = float(np.ptp(rec.x)) or 0.0
    return span > 0 and float(rec.x[0]) - 1.0 <= 0.05 * span


def offset_applicable(rec: Record) -> bool:
    """A load-cell offset is separable where the data reach the reference state (P_model = 0)."""
    ref = 0.0 if rec.test.mode == "simple_shear" else 1.0
    span = float(np.ptp(rec.x)) or 1.0
    return float(np.min(np.abs(rec.x - ref))) <= 0.05 * span


def drift_applicable(rec: Record) -> bool:
    """A drift is separable from the material only where the zero-force state is seen early *and* late.

    That is a test that starts and ends near its reference state (a load-unload
    cycle, or a tension test whose slack specimen reads zero force at the end).
    In a relaxation test the drift would be indistinguishable from slow relaxation.
    """
    if rec.t is None or rec.T <= 0:
        return False
    ref = 0.0 if rec.test.mode == "simple_shear" else 1.0
    span = float(np.ptp(rec.x)) or 1.0
    near = np.abs(rec.x - ref) <= 0.05 * span
    tn = (rec.t - rec.t[0]) / rec.T
    return bool(np.any(near & (tn <= 0.25)) and np.any(near & (tn >= 0.75)))


# --------------------------------------------------------------------------- problem
class Problem:
    """The least-squares problem of one model (base + effects) on some records.

    Parameters
    ----------
    model : MaterialModel
    records : sequence of Record
    spec : Spec
    fixed : mapping
        Base parameters held (SI).
    directions : list of str or None
        Fibre directions of an anisotropic fit (as the calibrate fit).
    bounds : Bounds
    train : list of (ndarray or None), optional
        Per record: positions *within its fitting samples* that enter the
        objective (None: all). Records with an empty array are predicted (for
        their history) but do not count.
    """

    def __init__(self, model, records: Sequence[Record], spec: Spec, *, fixed: Mapping[str, float],
                 directions: list[str] | None, bounds: Bounds, train=None):
        self.model = model
        self.records = list(records)
        self.spec = spec
        self.fixed = dict(fixed)
        self.directions = directions
        self.bounds = bounds
        # the base parameters' slots: those of the calibrate fit on the fitting samples
        self.layout = layout_for(model, [view_test(r) for r in self.records], fixed=self.fixed,
                                 directions=directions)
        slots = [Slot(s.name, None, None, s.log, s.lo, s.hi, s.kind, s.direction) for s in self.layout.slots]
        self.n_base = len(slots)
        b = bounds
        if spec.viscoelastic:
            for i in range(spec.viscoelastic):
                slots.append(Slot(f"u[{i}]", "viscoelastic", None, False, 0.0, U_MAX))
                slots.append(Slot(f"tau[{i}]", "viscoelastic", None, True, math.log(b.tau_min),
                                  math.log(b.tau_max), "time"))
        if spec.mullins:
            slots.append(Slot("s", "mullins", None, False, 0.0, 0.99))  # s = 1/r
            slots.append(Slot("m", "mullins", None, True, math.log(1e-5 * b.w_ref),
                              math.log(10.0 * b.w_ref), "stress"))
            if spec.mullins == 3:
                slots.append(Slot("beta", "mullins", None, False, 0.0, 5.0))
        if spec.damage:
            slots.append(Slot("onset", "damage", None, False, 1.0, b.xi_max))
            slots.append(Slot("scale", "damage", None, True, math.log(1e-3 * b.xi_span),
                              math.log(10.0 * b.xi_span)))
            slots.append(Slot("shape", "damage", None, False, 1.0, 8.0))
        self.n_shared = len(slots)
        self.slack_files = []
        if spec.slack:
            for k, r in enumerate(self.records):
                if slack_applicable(r):
                    hi = max(0.5 * (float(np.max(r.x)) - 1.0), 1e-6)
                    slots.append(Slot("slack", "slack", k, False, 0.0, hi))
                    self.slack_files.append(k)
        self.slots = slots
        self.lower = np.array([s.lo for s in slots])
        self.upper = np.array([s.hi for s in slots])
        self.n_offset = [0] * len(self.records)
        if spec.sensor_offset:
            for k, r in enumerate(self.records):
                if offset_applicable(r):
                    self.n_offset[k] = 2 if (spec.sensor_offset == 2 and drift_applicable(r)) else 1
        self.set_train(train)
        self._cache: list[dict] = [dict() for _ in self.records]
        self.active = np.arange(len(slots))
        self.z_full = self.default_z()

    def derived(self, spec: Spec | None = None, *, train=None) -> Problem:
        """The problem of the same records, base and bounds with another *spec* and/or training set."""
        return Problem(self.model, self.records, self.spec if spec is None else spec, fixed=self.fixed,
                       directions=self.directions, bounds=self.bounds, train=train)

    # ------------------------------------------------------------ layout
    def set_train(self, train) -> None:
        m = len(self.records)
        self.train = [None] * m if train is None else list(train)
        self.factor = np.zeros(m)
        self.n_train = np.zeros(m, dtype=int)
        for k, r in enumerate(self.records):
            n = r.fit_idx.size if self.train[k] is None else len(self.train[k])
            self.n_train[k] = n
            self.factor[k] = math.sqrt(r.weight / n) if n else 0.0
        self._X = [self._design(k) for k in range(m)]

    def _design(self, k: int):
        n_o = self.n_offset[k] if hasattr(self, "n_offset") else 0
        if not n_o:
            return None
        r = self.records[k]
        cols = [np.ones(r.fit_idx.size)]
        if n_o == 2:
            tt = r.t[r.fit_idx]
            cols.append((tt - r.t[0]) / (r.T or 1.0))
        X = np.stack(cols, axis=1)
        pos = self.train[k]
        return X if pos is None else X[pos]

    def keys(self) -> list[str]:
        return [s.key if s.file is None else f"{s.key}[{self.records[s.file].name}]" for s in self.slots]

    def default_z(self) -> np.ndarray:
        """A neutral starting vector: base defaults; effects nearly off."""
        z = np.empty(len(self.slots))
        z[: self.n_base] = self.layout.from_params({**self.model.defaults(), **self.fixed})
        b = self.bounds
        for i, s in enumerate(self.slots[self.n_base:], start=self.n_base):
            if s.effect == "viscoelastic":
                j = int(s.name[s.name.index("[") + 1:-1])
                n = self.spec.viscoelastic
                if s.name.startswith("u"):
                    z[i] = 0.2
                else:
                    z[i] = math.log(b.tau_min) + (j + 1) / (n + 1) * (math.log(b.tau_max / 10) - math.log(b.tau_min))
            elif s.effect == "mullins":
                z[i] = {"s": 0.3, "m": math.log(0.1 * b.w_ref), "beta": 0.0}[s.name]
            elif s.effect == "damage":
                z[i] = {"onset": 1.0 + 0.7 * b.xi_span, "scale": math.log(0.2 * b.xi_span), "shape": 2.0}[s.name]
            elif s.effect == "slack":
                z[i] = 0.0
        return np.clip(z, self.lower, self.upper)

    def set_base(self, z_full: np.ndarray, params: Mapping[str | None, Mapping[str, float]]) -> np.ndarray:
        """Write base parameter values (per direction, SI) into *z_full*."""
        z = z_full.copy()
        for i, s in enumerate(self.slots[: self.n_base]):
            src = params.get(s.direction) if s.direction else params.get(None)
            if src is None or s.name not in src:
                continue
            v = float(src[s.name])
            z[i] = math.log(max(v, 1e-300)) if s.log else v
        return np.clip(z, self.lower, self.upper)

    def encode(self, base: Mapping[str | None, Mapping[str, float]], effects: MaterialEffects | None = None,
               ) -> np.ndarray:
        """Optimiser vector from base parameters (per direction, SI) and material effects.

        Slots of effects absent from *effects* keep their neutral defaults;
        per-file artefact slots start at zero.
        """
        z = self.set_base(self.default_z(), base)
        vals: dict[tuple[str, str], float] = {}
        if effects is not None and effects.viscoelastic is not None:
            rest = 1.0
            for j, (g, tau) in enumerate(zip(effects.viscoelastic.g, effects.viscoelastic.tau)):
                u = g / rest if rest > 0 else 0.0
                rest -= g
                vals[("viscoelastic", f"u[{j}]")] = u
                vals[("viscoelastic", f"tau[{j}]")] = math.log(tau)
        if effects is not None and effects.mullins is not None:
            vals[("mullins", "s")] = 1.0 / effects.mullins.r
            vals[("mullins", "m")] = math.log(effects.mullins.m)
            vals[("mullins", "beta")] = effects.mullins.beta
        if effects is not None and effects.damage is not None:
            vals[("damage", "onset")] = effects.damage.onset
            vals[("damage", "scale")] = math.log(effects.damage.scale)
            vals[("damage", "shape")] = effects.damage.shape
        for i, s in enumerate(self.slots):
            if (s.effect, s.name) in vals:
                z[i] = vals[(s.effect, s.name)]  # not clipped: a saved value stands as it is
        return z

    def transfer(self, other: Problem, z_other: np.ndarray) -> np.ndarray:
        """Map another problem's vector onto this one (matching slots by key and file name)."""
        z = self.default_z()
        src = {}
        for s, v in zip(other.slots, z_other):
            fname = other.records[s.file].name if s.file is not None else None
            src[(s.key, fname)] = v
        for i, s in enumerate(self.slots):
            fname = self.records[s.file].name if s.file is not None else None
            if (s.key, fname) in src:
                z[i] = src[(s.key, fname)]
        return np.clip(z, self.lower, self.upper)

    # ------------------------------------------------------------ decoding
    def state(self, z_full: np.ndarray) -> State:
        per_dir = self.layout.to_params(z_full[: self.n_base])
        st = State(base=per_dir)
        sl = self.slots
        if self.spec.viscoelastic:
            n = self.spec.viscoelastic
            us, taus = [], []
            for i in range(self.n_base, self.n_shared):
                if sl[i].effect == "viscoelastic":
                    (us if sl[i].name.startswith("u") else taus).append(z_full[i])
            g, rest = [], 1.0
            for u in us[:n]:
                g.append(rest * u)
                rest *= 1.0 - u
            st.g = np.array(g)
            st.tau = np.exp(np.array(taus[:n]))
        if self.spec.mullins:
            vals = {sl[i].name: z_full[i] for i in range(self.n_base, self.n_shared) if sl[i].effect == "mullins"}
            s = max(vals["s"], 1e-12)
            st.mullins = (1.0 / s, math.exp(vals["m"]), vals.get("beta", 0.0))
        if self.spec.damage:
            vals = {sl[i].name: z_full[i] for i in range(self.n_base, self.n_shared) if sl[i].effect == "damage"}
            st.damage = (vals["onset"], math.exp(vals["scale"]), vals["shape"])
        slack = np.zeros(len(self.records))
        for i in range(self.n_shared, len(sl)):
            if sl[i].effect == "slack":
                slack[sl[i].file] = z_full[i]
        st.slack = slack
        return st

    # ------------------------------------------------------------ forward model
    def _key(self, k: int, st: State):
        r = self.records[k]
        params = st.base[r.key if self.directions else None]
        delta = float(st.slack[k]) if st.slack is not None else 0.0
        return (tuple(sorted(params.items())), delta), params, delta

    def _compute_elastic(self, mode: str, params, xs: list[np.ndarray]):
        """(P_e, W, ξ) for several stretch arrays of one mode and parameter set, in one call each."""
        x = np.concatenate(xs) if len(xs) > 1 else xs[0]
        with np.errstate(all="ignore"):
            pe = np.asarray(nominal_stress(self.model, params, mode, x), float)
            w = np.asarray(energy_density(self.model, params, mode, x), float) if self.spec.mullins else None
            xi = None
            if self.spec.damage:
                i1, _ = invariants(mode, x)
                xi = equivalent_stretch(i1)
        cuts = np.cumsum([a.size for a in xs])[:-1]

        def split(a):
            return [None] * len(xs) if a is None else np.split(a, cuts)

        return list(zip(split(pe), split(w), split(xi)))

    def _x_true(self, k: int, delta: float, idx: np.ndarray) -> np.ndarray:
        x = self.records[k].x[idx]
        return np.maximum(x / (1.0 + delta), 1.0) if delta > 0.0 else x

    def _remember(self, k: int, key, value) -> None:
        c = self._cache[k]
        c[key] = value
        while len(c) > 24:
            c.pop(next(iter(c)))

    def prefetch(self, st: State, ks) -> None:
        """Compute the elastic responses of records *ks* missing from the cache, batched by mode."""
        groups: dict = {}
        for k in ks:
            key, params, delta = self._key(k, st)
            c = self._cache[k]
            if key in c:
                c[key] = c.pop(key)  # most recently used
                continue
            gk = (self.records[k].test.mode, key[0])
            groups.setdefault(gk, (params, []))[1].append((k, key, delta))
        for (mode, _), (params, items) in groups.items():
            xs = [self._x_true(k, delta, self.records[k].fit_idx) for k, key, delta in items]
            for (k, key, _), val in zip(items, self._compute_elastic(mode, params, xs)):
                self._remember(k, key, val)

    def _elastic(self, k: int, st: State, idx: np.ndarray, use_cache: bool):
        """(P_e, W, ξ) on samples *idx* of record k (after slack)."""
        key, params, delta = self._key(k, st)
        if use_cache:
            hit = self._cache[k].get(key)
            if hit is None:
                self.prefetch(st, [k])
                hit = self._cache[k][key]
            return hit
        return self._compute_elastic(self.records[k].test.mode, params, [self._x_true(k, delta, idx)])[0]

    def predict(self, k: int, st: State, idx: np.ndarray | None = None, *, use_cache: bool = True) -> np.ndarray:
        """Model stress of record k on samples *idx* (default: its fitting samples), before offsets."""
        r = self.records[k]
        if idx is None:
            idx = r.fit_idx
        else:
            use_cache = False
        p = self.softened(k, st, idx, use_cache=use_cache)
        if st.g is not None and r.t is not None:
            p = qlv_stress(r.t[idx], p, st.g, st.tau)
        if r.tension_only:
            p = np.maximum(p, 0.0)
        return p

    def softened(self, k: int, st: State, idx: np.ndarray, *, use_cache: bool = True) -> np.ndarray:
        """Elastic stress after slack, damage and Mullins softening (before relaxation)."""
        r = self.records[k]
        pe, w, xi = self._elastic(k, st, idx, use_cache)
        p = pe
        if st.damage is not None:
            xm = np.maximum.accumulate(xi) if r.history else xi
            p = p * damage_factor(xm, *st.damage)
        if st.mullins is not None and r.history:
            wm = np.maximum.accumulate(np.where(np.isfinite(w), w, np.inf))
            with np.errstate(invalid="ignore"):
                p = p * mullins_factor(w, wm, *st.mullins)
        return p

    def add_offsets(self, k: int, pred: np.ndarray, coef: np.ndarray | None, idx: np.ndarray | None = None,
                    ) -> np.ndarray:
        """*pred* of record k on samples *idx* (default: its fitting samples) plus its offset and drift *coef*."""
        X = self.offset_columns(k, self.records[k].fit_idx if idx is None else idx)
        return pred if X is None or coef is None else pred + X @ coef

    @contextlib.contextmanager
    def offsets_held(self) -> Iterator[None]:
        """Within: the offsets are not eliminated in closed form (derivatives at fixed offsets)."""
        saved = self._X
        self._X = [None] * len(self.records)
        try:
            yield
        finally:
            self._X = saved

    def offset_columns(self, k: int, idx: np.ndarray) -> np.ndarray | None:
        n_o = self.n_offset[k]
        if not n_o:
            return None
        r = self.records[k]
        cols = [np.ones(idx.size)]
        if n_o == 2:
            cols.append((r.t[idx] - r.t[0]) / (r.T or 1.0))
        return np.stack(cols, axis=1)

    def residual_block(self, k: int, st: State) -> tuple[np.ndarray, np.ndarray | None]:
        """Normalised residual block of record k (training samples) and its offset coefficients."""
        r = self.records[k]
        pred = self.predict(k, st)
        pos = self.train[k]
        y = r.y[r.fit_idx]
        if pos is not None:
            pred, y = pred[pos], y[pos]
        res = pred - y
        coef = None
        X = self._X[k]
        if X is not None and res.size:
            good = np.isfinite(res)
            if good.sum() > X.shape[1]:
                coef, *_ = np.linalg.lstsq(X[good], -res[good], rcond=None)
                res = res + X @ coef
        out = self.factor[k] * res / r.scale
        bad = ~np.isfinite(out)
        if bad.any():
            out[bad] = NAN_PENALTY
        return out, coef

    # ------------------------------------------------------------ objective
    def _full(self, z: np.ndarray) -> np.ndarray:
        zf = self.z_full.copy()
        zf[self.active] = z
        return zf

    def residuals(self, z: np.ndarray) -> np.ndarray:
        st = self.state(self._full(z))
        self.prefetch(st, [k for k in range(len(self.records)) if self.n_train[k]])
        blocks = [self.residual_block(k, st)[0] if self.n_train[k] else np.zeros(0) for k in range(len(self.records))]
        return np.concatenate(blocks)

    def jac(self, z: np.ndarray) -> np.ndarray:
        zf = self._full(z)
        st0 = self.state(zf)
        self.prefetch(st0, [k for k in range(len(self.records)) if self.n_train[k]])
        base_blocks = [self.residual_block(k, st0)[0] if self.n_train[k] else np.zeros(0)
                       for k in range(len(self.records))]
        offs = np.concatenate([[0], np.cumsum([b.size for b in base_blocks])])
        r0 = np.concatenate(base_blocks)
        J = np.zeros((r0.size, len(self.active)))
        for c, i in enumerate(self.active):
            s = self.slots[i]
            h = 1e-6 * max(1.0, abs(zf[i]))
            if zf[i] + h > self.upper[i]:
                h = -h
            zp = zf.copy()
            zp[i] += h
            stp = self.state(zp)
            files = [k for k in range(len(self.records)) if self.n_train[k]] if s.file is None else [s.file]
            self.prefetch(stp, files)
            for k in files:
                if not self.n_train[k]:
                    continue
                J[offs[k]:offs[k + 1], c] = (self.residual_block(k, stp)[0] - base_blocks[k]) / h
        return J

    def cost(self, z: np.ndarray) -> float:
        r = self.residuals(z)
        return 0.5 * float(r @ r)

    def solve(self, z_full0: np.ndarray, *, active: Sequence[int] | None = None, max_nfev: int | None = None,
              ftol: float = 1e-5):
        """Least squares from *z_full0* over the *active* slots (default: all); returns z_full."""
        self.z_full = np.asarray(z_full0, float).copy()
        self.active = np.arange(len(self.slots)) if active is None else np.asarray(active, dtype=int)
        if self.active.size == 0:
            return self.z_full.copy(), None
        lo, hi = self.lower[self.active], self.upper[self.active]
        z0 = np.clip(self.z_full[self.active], lo, hi)
        # keep strictly inside for trf
        z0 = np.where(z0 <= lo, lo + 1e-10 * np.maximum(1, np.abs(lo)), z0)
        z0 = np.where(z0 >= hi, hi - 1e-10 * np.maximum(1, np.abs(hi)), z0)
        try:
            with single_threaded_blas():
                sol = optimize.least_squares(self.residuals, z0, jac=self.jac, bounds=(lo, hi),
                                             x_scale="jac", method="trf", ftol=ftol, xtol=1e-8,
                                             max_nfev=max_nfev or 12 * (self.active.size + 2))
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise FitError(f"the extended fit failed ({exc}); check the data") from None
        zf = self._full(sol.x)
        self.z_full = zf
        return zf, sol

    # ------------------------------------------------------------ evaluation
    def offsets(self, z_full: np.ndarray) -> list[np.ndarray | None]:
        """Offset/drift coefficients (Pa) per record, as estimated on its training samples."""
        st = self.state(z_full)
        return [self.residual_block(k, st)[1] if self.n_train[k] else None for k in range(len(self.records))]

    def full_prediction(self, k: int, z_full: np.ndarray, coef=None) -> np.ndarray:
        """Prediction of record k on *all* its samples, with its offsets applied."""
        st = self.state(z_full)
        r = self.records[k]
        idx = np.arange(r.test.n)
        return self.add_offsets(k, self.predict(k, st, idx), coef, idx)

    def fit_residuals(self, z_full: np.ndarray) -> list[np.ndarray]:
        """Unnormalised residuals (Pa, model - data) on each record's training samples."""
        st = self.state(z_full)
        out = []
        for k, r in enumerate(self.records):
            if not self.n_train[k]:
                out.append(np.zeros(0))
                continue
            blk, _ = self.residual_block(k, st)
            out.append(blk * r.scale / self.factor[k])
        return out

    def n_params(self) -> int:
        """Free parameters: active slots + offset coefficients of the training records."""
        return int(len(self.active) + sum(n for k, n in enumerate(self.n_offset) if self.n_train[k]))
