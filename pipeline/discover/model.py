r"""The extended model: a hyperelastic base plus effects, and its least-squares fit.

The objective is the one of :func:`esmm.pipeline.calibrate.fit.fit_material`
(docs/calibrate.md), so that a base model fitted here and there agree:

.. math::

    r_{f,k} = \sqrt{w_f / n_f}\;\frac{\hat P_{f,k}(\theta, \phi, \psi_f) - P_{f,k}}{s_f},
    \qquad s_f = \max_k |P_{f,k}|,

with θ the base parameters (laid out, bounded and log-transformed exactly as
the calibrate fit does: its ``_Problem`` provides the slots), φ the material
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

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize, stats

from ..blas import single_threaded_blas
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
#: where a NaN (outside the model's domain) appears, the normalised residual is this
NAN_PENALTY = 1e3
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
        self.scale = max(float(np.max(np.abs(self.y))), 1e-30)
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
        from ..calibrate.fit import _Problem

        self.model = model
        self.records = list(records)
        self.spec = spec
        self.fixed = dict(fixed)
        self.directions = directions
        self.bounds = bounds
        views = [view_test(r) for r in self.records]
        self._base = _Problem(model, views, [r.weight for r in self.records], self.fixed, directions)
        slots: list[Slot] = []
        for s in self._base.slots:
            slots.append(Slot(s.name, None, None, s.log, s.lo, s.hi, s.kind, s.direction))
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
        from ..calibrate.fit import _defaults

        z = np.empty(len(self.slots))
        z[: self.n_base] = self._base.from_params({**_defaults(self.model), **self.fixed})
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
        per_dir = self._base.to_params(z_full[: self.n_base])
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
        from ..materials.loading import energy_density, invariants, nominal_stress

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

    def offset_columns(self, k: int, idx: np.ndarray) -> np.ndarray | None:
        n_o = self.n_offset[k]
        if not n_o:
            return None
        r = self.records[k]
        cols = [np.ones(idx.size)]
        if n_o == 2:
            cols.append((r.t[idx] - r.t[0]) / (r.T or 1.0))
        return np.stack(cols, axis=1)

    def _block(self, k: int, st: State) -> tuple[np.ndarray, np.ndarray | None]:
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
        blocks = [self._block(k, st)[0] if self.n_train[k] else np.zeros(0) for k in range(len(self.records))]
        return np.concatenate(blocks)

    def jac(self, z: np.ndarray) -> np.ndarray:
        zf = self._full(z)
        st0 = self.state(zf)
        self.prefetch(st0, [k for k in range(len(self.records)) if self.n_train[k]])
        base_blocks = [self._block(k, st0)[0] if self.n_train[k] else np.zeros(0)
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
                J[offs[k]:offs[k + 1], c] = (self._block(k, stp)[0] - base_blocks[k]) / h
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
        return [self._block(k, st)[1] if self.n_train[k] else None for k in range(len(self.records))]

    def full_prediction(self, k: int, z_full: np.ndarray, coef=None) -> np.ndarray:
        """Prediction of record k on *all* its samples, with its offsets applied."""
        st = self.state(z_full)
        r = self.records[k]
        idx = np.arange(r.test.n)
        p = self.predict(k, st, idx)
        X = self.offset_columns(k, idx)
        if X is not None and coef is not None:
            p = p + X @ coef
        return p

    def fit_residuals(self, z_full: np.ndarray) -> list[np.ndarray]:
        """Unnormalised residuals (Pa, model - data) on each record's training samples."""
        st = self.state(z_full)
        out = []
        for k, r in enumerate(self.records):
            if not self.n_train[k]:
                out.append(np.zeros(0))
                continue
            blk, _ = self._block(k, st)
            out.append(blk * r.scale / self.factor[k])
        return out

    def n_params(self) -> int:
        """Free parameters: active slots + offset coefficients of the training records."""
        return int(len(self.active) + sum(n for k, n in enumerate(self.n_offset) if self.n_train[k]))


# --------------------------------------------------------------------------- statistics
def lag1(r: np.ndarray) -> float:
    """Lag-1 autocorrelation of a residual sequence (0 for fewer than 3 values)."""
    r = np.asarray(r, float)
    r = r[np.isfinite(r)]
    if r.size < 3:
        return 0.0
    r = r - r.mean()
    den = float(r @ r)
    return 0.0 if den == 0 else float(r[:-1] @ r[1:] / den)


