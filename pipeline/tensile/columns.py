"""Column names and column units of tensile-test files.

A header cell such as ``"Standard force [kN]"`` is split into a name
(``"Standard force"``) and a unit (``"kN"``); the name is matched,
case-insensitively, against an explicit table of synonyms (:data:`SYNONYMS`)
to give a *quantity*; the unit is converted to SI through
:mod:`esmm.pipeline.units` plus the few extra spellings of
:data:`EXTRA_UNITS`. Nothing is guessed: an unknown name is reported as
unknown, a missing unit as missing.
"""

from __future__ import annotations

import re

from .. import units as _units
from ..errors import InputError

#: quantity -> unit kind of :data:`esmm.pipeline.units.UNITS`
QUANTITIES: dict[str, str] = {
    "time": "time",
    "displacement": "length",
    "force": "force",
    "stretch": "dimensionless",
    "strain": "dimensionless",
    "true_strain": "dimensionless",
    "stress": "stress",
    "true_stress": "stress",
    "shear_strain": "dimensionless",
    "shear_stress": "stress",
}

#: The quantity name that marks a column to be skipped (sidecar ``columns``).
IGNORE = "ignore"

#: Quantities that are recognised in order to be refused with a message (none at present:
#: true stress is converted, see esmm.pipeline.tensile.reader).
REFUSED: dict[str, str] = {}

# Normalised header names (see normalise_name) -> quantity. English names come
# from the contract (docs/reference/tensile-input.md) and from the exports of common
# testing machines (Instron Bluehill, ZwickRoell testXpert, MTS, Shimadzu
# Trapezium, Chinese machines); a few German and Chinese names are included.
SYNONYMS: dict[str, str] = {}


def _add(quantity: str, *names: str) -> None:
    for n in names:
        SYNONYMS[n] = quantity


_add("time", "time", "t", "elapsed time", "test time", "total time", "time elapsed",
     "timestamp", "time stamp", "date time", "datetime", "date/time",
     "running time", "zeit", "prüfzeit", "pruefzeit", "testzeit",
     "时间", "试验时间", "测试时间", "时间 s")
_add("displacement", "displacement", "extension", "axial displacement", "elongation", "position", "crosshead",
     "crosshead position", "crosshead displacement", "crosshead extension", "crosshead travel",
     "machine extension", "tensile extension", "travel", "stroke", "disp", "axial disp", "actuator position",
     "standard travel", "grip separation", "grip to grip separation", "deformation", "displ",
     "weg", "standardweg", "traversenweg", "traversenposition", "verlängerung", "dehnweg",
     "位移", "伸长", "伸长量", "变形", "横梁位移", "横梁位置", "试验机位移")
_add("force", "force", "load", "axial force", "axial load", "standard force", "tensile force", "load cell", "tensile load",
     "kraft", "standardkraft", "prüfkraft", "力", "载荷", "负荷", "拉力", "试验力")
_add("stretch", "stretch", "lambda", "λ", "stretch ratio", "extension ratio", "伸长比", "拉伸比")
_add("strain", "strain", "engineering strain", "nominal strain", "tensile strain", "eng strain",
     "dehnung", "nominelle dehnung", "应变", "工程应变", "名义应变")
_add("true_strain", "true strain", "logarithmic strain", "log strain", "hencky strain", "真应变")
_add("stress", "stress", "nominal stress", "engineering stress", "tensile stress", "eng stress",
     "first piola kirchhoff stress", "pk1 stress", "spannung", "nominelle spannung",
     "应力", "工程应力", "名义应力")
_add("true_stress", "true stress", "cauchy stress", "true tensile stress", "真应力", "真实应力")
_add("shear_strain", "shear strain", "gamma", "γ", "amount of shear", "scherung", "剪切应变", "剪应变")
_add("shear_stress", "shear stress", "tau", "τ", "schubspannung", "剪切应力", "剪应力")

#: Names of channels that testing software derives from another column of the same quantity
#: (Bluehill's "Tensile extension" is "Extension" re-zeroed at the start of the test). When a
#: file has both, the raw channel is used and the derived one is only reported.
DERIVED = frozenset({"tensile extension", "crosshead extension", "tensile load", "tensile force"})

