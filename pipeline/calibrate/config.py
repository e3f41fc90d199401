"""The options of a calibration: the ``[calibrate]`` table of a config file, merged with the caller's.

A calibrate config is a TOML file whose ``[calibrate]`` table (or top level)
may hold::

    [calibrate]
    model = "esedf"                 # a registered model (esmm.pipeline.materials.MODEL_NAMES)
    loss = "linear"                 # linear, soft_l1, huber, cauchy, arctan
    starts = 8                      # starting points of the fit
    seed = 0                        # seed of the starting points
    stress_unit = "kPa"             # unit of bare-number stress values in [calibrate.fix]
    weights = { cortex_simple_shear = 2.0 }   # per-file weights, by path, name or stem
    fix = { f = 0.002, mu = "3 kPa" }         # parameters held at a value

:func:`load_calibrate_config` reads it (every value checked, one-line
:class:`~esmm.pipeline.errors.ConfigError` naming the file and key) and lays the
caller's options over it; :meth:`CalibrateConfig.fit_kwargs` are the keyword
arguments of :func:`esmm.pipeline.calibrate.fit.fit_material`.
docs/reference/configuration.md ("Calibrate config") describes the table.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..checks import choice, keys, number, number_text, table
from ..config import load_toml
from ..errors import ConfigError, EsmmError
from ..materials import MODEL_NAMES, get_model
from ..materials.composite import split_name
from ..units import factor, parse_quantity
from .problem import check_parameter_names

#: the robust losses of :func:`scipy.optimize.least_squares`
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")
#: the keys of the ``[calibrate]`` table
TABLE_KEYS = ("model", "loss", "starts", "seed", "weights", "fix", "stress_unit")


def check_model(value: Any, name: str = "model", *, terms: bool = True) -> str:
    """A registered model name, or (*terms*) one plus strain-energy terms, ``esedf+i2exp`` (the message
    lists the models)."""
    base, extra = split_name(str(value)) if isinstance(value, str) else (value, ())
    if base not in MODEL_NAMES or (extra and not terms):
        more = " (plus strain-energy terms joined by '+')" if terms else ""
        raise ConfigError(f"{name}: unknown model {value!r}; choose one of {', '.join(MODEL_NAMES)}{more}",
                          parameter=name)
    if extra:
        try:
            get_model(value)
        except ConfigError as exc:
            raise ConfigError(f"{name}: {exc}", parameter=name) from None
    return value


def check_loss(value: Any, name: str = "loss") -> str:
    """One of :data:`LOSSES`."""
    return choice(value, LOSSES, name)


def check_starts(value: Any, name: str = "n_starts") -> int:
    """A number of starting points (a whole number >= 1)."""
    return number(value, name, lo=1, integer=True)


@dataclass(frozen=True)
class CalibrateConfig:
    """The options of :func:`esmm.pipeline.calibrate.fit.fit_material`, checked.

    Attributes
    ----------
    model, loss : str
    n_starts, seed : int
    weights : dict
        File path, name or stem -> weight.
    fixed : dict
        Parameter -> value held (SI).
    free : tuple of str
        Parameters the model holds by default, fitted anyway.
    """

    model: str = "esedf"
    loss: str = "linear"
    n_starts: int = 8
    seed: int = 0
    weights: dict[str, float] = field(default_factory=dict)
    fixed: dict[str, float] = field(default_factory=dict)
    free: tuple[str, ...] = ()

    def fit_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~esmm.pipeline.calibrate.fit.fit_material` (plain data)."""
        return dict(model=self.model, loss=self.loss, n_starts=self.n_starts, seed=self.seed,
                    weights=dict(self.weights) or None, fixed=dict(self.fixed) or None, free=tuple(self.free))


