r"""The extended model: a hyperelastic base, strain-energy terms and effects, and its least-squares fit.

The objective is the one of :func:`esmm.pipeline.calibrate.fit.fit_material`
(docs/design/calibration.md, "The objective"), so that a base model fitted here and there agree:

.. math::

    r_{f,k} = \sqrt{w_f / n_f}\;\frac{\hat P_{f,k}(\theta, \phi, \psi_f) - P_{f,k}}{s_f},
    \qquad s_f = \max_k |P_{f,k}|,

with θ the parameters of the elastic law (the base model's, laid out, bounded
and log-transformed exactly as the calibrate fit does, plus those of the
strain-energy terms of :mod:`esmm.pipeline.materials.terms` a discovery added),
φ the material effects' parameters (shared by all files) and ψ_f the artefact
parameters of file *f*. The sum runs over the thinned fitting samples of each
file (:func:`~esmm.pipeline.discover.covariates.thin`); reported errors use
every sample.

Prediction of one file, in this order (docs/design/discovery.md, "The extended model"):

1. grip slip: ``x ← x - Σ_j δ_j [k ≥ k_j]`` (the extension lost at each slip);
   slack: ``x_true = max(x / (1 + δ_f), 1)`` (tension tests only);
2. permanent set: ``λ_s = 1 + s_p (max x_true - 1)^q`` (q = 1 in variant 1), elastic stretch ``x_true/λ_s``;
3. ``P_e = nominal_stress(elastic law, x_true/λ_s) / λ_s``;
4. damage ``× (1 - D(ξ_max))``, Mullins ``× η(W, W_max)``, cyclic softening ``× c(α)``;
5. viscoelastic: ``P = QLV[P_e]`` (with κ: the relaxed part scaled by s(ξ); with κ_τ: the
   relaxation times ``τ_i exp(-κ_τ (ξ - 1))``);
6. a tension-only specimen cannot carry compression: ``P = max(P, 0)`` (a strip that
   buckles), except, with ``Spec.compression``, on a record that reads compression;
7. per-specimen stress scale: ``× c_s`` (the scales' geometric mean is held at 1);
8. load-cell offset and drift: ``+ o_f + d_f (t - t_0)/T_f`` — linear, eliminated
   in closed form (variable projection) at every evaluation.

The Jacobian is by forward differences, evaluated per block: a file's own
parameters perturb only that file's residuals, and perturbing an effect
parameter reuses the cached elastic stresses.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize

from ..blas import single_threaded_blas
from ..calibrate.problem import NAN_PENALTY, layout_for
from ..errors import FitError
from ..materials import get_model
from ..materials.composite import composite_name
from ..materials.effects import (
    CyclicSofteningEffect,
    DamageEffect,
    MaterialEffects,
    MullinsEffect,
    PermanentSetEffect,
    ViscoelasticEffect,
    accumulated_energy,
    cyclic_factor,
    damage_factor,
    equivalent_stretch,
    mullins_factor,
    qlv_decay,
    qlv_rate_decay,
    qlv_stress,
    relaxation_strength,
    set_stretch,
)
from ..materials.loading import energy_density, invariants, nominal_stress, path_kinematics
from ..materials.terms import TERM_NAMES, TERMS
from .records import (
    Record,
    drift_applicable,
    fitting_view,
    largest_span,
    offset_applicable,
    rest_reading,
    slack_applicable,
    slip_applicable,
    specimen_groups,
)

#: variants of each effect: name -> allowed variant numbers (0 = off)
VARIANTS = {
    "viscoelastic": (1, 2, 3),  # Prony terms
    # (needs viscoelastic) two alternative forms, one parameter each: 1, kappa (the relaxed amount depends on
    # stretch); 2, kappa_tau (the relaxation times do) (docs/design/discovery.md, "Stretch-dependent relaxation")
    "nonlinear_viscoelastic": (1, 2),
    "mullins": (2, 3),  # (r, m) or (r, m, beta)
    # (onset, scale, shape). Variant 4 adds a floor (the fraction damage leaves at large stretch): a model
    # esmm fits, evaluates and simulates where params.toml gives it, not searched (docs/design/discovery.md,
    # the effects' table: it named four more damages of seeds 22-25 but moved three foam rows and a tendon
    # failure's held-out and nested errors both ways)
    "damage": (3,),
    "cyclic_softening": (2,),  # (d_inf, eta)
    "permanent_set": (1, 2),  # fraction, or fraction and exponent
    "slack": (1,),  # one slack length per file
    "sensor_offset": (1, 2),  # offset, or offset + linear drift, per file
    "specimen_scale": (1,),  # one stress scale per specimen
    "grip_slip": (1,),  # one extension loss per detected slip
}
#: effects whose variants are alternative forms with as many parameters, not nested (neither contains the
#: other): each is fitted from the current model and the better fit is the candidate
ALTERNATIVE_VARIANTS = frozenset({"nonlinear_viscoelastic"})
#: every effect and artefact a discovery can add (the Spec's integer fields)
EFFECTS: tuple[str, ...] = tuple(VARIANTS)
#: every candidate: effects, artefacts and strain-energy terms
CANDIDATES: tuple[str, ...] = EFFECTS + TERM_NAMES
#: the material effects decoded from shared slots, in the order :meth:`ParameterLayout.values` decodes them
_DECODED = ("viscoelastic", "nonlinear_viscoelastic", "mullins", "damage", "cyclic_softening", "permanent_set")
#: Prony weights are stick-broken fractions u_i in [0, U_MAX]
U_MAX = 0.995
#: weight of the row that holds the specimen scales' geometric mean at 1
SCALE_CONSTRAINT = 100.0


@dataclass(frozen=True)
class Spec:
    """Which effects and strain-energy terms a model has, and in which variant (0 = absent)."""

    viscoelastic: int = 0
    nonlinear_viscoelastic: int = 0
    mullins: int = 0
    damage: int = 0
    cyclic_softening: int = 0
    permanent_set: int = 0
    slack: int = 0
    sensor_offset: int = 0
    specimen_scale: int = 0
    grip_slip: int = 0
    terms: tuple[str, ...] = ()
    #: 1: tension records that read compression beyond their noise (``Record.compressive``) are not clamped
    #: at zero force, so a relaxing specimen carries the compression it reads on the way down; 0: every
    #: tension record is clamped (a strip that buckles). Only a relaxation makes the two differ, so it goes
    #: with ``viscoelastic`` and is chosen by the fit when a relaxation is proposed.
    compression: int = 0

    def variant(self, name: str) -> int:
        """The variant of effect or term *name* (0 = absent)."""
        if name in TERMS:
            return int(name in self.terms)
        return int(getattr(self, name))

    def names(self) -> list[str]:
        """Effects present, then terms (library order)."""
        return [n for n in EFFECTS if getattr(self, n)] + [t for t in TERM_NAMES if t in self.terms]

    def with_(self, name: str, variant: int) -> Spec:
        if name in TERMS:
            terms = set(self.terms) | {name} if variant else set(self.terms) - {name}
            return replace(self, terms=tuple(t for t in TERM_NAMES if t in terms))
        out = replace(self, **{name: int(variant)})
        if name == "nonlinear_viscoelastic" and variant and not out.viscoelastic:
            out = replace(out, viscoelastic=1)
        if not out.viscoelastic and out.compression:
            out = replace(out, compression=0)
        return out

    def variant_text(self, name: str) -> str:
        v = self.variant(name)
        if name in TERMS:
            return f"strain-energy term {TERMS[name].equation}"
        return {
            "viscoelastic": f"{v} Prony term{'s' if v != 1 else ''}",
            "nonlinear_viscoelastic": ("relaxation times scaled by exp(-kappa_tau (xi - 1))" if v == 2
                                       else "relaxed amount scaled by exp(kappa (xi - 1))"),
            "mullins": "r, m, beta" if v == 3 else "r, m (beta = 0)",
            "sensor_offset": "offset and drift" if v == 2 else "offset",
            "slack": "one slack length per file",
            "damage": "onset, scale, shape, floor" if v == 4 else "onset, scale, shape",
            "cyclic_softening": "d_inf, eta",
            "permanent_set": "set fraction and exponent" if v == 2 else "set fraction (exponent 1)",
            "specimen_scale": "one stress scale per specimen (geometric mean 1)",
            "grip_slip": "one extension loss per detected slip",
        }.get(name, str(v))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {n: getattr(self, n) for n in EFFECTS}
        d["terms"] = list(self.terms)
        d["compression"] = self.compression
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Spec:
        terms = tuple(t for t in TERM_NAMES if t in set(d.get("terms") or ()))
        return cls(**{n: int(d.get(n, 0)) for n in EFFECTS}, terms=terms, compression=int(d.get("compression", 0)))


# --------------------------------------------------------------------------- slots
@dataclass
class Slot:
    """One optimiser coordinate."""

    name: str  # reported name, e.g. "mu", "tau[1]", "slack"
    effect: str | None  # None: a parameter of the elastic law
    file: int | None  # None: shared; else the (first) record it belongs to
    log: bool
    lo: float
    hi: float
    kind: str = "dimensionless"  # "stress", "time", "dimensionless"
    direction: str | None = None
    group: tuple[int, ...] = ()  # every record a per-specimen slot acts on

    @property
    def key(self) -> str:
        k = self.name if self.effect is None else f"{self.effect}.{self.name}"
        if self.direction:
            k += f"[{self.direction}]"
        return k

    @property
    def records(self) -> tuple[int, ...]:
        return self.group or (() if self.file is None else (self.file,))


@dataclass
class Values:
    """The parameter values an optimiser vector stands for, decoded (SI)."""

    base: dict[str | None, dict[str, float]]
    g: np.ndarray | None = None
    tau: np.ndarray | None = None
    kappa: float = 0.0
    kappa_tau: float = 0.0
    mullins: tuple[float, float, float] | None = None  # (r, m, beta)
    damage: tuple[float, float, float] | None = None  # (onset, scale, shape)
    cyclic: tuple[float, float] | None = None  # (d_inf, eta)
    set_fraction: float = 0.0
    set_exponent: float = 1.0
    slack: np.ndarray | None = None  # (n_files,) relative slack delta = s / L0
    scale: np.ndarray | None = None  # (n_files,) specimen stress scale
    slips: list[np.ndarray] = field(default_factory=list)  # per file: extension losses (stretch units)
    #: per record: the elastic cache key of :class:`ForwardModel` at these values (filled on first use)
    memo: dict = field(default_factory=dict, repr=False, compare=False)

    def material_effects(self) -> MaterialEffects:
        v = m = d = c = p = None
        if self.g is not None:
            v = ViscoelasticEffect(tuple(self.g), tuple(self.tau), float(self.kappa), float(self.kappa_tau))
        if self.mullins is not None:
            m = MullinsEffect(*self.mullins)
        if self.damage is not None:
            d = DamageEffect(*self.damage)
        if self.cyclic is not None:
            c = CyclicSofteningEffect(*self.cyclic)
        if self.set_fraction > 0.0:
            p = PermanentSetEffect(self.set_fraction, self.set_exponent)
        return MaterialEffects(v, m, d, {}, c, p)


class Bounds:
    """Data-derived bounds of the effect parameters (fixed for a whole discovery)."""

    def __init__(self, records: Sequence[Record], w_ref: float):
        dts = [float(np.median(np.diff(r.t))) for r in records if r.t is not None and r.t.size > 1]
        Ts = [r.T for r in records if r.t is not None]
        self.tau_min = max(min(dts) * 0.5, 1e-4) if dts else 1e-3
        #: a relaxation time longer than the longest record is a linear trend over it (not identifiable)
        self.tau_max = max(Ts) if Ts else 1e3
        self.w_ref = max(w_ref, 1e-12)  # largest base strain energy in the data [Pa]
        self.xi_max = 1.0 + largest_span(records)
        self._derive()

    def _derive(self) -> None:
        self.xi_span = max(self.xi_max - 1.0, 1e-3)
        #: |kappa (xi - 1)| <= 3 over the data: the relaxed amount (kappa) or the relaxation times (kappa_tau)
        #: change by at most e^3 ~ 20 times
        self.kappa_max = 3.0 / self.xi_span

    def to_dict(self) -> dict[str, float]:
        return dict(tau_min=self.tau_min, tau_max=self.tau_max, w_ref=self.w_ref, xi_max=self.xi_max)

    @classmethod
    def from_dict(cls, d: Mapping[str, float]) -> Bounds:
        b = cls.__new__(cls)
        b.tau_min, b.tau_max, b.w_ref = float(d["tau_min"]), float(d["tau_max"]), float(d["w_ref"])
        b.xi_max = float(d["xi_max"])
        b._derive()
        return b


def effect_slots(spec: Spec, b: Bounds) -> list[Slot]:
    """The shared (material) effect slots of *spec*, in a fixed order."""
    slots: list[Slot] = []
    for i in range(spec.viscoelastic):
        slots.append(Slot(f"u[{i}]", "viscoelastic", None, False, 0.0, U_MAX))
        slots.append(Slot(f"tau[{i}]", "viscoelastic", None, True, math.log(b.tau_min), math.log(b.tau_max), "time"))
    if spec.nonlinear_viscoelastic:
        name = "kappa_tau" if spec.nonlinear_viscoelastic == 2 else "kappa"
        slots.append(Slot(name, "nonlinear_viscoelastic", None, False, -b.kappa_max, b.kappa_max))
    if spec.mullins:
        slots.append(Slot("s", "mullins", None, False, 0.0, 0.99))  # s = 1/r
        slots.append(Slot("m", "mullins", None, True, math.log(1e-5 * b.w_ref), math.log(10.0 * b.w_ref), "stress"))
        if spec.mullins == 3:
            slots.append(Slot("beta", "mullins", None, False, 0.0, 5.0))
    if spec.damage:
        slots.append(Slot("onset", "damage", None, False, 1.0, b.xi_max))
        slots.append(Slot("scale", "damage", None, True, math.log(1e-3 * b.xi_span), math.log(10.0 * b.xi_span)))
        slots.append(Slot("shape", "damage", None, False, 1.0, 8.0))
        if spec.damage == 4:
            slots.append(Slot("floor", "damage", None, False, 0.0, 0.95))
    if spec.cyclic_softening:
        slots.append(Slot("d_inf", "cyclic_softening", None, False, 0.0, 0.95))
        slots.append(Slot("eta", "cyclic_softening", None, True, math.log(1e-3 * b.w_ref), math.log(1e3 * b.w_ref),
                          "stress"))
    if spec.permanent_set:
        slots.append(Slot("fraction", "permanent_set", None, False, 0.0, 0.9))
        if spec.permanent_set == 2:
            slots.append(Slot("exponent", "permanent_set", None, False, 0.5, 3.0))
    return slots


def file_slots(spec: Spec, records: Sequence[Record], *, free_scales: bool = False) -> list[Slot]:
    """The per-file (artefact) slots of *spec*: slack, slips, per-specimen scales.

    Per-specimen scales need two specimens (one scale is the material's
    modulus), unless *free_scales* (the material is held: each new file's scale
    is its own, as ``esmm evaluate`` re-estimates it).
    """
    slots: list[Slot] = []
    if spec.slack:
        for k, r in enumerate(records):
            if slack_applicable(r):
                slots.append(Slot("slack", "slack", k, False, 0.0, max(0.5 * (float(np.max(r.x)) - 1.0), 1e-6)))
    if spec.grip_slip:
        for k, r in enumerate(records):
            if slip_applicable(r):
                for j, e in enumerate(r.slips):
                    hi = max(float(r.x[e]) - 1.0, 1e-6)
                    slots.append(Slot(f"slip[{j}]", "grip_slip", k, False, 0.0, hi))
    if spec.specimen_scale:
        groups = specimen_groups(records)
        if len(groups) >= 2 or free_scales:
            for g in groups:
                slots.append(Slot("scale", "specimen_scale", g[0], True, math.log(0.1), math.log(10.0), group=tuple(g)))
    return slots


# --------------------------------------------------------------------------- parameters
class ParameterLayout:
    """The optimiser vector of one model on some records: where each parameter sits, and what a vector means.

    The elastic law's slots come first (laid out as the calibrate fit lays
    them), then the shared effect slots (:func:`effect_slots`), then the
    per-file artefact slots (:func:`file_slots`). This class gives their
    bounds, a neutral start, the encoding of known parameter values into a
    vector and the decoding of a vector into :class:`Values`.

    Parameters
    ----------
    model : MaterialModel
        The elastic law (the base model with the strain-energy terms of *spec*).
    records, spec, fixed, directions, bounds, free_scales
        As in :class:`Problem`.
    """

    def __init__(self, model, records: Sequence[Record], spec: Spec, *, fixed: Mapping[str, float],
                 directions: list[str] | None, bounds: Bounds, free_scales: bool):
        self.model = model
        self.records = list(records)
        self.spec = spec
        self.fixed = dict(fixed)
        self.bounds = bounds
        # the elastic law's slots: those of the calibrate fit on the fitting samples
        self.layout = layout_for(self.model, [fitting_view(r) for r in self.records], fixed=self.fixed,
                                 directions=directions)
        slots = [Slot(s.name, None, None, s.log, s.lo, s.hi, s.kind, s.direction) for s in self.layout.slots]
        self.n_base = len(slots)
        slots += effect_slots(spec, bounds)
        self.n_shared = len(slots)
        slots += file_slots(spec, self.records, free_scales=free_scales)
        self.slots = slots
        self.lower = np.array([s.lo for s in slots])
        self.upper = np.array([s.hi for s in slots])

    def keys(self) -> list[str]:
        return [s.key if s.file is None else f"{s.key}[{self.records[s.file].name}]" for s in self.slots]

    def default_z(self) -> np.ndarray:
        """A neutral starting vector: base defaults; effects nearly off; artefacts at zero."""
        z = np.empty(len(self.slots))
        z[: self.n_base] = self.layout.from_params({**self.model.defaults(), **self.fixed})
        b = self.bounds
        n_ve = self.spec.viscoelastic
        for i, s in enumerate(self.slots[self.n_base:], start=self.n_base):
            if s.effect == "viscoelastic" and s.name.startswith("u"):
                z[i] = 0.2
            elif s.effect == "viscoelastic":
                j = int(s.name[s.name.index("[") + 1:-1])
                z[i] = math.log(b.tau_min) + (j + 1) / (n_ve + 1) * (math.log(b.tau_max / 10) - math.log(b.tau_min))
            elif s.effect == "mullins":
                z[i] = {"s": 0.3, "m": math.log(0.1 * b.w_ref), "beta": 0.0}[s.name]
            elif s.effect == "damage":
                z[i] = {"onset": 1.0 + 0.7 * b.xi_span, "scale": math.log(0.2 * b.xi_span), "shape": 2.0,
                        "floor": 0.0}[s.name]
            elif s.effect == "cyclic_softening":
                z[i] = {"d_inf": 0.1, "eta": math.log(b.w_ref)}[s.name]
            else:  # kappa, kappa_tau, set fraction, slack, slips, log scales
                z[i] = 0.0
        return np.clip(z, self.lower, self.upper)

    def set_base(self, z_full: np.ndarray, params: Mapping[str | None, Mapping[str, float]]) -> np.ndarray:
        """Write elastic-law parameter values (per direction, SI) into *z_full*."""
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
        """Optimiser vector from elastic-law parameters (per direction, SI) and material effects.

        Slots of effects absent from *effects* keep their neutral defaults;
        per-file artefact slots start at zero.
        """
        z = self.set_base(self.default_z(), base)
        vals = _effect_values(effects) if effects is not None else {}
        for i, s in enumerate(self.slots):
            if (s.effect, s.name) in vals:
                z[i] = vals[(s.effect, s.name)]  # not clipped: a saved value stands as it is
        return z

    def transfer(self, other: ParameterLayout, z_other: np.ndarray) -> np.ndarray:
        """Map another layout's vector onto this one (matching slots by key and file name)."""
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
    def _shared(self, z_full: np.ndarray, effect: str) -> dict[str, float]:
        return {s.name: float(z_full[i]) for i, s in enumerate(self.slots[self.n_base:self.n_shared], self.n_base)
                if s.effect == effect}

    def values(self, z_full: np.ndarray) -> Values:
        """The parameter values *z_full* stands for (Prony weights from their stick-broken fractions)."""
        st = Values(base=self.layout.to_params(z_full[: self.n_base]))
        for effect in _DECODED:
            if getattr(self.spec, effect):
                self._decode(st, z_full, effect)
        self._file_state(st, z_full)
        return st

    def perturbed(self, st: Values, z_full: np.ndarray, i: int) -> Values:
        """``values(z_full)`` where *z_full* differs from the vector of *st* in slot *i* only.

        Only the part of *st* that slot stands for is decoded again (the same
        operations as :meth:`values`, so the same numbers); the rest is shared.
        """
        new = object.__new__(Values)  # a shallow copy (dataclasses.replace is slow for this hot path)
        new.__dict__.update(st.__dict__)
        s = self.slots[i]
        if i < self.n_base or s.effect in ("permanent_set", "slack", "grip_slip"):
            new.memo = {}  # the elastic responses' keys change; the other slots keep them (memo shared)
        if i < self.n_base:
            new.base = self.layout.to_params(z_full[: self.n_base])
        elif i < self.n_shared:
            self._decode(new, z_full, self.slots[i].effect)
        else:
            if s.effect == "slack":
                new.slack = st.slack.copy()
                new.slack[s.file] = z_full[i]
            elif s.effect == "grip_slip":
                new.slips = list(st.slips)
                new.slips[s.file] = st.slips[s.file].copy()
                new.slips[s.file][int(s.name[5:-1])] = z_full[i]
            elif s.effect == "specimen_scale":
                new.scale = st.scale.copy()
                new.scale[list(s.group)] = math.exp(z_full[i])
        return new

    def _decode(self, st: Values, z_full: np.ndarray, effect: str) -> None:
        """Write material *effect*'s values from *z_full* into *st*."""
        v = self._shared(z_full, effect)
        if effect == "viscoelastic":
            n = self.spec.viscoelastic
            g, rest = [], 1.0
            for j in range(n):
                g.append(rest * v[f"u[{j}]"])
                rest *= 1.0 - v[f"u[{j}]"]
            st.g = np.array(g)
            st.tau = np.exp(np.array([v[f"tau[{j}]"] for j in range(n)]))
        elif effect == "nonlinear_viscoelastic":
            st.kappa, st.kappa_tau = v.get("kappa", 0.0), v.get("kappa_tau", 0.0)
        elif effect == "mullins":
            st.mullins = (1.0 / max(v["s"], 1e-12), math.exp(v["m"]), v.get("beta", 0.0))
        elif effect == "damage":
            st.damage = (v["onset"], math.exp(v["scale"]), v["shape"]) + ((v["floor"],) if "floor" in v else ())
        elif effect == "cyclic_softening":
            st.cyclic = (v["d_inf"], math.exp(v["eta"]))
        elif effect == "permanent_set":
            st.set_fraction = v["fraction"]
            st.set_exponent = v.get("exponent", 1.0)

    def _file_state(self, st: Values, z_full: np.ndarray) -> None:
        m = len(self.records)
        st.slack, st.scale = np.zeros(m), np.ones(m)
        st.slips = [np.zeros(len(r.slips)) if self.spec.grip_slip else np.zeros(0) for r in self.records]
        for i in range(self.n_shared, len(self.slots)):
            s = self.slots[i]
            if s.effect == "slack":
                st.slack[s.file] = z_full[i]
            elif s.effect == "grip_slip":
                st.slips[s.file][int(s.name[5:-1])] = z_full[i]
            elif s.effect == "specimen_scale":
                st.scale[list(s.group)] = math.exp(z_full[i])