#: Channels of machine exports that esmm knows and does not use (not warned about as unknown).
KNOWN_UNUSED: dict[str, str] = {
    "tenacity": "force per linear density (N/tex)",
    "pip count": "a counter channel of Instron Bluehill",
    "points": "a sample counter (Bose ElectroForce WinTest)",
    "scan time": "the time within one scan of Bose ElectroForce WinTest (the record's clock is its elapsed time)",
}

#: Names whose values are absolute positions: stretch uses the change from the first sample.
ABSOLUTE_POSITION = frozenset(
    {"position", "crosshead position", "traversenposition", "横梁位置", "disp", "axial disp", "actuator position"}
)

# Explicit spellings of the sidecar's ``columns`` entries (besides the names above).
_COLUMN_KEYWORDS = {
    "ignore": IGNORE, "skip": IGNORE, "-": IGNORE, "": IGNORE, "none": IGNORE,
    "nominal_stress": "stress", "shear_strain": "shear_strain", "shear_stress": "shear_stress",
    "true_strain": "true_strain", "true_stress": "true_stress",
}

_TRANSLATE = str.maketrans({
    "（": "(", "）": ")", "［": "[", "］": "]", "【": "[", "】": "]", "｛": "{", "｝": "}",
    "：": ":", "，": ",", "\u3000": " ", "\ufeff": "",
})
_UNIT_TAIL = re.compile(r"^(?P<name>.*?)\s*[\[({](?P<unit>[^\[\](){}]*)[\])}]\s*$", re.S)
_UNIT_SLASH = re.compile(r"^(?P<name>.*\S)\s+/\s*(?P<unit>\S+)$")
_UNIT_COMMA = re.compile(r"^(?P<name>.*\S)\s*,\s*(?P<unit>\S+)$")
_UNIT_WORD = re.compile(r"^(?P<name>.*\S)\s+(?P<unit>\S+)$")
_SEPARATORS = re.compile(r"[\s_\-.:]+")
_CHANNEL = re.compile(r"\s+(ch|chan|channel)?\s*\d+$")
_CHANNEL_FIRST = re.compile(r"^(ch|chan|channel)\s*\d+\s+")


def clean_cell(cell: str) -> str:
    """Strip whitespace, a BOM, surrounding quotes and full-width brackets."""
    c = cell.translate(_TRANSLATE).strip()
    if len(c) >= 2 and c[0] == c[-1] and c[0] in "\"'":
        c = c[1:-1].strip()
    return c


def split_header(cell: str) -> tuple[str, str | None]:
    """Split a header cell into (name, unit or None).

    ``"Time (s)" -> ("Time", "s")``, ``"Strain [%]" -> ("Strain", "%")``,
    ``"Kraft / N" -> ("Kraft", "N")``, ``"Load, kN" -> ("Load", "kN")``,
    ``"Extension mm" -> ("Extension", "mm")`` (the last two only with a known
    unit and name; a trailing number is a channel, ``"Load 1" -> ("Load 1", None)``),
    ``"Strain [-]" -> ("Strain", "-")``, ``"stretch" -> ("stretch", None)``.
    A bracketed qualifier that names a quantity is dropped, not taken as a unit:
    ``"Tensile strain (Extension)" -> ("Tensile strain", None)``.
    """
    c = clean_cell(cell)
    unit = None
    while True:
        m = _UNIT_TAIL.match(c)
        if not m or not m.group("name").strip():
            break
        content = m.group("unit").strip()
        if _is_qualifier(content):
            c = m.group("name").strip()
        elif unit is None:
            unit, c = content, m.group("name").strip()
        else:
            break
    if unit is not None:
        return c, unit
    for pattern in (_UNIT_SLASH, _UNIT_COMMA, _UNIT_WORD):
        m = pattern.match(c)
        if pattern is _UNIT_WORD and m and m.group("unit").isdigit():
            break                                  # "Load 1": a channel number, not the unit "1"
        if m and (pattern is _UNIT_SLASH or (is_unit_cell(m.group("unit")) and
                                              (pattern is _UNIT_COMMA or quantity_of(m.group("name"))))):
            return m.group("name").strip(), m.group("unit").strip()
    return c, None


def _is_qualifier(content: str) -> bool:
    """``(Extension)`` in ``Tensile strain (Extension)``: a quantity name, not a unit."""
    return bool(content) and not is_unit_cell(content) and quantity_of(content) is not None


