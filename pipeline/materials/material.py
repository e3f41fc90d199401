"""Material: a model name, its parameters (SI) and optional per-direction values.

Material files (TOML)::

    [material]
    model = "esedf"                  # a registered model (esmm.pipeline.materials.MODEL_NAMES)
    name = "porcine liver"           # optional, default: the file name
    source = "ESMM paper, Table 2"   # optional provenance
    stress_unit = "MPa"              # unit of the bare-number stress parameters

    [material.parameters]            # every parameter of the model
    mu = 2.973e-06                   # stress: bare number in stress_unit ...
    A1 = "3.9106 MPa"                # ... or a string with its own unit
    N = 1.1074                       # dimensionless

    [material.directions.x]          # optional: per-direction overrides of the
    A1 = 4.2                         # model's *directional* parameters (x, y, z)

    [material.reported]              # optional free tables/keys: kept as metadata
    E = 0.67712

Bundled presets (``configs/materials/*.toml``) are loaded by name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from .. import config as _config
from ..atomicio import write_text
from ..errors import ConfigError, EsmmError
from ..units import factor, parse_quantity
from . import get_model, loading
from .base import MaterialModel

__all__ = ["DIRECTIONS", "Material", "load_material"]

#: The fibre directions of the spring network.
DIRECTIONS = ("x", "y", "z")
#: The material preset used where none is given (``esmm prepare``, the validation specimen).
DEFAULT_MATERIAL = "porcine_liver_paper"

_RESERVED = ("model", "name", "source", "stress_unit", "parameters", "directions")


@dataclass
class Material:
    """A material: model name, SI parameters, optional per-direction overrides.

    Attributes
    ----------
    model : str
        Registered model name.
    params : dict[str, float]
        Every parameter of the model, SI (stress in Pa).
    directions : dict[str, dict[str, float]] or None
        Per-direction overrides (keys ``"x"``, ``"y"``, ``"z"``) of the model's
        directional parameters, SI; None for an isotropic material. Full
        parameter sets are accepted: shared (non-directional) entries equal to
        ``params`` are dropped, different ones are an error.
    name : str
        Human-readable name.
    source : str
        Provenance (paper, fit file) or the file it was read from.
    metadata : dict
        Anything else (e.g. ``{"reported": {"E": 0.67712}}``), written back by
        :meth:`to_toml` under ``[material]``.
    stress_unit : str
        Unit in which :meth:`to_toml` writes stress parameters (default MPa).

    Raises
    ------
    ConfigError
        On construction, if the model is unknown or a parameter is missing,
        unknown, not finite or out of bounds (one line naming the key).
    """

    model: str
    params: dict[str, float]
    directions: dict[str, dict[str, float]] | None = None
    name: str = ""
    source: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)
    stress_unit: str = "MPa"

    def __post_init__(self):
        where = self.name or "material"
        m = get_model(self.model)
        self.model = m.name
        self.params = m.check(dict(self.params), where=f"{where} parameters")
        if self.directions is not None:
            dirs: dict[str, dict[str, float]] = {}
            for d, over in self.directions.items():
                if d not in DIRECTIONS:
                    raise ConfigError(
                        f"{where}: unknown direction {d!r}; use {', '.join(DIRECTIONS)}"
                    )
                # full per-direction parameter sets are accepted: shared
                # parameters equal to the base value are redundant and dropped
                over = {
                    k: v for k, v in dict(over).items()
                    if not (k in self.params and not m.parameter(k).directional
                            and _same(v, self.params[k]))
                }
                dirs[d] = _check_overrides(m, over, where=f"{where} directions.{d}")
            self.directions = dirs
        for key in self.metadata:
            if key in _RESERVED:
                raise ConfigError(f"{where}: metadata key {key!r} is reserved; rename it")
        _stress_factor(self.stress_unit, f"{where} stress_unit")

    # ----------------------------------------------------------- accessors
    @property
    def model_obj(self) -> MaterialModel:
        """The :class:`MaterialModel` instance."""
        return get_model(self.model)

    @property
    def is_isotropic(self) -> bool:
        """True when no direction overrides any parameter."""
        return not self.directions or not any(self.directions.values())

    def params_for(self, direction: str | None = None) -> dict[str, float]:
        """Parameters (SI) for fibre *direction* (``"x"``, ``"y"``, ``"z"``) or the base set."""
        p = dict(self.params)
        if direction is None:
            return p
        if direction not in DIRECTIONS:
            raise ConfigError(f"unknown direction {direction!r}; use {', '.join(DIRECTIONS)}")
        if self.directions and direction in self.directions:
            p.update(self.directions[direction])
        return p

    # ------------------------------------------------------------ physics
    def uniaxial_energy(self, lam, direction: str | None = None):
        """Energy per reference volume W(λ) [Pa] of incompressible uniaxial stretch.

        Parameters
        ----------
        lam : array_like, shape (...)
        direction : {"x", "y", "z"} or None

        Returns
        -------
        ndarray, shape (...)
            NaN outside the admissible range (see :meth:`stretch_range`).
        """
        return loading.energy_density(self.model_obj, self.params_for(direction), "uniaxial", lam)

    def mu_e(self, lam, direction: str | None = None):
        """Equivalent spring modulus μ_e(λ) = 2W(λ)/(λ−1)² [Pa] (the ESMM stiffness law).

        Exact limit W''(1) = E at λ = 1, smooth through it; valid in
        compression and in tension up to just below locking.

        Parameters
        ----------
        lam : array_like, shape (...)
        direction : {"x", "y", "z"} or None

        Returns
        -------
        ndarray, shape (...)
            NaN outside the admissible range.
        """
        return loading.mu_e(self.model_obj, self.params_for(direction), lam)

    def stretch_range(self, direction: str | None = None) -> tuple[float, float]:
        """Open interval of uniaxial stretch where the energy is finite (locking)."""
        return loading.admissible_range(self.model_obj, self.params_for(direction), "uniaxial")

    def youngs_modulus(self, direction: str | None = None) -> float:
        """Small-strain Young's modulus E = 3 μ0 [Pa] (equals μ_e(1))."""
        return 3.0 * self.model_obj.initial_shear_modulus(self.params_for(direction))

    # ------------------------------------------------------------- output
    def to_toml(self) -> str:
        """TOML text readable back by :func:`load_material`.

        Stress parameters are written in :attr:`stress_unit`; each parameter
        line carries its description as a comment.
        """
        m = self.model_obj
        f = factor(self.stress_unit, "stress")
        head = {"model": self.model, "name": self.name or self.model}
        if self.source:
            head["source"] = self.source
        head["stress_unit"] = self.stress_unit
        lines = [f"# material for esmm (model {self.model!r}); equations: docs/design/model.md",
                 "[material]", tomli_w.dumps(head).rstrip("\n")]
        scalars = {k: v for k, v in self.metadata.items() if not isinstance(v, Mapping)}
        if scalars:
            lines.append(tomli_w.dumps(_plain(scalars)).rstrip("\n"))
        lines += ["", "[material.parameters]"]
        for p in m.parameters:
            lines.append(_param_line(p, self.params[p.name], f, self.stress_unit))
        for d in DIRECTIONS:
            over = (self.directions or {}).get(d)
            if over:
                lines += ["", f"[material.directions.{d}]"]
                for p in m.parameters:
                    if p.name in over:
                        lines.append(_param_line(p, over[p.name], f, self.stress_unit))
        tables = {k: v for k, v in self.metadata.items() if isinstance(v, Mapping)}
        if tables:
            lines += ["", tomli_w.dumps({"material": _plain(tables)}).rstrip("\n")]
        return "\n".join(lines) + "\n"

    def save(self, path: str | os.PathLike) -> Path:
        """Write :meth:`to_toml` to *path* atomically; return the path."""
        return write_text(path, self.to_toml())