def load_calibrate_config(config: str | os.PathLike | None = None, *, model: str | None = None,
                          loss: str | None = None, n_starts: Any = None, seed: Any = None,
                          weights: Mapping[str, Any] | None = None, fixed: Mapping[str, Any] | None = None,
                          free: Sequence[str] | None = None) -> CalibrateConfig:
    """The calibrate options: the config file's ``[calibrate]`` table, then the keyword arguments.

    Parameters
    ----------
    config : path, optional
        A TOML file (module docstring).
    model, loss, n_starts, seed
        Override the file's ``model``, ``loss``, ``starts``, ``seed`` (None: keep it).
        Numbers may be given as text.
    weights : mapping, optional
        File -> weight (a number or its text), laid over the file's ``weights``.
    fixed : mapping, optional
        Parameter -> value held, laid over the file's ``fix``: a number, or text;
        stress-like parameters need a unit (``"3 kPa"``).
    free : sequence of str, optional
        Parameters the model holds by default, to fit anyway.

    Raises
    ------
    ConfigError
        One line naming the file and key, or the parameter, of the first bad value.
    """
    file_opts, file_fixed, where = _read_table(config)
    opts = {**file_opts, **{k: v for k, v in (("model", model), ("loss", loss)) if v is not None}}
    if n_starts is not None:
        opts["n_starts"] = number_text(n_starts, "n_starts", lo=1, integer=True)
    if seed is not None:
        opts["seed"] = number_text(seed, "seed", lo=0, integer=True)
    opts["model"] = check_model(opts.get("model", "esedf"))
    if loss is not None:
        opts["loss"] = check_loss(loss)
    m = get_model(opts["model"])
    held = _fixed_values(m, file_fixed, where) if file_fixed else {}
    held.update(_fixed_values(m, (fixed or {}, None), "fixed"))
    given = {str(k): _weight(v, "weights", str(k)) for k, v in (weights or {}).items()}
    return CalibrateConfig(weights={**opts.pop("weights", {}), **given}, fixed=held,
                           free=tuple(free or ()), **opts)


def _read_table(config) -> tuple[dict[str, Any], tuple[dict, float | None] | None, str]:
    """The checked values of the file's ``[calibrate]`` table (``fix`` still raw: it needs the model)."""
    if config is None:
        return {}, None, ""
    data = load_toml(config)
    c = data.get("calibrate", data)
    where = f"{config}: [calibrate]"
    c = table(c, where)
    keys(c, TABLE_KEYS, where)
    out: dict[str, Any] = {}
    if "model" in c:
        out["model"] = check_model(c["model"], f"{where} model")
    if "loss" in c:
        out["loss"] = check_loss(c["loss"], f"{where} loss")
    if "starts" in c:
        out["n_starts"] = number_text(c["starts"], f"{where} starts", lo=1, integer=True)
    if "seed" in c:
        out["seed"] = number_text(c["seed"], f"{where} seed", lo=0, integer=True)
    if "weights" in c:
        out["weights"] = {str(k): _weight(v, f"{where} weights", str(k))
                          for k, v in table(c["weights"], f"{where} weights").items()}
    unit = None
    if "stress_unit" in c:
        unit = _stress_factor(c["stress_unit"], f"{where} stress_unit")
    fix = (table(c["fix"], f"{where} fix"), unit) if "fix" in c else None
    return out, fix, where


def _weight(value: Any, name: str, key: str) -> float:
    try:
        return number_text(value, name)
    except ConfigError:
        raise ConfigError(f"{name}: the weight of {key} must be a number, got {value!r}",
                          parameter=name) from None


def _stress_factor(unit: Any, name: str) -> float:
    if not isinstance(unit, str):
        raise ConfigError(f"{name}: expected a stress unit such as \"kPa\", got {unit!r}", parameter=name)
    try:
        return factor(unit, "stress", where=name)
    except EsmmError as exc:
        raise ConfigError(str(exc), parameter=name) from None


def _fixed_values(model, given: tuple[Mapping[str, Any], float | None], name: str) -> dict[str, float]:
    """Held values in SI: stress-like ones with their unit (or a bare number in the table's stress_unit)."""
    values, stress_factor = given
    fix_name = name if name == "fixed" else f"{name} fix"
    check_parameter_names(model, values, fix_name)
    out: dict[str, float] = {}
    for k, v in values.items():
        where = f"{fix_name}: {k}"
        try:
            if model.parameter(k).kind != "stress":
                out[k] = float(number_text(v, where))
            elif isinstance(v, int | float) and not isinstance(v, bool) and name != "fixed":
                if stress_factor is None:
                    raise ConfigError(f"{where}: {v!r} is a bare number but the table has no stress_unit; add "
                                      f"stress_unit = \"kPa\" (or MPa, Pa) or write {k} = \"{v} kPa\"")
                out[k] = float(number(v, where)) * stress_factor
            else:
                out[k] = parse_quantity(str(v), "stress", where=where)
        except EsmmError as exc:
            raise ConfigError(str(exc), parameter=fix_name) from None
    return out