def runs_test(r: np.ndarray) -> tuple[int, float]:
    """Wald-Wolfowitz runs test of the residual signs: (runs, z-score; z << 0 = too few runs)."""
    s = np.sign(np.asarray(r, float))
    s = s[s != 0]
    n = s.size
    if n < 3:
        return 0, 0.0
    n1 = int((s > 0).sum())
    n2 = n - n1
    runs = 1 + int(np.count_nonzero(s[1:] != s[:-1]))
    if n1 == 0 or n2 == 0:
        return runs, -math.inf
    mu = 2.0 * n1 * n2 / n + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    return runs, (runs - mu) / math.sqrt(var) if var > 0 else 0.0


#: lag-1 autocorrelation is clipped to this for the effective sample size
RHO_MAX = 0.98
#: ... and a file counts for at least this many effective samples (or its size)
NU_MIN = 5.0


def n_effective(res: Sequence[np.ndarray]) -> list[float]:
    """Effective sample sizes per record: ``n (1-ρ)/(1+ρ)``, ρ = lag-1 autocorrelation in [0, RHO_MAX],
    at least ``min(n, NU_MIN)``."""
    out = []
    for r in res:
        rho = min(max(lag1(r), 0.0), RHO_MAX)
        out.append(max(r.size * (1.0 - rho) / (1.0 + rho), min(float(r.size), NU_MIN)))
    return out


def information(res: Sequence[np.ndarray], n_eff: Sequence[float], k: int) -> dict[str, float]:
    """Gaussian log-likelihood with one noise level per file, AICc and BIC on effective sizes.

    ``logL = -sum_f nu_f/2 (log(2 pi RSS_f/n_f) + 1)``, ``N = sum_f nu_f``,
    ``AICc = -2 logL + 2k + 2k(k+1)/max(N-k-1, 1)``, ``BIC = -2 logL + k log N``.
    """
    ll = 0.0
    N = 0.0
    for r, nu in zip(res, n_eff):
        if r.size == 0:
            continue
        rss = float(np.sum(r[np.isfinite(r)] ** 2)) or 1e-300
        ll += -0.5 * nu * (math.log(2 * math.pi * rss / r.size) + 1.0)
        N += nu
    # small-sample correction; its denominator is floored at 1 so that the criterion
    # stays finite (and heavily penalising) when the effective size is tiny
    corr = 2.0 * k * (k + 1) / max(N - k - 1, 1.0)
    return {"loglik": ll, "aicc": -2 * ll + 2 * k + corr, "bic": -2 * ll + k * math.log(max(N, 1.0)),
            "n_eff": N, "k": k}


@dataclass
class Estimate:
    """A reported parameter with its 95 % interval (SI)."""

    key: str
    value: float
    lower: float
    upper: float
    unit: str = ""
    wide: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "ci95": [self.lower, self.upper], "unit": self.unit,
                "not_identifiable": self.wide}