# --------------------------------------------------------------------------- forward model
@dataclass(frozen=True)
class _Path:
    """A batch of true-stretch arrays of one mode, after the permanent set: what the elastic law is evaluated on."""

    mode: str
    x: np.ndarray  # (n,) the arrays' elastic stretches, concatenated
    kin: tuple  # path_kinematics(mode, x)
    lam_s: list  # per array: the set stretch (or None)
    cuts: np.ndarray  # where to split x back into the arrays
    xis: list  # per array: the uniaxial-equivalent stretch (or None where no effect needs it)


class ForwardModel:
    """The model stress of each record at decoded :class:`Values` (steps 1-7 of the module docstring).

    Also the design of each record's load-cell offset and drift (step 8),
    which the residuals eliminate in closed form. The elastic responses are
    cached per record (the most recent 24 parameter sets), so that perturbing
    an effect parameter in the Jacobian reuses them.

    Parameters
    ----------
    model : MaterialModel
        The elastic law.
    records, spec, directions
        As in :class:`Problem`.
    """

    def __init__(self, model, records: Sequence[Record], spec: Spec, *, directions: list[str] | None):
        self.model = model
        self.records = list(records)
        self.spec = spec
        self.directions = directions
        self.n_offset = [0] * len(self.records)
        #: per record: the prediction clamped at zero force (``Spec.compression``)
        self.clamp = [r.tension_only and not (spec.compression and r.compressive) for r in self.records]
        #: per record: the offset read at rest before loading (held, not fitted), or None
        self.pinned: list[float | None] = [None] * len(self.records)
        if spec.sensor_offset:
            for k, r in enumerate(self.records):
                if offset_applicable(r):
                    self.n_offset[k] = 2 if (spec.sensor_offset == 2 and drift_applicable(r)) else 1
                    self.pinned[k] = rest_reading(r)
        self._cache: list[dict] = [dict() for _ in self.records]
        self._paths: dict = {}
        #: per record: the time of its fitting samples
        self._t_fit = [None if r.t is None else np.ascontiguousarray(r.t[r.fit_idx]) for r in self.records]
        self._decays: list[dict] = [dict() for _ in self.records]
        self._soft: list[dict] = [dict() for _ in self.records]
        self._strengths: list[dict] = [dict() for _ in self.records]
        self._rate_decays: list[dict] = [dict() for _ in self.records]

    def _key(self, k: int, st: Values):
        """(cache key of record k's elastic response at *st*, its elastic-law parameters), memoised on *st*."""
        hit = st.memo.get(k)
        if hit is None:
            r = self.records[k]
            params = st.base[r.key if self.directions else None]
            delta = float(st.slack[k]) if st.slack is not None else 0.0
            slips = tuple(float(v) for v in st.slips[k]) if st.slips else ()
            hit = st.memo[k] = (tuple(sorted(params.items())), delta, slips, st.set_fraction, st.set_exponent), params
        return hit

    def _x_true(self, k: int, st: Values, idx: np.ndarray) -> np.ndarray:
        """The specimen's stretch at samples *idx* after the slips and the slack."""
        r = self.records[k]
        x = r.x[idx]
        if st.slips and st.slips[k].size and np.any(st.slips[k]):
            for e, d in zip(r.slips, st.slips[k]):
                x = x - d * (idx >= e)
        delta = float(st.slack[k]) if st.slack is not None else 0.0
        return np.maximum(x / (1.0 + delta), 1.0) if delta > 0.0 else x

    def _path(self, mode: str, xs: list[np.ndarray], set_fraction: float, set_exponent: float = 1.0) -> _Path:
        """The loading path of several true-stretch arrays of one mode (after the set), evaluated once."""
        lam_s = [set_stretch(np.maximum.accumulate(x), set_fraction, set_exponent) for x in xs] if set_fraction > 0 \
            and mode != "simple_shear" else [None] * len(xs)
        xe = [x if s is None else x / s for x, s in zip(xs, lam_s)]
        x = np.concatenate(xe) if len(xe) > 1 else xe[0]
        need_xi = self.spec.damage or self.spec.nonlinear_viscoelastic
        xis = [_xi(mode, xx) for xx in xs] if need_xi else [None] * len(xs)
        return _Path(mode, x, path_kinematics(mode, x), lam_s, np.cumsum([a.size for a in xs])[:-1], xis)

    def _compute_elastic(self, path: _Path, params_list: list) -> list[list[tuple]]:
        """Per parameter set of *params_list*: (P_e, W, ξ) of each array of *path*.

        The stresses of several parameter sets are evaluated in one call where
        the law takes parameter arrays (``array_parameters``: each row the
        scalar result, bit for bit); the energies (Mullins, cyclic softening)
        one set at a time.
        """
        need_w = self.spec.mullins or self.spec.cyclic_softening
        mode, x, kin = path.mode, path.x, path.kin
        with np.errstate(all="ignore"):
            if len(params_list) > 1 and self.model.array_parameters:
                stacked = {n: np.array([p[n] for p in params_list], dtype=float)[:, None] for n in params_list[0]}
                pes = list(np.asarray(nominal_stress(self.model, stacked, mode, x, kinematics=kin), float))
            else:
                pes = [np.asarray(nominal_stress(self.model, p, mode, x, kinematics=kin), float) for p in params_list]
            ws = [np.asarray(energy_density(self.model, p, mode, x, kinematics=kin), float) if need_w else None
                  for p in params_list]
        return [self._split(path, pe, w) for pe, w in zip(pes, ws)]

    @staticmethod
    def _split(path: _Path, pe: np.ndarray, w: np.ndarray | None) -> list[tuple]:
        """(P_e, W, ξ) of each array of *path* from the stress and energy on the whole path."""
        n = len(path.lam_s)

        def split(a):
            return [None] * n if a is None else np.split(a, path.cuts) if n > 1 else [a]

        pes = [p if s is None else p / s for p, s in zip(split(pe), path.lam_s)]
        return list(zip(pes, split(w), path.xis))

    def _remember(self, cache: dict, key, value, size: int) -> None:
        cache[key] = value
        while len(cache) > size:
            cache.pop(next(iter(cache)))

    def prefetch(self, st: Values, ks) -> None:
        """Compute the elastic responses of records *ks* missing from the cache, batched by mode.

        The loading path of each batch (true stretches, set, kinematics) is
        kept too: perturbing an elastic-law parameter evaluates the law on it.
        """
        self.prefetch_many([(st, ks)])

    def prefetch_many(self, requests) -> None:
        """:meth:`prefetch` for several ``(values, records)`` at once (a Jacobian's columns).

        The parameter sets that meet on one loading path are evaluated in one
        call (see :meth:`_compute_elastic`).
        """
        batches: dict = {}
        for st, ks in requests:
            groups: dict = {}
            for k in ks:
                key, params = self._key(k, st)
                c = self._cache[k]
                if key in c:
                    c[key] = c.pop(key)  # most recently used
                    continue
                groups.setdefault((self.records[k].test.mode, key[0]), (params, []))[1].append((k, key))
            for (mode, pk), (params, items) in groups.items():
                pkey = (mode, tuple((k, key[1:]) for k, key in items))
                batches.setdefault(pkey, (st, {}))[1].setdefault(pk, (params, items))
        size = max([24] + [len(rows) + 1 for _, rows in batches.values()])
        for pkey, (st, rows) in batches.items():
            path = self._paths.get(pkey)
            if path is None:
                xs = [self._x_true(k, st, self.records[k].fit_idx) for k, _ in pkey[1]]
                path = self._path(pkey[0], xs, st.set_fraction, st.set_exponent)
                self._remember(self._paths, pkey, path, 16)
            for (_, items), vals in zip(rows.values(), self._compute_elastic(path, [p for p, _ in rows.values()])):
                for (k, key), val in zip(items, vals):
                    self._remember(self._cache[k], key, val, size)

    def _elastic(self, k: int, st: Values, idx: np.ndarray, use_cache: bool):
        """(P_e, W, ξ) on samples *idx* of record k (after slips, slack and set)."""
        if use_cache:
            key, _ = self._key(k, st)
            hit = self._cache[k].get(key)
            if hit is None:
                self.prefetch(st, [k])
                hit = self._cache[k][key]
            return hit
        _, params = self._key(k, st)
        mode = self.records[k].test.mode
        path = self._path(mode, [self._x_true(k, st, idx)], st.set_fraction, st.set_exponent)
        return self._compute_elastic(path, [params])[0][0]

    def predict(self, k: int, st: Values, idx: np.ndarray | None = None, *, use_cache: bool = True) -> np.ndarray:
        """Model stress of record k on samples *idx* (default: its fitting samples), before offsets."""
        r = self.records[k]
        fit = idx is None
        if fit:
            idx = r.fit_idx
        else:
            use_cache = False
        pe, w, xi = self._elastic(k, st, idx, use_cache)
        p = self._softened_cached(k, st, pe, w, xi) if use_cache else self._softened(k, st, pe, w, xi)
        if st.g is not None and r.t is not None:
            if st.kappa_tau:
                decay = _rate_decay(self._rate_decays[k], self._t_fit[k], xi, st) if fit \
                    else qlv_rate_decay(r.t[idx], st.tau, xi, st.kappa_tau)
                q = qlv_stress(None, p, st.g, st.tau, decay=decay)
            else:
                q = qlv_stress(self._t_fit[k], p, st.g, st.tau, decay=self._decay(k, st.tau)) if fit \
                    else qlv_stress(r.t[idx], p, st.g, st.tau)
            if st.kappa:
                with np.errstate(invalid="ignore"):
                    q = p - relaxation_strength(xi, st.kappa, float(np.sum(st.g))) * (p - q)
            p = q
        if self.clamp[k]:
            p = np.maximum(p, 0.0)
        return p * st.scale[k] if st.scale is not None else p

    def fitted_residual(self, k: int, st: Values, pos: np.ndarray, y: np.ndarray, pin: float | None,
                        norm: tuple[float, float] | None) -> np.ndarray:
        """``predict(k, st)[pos] - y`` (plus the held offset *pin*), normalised as ``factor * r / scale``
        with non-finite values replaced by the penalty where *norm* = (factor, scale) is given.

        What :meth:`predict` and :meth:`Problem.residual_block` compute, bit for bit, in one
        compiled pass after the (cached) elastic response and softening.
        """
        r = self.records[k]
        pe, w, xi = self._elastic(k, st, r.fit_idx, True)
        p = np.ascontiguousarray(self._softened_cached(k, st, pe, w, xi), dtype=float)
        g, (a, b), s = _NO_TERMS, (_NO_DECAY, _NO_DECAY), _NO_TERMS
        if st.g is not None and r.t is not None:
            g = np.ascontiguousarray(st.g, dtype=float)
            a, b = _rate_decay(self._rate_decays[k], self._t_fit[k], xi, st) if st.kappa_tau else self._decay(k, st.tau)
            if st.kappa:
                s = self._strength(k, xi, st)
        flags = np.array([self.clamp[k], st.scale is not None, pin is not None, norm is not None])
        consts = np.array([float(st.scale[k]) if st.scale is not None else 1.0, pin or 0.0,
                           *(norm or (1.0, 1.0)), NAN_PENALTY])
        out = np.empty(pos.size)
        _residual_kernel()(p, g, a, b, s, pos, y, flags, consts, out)
        return out

    def _strength(self, k: int, xi: np.ndarray, st: Values) -> np.ndarray:
        """The relaxed amount's scale s(ξ) of record k (:func:`relaxation_strength`), kept per (ξ, κ, g)."""
        key = (id(xi), st.kappa, st.g.tobytes())
        hit = self._strengths[k].get(key)
        if hit is None or hit[0] is not xi:
            with np.errstate(invalid="ignore"):
                s = np.ascontiguousarray(relaxation_strength(xi, st.kappa, float(np.sum(st.g))), dtype=float)
            hit = (xi, s)
            self._remember(self._strengths[k], key, hit, 8)
        return hit[1]

    def _decay(self, k: int, tau: np.ndarray) -> tuple:
        """The QLV factors of record k's fitting samples at relaxation times *tau* (kept: only the
        relaxation times' own Jacobian columns change them)."""
        key = tau.tobytes()
        hit = self._decays[k].get(key)
        if hit is None:
            hit = qlv_decay(self._t_fit[k], tau)
            self._remember(self._decays[k], key, hit, 8)
        return hit

    def _softened_cached(self, k: int, st: Values, pe, w, xi) -> np.ndarray:
        """:meth:`_softened` of a cached elastic response, kept for the Jacobian's steps that leave
        the elastic response and the softening as they are (relaxation, scales)."""
        if st.damage is None and st.mullins is None and st.cyclic is None:
            return pe
        key = (id(pe), st.damage, st.mullins, st.cyclic)
        hit = self._soft[k].get(key)
        if hit is None or hit[0] is not pe:  # (the array itself kept: its id is not reused meanwhile)
            hit = (pe, self._softened(k, st, pe, w, xi))
            self._remember(self._soft[k], key, hit, 8)
        return hit[1]

    def _softened(self, k: int, st: Values, pe, w, xi) -> np.ndarray:
        """Elastic stress after damage, Mullins and cyclic softening (before relaxation)."""
        r = self.records[k]
        p = pe
        if st.damage is not None:
            p = p * damage_factor(np.maximum.accumulate(xi) if r.history else xi, *st.damage)
        if r.history and (st.mullins is not None or st.cyclic is not None):
            with np.errstate(invalid="ignore"):
                if st.mullins is not None:
                    wm = np.maximum.accumulate(np.where(np.isfinite(w), w, np.inf))
                    p = p * mullins_factor(w, wm, *st.mullins)
                if st.cyclic is not None:
                    p = p * cyclic_factor(accumulated_energy(w), *st.cyclic)
        return p

    def elastic(self, k: int, st: Values) -> tuple:
        """(P_e, W, ξ) of record k on its fitting samples (W, ξ None where no effect needs them)."""
        return self._elastic(k, st, self.records[k].fit_idx, True)

    def softened(self, k: int, st: Values, idx: np.ndarray, *, use_cache: bool = True) -> np.ndarray:
        """Elastic stress after slips, slack, set and softening (before relaxation), on samples *idx*."""
        pe, w, xi = self._elastic(k, st, idx, use_cache)
        return self._softened(k, st, pe, w, xi)

    # ------------------------------------------------------------ load-cell offset and drift
    def add_offsets(self, k: int, pred: np.ndarray, coef: np.ndarray | None, idx: np.ndarray | None = None,
                    ) -> np.ndarray:
        """*pred* of record k on samples *idx* (default: its fitting samples) plus its offset and drift *coef*."""
        X = self.offset_columns(k, self.records[k].fit_idx if idx is None else idx)
        return pred if X is None or coef is None else pred + X @ coef

    def offset_columns(self, k: int, idx: np.ndarray) -> np.ndarray | None:
        """Design of record k's offset (and drift, (t - t0)/T) on samples *idx*; None without an offset."""
        n_o = self.n_offset[k]
        if not n_o:
            return None
        r = self.records[k]
        cols = [np.ones(idx.size)]
        if n_o == 2:
            cols.append((r.t[idx] - r.t[0]) / (r.T or 1.0))
        return np.stack(cols, axis=1)

    def free_offset_columns(self, k: int, idx: np.ndarray) -> np.ndarray | None:
        """The fitted columns of :meth:`offset_columns` (an offset read at rest is held; None if nothing is fitted)."""
        X = self.offset_columns(k, idx)
        if X is None or self.pinned[k] is None:
            return X
        return X[:, 1:] if X.shape[1] > 1 else None

    def n_free_offsets(self, k: int) -> int:
        return self.n_offset[k] - (1 if self.pinned[k] is not None and self.n_offset[k] else 0)


