"""Units: one explicit table, never a guess.

Every dimensional value that enters esmm names its unit, and is converted to
SI here. Unknown units raise :class:`~esmm.pipeline.errors.InputError` naming
the unit and the accepted ones.

>>> to_si(30.0, "mm", "length")
0.03
>>> parse_quantity("30 mm", "length", where="gauge_length")
0.03
"""

from __future__ import annotations

import math
import re

from .errors import InputError

#: kind -> {unit spelling (lower case) -> factor to SI}
UNITS: dict[str, dict[str, float]] = {
    "time": {"s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3, "min": 60.0, "h": 3600.0},
    "length": {
        "m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "micron": 1e-6,
        "in": 0.0254,
    },
    "area": {"m2": 1.0, "m^2": 1.0, "cm2": 1e-4, "cm^2": 1e-4, "mm2": 1e-6, "mm^2": 1e-6, "mm²": 1e-6},
    "force": {"n": 1.0, "mn": 1e-3, "kn": 1e3},
    "stress": {
        "pa": 1.0, "kpa": 1e3, "mpa": 1e6, "gpa": 1e9, "n/mm2": 1e6, "n/mm^2": 1e6, "n/m2": 1.0,
    },
    "density": {"kg/m3": 1.0, "kg/m^3": 1.0, "g/cm3": 1e3, "g/cm^3": 1e3, "g/mm3": 1e6},
    # Dimensionless quantities: stretch, engineering strain, shear strain.
    "dimensionless": {"": 1.0, "-": 1.0, "1": 1.0, "mm/mm": 1.0, "m/m": 1.0, "%": 1e-2},
}

#: The SI unit that each kind is converted to, for messages and metadata.
SI_UNIT = {
    "time": "s", "length": "m", "area": "m2", "force": "N", "stress": "Pa",
    "density": "kg/m3", "dimensionless": "",
}

_ALIASES = {"newton": "n", "newtons": "n", "millimeter": "mm", "millimetre": "mm", "meter": "m",
            "metre": "m", "percent": "%"}


def normalise_unit(unit: str) -> str:
    """Lower-case, strip brackets and spaces: ``'(mm)' -> 'mm'``, ``'[N]' -> 'n'``."""
    u = unit.strip().strip("()[]{}").strip().lower().replace(" ", "")
    return _ALIASES.get(u, u)


def factor(unit: str, kind: str, *, where: str = "") -> float:
    """Factor that converts a value in *unit* to the SI unit of *kind*."""
    table = UNITS[kind]
    u = normalise_unit(unit)
    if u in table:
        return table[u]
    accepted = ", ".join(sorted({k for k in table if k}))
    loc = f"{where}: " if where else ""
    raise InputError(
        f"{loc}unknown {kind} unit {unit!r}; accepted: {accepted or '(none)'}"
    )


def to_si(value, unit: str, kind: str, *, where: str = ""):
    """Convert *value* (scalar or array) from *unit* to SI."""
    return value * factor(unit, kind, where=where)


def from_si(value, unit: str, kind: str, *, where: str = ""):
    """Convert *value* from SI to *unit*."""
    return value / factor(unit, kind, where=where)


_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


def parse_quantity(text, kind: str, *, where: str = "") -> float:
    """Parse ``"30 mm"`` into an SI float. A bare number is refused.

    Parameters
    ----------
    text
        A string with a number and a unit (``"22 mm2"``, ``"1.5 cm"``).
    kind
        ``"length"``, ``"area"``, ... (a key of :data:`UNITS`).
    where
        What is being parsed, for the error message (file and key).
    """
    loc = f"{where}: " if where else ""
    if isinstance(text, bool) or not isinstance(text, str):
        raise InputError(
            f"{loc}{text!r} has no unit; write it as a string with its unit, "
            f"e.g. \"30 {_example_unit(kind)}\""
        )
    m = _QUANTITY.match(text)
    if not m:
        raise InputError(f"{loc}cannot read {text!r} as a number with a unit, e.g. \"30 {_example_unit(kind)}\"")
    number, unit = float(m.group(1)), m.group(2)
    if not unit and kind != "dimensionless":
        raise InputError(
            f"{loc}{text!r} has no unit; write it with its unit, e.g. \"{number:g} {_example_unit(kind)}\""
        )
    value = number * factor(unit, kind, where=where.strip() or "")
    if not math.isfinite(value):
        raise InputError(f"{loc}{text!r} is not a finite number")
    return value


def _example_unit(kind: str) -> str:
    return {"length": "mm", "area": "mm2", "time": "s", "force": "N", "stress": "kPa",
            "density": "kg/m3"}.get(kind, "")