def estimates(problem: Problem, z_full: np.ndarray) -> list[Estimate]:
    """Parameters of *problem* at *z_full* with 95 % intervals.

    Covariance ``s² (JᵀJ)⁻¹`` over all slots plus the offset coefficients
    (explicit columns), inflated by ``(1+ρ)/(1-ρ)`` as in the calibrate fit;
    derived parameters (Prony weights, r, offsets in N) by the delta method.
    """
    prob = problem
    prob.z_full = z_full.copy()
    prob.active = np.arange(len(prob.slots))
    st = prob.state(z_full)
    coefs = prob.offsets(z_full)
    # Jacobian at fixed offsets: FD over slots with the projection switched off
    saved = prob._X
    prob._X = [None] * len(prob.records)
    try:
        # residuals with the fitted offsets added explicitly
        def res_fixed(zz, cf):
            zf = z_full.copy()
            zf[prob.active] = zz
            s = prob.state(zf)
            out = []
            for k, r in enumerate(prob.records):
                if not prob.n_train[k]:
                    continue
                p = prob.predict(k, s)
                X = prob.offset_columns(k, r.fit_idx)
                if X is not None and cf[k] is not None:
                    p = p + X @ cf[k]
                pos = prob.train[k]
                y = r.y[r.fit_idx]
                if pos is not None:
                    p, y = p[pos], y[pos]
                o = prob.factor[k] * (p - y) / r.scale
                out.append(np.where(np.isfinite(o), o, NAN_PENALTY))
            return np.concatenate(out)

        r0 = res_fixed(z_full, coefs)
        Js = prob.jac(z_full)  # projection off: plain derivatives
        cols = [Js]
        off_keys = []
        for k, r in enumerate(prob.records):
            if not prob.n_train[k] or coefs[k] is None:
                continue
            X = prob.offset_columns(k, r.fit_idx)
            pos = prob.train[k]
            if pos is not None:
                X = X[pos]
            block = np.zeros((r0.size, X.shape[1]))
            start = int(sum(prob.n_train[j] for j in range(k) if prob.n_train[j]))
            block[start:start + X.shape[0]] = prob.factor[k] * X / r.scale
            cols.append(block)
            off_keys += [(k, j) for j in range(X.shape[1])]
        J = np.concatenate(cols, axis=1)
    finally:
        prob._X = saved
    n, p = J.shape
    dof = max(n - p, 1)
    s2 = float(r0 @ r0) / dof
    rhos = [lag1(b) for b in prob.fit_residuals(z_full) if b.size]
    ns = [b.size for b in prob.fit_residuals(z_full) if b.size]
    rho = float(np.clip(np.average(rhos, weights=ns), 0.0, 0.99)) if ns else 0.0
    infl = (1 + rho) / (1 - rho)
    # as the calibrate fit: the pseudo-inverse on the identified subspace; a
    # quantity with weight in the null space (relative singular value < 1e-7) is unbounded
    _, sv, Vt = np.linalg.svd(J, full_matrices=False)
    null = sv <= 1e-7 * sv.max() if sv.size and sv.max() > 0 else np.ones_like(sv, bool)
    keep = ~null
    cov = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep] * s2 * infl
    Vnull = Vt[null]
    tq = float(stats.t.ppf(0.975, dof))
    out: list[Estimate] = []

    def add(key, grad, value, *, positive, unit=""):
        var = float(grad @ cov @ grad)
        gn = float(np.linalg.norm(grad)) or 1.0
        if Vnull.size and float(np.sum((Vnull @ grad) ** 2)) / gn**2 > 1e-2:
            var = math.inf
        sd = math.sqrt(max(var, 0.0)) if math.isfinite(var) else math.inf
        if positive and value > 0:
            sl = sd / value
            lo = value * math.exp(-tq * sl) if math.isfinite(sl) else 0.0
            hi = value * math.exp(min(tq * sl, 700)) if math.isfinite(sl) else math.inf
            wide = (not math.isfinite(sl)) or hi / max(lo, 1e-300) > 10.0
        else:
            lo, hi = value - tq * sd, value + tq * sd
            wide = (not math.isfinite(sd)) or 2 * tq * sd > max(abs(value), 1e-12)
        out.append(Estimate(key, float(value), float(lo), float(hi), unit, bool(wide)))

    P = J.shape[1]
    # base and direct slots
    for i, s in enumerate(prob.slots):
        if s.effect in ("viscoelastic",) or (s.effect == "mullins" and s.name == "s"):
            continue
        grad = np.zeros(P)
        if s.log:
            v = math.exp(z_full[i])
            grad[i] = v
        else:
            v = float(z_full[i])
            grad[i] = 1.0
        unit = {"stress": "Pa", "time": "s"}.get(s.kind, "")
        key = s.key if s.file is None else f"{s.key}[{prob.records[s.file].name}]"
        if s.effect == "slack":
            r = prob.records[s.file]
            if r.gauge:
                add(f"slack.length[{r.name}]", grad * r.gauge, v * r.gauge, positive=False, unit="m")
            add(key, grad, v, positive=False)
            continue
        add(key, grad, v, positive=s.log or s.kind == "stress", unit=unit)
    # derived: Prony weights and mullins r
    if st.g is not None:
        idx_u = [i for i, s in enumerate(prob.slots) if s.effect == "viscoelastic" and s.name.startswith("u")]
        idx_t = [i for i, s in enumerate(prob.slots) if s.effect == "viscoelastic" and s.name.startswith("tau")]
        u = z_full[idx_u]
        rank = {int(j): r for r, j in enumerate(np.argsort(st.tau))}  # report sorted by tau, as MaterialEffects
        for j in range(len(u)):
            grad = np.zeros(P)
            for q in range(j + 1):
                # dg_j/du_q
                if q == j:
                    d = np.prod(1 - u[:j])
                else:
                    d = -u[j] * np.prod([1 - u[m] for m in range(j) if m != q])
                grad[idx_u[q]] = d
            add(f"viscoelastic.g[{rank[j]}]", grad, float(st.g[j]), positive=True)
            gt = np.zeros(P)
            gt[idx_t[j]] = st.tau[j]
            add(f"viscoelastic.tau[{rank[j]}]", gt, float(st.tau[j]), positive=True, unit="s")
        grad = np.zeros(P)
        for q in range(len(u)):
            grad[idx_u[q]] = -np.prod([1 - u[m] for m in range(len(u)) if m != q])
        add("viscoelastic.g_inf", grad, float(np.prod(1 - u)), positive=False)
    if st.mullins is not None:
        i = next(i for i, s in enumerate(prob.slots) if s.effect == "mullins" and s.name == "s")
        grad = np.zeros(P)
        grad[i] = -1.0 / max(z_full[i], 1e-12) ** 2
        add("mullins.r", grad, st.mullins[0], positive=True)
    # offsets
    for c, (k, j) in enumerate(off_keys):
        r = prob.records[k]
        grad = np.zeros(P)
        grad[len(prob.slots) + c] = 1.0
        v = float(coefs[k][j])
        # data = model + offset: the load cell reads `offset` when the true force is zero
        if r.area:
            g2 = grad * r.area
            if j == 0:
                add(f"sensor_offset.force[{r.name}]", g2, v * r.area, positive=False, unit="N")
            else:
                add(f"sensor_offset.drift[{r.name}]", g2 / (r.T or 1.0), v * r.area / (r.T or 1.0),
                    positive=False, unit="N/s")
        else:
            if j == 0:
                add(f"sensor_offset.stress[{r.name}]", grad, v, positive=False, unit="Pa")
            else:
                add(f"sensor_offset.drift[{r.name}]", grad / (r.T or 1.0), v / (r.T or 1.0),
                    positive=False, unit="Pa/s")
    # Prony terms in order of their relaxation time
    ve = sorted((e for e in out if e.key.startswith("viscoelastic.") and "[" in e.key),
                key=lambda e: (int(e.key[e.key.index("[") + 1:-1]), e.key))
    it = iter(ve)
    return [next(it) if (e.key.startswith("viscoelastic.") and "[" in e.key) else e for e in out]