def _rate_decay(cache: dict, t: np.ndarray, xi: np.ndarray, st: Values) -> tuple:
    """The factors of a record's fitting samples (times *t*) with stretch-dependent relaxation times
    (:func:`qlv_rate_decay`), kept in *cache* per (ξ, τ, κ_τ), the eight most recent."""
    key = (id(xi), st.tau.tobytes(), st.kappa_tau)
    hit = cache.get(key)
    if hit is None or hit[0] is not xi:
        with np.errstate(invalid="ignore", over="ignore"):
            hit = (xi, qlv_rate_decay(t, st.tau, xi, st.kappa_tau))
        cache[key] = hit
        while len(cache) > 8:
            cache.pop(next(iter(cache)))
    return hit[1]


# --------------------------------------------------------------------------- problem
class Problem:
    """The least-squares problem of one model (elastic law + effects) on some records.

    It holds the training set, assembles the normalised residuals (with the
    load-cell offsets eliminated in closed form) and their Jacobian, and
    solves. What the optimiser vector means is :attr:`params`
    (:class:`ParameterLayout`); the model stress of a record is
    :attr:`forward` (:class:`ForwardModel`).

    Parameters
    ----------
    model : MaterialModel
        The base model (the ESEDF); the strain-energy terms come from *spec*.
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
    free_scales : bool
        Every specimen's stress scale free, none held by the geometric-mean
        constraint (for predicting new files with the material held).
    """

    def __init__(self, model, records: Sequence[Record], spec: Spec, *, fixed: Mapping[str, float],
                 directions: list[str] | None, bounds: Bounds, train=None, free_scales: bool = False):
        self.base_model = model
        self.model = get_model(composite_name(model.name, spec.terms)) if spec.terms else model
        self.records = list(records)
        self.spec = spec
        self.fixed = dict(fixed)
        self.directions = directions
        self.bounds = bounds
        self.free_scales = free_scales
        self.params = ParameterLayout(self.model, self.records, spec, fixed=self.fixed, directions=directions,
                                      bounds=bounds, free_scales=free_scales)
        self.forward = ForwardModel(self.model, self.records, spec, directions=directions)
        #: per record: the load cell's offset read at rest and held (``forward.pinned``; a fold's own, read
        #: from its training samples, :meth:`derived`)
        self.pinned = self.forward.pinned
        #: per record: the samples whose readings the offset may not be read from (None: every one may be read)
        self.unread: list[np.ndarray | None] = [None] * len(self.records)
        self._setup(train)

    def _setup(self, train) -> None:
        """Everything that depends on the training set (and the neutral starting point)."""
        slots = self.slots = self.params.slots
        self.lower, self.upper = self.params.lower, self.params.upper
        self.set_train(train)
        # the specimens whose scales the constraint holds: those with training samples now
        self.scale_ref = [] if self.free_scales else [i for i, s in enumerate(slots) if s.effect == "specimen_scale"
                                                      and any(self.n_train[k] for k in s.group)]
        self.active = np.arange(len(slots))
        self.z_full = self.params.default_z()

    def derived(self, spec: Spec | None = None, *, train=None, pins=None) -> Problem:
        """The problem of the same records, base and bounds with another *spec* and/or training set.

        With the same spec (a held-out fold) the parameter layout and the forward model, with
        its caches, are shared: they do not depend on the training set. *pins*: per record, the
        load cell's offset read at rest from the fold's training samples (in place of
        ``forward.pinned``, read from all of them).
        """
        if spec is not None and spec != self.spec:
            return Problem(self.base_model, self.records, spec, fixed=self.fixed, directions=self.directions,
                           bounds=self.bounds, train=train, free_scales=self.free_scales)
        new = object.__new__(Problem)
        new.__dict__.update(self.__dict__)
        new._setup(train)
        if pins is not None:
            new.pinned = list(pins)
        return new

    def set_train(self, train) -> None:
        """Use the samples *train* (see the class docstring) in the objective."""
        m = len(self.records)
        self.train = [None] * m if train is None else list(train)
        self.factor = np.zeros(m)
        self.n_train = np.zeros(m, dtype=int)
        for k, r in enumerate(self.records):
            n = r.fit_idx.size if self.train[k] is None else len(self.train[k])
            self.n_train[k] = n
            self.factor[k] = math.sqrt(r.weight / n) if n else 0.0
        self._X = [self._design(k) for k in range(m)]
        #: per record: the data on its training samples
        self._y = [r.y[r.fit_idx] if pos is None else r.y[r.fit_idx][pos] for r, pos in zip(self.records, self.train)]
        #: per record: the positions of its training samples within its fitting samples
        self._pos = [np.arange(r.fit_idx.size) if pos is None else _positions(pos)
                     for r, pos in zip(self.records, self.train)]
        #: the most recent evaluation (see :meth:`_evaluated`)
        self._last = None

    def _design(self, k: int):
        X = self.forward.free_offset_columns(k, self.records[k].fit_idx)
        if X is None:
            return None
        pos = self.train[k]
        return X if pos is None else X[pos]

    @contextlib.contextmanager
    def offsets_held(self) -> Iterator[None]:
        """Within: the offsets are not eliminated in closed form (derivatives at fixed offsets)."""
        saved = self._X
        self._X = [None] * len(self.records)
        self._last = None
        try:
            yield
        finally:
            self._X = saved
            self._last = None

    def residual_block(self, k: int, st: Values) -> tuple[np.ndarray, np.ndarray | None]:
        """Normalised residual block of record k (training samples) and its offset coefficients."""
        r = self.records[k]
        coef = None
        X = self._X[k]
        n_offset = self.forward.n_offset[k]
        pin = self.pinned[k] if n_offset else None
        if pin is not None:
            coef = np.array([pin] + [0.0] * (n_offset - 1))
        fused = X is None or not self._pos[k].size
        res = self.forward.fitted_residual(k, st, self._pos[k], self._y[k], pin,
                                           (self.factor[k], r.scale) if fused else None)
        if fused:  # normalised in the pass
            return res, coef
        good = np.isfinite(res)
        if good.sum() > X.shape[1]:
            c, *_ = np.linalg.lstsq(X[good], -res[good], rcond=None)
            res = res + X @ c
            coef = c if pin is None else np.concatenate([[pin], c])
        out = self.factor[k] * res / r.scale
        bad = ~np.isfinite(out)
        if bad.any():
            out[bad] = NAN_PENALTY
        return out, coef

    def constraint_residual(self, z_full: np.ndarray) -> np.ndarray:
        """The row holding the specimen scales' geometric mean at 1 (empty without scales)."""
        if len(self.scale_ref) < 2:
            return np.zeros(0)
        return np.array([SCALE_CONSTRAINT * float(np.mean(z_full[self.scale_ref]))])

    # ------------------------------------------------------------ objective
    def _full(self, z: np.ndarray) -> np.ndarray:
        zf = self.z_full.copy()
        zf[self.active] = z
        return zf

    def _trained(self) -> list[int]:
        return [k for k in range(len(self.records)) if self.n_train[k]]

    def _blocks(self, st: Values) -> list[np.ndarray]:
        """Every record's residual block at *st* (empty for records without training samples)."""
        self.forward.prefetch(st, self._trained())
        return [self.residual_block(k, st)[0] if self.n_train[k] else np.zeros(0) for k in range(len(self.records))]

    def _evaluated(self, zf: np.ndarray) -> tuple[Values, list[np.ndarray]]:
        """(values, residual blocks) at *zf*; the optimiser asks for the Jacobian where it has just
        evaluated the residuals, so the most recent evaluation is kept and reused."""
        key = zf.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1], self._last[2]
        st = self.params.values(zf)
        blocks = self._blocks(st)
        self._last = (key, st, blocks)
        return st, blocks

    def residuals(self, z: np.ndarray) -> np.ndarray:
        zf = self._full(z)
        _, blocks = self._evaluated(zf)
        return np.concatenate(blocks + [self.constraint_residual(zf)])

    def jac(self, z: np.ndarray) -> np.ndarray:
        """Forward differences, per block: a slot perturbs only the residuals of the records it acts on."""
        zf = self._full(z)
        st0, base_blocks = self._evaluated(zf)
        offs = np.concatenate([[0], np.cumsum([b.size for b in base_blocks])])
        n_c = self.constraint_residual(zf).size
        J = np.zeros((int(offs[-1]) + n_c, len(self.active)))
        steps = []
        for i in self.active:
            h = 1e-6 * max(1.0, abs(zf[i]))
            if zf[i] + h > self.upper[i]:
                h = -h
            zp = zf.copy()
            zp[i] += h
            files = [k for k in (self.slots[i].records or self._trained()) if self.n_train[k]]
            steps.append((i, h, self.params.perturbed(st0, zp, i), files))
        # the elastic responses of every step first: the elastic-law steps in one call per loading path
        self.forward.prefetch_many([(stp, files) for _, _, stp, files in steps])
        trained = self._trained()
        base_all = np.concatenate(base_blocks)
        for c, (i, h, stp, files) in enumerate(steps):
            if len(files) > 1 and files == trained:  # every training row at once (the same numbers)
                J[:base_all.size, c] = (np.concatenate([self.residual_block(k, stp)[0] for k in files]) - base_all) / h
            else:
                for k in files:
                    J[offs[k]:offs[k + 1], c] = (self.residual_block(k, stp)[0] - base_blocks[k]) / h
            if n_c and i in self.scale_ref:
                J[-1, c] = SCALE_CONSTRAINT / len(self.scale_ref)
        return J

    def cost(self, z: np.ndarray) -> float:
        r = self.residuals(z)
        return 0.5 * float(r @ r)

    def objective(self, z_full: np.ndarray) -> float:
        """The objective at *z_full* (every slot as given); the optimiser's state is left as it is."""
        _, blocks = self._evaluated(z_full)
        r = np.concatenate(blocks + [self.constraint_residual(z_full)])
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
            # a trial step whose cost overflows is rejected by trf itself: no warning for it
            with single_threaded_blas(), np.errstate(over="ignore"):
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
        st = self.params.values(z_full)
        return [self.residual_block(k, st)[1] if self.n_train[k] else None for k in range(len(self.records))]

    def full_prediction(self, k: int, z_full: np.ndarray, coef=None) -> np.ndarray:
        """Prediction of record k on *all* its samples, with its offsets applied."""
        st = self.params.values(z_full)
        r = self.records[k]
        idx = np.arange(r.test.n)
        return self.forward.add_offsets(k, self.forward.predict(k, st, idx), coef, idx)

    def specimen_stretches(self, z_full: np.ndarray) -> list[np.ndarray]:
        """The specimen's stretch of each record on *all* its samples: the crosshead's less the slips and the
        slack of *z_full* (what the elastic law is a function of)."""
        st = self.params.values(z_full)
        return [self.forward._x_true(k, st, np.arange(r.test.n)) for k, r in enumerate(self.records)]

    def fit_residuals(self, z_full: np.ndarray) -> list[np.ndarray]:
        """Unnormalised residuals (Pa, model - data) on each record's training samples."""
        st = self.params.values(z_full)
        out = []
        for k, r in enumerate(self.records):
            if not self.n_train[k]:
                out.append(np.zeros(0))
                continue
            blk, _ = self.residual_block(k, st)
            out.append(blk * r.scale / self.factor[k])
        return out

    def n_params(self) -> int:
        """Free parameters: active slots + offset coefficients of the training records - the scale constraint."""
        k = int(len(self.active) + sum(self.forward.n_free_offsets(j) for j in range(len(self.records))
                                       if self.n_train[j]))
        return k - (1 if len(self.scale_ref) >= 2 else 0)


