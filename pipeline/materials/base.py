"""Material models: parameter specifications and the model base class.

A material model is an incompressible, isotropic strain-energy function
:math:`W(I_1, I_2)` [Pa] of the first two invariants of the right Cauchy-Green
tensor, with its parameter specifications. Every model lives in one small
module of this package (the module docstring and the class docstring carry the
equation) and is registered by one line in :mod:`esmm.pipeline.materials`.

Conventions
-----------
* ``params`` is a ``Mapping[str, float]`` in SI: stress-like parameters in Pa,
  the others dimensionless.
* Functions are vectorised: ``I1`` and ``I2`` may be arrays of any (common,
  broadcastable) shape; outputs have the broadcast shape.
* Evaluating a model does not validate parameter bounds (a fitter may probe
  outside them); :meth:`MaterialModel.check` does, with one-line
  :class:`~esmm.pipeline.errors.ConfigError` messages.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import ConfigError

__all__ = ["Parameter", "MaterialModel", "PARAMETER_KINDS", "broadcast_zeros"]

#: The kinds of parameter a model may declare.
PARAMETER_KINDS = ("stress", "dimensionless")


def broadcast_zeros(I1, I2) -> np.ndarray:
    """Zeros of the broadcast shape of *I1* and *I2* (equal shapes, the usual case, without broadcasting)."""
    s1, s2 = np.shape(I1), np.shape(I2)
    return np.zeros(s1 if s1 == s2 else np.broadcast_shapes(s1, s2))


@dataclass(frozen=True)
class Parameter:
    """Specification of one material parameter.

    Attributes
    ----------
    name
        Key in ``params`` and in ``[material.parameters]`` of a material file.
    kind
        ``"stress"`` (SI value in Pa; written in the file's ``stress_unit``) or
        ``"dimensionless"``.
    default
        Typical value (SI), a starting point for fits.
    lower, upper
        Closed admissible interval (SI). Values outside are refused by
        :meth:`MaterialModel.check` and by material files.
    description
        One line for reports and the TOML comments.
    directional
        True for parameters that an anisotropic fit determines separately per
        fibre direction (x, y, z) and that a material file may override in
        ``[material.directions.x|y|z]``; False for parameters shared by all
        directions (matrix properties, locking).
    fit
        False for parameters that homogeneous tests cannot identify together
        with the others (held at their value unless a user frees them; see
        docs/design/model.md for the reason per model).
    optional
        True for a parameter added to a model after files were written without
        it: a file that does not give it takes the default, the law such files
        were written with (the toe's recruitment shape).
    """

    name: str
    kind: str
    default: float
    lower: float
    upper: float
    description: str
    directional: bool = False
    fit: bool = True
    optional: bool = False

    def __post_init__(self):
        if self.kind not in PARAMETER_KINDS:
            raise ValueError(f"Parameter {self.name!r}: kind must be one of {PARAMETER_KINDS}")
        if not (self.lower <= self.default <= self.upper):
            raise ValueError(f"Parameter {self.name!r}: default outside [lower, upper]")


def _parameter_value(v):
    """A parameter as the model functions take it: a float, or a float array (see ``array_parameters``)."""
    return np.asarray(v, dtype=float) if isinstance(v, np.ndarray) else float(v)


class MaterialModel:
    """Base class of the incompressible isotropic strain-energy models.

    Subclasses set the class attributes :attr:`name`, :attr:`parameters` and
    :attr:`equation`, and implement the pure functions ``_energy``, ``_dW``
    (and, where feasible, ``_d2W``) and ``_max_I1``, which receive the
    parameters as keyword arguments in SI.

    Attributes
    ----------
    name : str
        Registry name (``"esedf"``, ``"arruda-boyce"``).
    parameters : tuple of Parameter
        The parameter specifications, in a fixed order.
    equation : str
        The strain-energy function in plain text, for reports.
    """

    name: ClassVar[str] = ""
    parameters: ClassVar[tuple[Parameter, ...]] = ()
    equation: ClassVar[str] = ""
    #: Names that users may carry over from a source paper but that are not
    #: parameters of this model -> why (used in the "unknown parameter" error).
    not_parameters: ClassVar[dict[str, str]] = {}
    #: True when :meth:`energy`, :meth:`dW` and :meth:`d2W` take parameter arrays
    #: of shape (m, 1) (m parameter sets, one per row of the result, each row
    #: what the scalar parameters give, bit for bit): a fitter evaluates its
    #: finite-difference steps in one call.
    array_parameters: ClassVar[bool] = False

    # ------------------------------------------------------------------ API
    def energy(self, I1, I2, params: Mapping[str, float]):
        """Strain energy per unit reference volume.

        Parameters
        ----------
        I1, I2 : array_like, shape (...)
            First and second invariants of C (incompressible: I3 = 1).
        params
            Parameter values in SI.

        Returns
        -------
        ndarray, shape (...)
            W [Pa]; ``inf`` at ``I1 == max_I1``, NaN beyond.
        """
        return self._energy(np.asarray(I1, float), np.asarray(I2, float), **self._args(params))

    def dW(self, I1, I2, params: Mapping[str, float]):
        """First derivatives ``(W1, W2) = (∂W/∂I1, ∂W/∂I2)`` [Pa], shapes as ``I1``."""
        return self._dW(np.asarray(I1, float), np.asarray(I2, float), **self._args(params))

    def d2W(self, I1, I2, params: Mapping[str, float]):
        """Second derivatives ``(W11, W12, W22)`` [Pa], shapes as ``I1``."""
        return self._d2W(np.asarray(I1, float), np.asarray(I2, float), **self._args(params))

    def max_I1(self, params: Mapping[str, float]) -> float:
        """Upper limit of I1 where W is finite (exclusive); ``inf`` if none."""
        return float(self._max_I1(**self._args(params)))

    # -------------------------------------------------------------- helpers
    @functools.cached_property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the parameters, in declaration order."""
        return tuple(p.name for p in self.parameters)

    def parameter(self, name: str) -> Parameter:
        """The specification of parameter *name* (ConfigError if unknown)."""
        for p in self.parameters:
            if p.name == name:
                return p
        raise self.unknown_parameter_error(name)

    def defaults(self) -> dict[str, float]:
        """The default parameter values (SI)."""
        return {p.name: float(p.default) for p in self.parameters}

    def initial_shear_modulus(self, params: Mapping[str, float]) -> float:
        """Small-strain shear modulus μ0 = 2(W1 + W2) at I1 = I2 = 3 [Pa].

        The small-strain Young's modulus of the incompressible material is
        E = 3 μ0.
        """
        w1, w2 = self.dW(3.0, 3.0, params)
        return float(2.0 * (w1 + w2))

    def check(self, params: Mapping[str, float], *, where: str = "") -> dict[str, float]:
        """Validate a full parameter set; return it as a plain dict of floats.

        Parameters
        ----------
        params
            Parameter values in SI.
        where
            Location for messages (file, table).

        Raises
        ------
        ConfigError
            One line naming the parameter: missing, unknown, not a finite
            number, or outside [lower, upper].
        """
        loc = f"{where}: " if where else ""
        unknown = [k for k in params if k not in self.parameter_names]
        if unknown:
            raise self.unknown_parameter_error(unknown[0], where=where)
        out: dict[str, float] = {}
        for p in self.parameters:
            if p.name not in params and p.optional:
                out[p.name] = p.default
                continue
            if p.name not in params:
                raise ConfigError(
                    f"{loc}parameter {p.name!r} of model {self.name!r} is missing; "
                    f"add it ({p.description})"
                )
            out[p.name] = self.check_value(p.name, params[p.name], where=where)
        self._check_extra(out, where=where)
        return out

    def unknown_parameter_error(self, name: str, *, where: str = "", parameter: str | None = None) -> ConfigError:
        """The one-line error for a key that is not a parameter of this model.

        *where* starts the message; *parameter* is the library option the key was
        given to (then *where* should be that option's name).
        """
        loc = f"{where}: " if where else ""
        if name in self.not_parameters:
            return ConfigError(
                f"{loc}{name!r} is not a parameter of model {self.name!r}: {self.not_parameters[name]}",
                parameter=parameter,
            )
        return ConfigError(
            f"{loc}unknown parameter {name!r} for model {self.name!r}; "
            f"its parameters are {', '.join(self.parameter_names)}", parameter=parameter,
        )

    def check_value(self, name: str, value, *, where: str = "") -> float:
        """Validate one parameter value (SI); return it as float."""
        p = self.parameter(name)
        loc = f"{where}: " if where else ""
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
            raise ConfigError(f"{loc}parameter {name!r} must be a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            raise ConfigError(f"{loc}parameter {name!r} is not a finite number ({value!r})")
        if not (p.lower <= v <= p.upper):
            unit = " Pa" if p.kind == "stress" else ""
            raise ConfigError(
                f"{loc}parameter {name!r} = {v:g}{unit} is outside its admissible range "
                f"[{p.lower:g}, {p.upper:g}]{unit}; {p.description}"
            )
        return v

    # --------------------------------------------------------- for subclasses
    def _args(self, params: Mapping[str, float]) -> dict[str, float]:
        out: dict[str, float] = {}
        for p in self.parameters:
            if p.name in params:
                out[p.name] = _parameter_value(params[p.name])
            elif p.optional:
                out[p.name] = p.default
            else:
                raise ConfigError(
                    f"parameter {p.name!r} of model {self.name!r} is missing; "
                    f"its parameters are {', '.join(self.parameter_names)}"
                )
        return out

    def _check_extra(self, params: dict[str, float], *, where: str) -> None:
        """Cross-parameter conditions (override where needed)."""

    def _energy(self, I1, I2, **p):  # pragma: no cover - abstract
        raise NotImplementedError

    def _dW(self, I1, I2, **p):  # pragma: no cover - abstract
        raise NotImplementedError

    def _d2W(self, I1, I2, **p):
        """Default: central differences of ``_dW`` (override with the analytic form)."""
        h1 = 1e-6 * np.maximum(1.0, np.abs(I1))
        h2 = 1e-6 * np.maximum(1.0, np.abs(I2))
        a1, a2 = self._dW(I1 + h1, I2, **p)
        b1, b2 = self._dW(I1 - h1, I2, **p)
        c1, c2 = self._dW(I1, I2 + h2, **p)
        d1, d2 = self._dW(I1, I2 - h2, **p)
        w11 = (a1 - b1) / (2 * h1)
        w22 = (c2 - d2) / (2 * h2)
        w12 = 0.5 * ((a2 - b2) / (2 * h1) + (c1 - d1) / (2 * h2))
        return w11, w12, w22

    def _max_I1(self, **p) -> float:
        return math.inf

    def __repr__(self) -> str:
        return f"<material model {self.name!r}: {', '.join(self.parameter_names)}>"