def normalise_name(name: str) -> str:
    """Lower case; ``_ - . :`` and runs of spaces become one space; a channel number goes (``Load 1``,
    ``Force Ch1``, ``Ch 2 Load``: what data-acquisition software appends or prepends)."""
    n = _SEPARATORS.sub(" ", clean_cell(name).lower()).strip()
    return _CHANNEL_FIRST.sub("", _CHANNEL.sub("", n))


def quantity_of(name: str) -> str | None:
    """The quantity a header name stands for, or None when it is not a known name."""
    return SYNONYMS.get(normalise_name(name))


def column_keyword(entry: str, *, where: str) -> str:
    """Resolve one entry of a ``columns`` list (sidecar or override) to a quantity."""
    raw = str(entry).strip()
    key = raw.lower()
    if key in _COLUMN_KEYWORDS:
        return _COLUMN_KEYWORDS[key]
    q = quantity_of(raw)
    if q is None:
        raise InputError(
            f"{where}: unknown column quantity {raw!r}; use one of "
            f"{', '.join(QUANTITIES)}, or 'ignore' for a column to skip"
        )
    return q


def is_unit_cell(cell: str) -> bool:
    """True if a cell of a units row looks like a unit: ``(s)``, ``[mm]``, ``N``, ``%``, ``-``."""
    c = clean_cell(cell)
    if not c:
        return True
    if c[0] in "([{" and c[-1] in ")]}":
        return True
    u = _units.normalise_unit(c)
    return any(u in table for table in _units.UNITS.values()) or any(
        u in table for table in EXTRA_UNITS.values()
    )


# Unit spellings met in machine exports but absent from esmm.pipeline.units
# (kept local; the lead may move them into the central table).
EXTRA_UNITS: dict[str, dict[str, float]] = {
    "time": {"msec": 1e-3, "secs": 1.0, "hr": 3600.0, "hrs": 3600.0, "minutes": 60.0, "mins": 60.0},
    "length": {"inch": 0.0254, "inches": 0.0254},
    "force": {"lbf": 4.4482216152605, "kgf": 9.80665, "gf": 9.80665e-3},
    "stress": {"n/mm²": 1e6, "psi": 6894.757293168361, "kpsi": 6894757.293168361,
               "kn/m2": 1e3, "kn/m^2": 1e3},
    "dimensionless": {"mm/mm": 1.0, "m/m": 1.0, "in/in": 1.0, "pct": 1e-2},
}

#: The units named in messages (all spellings of esmm.pipeline.units and EXTRA_UNITS are accepted).
SHOWN_UNITS = {
    "time": ("s", "ms", "min", "h"),
    "length": ("m", "cm", "mm", "um", "in"),
    "force": ("N", "mN", "kN", "lbf", "kgf"),
    "stress": ("Pa", "kPa", "MPa", "GPa", "N/mm2", "psi"),
    "dimensionless": ("(none)", "-", "%", "mm/mm"),
}

# Spellings that lower-casing would misread: refused with a reason.
_CASE_REFUSED = {
    "MN": "MN is meganewton (for millinewton write mN)",
    "mPa": "mPa is millipascal (for megapascal write MPa)",
    "Mm": "Mm is megametre (for millimetre write mm)",
    "MS": "MS is megasecond (for milliseconds write ms)",
    "Ms": "Ms is megasecond (for milliseconds write ms)",
}


def unit_factor(unit: str | None, quantity: str, *, where: str) -> float:
    """Factor from *unit* to SI for a column of *quantity*.

    ``None`` (no unit stated) is accepted only for dimensionless quantities;
    for the others the caller reports the missing unit.
    """
    kind = QUANTITIES[quantity]
    if unit is None:
        if kind == "dimensionless":
            return 1.0
        raise AssertionError("missing unit must be handled by the caller")  # pragma: no cover
    raw = clean_cell(unit).strip("()[]{}").strip()
    if raw in _CASE_REFUSED and kind in ("force", "stress", "length", "time"):
        raise InputError(f"{where}: unit {raw!r} refused: {_CASE_REFUSED[raw]}")
    u = _units.normalise_unit(raw)
    table = _units.UNITS[kind]
    if u in table:
        return table[u]
    if u in EXTRA_UNITS.get(kind, {}):
        return EXTRA_UNITS[kind][u]
    what = quantity.replace("_", " ")
    raise InputError(f"{where}: unknown {what} unit {raw!r}; write one of {', '.join(SHOWN_UNITS[kind])}")