def _residual_loop(soft, g, a, b, s, pos, y, flags, consts, out):  # pragma: no cover - compiled by numba
    """:meth:`ForwardModel.predict` after the softening and :meth:`Problem.residual_block` before the
    offsets' elimination, as one loop (the same operations in the same order: the same bits).

    *flags*: (tension only, has a scale, has a held offset, normalise); *consts*: (scale, held
    offset, factor, stress scale of the record, NaN penalty). ``g`` empty: no relaxation; ``s``
    empty: no stretch-dependent strength. Writes ``out[j]`` for the samples ``pos[j]``.
    """
    n, m = soft.shape[0], g.shape[0]
    pred = soft.copy()
    if m and n:
        ginf = 1.0 - g.sum()
        h = np.full(m, soft[0])
        for k in range(1, n):
            dp = soft[k] - soft[k - 1]
            acc = ginf * soft[k]
            for i in range(m):
                h[i] = a[k, i] * h[i] + b[k, i] * dp
                acc += g[i] * h[i]
            pred[k] = acc
        if s.shape[0]:
            for k in range(n):
                pred[k] = soft[k] - s[k] * (soft[k] - pred[k])
    for j in range(pos.shape[0]):
        v = pred[pos[j]]
        if flags[0] and not (v >= 0.0 or v != v):  # np.maximum(v, 0): NaN stays NaN
            v = 0.0
        if flags[1]:
            v = v * consts[0]
        r = v - y[j]
        if flags[2]:
            r = r + consts[1]
        if flags[3]:
            r = consts[2] * r / consts[3]
            if not math.isfinite(r):
                r = consts[4]
        out[j] = r


