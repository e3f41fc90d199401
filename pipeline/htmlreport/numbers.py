"""Numbers with their units, for reports: a readable unit per quantity, a fixed number of digits.

Every number a report shows carries its unit. Values are SI inside esmm; a report
shows each in the decimal multiple of its SI unit that puts it between 1 and 1000
(0.67 Pa, not 6.7e-07 MPa), chosen per quantity, never per table.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

#: The unit of a dimensionless number (a stretch, a ratio). Shown as "–" in table headers.
DIMENSIONLESS = "1"

#: SI unit -> its multiples that reports use, largest first: (name, factor to SI).
MULTIPLES: dict[str, tuple[tuple[str, float], ...]] = {
    "Pa": (("GPa", 1e9), ("MPa", 1e6), ("kPa", 1e3), ("Pa", 1.0)),  # a stress below 1 Pa reads best in Pa
    "N": (("kN", 1e3), ("N", 1.0), ("mN", 1e-3), ("µN", 1e-6)),
    "m": (("m", 1.0), ("mm", 1e-3), ("µm", 1e-6)),
    "s": (("s", 1.0), ("ms", 1e-3), ("µs", 1e-6)),
    "m2": (("m²", 1.0), ("mm²", 1e-6)),
}


def _finite(values: Iterable[float | None]) -> list[float]:
    out = []
    for v in values:
        try:
            f = float(v)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            continue
        if math.isfinite(f) and f != 0.0:
            out.append(abs(f))
    return out


def readable_unit(values: Iterable[float | None], unit: str) -> tuple[str, float]:
    """The multiple of SI *unit* in which the largest of *values* lies between 1 and 1000.

    Parameters
    ----------
    values : iterable of float
        Values in *unit* (SI); non-finite values and zeros are ignored.
    unit : str
        An SI unit of :data:`MULTIPLES` (``"Pa"``, ``"N"``, ``"m"``, ``"s"``, ``"m2"``);
        any other unit is returned as it is, with factor 1.

    Returns
    -------
    (str, float)
        The unit to show and the factor to divide the SI values by.
    """
    steps = MULTIPLES.get(unit)
    if not steps:
        return unit, 1.0
    vals = _finite(values)
    vmax = max(vals) if vals else 1.0
    for name, fac in steps:
        if vmax >= fac * (1.0 - 1e-12):
            return name, fac
    return steps[-1]


def format_number(value: float | None, digits: int = 4) -> str:
    """*value* with *digits* significant digits; ``–`` for None or NaN, ``∞`` for infinity."""
    if value is None:
        return "–"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(v):
        return "–"
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    text = f"{v:.{digits}g}"
    return text.replace("-", "−") if text.startswith("-") else text


def quantity_text(value: float | None, unit: str, *, digits: int = 4, readable: bool = True) -> str:
    """A value with its unit, in words: ``"0.6663 Pa"``, ``"26 (dimensionless)"``, ``"12.5 %"``.

    *value* is in SI *unit*; with *readable* (default) it is shown in the multiple
    of :func:`readable_unit`. A *unit* of ``"%"`` expects a fraction (0.125 -> 12.5 %).
    """
    if unit == "%":
        return f"{format_number(None if value is None else float(value) * 100.0, digits)} %"
    if unit in (DIMENSIONLESS, "", "-"):
        return f"{format_number(value, digits)} (dimensionless)"
    shown, fac = readable_unit([value], unit) if readable else (unit, 1.0)
    v = None if value is None else float(value) / fac
    return f"{format_number(v, digits)} {shown}"


def interval_text(lower: float | None, upper: float | None, unit: str, *, digits: int = 4,
                  like: float | None = None) -> str:
    """An interval in the readable unit of *like* (its estimate), else of its larger finite end:
    ``"[12.0, 1386] MPa"``, ``"[0, ∞] GPa"``, ``"unbounded"``."""
    lo = None if lower is None or not math.isfinite(float(lower)) else float(lower)
    hi = None if upper is None or not math.isfinite(float(upper)) else float(upper)
    if lo is None and hi is None:
        return "unbounded"
    if unit in (DIMENSIONLESS, "", "-"):
        shown, fac = "(dimensionless)", 1.0
    else:
        shown, fac = readable_unit([like] if like is not None else [lo, hi], unit)
    lo_t = "−∞" if lo is None else format_number(lo / fac, digits)
    hi_t = "∞" if hi is None else format_number(hi / fac, digits)
    return f"[{lo_t}, {hi_t}] {shown}"