# --------------------------------------------------------------------------- errors
@dataclass
class Errors:
    """Error measures over files (every file counts equally)."""

    rmse: float
    nrmse: float
    max_abs: float
    per_file: list[dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        return {"rmse": self.rmse, "nrmse": self.nrmse, "max_abs": self.max_abs, "unit": "Pa",
                "per_file": self.per_file}


def error_measures(items: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> Errors:
    """Errors from ``(name, measured, predicted)`` triples (Pa).

    Per file: RMSE, NRMSE = RMSE / range of its measured stress, max |error|,
    R². Overall: RMSE = sqrt(mean over files of MSE_f) (files count equally,
    as in the fit's objective), NRMSE = that RMSE / range of all measured stress
    pooled, max = largest |error| anywhere.
    """
    per = []
    mses, lo, hi, mx = [], math.inf, -math.inf, 0.0
    for name, y, p in items:
        y = np.asarray(y, float)
        p = np.asarray(p, float)
        good = np.isfinite(p)
        if not good.any():
            per.append({"file": name, "n": int(y.size), "rmse": math.inf, "nrmse": math.inf,
                        "max_abs": math.inf, "r2": -math.inf})
            mses.append(math.inf)
            continue
        e = np.where(good, p - y, np.nan)
        e = np.nan_to_num(e, nan=float(np.nanmax(np.abs(e))))
        mse = float(np.mean(e**2))
        rng = float(np.ptp(y)) or 1.0
        ss = float(np.sum((y - y.mean()) ** 2)) or 1.0
        per.append({"file": name, "n": int(y.size), "rmse": math.sqrt(mse), "nrmse": math.sqrt(mse) / rng,
                    "max_abs": float(np.max(np.abs(e))), "r2": 1.0 - float(np.sum(e**2)) / ss})
        mses.append(mse)
        lo, hi = min(lo, float(y.min())), max(hi, float(y.max()))
        mx = max(mx, float(np.max(np.abs(e))))
    rmse = math.sqrt(float(np.mean(mses))) if mses else math.nan
    rng = (hi - lo) if hi > lo else 1.0
    return Errors(rmse, rmse / rng, mx, per)