@functools.cache
def _residual_kernel():
    """:func:`_residual_loop` compiled (numba, on first use, cached on disk); the plain loop without numba."""
    try:
        from numba import njit
    except ImportError:  # pragma: no cover
        return _residual_loop
    return njit(cache=True, nogil=True, error_model="numpy")(_residual_loop)


def _positions(pos) -> np.ndarray:
    """Training positions as int64 (a boolean mask as the positions it selects)."""
    a = np.asarray(pos)
    return np.flatnonzero(a) if a.dtype == bool else a.astype(np.int64).reshape(-1)


_NO_TERMS = np.zeros(0)
_NO_DECAY = np.zeros((0, 0))

_XI_CACHE: dict = {}


def _xi(mode: str, x: np.ndarray) -> np.ndarray:
    """Uniaxial-equivalent stretch of *x* in *mode* (memoised: it depends on the kinematics only)."""
    key = (mode, x.size, hash(x.tobytes()))
    hit = _XI_CACHE.get(key)
    if hit is None:
        hit = equivalent_stretch(invariants(mode, x)[0])
        if len(_XI_CACHE) > 256:
            _XI_CACHE.clear()
        _XI_CACHE[key] = hit
    return hit


def _effect_values(effects: MaterialEffects) -> dict[tuple[str, str], float]:
    """Optimiser values of the slots of saved material *effects* (effect, slot name) -> value."""
    vals: dict[tuple[str, str], float] = {}
    v = effects.viscoelastic
    if v is not None:
        rest = 1.0
        for j, (g, tau) in enumerate(zip(v.g, v.tau)):
            vals[("viscoelastic", f"u[{j}]")] = g / rest if rest > 0 else 0.0
            rest -= g
            vals[("viscoelastic", f"tau[{j}]")] = math.log(tau)
        vals[("nonlinear_viscoelastic", "kappa")] = v.kappa
        vals[("nonlinear_viscoelastic", "kappa_tau")] = v.kappa_tau
    if effects.mullins is not None:
        m = effects.mullins
        vals.update({("mullins", "s"): 1.0 / m.r, ("mullins", "m"): math.log(m.m), ("mullins", "beta"): m.beta})
    if effects.damage is not None:
        d = effects.damage
        vals.update({("damage", "onset"): d.onset, ("damage", "scale"): math.log(d.scale),
                     ("damage", "shape"): d.shape, ("damage", "floor"): d.floor})
    if effects.cyclic_softening is not None:
        c = effects.cyclic_softening
        vals.update({("cyclic_softening", "d_inf"): c.d_inf, ("cyclic_softening", "eta"): math.log(c.eta)})
    if effects.permanent_set is not None:
        vals[("permanent_set", "fraction")] = effects.permanent_set.fraction
        if effects.permanent_set.exponent != 1.0:
            vals[("permanent_set", "exponent")] = effects.permanent_set.exponent
    return vals


def spec_of_effects(effects: MaterialEffects, terms=()) -> Spec:
    """The Spec of saved material *effects* (and strain-energy *terms*)."""
    v = effects.viscoelastic
    nl = 0 if v is None else 2 if v.kappa_tau else 1 if v.kappa else 0
    return Spec(viscoelastic=len(v.g) if v else 0, nonlinear_viscoelastic=nl,
                mullins=3 if effects.mullins else 0, damage=(4 if effects.damage.floor else 3) if effects.damage else 0,
                cyclic_softening=2 if effects.cyclic_softening else 0,
                permanent_set=(0 if effects.permanent_set is None else 1 if effects.permanent_set.exponent == 1.0 else 2),
                terms=tuple(terms))


__all__ = ["VARIANTS", "ALTERNATIVE_VARIANTS", "EFFECTS", "CANDIDATES", "Spec", "Slot", "Values", "Bounds", "ParameterLayout", "ForwardModel",
           "Problem", "spec_of_effects"]
