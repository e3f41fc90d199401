"""A fitted extended model, how one is fitted from another, and what it says about each effect."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..materials.terms import TERMS
from .estimates import Estimate
from .initialise import extend_variant, initialise
from .model import Problem, Spec, Values
from .statistics import Errors, error_measures, information, n_effective


@dataclass
class Fitted:
    """One fitted model: its problem, parameters, information and errors."""

    spec: Spec
    problem: Problem
    z: np.ndarray
    info: dict[str, float]
    errors: Errors  # on all samples of the fitting files
    heldout: Errors | None = None
    estimates: list[Estimate] = field(default_factory=list)
    cv: dict[str, Errors] = field(default_factory=dict)  # held-out errors per fold set (material, artefact)

    @property
    def values(self) -> Values:
        return self.problem.params.values(self.z)


def finish(prob: Problem, z: np.ndarray) -> Fitted:
    """The :class:`Fitted` of *prob* at *z*: information criteria and errors on all samples."""
    res = prob.fit_residuals(z)
    info = information(res, n_effective(res), prob.n_params())
    return Fitted(prob.spec, prob, z, info, full_errors(prob, z))


def full_errors(prob: Problem, z: np.ndarray) -> Errors:
    """Errors of every record on all its samples."""
    coefs = prob.offsets(z)
    return error_measures([(r.name, r.y, prob.full_prediction(k, z, coefs[k])) for k, r in enumerate(prob.records)])


def fit_spec(spec: Spec, current: Fitted, *, init_from: Fitted | None = None) -> Fitted:
    """Fit *spec* on all fitting samples of *current*'s records.

    Started from *init_from* (default *current*), its new effects first set by
    :func:`~esmm.pipeline.discover.initialise.initialise` and the added slots of
    a richer variant by :func:`~esmm.pipeline.discover.initialise.extend_variant`.
    A fit stopped by its evaluation cap where its objective is still above the
    current model's (its parameters carried over, the new ones at their
    defaults) is continued once from where it stopped: a start far from the
    optimum (a slip's extension loss from its fall, taken on an elastic law
    that misfits the toe) can spend the cap reshaping the law and end worse
    than the model it extends, and its Δχ² then reads as a rejection.
    """
    prob = current.problem.derived(spec)
    src = init_from or current
    z0 = prob.params.transfer(src.problem.params, src.z)
    new = [n for n in spec.names() if not src.spec.variant(n)]
    for n in new:
        z0 = initialise(prob, z0, n)
    # slots of a richer variant of an effect already present (another Prony term, beta)
    old_keys = {s.key for s in src.problem.slots}
    extra = [i for i, s in enumerate(prob.slots) if s.effect is not None and s.effect not in new
             and s.file is None and s.key not in old_keys]
    if extra:
        z0 = extend_variant(prob, z0, extra)
    z, sol = prob.solve(z0)
    if sol is not None and sol.status == 0 and prob.objective(z) > prob.objective(
            prob.params.transfer(current.problem.params, current.z)):
        z, _ = prob.solve(z)
    return finish(prob, z)


def effect_params(f: Fitted, name: str) -> dict[str, Any]:
    """The fitted parameters of effect or term *name* in *f* (values only; intervals in the final model)."""
    st = f.values
    if name in TERMS:
        return {p.name: float(st.base[None][p.name]) for p in TERMS[name].parameters if p.name in st.base[None]}
    if name == "viscoelastic" and st.g is not None:
        return {"g": [float(v) for v in st.g], "tau": [float(v) for v in st.tau],
                "g_inf": float(max(0.0, 1 - float(np.sum(st.g))))}
    nl = f.spec.nonlinear_viscoelastic
    simple = {"nonlinear_viscoelastic": (("kappa_tau",), (st.kappa_tau,)) if nl == 2 else
              (("kappa",), (st.kappa,) if nl else None),
              "mullins": (("r", "m", "beta"), st.mullins), "damage": (("onset", "scale", "shape", "floor"), st.damage),
              "cyclic_softening": (("d_inf", "eta"), st.cyclic),
              "permanent_set": (("fraction", "exponent")[:f.spec.permanent_set],
                                (st.set_fraction, st.set_exponent)[:f.spec.permanent_set] or None)}
    if name in simple:
        keys, vals = simple[name]
        return {} if vals is None else dict(zip(keys, map(float, vals)))
    per_file = {"slack": _slack_params, "grip_slip": _slip_params, "specimen_scale": _scale_params}
    if name in per_file and f.spec.variant(name):
        return per_file[name](f.problem, st)
    if name == "sensor_offset":
        return _offset_params(f.problem, f.z)
    return {}


def _slip_params(prob: Problem, st: Values) -> dict[str, Any]:
    out = {}
    for k, r in enumerate(prob.records):
        if st.slips and st.slips[k].size:
            out[r.name] = [{"sample": int(e), "stretch": float(r.x[e]), "delta": float(d),
                            "length_m": float(d) * r.gauge if r.gauge else None}
                           for e, d in zip(r.slips, st.slips[k])]
    return out


def _scale_params(prob: Problem, st: Values) -> dict[str, Any]:
    return {r.name: {"specimen": r.specimen, "scale": float(st.scale[k])} for k, r in enumerate(prob.records)}


def _slack_params(prob: Problem, st: Values) -> dict[str, Any]:
    out = {}
    for k, r in enumerate(prob.records):
        if any(s.effect == "slack" and s.file == k for s in prob.slots):
            d = float(st.slack[k])
            out[r.name] = {"delta": d, "length_m": d * r.gauge if r.gauge else None}
    return out


def _offset_params(prob: Problem, z: np.ndarray) -> dict[str, Any]:
    out = {}
    for k, c in enumerate(prob.offsets(z)):
        if c is None:
            continue
        r = prob.records[k]
        o = float(c[0])  # data = model + offset (what the load cell reads at zero force)
        d = float(c[1]) / (r.T or 1.0) if len(c) > 1 else 0.0
        out[r.name] = {"stress_Pa": o, "drift_Pa_per_s": d,
                       "force_N": o * r.area if r.area else None,
                       "drift_N_per_s": d * r.area if r.area else None}
    return out