def _param_line(p, value: float, f: float, unit: str) -> str:
    if p.kind == "stress":
        return f"{p.name} = {value / f!r}  # [{unit}] {p.description}"
    return f"{p.name} = {float(value)!r}  # {p.description}"


def _plain(obj):
    """Metadata to TOML-serialisable types (numpy scalars/arrays to Python)."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _check_overrides(m: MaterialModel, over: Mapping[str, Any], *, where: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in over.items():
        if k not in m.parameter_names:
            raise ConfigError(
                f"{where}: unknown parameter {k!r} for model {m.name!r}; the parameters a "
                f"direction may override are {', '.join(_directional(m)) or '(none)'}"
            )
        if not m.parameter(k).directional:
            raise ConfigError(
                f"{where}: parameter {k!r} of model {m.name!r} is shared by all directions; "
                f"set it in [material.parameters] (directional: {', '.join(_directional(m))})"
            )
        out[k] = m.check_value(k, v, where=where)
    return out


def _same(a, b) -> bool:
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0)
    except (TypeError, ValueError):
        return False


def _directional(m: MaterialModel) -> list[str]:
    return [p.name for p in m.parameters if p.directional]


# --------------------------------------------------------------------- input
def load_material(name_or_path: str | os.PathLike) -> Material:
    """Read a material file, or a bundled preset by name.

    Parameters
    ----------
    name_or_path
        Path to a ``.toml`` file, or the name of a bundled preset
        (``configs/materials/<name>.toml``, e.g. ``"porcine_liver_paper"``).

    Returns
    -------
    Material

    Raises
    ------
    ConfigError
        One line naming the file and key: missing [material] or model, unknown
        model, missing/unknown parameter, out-of-bounds value, a bare number
        for a stress parameter without ``stress_unit``, unknown unit, bad
        direction.
    """
    data, src = _config.load("materials", name_or_path)
    where = src
    extra_top = [k for k in data if k != "material"]
    if "material" not in data or not isinstance(data["material"], dict):
        raise ConfigError(f"{where}: no [material] table; a material file starts with [material]")
    if extra_top:
        raise ConfigError(
            f"{where}: unexpected top-level key or table {extra_top[0]!r}; everything goes "
            f"under [material] (e.g. [material.{extra_top[0]}])"
        )
    mat = data["material"]
    model_name = mat.get("model")
    if not isinstance(model_name, str) or not model_name.strip():
        raise ConfigError(f"{where}: [material] model is missing; add e.g. model = \"esedf\"")
    try:
        m = get_model(model_name)
    except ConfigError as exc:
        raise ConfigError(f"{where}: [material] model: {exc}") from None
    unit = mat.get("stress_unit")
    f_stress = None
    if unit is not None:
        if not isinstance(unit, str):
            raise ConfigError(f"{where}: [material] stress_unit must be a string such as \"MPa\"")
        f_stress = _stress_factor(unit, f"{where}: [material] stress_unit")
    raw = mat.get("parameters")
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{where}: no [material.parameters] table; list the parameters of model "
            f"{m.name!r}: {', '.join(m.parameter_names)}"
        )
    params = _read_values(m, raw, f_stress, unit, where=f"{where}: [material.parameters]")
    params = m.check(params, where=f"{where}: [material.parameters]")
    directions = _read_directions(m, mat["directions"], f_stress, unit, where=where) if "directions" in mat else None
    name = mat.get("name")
    if name is not None and not isinstance(name, str):
        raise ConfigError(f"{where}: [material] name must be a string")
    source = mat.get("source", src)
    if not isinstance(source, str):
        raise ConfigError(f"{where}: [material] source must be a string")
    default_name = str(name_or_path) if src.startswith("bundled:") else Path(src).stem
    metadata = {k: v for k, v in mat.items() if k not in _RESERVED}
    return Material(
        model=m.name, params=params, directions=directions,
        name=name or default_name, source=source, metadata=metadata,
        stress_unit=unit if unit is not None else "MPa",
    )


def _read_directions(m: MaterialModel, dtab: Any, f_stress: float | None, unit: str | None, *,
                     where: str) -> dict[str, dict[str, float]]:
    """The ``[material.directions.x|y|z]`` tables: overrides of the model's directional parameters (SI)."""
    if not isinstance(dtab, dict):
        raise ConfigError(f"{where}: [material.directions] must be a table of x, y, z tables")
    directions = {}
    for d, over in dtab.items():
        w = f"{where}: [material.directions.{d}]"
        if d not in DIRECTIONS:
            raise ConfigError(f"{w}: unknown direction {d!r}; use {', '.join(DIRECTIONS)}")
        if not isinstance(over, dict):
            raise ConfigError(f"{w}: must be a table of parameter overrides")
        vals = _read_values(m, over, f_stress, unit, where=w, partial=True)
        directions[d] = _check_overrides(m, vals, where=w)
    return directions


