r"""The least-squares problem of a hyperelastic fit, shared by calibrate and discover.

Every file contributes on an equal footing whatever its number of samples or
stress level. The residual of sample *k* of file *f* is

.. math::

    r_{f,k} = \sqrt{w_f / n_f}\; \frac{P_\text{model}(x_{f,k}; \theta) - P_{f,k}}{s_f},
    \qquad s_f = \max_k |P_{f,k}| ,

with :math:`w_f` the per-file weight (default 1, :func:`file_weights`), :math:`n_f`
its sample count and :math:`s_f` its stress scale (:func:`stress_scale`). A
sample outside the model's domain (chain locked) gets the residual
:data:`NAN_PENALTY`.

:class:`ParameterLayout` maps the model's parameters to optimiser coordinates:
parameters held (``fixed``, or ``Parameter.fit`` False and not freed) are left
out; directional parameters get one coordinate per fibre direction of an
anisotropic fit (:func:`fibre_directions`); stress-like parameters, and
dimensionless ones spanning many decades, live in log space (they span decades:
the paper's liver has μ ≈ 3e-6 MPa next to A2 ≈ 452). :class:`FitProblem` is the
residual of :func:`esmm.pipeline.calibrate.fit.fit_material`; the discovery's
extended problem (:class:`esmm.pipeline.discover.model.Problem`) lays its base
parameters out with the same :class:`ParameterLayout` and normalises its
residual with the same weights, scales and penalty, so that a base model fitted
here and there agree.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..materials.loading import invariants, nominal_stress
from ..materials.material import DIRECTIONS
from ..tensile.data import TensileTest

#: the normalised residual of a sample outside the model's domain (a large, smooth-ish penalty)
NAN_PENALTY = 1e3


@dataclass(frozen=True)
class Slot:
    """One optimiser coordinate of a base parameter.

    Attributes
    ----------
    name : str
        The model's parameter name.
    direction : str or None
        Fibre direction (``x``, ``y``, ``z``) of a directional parameter of an
        anisotropic fit; None for a shared one.
    kind : str
        The parameter's kind (``"stress"``, ``"dimensionless"``).
    log : bool
        Whether the coordinate is the log of the value.
    lo, hi : float
        Bounds in optimiser coordinates.
    """

    name: str
    direction: str | None
    kind: str
    log: bool
    lo: float
    hi: float

    @property
    def key(self) -> str:
        return self.name if self.direction is None else f"{self.name}[{self.direction}]"


def check_parameter_names(model, names: Iterable[str], parameter: str) -> None:
    """Refuse names that are not parameters of *model* (the message starts with *parameter*)."""
    for name in names:
        if name not in model.parameter_names:
            raise model.unknown_parameter_error(name, where=parameter, parameter=parameter)


def stress_scale(stress: np.ndarray) -> float:
    """The stress scale :math:`s_f = \\max_k |P_{f,k}|` of one file [Pa] (floored above zero)."""
    return max(float(np.max(np.abs(stress))), 1e-30)


def file_weights(tests: Sequence[TensileTest], weights) -> list[float]:
    """Per-file weights :math:`w_f`.

    Parameters
    ----------
    tests : sequence of TensileTest
    weights : mapping, sequence or None
        None: every file 1. A mapping from a file's path, name or stem to its
        weight (files not named: 1). A sequence: one weight per file, in order.

    Raises
    ------
    ConfigError
        A weight is not a positive number, or the sequence has the wrong length.
    """
    if weights is None:
        return [1.0] * len(tests)
    if isinstance(weights, Mapping):
        out = []
        for t in tests:
            w = weights.get(str(t.source), weights.get(t.source.name, weights.get(t.source.stem, 1.0)))
            out.append(float(w))
    else:
        out = [float(v) for v in weights]
        if len(out) != len(tests):
            raise ConfigError(f"weights: {len(out)} weights for {len(tests)} files", parameter="weights")
    for t, v in zip(tests, out):
        if not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"weights: the weight of {t.source.name} must be a positive number, got {v}",
                              parameter="weights")
    return out


def fibre_directions(tests: Sequence[TensileTest]) -> list[str] | None:
    """The fibre directions the files are tagged with (sorted), or None for an isotropic fit.

    Raises
    ------
    ConfigError
        Tagged and untagged files are mixed, or a tag is not one of x, y, z.
    """
    tags = [t.orientation for t in tests]
    if all(o is None for o in tags):
        return None
    if any(o is None for o in tags):
        untagged = [t.source.name for t in tests if t.orientation is None]
        raise ConfigError(
            f"some files have an orientation and some do not ({', '.join(untagged[:3])} untagged); "
            "tag every file with orientation = x|y|z, or none for an isotropic fit"
        )
    bad = sorted({o for o in tags if o not in DIRECTIONS})
    if bad:
        raise ConfigError(
            f"orientation {bad[0]!r} is not one of x, y, z; angles are read but an anisotropic "
            "fit needs the fibre-frame axes x|y|z"
        )
    return sorted(set(tags))


def largest_i1(tests: Sequence[TensileTest]) -> float:
    """The largest first invariant reached by any sample of *tests* (at least 3)."""
    i1_max = 3.0
    for t in tests:
        i1, _ = invariants(t.mode, t.stretch)
        i1_max = max(i1_max, float(np.nanmax(i1)))
    return i1_max


# --------------------------------------------------------------------------- layout
class ParameterLayout:
    """The optimiser coordinates of a model's base parameters (module docstring).

    Parameters
    ----------
    model : MaterialModel
    fixed : mapping
        Parameters held at a value (SI).
    directions : list of str or None
        Fibre directions of an anisotropic fit (:func:`fibre_directions`).
    free : sequence of str
        Parameters the model holds by default (``Parameter.fit`` False) to fit anyway.
    i1_max : float
        The largest I1 in the data (:func:`largest_i1`): for chain-locking models
        the lower bound of ``N`` is raised so that the chain never locks inside the data.

    Attributes
    ----------
    slots : list of Slot
    fixed : dict
        Every held parameter, those held by default included.
    """

    def __init__(self, model, *, fixed: Mapping[str, float], directions: list[str] | None,
                 free: Sequence[str] = (), i1_max: float = 3.0):
        self.model = model
        self.directions = directions
        self.fixed = dict(fixed)
        self.i1_max = i1_max
        check_parameter_names(model, self.fixed, "fixed")
        check_parameter_names(model, free, "free")
        for p in model.parameters:
            if not getattr(p, "fit", True) and p.name not in self.fixed and p.name not in free:
                self.fixed[p.name] = float(p.default)
        self.slots = [s for p in model.parameters if p.name not in self.fixed for s in self._slots_of(p)]
        self.lower = np.array([s.lo for s in self.slots])
        self.upper = np.array([s.hi for s in self.slots])

    def _slots_of(self, p) -> list[Slot]:
        dirs = self.directions if (self.directions and getattr(p, "directional", False)) else [None]
        lo, hi = float(p.lower), float(p.upper)
        model = getattr(self.model, "base", self.model)
        if p.name == "N" and p.name in model.parameter_names and math.isfinite(model.max_I1(model.defaults())):
            lo = max(lo, self._n_lower())
        log = (p.kind == "stress" and hi > 0) or (lo > 0 and hi / lo > 1e3)
        if log:
            # a zero lower bound becomes a floor twelve decades below the default (or the upper bound)
            lo = max(lo, 1e-12 * (p.default if p.default > 0 else hi))
            lo, hi = math.log(lo), math.log(hi)
        return [Slot(p.name, d, p.kind, log, lo, hi) for d in dirs]

    def _n_lower(self) -> float:
        """Smallest N with the chain not locked at the largest I1 in the data (AB family).

        For a base model plus strain-energy terms, the base's own locking (a term such as
        Gent's locks on its own parameter)."""
        model = getattr(self.model, "base", self.model)
        base = model.defaults()
        lo, hi = 1e-6, 1e6
        for _ in range(200):
            mid = math.sqrt(lo * hi)
            if model.max_I1({**base, "N": mid}) > self.i1_max * (1 + 1e-6):
                hi = mid
            else:
                lo = mid
            if hi / lo < 1 + 1e-9:
                break
        return hi * (1 + 1e-6)

    def to_params(self, z: np.ndarray) -> dict[str | None, dict[str, float]]:
        """Parameter values (SI) per fibre direction from a vector.

        Key None: a full parameter set for the material as a whole, the one a
        material file's ``[material.parameters]`` holds. In an anisotropic fit
        its directional parameters are the mean over the fitted directions
        (the value an untested direction is given, see
        :func:`esmm.pipeline.calibrate.fit.fit_material`), so that the set is
        complete even when a single direction was tested.
        """
        base = dict(self.fixed)
        shared: dict[str, float] = {}
        directional: dict[str, dict[str, float]] = {}
        for s, v in zip(self.slots, z):
            val = math.exp(v) if s.log else float(v)
            if s.direction is None:
                shared[s.name] = val
            else:
                directional.setdefault(s.direction, {})[s.name] = val
        base.update(shared)
        per_dir: dict[str | None, dict[str, float]] = {}
        for d in self.directions or ():
            per_dir[d] = {**base, **directional.get(d, {})}
        if directional:
            names = {k for vals in directional.values() for k in vals}
            base = {**base, **{k: float(np.mean([per_dir[d][k] for d in self.directions])) for k in sorted(names)}}
        per_dir[None] = base
        return per_dir

    def from_params(self, values: Mapping[str, float]) -> np.ndarray:
        """The vector (clipped to the bounds) of one set of parameter values (SI)."""
        z = [math.log(float(values[s.name])) if s.log else float(values[s.name]) for s in self.slots]
        return np.clip(np.array(z), self.lower, self.upper)

    def keys(self) -> list[str]:
        return [s.key for s in self.slots]