def _stress_factor(unit: str, where: str) -> float:
    try:
        return factor(unit, "stress", where=where)
    except EsmmError as exc:
        raise ConfigError(str(exc)) from None


def _read_values(m: MaterialModel, raw: Mapping[str, Any], f_stress: float | None,
                 unit: str | None, *, where: str, partial: bool = False) -> dict[str, float]:
    """Convert a parameter table to SI floats (strings may carry their own unit)."""
    out: dict[str, float] = {}
    for key, val in raw.items():
        if key not in m.parameter_names:
            raise m.unknown_parameter_error(key, where=where)
        p = m.parameter(key)
        w = f"{where} {key}"
        if isinstance(val, bool) or not isinstance(val, int | float | str):
            raise ConfigError(f"{w}: expected a number, got {val!r}")
        if isinstance(val, str):
            out[key] = _parse_string(val, p.kind, w)
            continue
        v = float(val)
        if not math.isfinite(v):
            raise ConfigError(f"{w}: {val!r} is not a finite number")
        if p.kind == "stress":
            if f_stress is None:
                raise ConfigError(
                    f"{w}: {val!r} is a bare number but [material] has no stress_unit; add "
                    f"stress_unit = \"MPa\" (or kPa, Pa) or write {key} = \"{val} MPa\""
                )
            v *= f_stress
        out[key] = v
    return out


def _parse_string(text: str, kind: str, where: str) -> float:
    try:
        return parse_quantity(text, kind, where=where)
    except EsmmError as exc:
        raise ConfigError(str(exc)) from None