def layout_for(model, tests: Sequence[TensileTest], *, fixed: Mapping[str, float],
               directions: list[str] | None, free: Sequence[str] = ()) -> ParameterLayout:
    """The :class:`ParameterLayout` of *model* for the data *tests*."""
    return ParameterLayout(model, fixed=fixed, directions=directions, free=free, i1_max=largest_i1(tests))


# --------------------------------------------------------------------------- residual
class FitProblem:
    """The normalised residual of one material on some tests (module docstring).

    Parameters
    ----------
    layout : ParameterLayout
    tests : sequence of TensileTest
    weights : sequence of float
        Per-file weights (:func:`file_weights`).
    """

    def __init__(self, layout: ParameterLayout, tests: Sequence[TensileTest], weights: Sequence[float]):
        self.layout = layout
        self.model = layout.model
        self.tests = list(tests)
        self.weights = np.asarray(weights, float)
        self.scale = np.array([stress_scale(t.stress) for t in self.tests])
        self.subset: list[np.ndarray | None] = [None] * len(self.tests)

    def params_of(self, per_dir: Mapping[str | None, dict[str, float]], test: TensileTest) -> dict[str, float]:
        """The parameters that apply to *test* (its fibre direction's in an anisotropic fit)."""
        return per_dir[test.orientation if self.layout.directions else None]

    def predict(self, test: TensileTest, params: Mapping[str, float], idx=None) -> np.ndarray:
        """Nominal stress [Pa] of *test*'s samples (or those at *idx*); NaN outside the domain."""
        x = test.stretch if idx is None else test.stretch[idx]
        with np.errstate(all="ignore"):
            return np.asarray(nominal_stress(self.model, params, test.mode, x), float)

    def residuals(self, z: np.ndarray) -> np.ndarray:
        """The normalised residual vector at *z* (over the current subsets)."""
        per_dir = self.layout.to_params(z)
        out = []
        for k, t in enumerate(self.tests):
            idx = self.subset[k]
            pred = self.predict(t, self.params_of(per_dir, t), idx)
            data = t.stress if idx is None else t.stress[idx]
            n = t.n if idx is None else len(idx)
            f = math.sqrt(self.weights[k] / n)
            out.append(f * (pred - data) / self.scale[k])
        r = np.concatenate(out)
        r[~np.isfinite(r)] = NAN_PENALTY
        return r

    def use_subset(self, max_samples: int | None) -> None:
        """Evaluate the residual on at most *max_samples* evenly spaced samples per file (None: all)."""
        for k, t in enumerate(self.tests):
            if max_samples is None or t.n <= max_samples:
                self.subset[k] = None
            else:
                self.subset[k] = np.unique(np.linspace(0, t.n - 1, max_samples).round().astype(int))
