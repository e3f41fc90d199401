"""Specimen metadata of a tensile test: its three sources and their precedence.

Metadata come, in rising precedence, from

1. ``# key: value`` comment lines at the top of the data file, and the
   testing software's own header lines (Instron Bluehill's
   ``Specimen properties : Diameter,"0.39900",mm``),
2. a TOML sidecar with the data file's stem (``test1.csv`` -> ``test1.toml``),
3. the caller (the ``overrides`` mapping of :func:`esmm.pipeline.tensile.read`;
   the command line's metadata options).

Each key is taken from the highest source that states it. Dimensional keys
(``gauge_length``, ``width``, ``thickness``, ``area``) carry their unit as a
string (``"30 mm"``); a bare number is refused.
"""

from __future__ import annotations

import codecs
import difflib
import functools
import math
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import units as _units
from ..config import load_toml
from ..errors import ConfigError, EsmmError, InputError
from .columns import column_keyword
from .data import MODES

#: The keys of the contract (docs/reference/tensile-input.md) plus ``delimiter`` and ``decimal``.
KEYS = (
    "specimen", "gauge_length", "width", "thickness", "diameter", "area", "columns", "units", "encoding",
    "mode", "orientation", "tissue", "temperature", "notes", "delimiter", "decimal",
)
LENGTH_KEYS = ("gauge_length", "width", "thickness", "diameter")
TEXT_KEYS = ("specimen", "tissue", "temperature", "notes")

# Spellings of keys met in exports (after normalise_key) -> key.
_KEY_ALIASES = {
    "gauge length": "gauge_length", "gage length": "gauge_length", "initial length": "gauge_length",
    "initial gauge length": "gauge_length", "l0": "gauge_length", "gauge": "gauge_length",
    "cross section": "area", "cross section area": "area", "cross sectional area": "area",
    "section area": "area", "initial area": "area", "a0": "area",
    "sample": "specimen", "sample id": "specimen", "specimen id": "specimen",
    "sample name": "specimen", "specimen name": "specimen", "specimen label": "specimen",
    "sample label": "specimen", "dia": "diameter", "specimen diameter": "diameter",
    "temp": "temperature", "note": "notes", "comment": "notes", "comments": "notes",
    "material": "tissue", "test mode": "mode", "loading mode": "mode", "test type": "mode",
    "direction": "orientation", "loading direction": "orientation",
    "charset": "encoding", "separator": "delimiter", "decimal separator": "decimal",
    "decimal mark": "decimal", "column": "columns", "unit": "units",
}

# Spellings of modes -> mode.
_MODE_ALIASES = {
    "uniaxial": "uniaxial", "tension": "uniaxial", "compression": "uniaxial",
    "uniaxial tension": "uniaxial", "uniaxial compression": "uniaxial",
    "tension compression": "uniaxial", "uniaxial tension compression": "uniaxial",
    "equibiaxial": "equibiaxial", "equi biaxial": "equibiaxial", "equibiaxial tension": "equibiaxial",
    "pure shear": "pure_shear", "planar tension": "pure_shear", "planar": "pure_shear",
    "simple shear": "simple_shear",
}

_ANGLE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+))\s*(deg|degree|degrees|°|rad|radian|radians)\s*$", re.I)

# Source levels (rising precedence).
COMMENT, SIDECAR, OVERRIDE = 1, 2, 3


@dataclass(frozen=True)
class Entry:
    """One stated metadata value and where it was stated."""

    value: Any
    where: str   # e.g. "test1.toml: gauge_length", "test1.csv line 2: gauge_length" or "gauge_length" (override)
    level: int   # COMMENT, SIDECAR or OVERRIDE
    parameter: str | None = None  # an override: the key of the reader's overrides (the CLI maps it to its flag)

    @property
    def error(self) -> Callable[[str], EsmmError]:
        """The exception for a bad value: ConfigError naming the override, else InputError (a file's)."""
        if self.level == OVERRIDE:
            return functools.partial(ConfigError, parameter=self.parameter)
        return InputError

    @property
    def described(self) -> str:
        """Where the value was stated, for the middle of a sentence."""
        return f"the {self.where} option" if self.level == OVERRIDE and self.parameter else self.where


@dataclass
class Metadata:
    """The merged metadata: the winning entry of each key, plus unknown comment keys."""

    entries: dict[str, Entry] = field(default_factory=dict)
    extra: dict[str, str] = field(default_factory=dict)
    sidecar: Path | None = None

    def get(self, key: str) -> Entry | None:
        return self.entries.get(key)

    def value(self, key: str, default: Any = None) -> Any:
        e = self.entries.get(key)
        return default if e is None else e.value

    def source(self, key: str) -> str | None:
        e = self.entries.get(key)
        return None if e is None else {COMMENT: "comment", SIDECAR: "sidecar", OVERRIDE: "override"}[e.level]

    def merged(self, other: Metadata) -> Metadata:
        """Entries of *other* replace those of the same key of a lower level."""
        out = Metadata(dict(self.entries), dict(self.extra), other.sidecar or self.sidecar)
        for k, e in other.entries.items():
            cur = out.entries.get(k)
            if cur is None or e.level >= cur.level:
                out.entries[k] = e
        out.extra.update(other.extra)
        return out


def normalise_key(key: str) -> str:
    """``'Gauge length' -> 'gauge_length'``; aliases resolved; unknown keys returned normalised."""
    k = re.sub(r"[\s_\-.]+", " ", str(key).strip().lower()).strip()
    if k in _KEY_ALIASES:
        return _KEY_ALIASES[k]
    return k.replace(" ", "_")


def _unknown_key_message(where: str, key: str) -> str:
    close = difflib.get_close_matches(key, KEYS, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{where}: unknown key {key!r}{hint}; accepted keys: {', '.join(KEYS)}"


# ---------------------------------------------------------------------------
# the three sources

_COMMENT_KV = re.compile(r"^#+\s*([^:=#]{1,40}?)\s*[:=：]\s*(.*?)\s*$")


def comment_value(text: str) -> Any:
    """A comment value: TOML syntax if it starts with ``[`` or a quote, else the text as is."""
    t = text.strip()
    if t[:1] in ("[", '"', "'"):
        try:
            return tomllib.loads(f"v = {t}")["v"]
        except tomllib.TOMLDecodeError:
            pass
    return t


def from_comments(lines: list[tuple[int, str]], *, label: str) -> Metadata:
    """Metadata from ``# key: value`` lines given as (line number, text)."""
    md = Metadata()
    for lineno, text in lines:
        m = _COMMENT_KV.match(text.strip())
        if not m:
            continue
        key = normalise_key(m.group(1))
        value = comment_value(m.group(2))
        if key in KEYS:
            md.entries[key] = Entry(value, f"{label} line {lineno}: {key}", COMMENT)
        else:
            md.extra[m.group(1).strip()] = m.group(2).strip()
    return md


# A testing program's own header line: "<section> : <name>,<value>[,<unit>]" (Instron Bluehill),
# e.g. 'Specimen properties : Diameter,"0.39900",mm' or 'Test : Rate 1,"5.00000",mm/min'.
_MACHINE_LINE = re.compile(r"^\s*(?P<section>[^:,\"]{1,60}?)\s*:\s*(?P<name>[^,]{1,60}?)\s*$")
_SPECIMEN_SECTIONS = frozenset({"specimen properties", "specimen", "sample", "sample properties",
                                "specimen data", "specimen parameters"})
# Names that mean a metadata key only inside a specimen section ("Length" of a test is not the gauge length).
_SPECIMEN_NAMES = {"length": "gauge_length", "label": "specimen", "name": "specimen", "id": "specimen"}


def from_machine_header(lines: list[tuple[int, list[str]]], *, label: str) -> Metadata:
    """Metadata from a testing program's header lines above the column header.

    *lines* are (line number, cells split at the file's delimiter). A line
    ``Specimen properties : Diameter,"0.39900",mm`` states ``diameter = "0.39900 mm"``
    (the unit cell joins the value); ``Specimen properties : Length,...`` is the gauge
    length. Lines of other sections (``Test : Rate 1,"5.00000",mm/min``) and names that
    are not keys go to ``extra``; empty values are skipped. Level: :data:`COMMENT`
    (the file's own statements).
    """
    md = Metadata()
    for lineno, cells in lines:
        if len(cells) < 2:
            continue
        m = _MACHINE_LINE.match(cells[0])
        if not m:
            continue
        value = cells[1].strip().strip('"').strip()
        unit = cells[2].strip().strip('"').strip() if len(cells) > 2 else ""
        if not value:
            continue
        section, name = m.group("section").strip(), m.group("name").strip()
        key = normalise_key(name)
        specimen = re.sub(r"\s+", " ", section.lower()) in _SPECIMEN_SECTIONS
        if specimen and key not in KEYS:
            key = _SPECIMEN_NAMES.get(name.strip().lower(), key)
        text = f"{value} {unit}".strip()
        if key in KEYS and (specimen or key not in LENGTH_KEYS + ("area",)):
            md.entries[key] = Entry(text, f"{label} line {lineno}: {section} : {name}", COMMENT)
        else:
            md.extra[f"{section} : {name}"] = text
    return md


def sidecar_path(path: Path) -> Path:
    """The TOML sidecar of a data file: same folder, same stem, ``.toml``."""
    return path.with_suffix(".toml")


def from_sidecar(path: Path) -> Metadata:
    """Metadata from the data file's sidecar, or empty metadata when it has none."""
    side = sidecar_path(path)
    if side == path or not side.is_file():
        return Metadata()
    try:
        data = load_toml(side)
    except ConfigError as exc:
        raise InputError(f"sidecar {exc}") from None
    md = Metadata(sidecar=side)
    for k, v in data.items():
        key = normalise_key(k)
        if key not in KEYS:
            raise InputError(_unknown_key_message(str(side), k))
        md.entries[key] = Entry(v, f"{side}: {key}", SIDECAR)
    return md


def from_overrides(overrides: Mapping[str, Any] | None, *, encoding: str | None = None) -> Metadata:
    """Metadata from the caller's *overrides* (``None`` values are left out).

    An override's messages start with its key (``gauge_length: ...``), which the
    command line shows as its flag.
    """
    md = Metadata()
    for k, v in (overrides or {}).items():
        if v is None:
            continue
        key = normalise_key(k)
        if key not in KEYS:
            raise ConfigError(_unknown_key_message("overrides", str(k)), parameter="overrides")
        md.entries[key] = Entry(v, key, OVERRIDE, parameter=key)
    if encoding is not None:
        md.entries["encoding"] = Entry(encoding, "encoding argument", OVERRIDE)
    return md


# ---------------------------------------------------------------------------
# validated values


def text_value(e: Entry) -> str:
    """A free-text key (specimen, tissue, temperature, notes) as a string."""
    if isinstance(e.value, (dict, list)):
        raise e.error(f"{e.where}: expected text, got {type(e.value).__name__}")
    return str(e.value).strip()


def mode_value(e: Entry) -> str:
    """The test mode, one of :data:`~esmm.pipeline.tensile.data.MODES`."""
    v = re.sub(r"[\s_\-]+", " ", str(e.value).strip().lower())
    if v in _MODE_ALIASES:
        return _MODE_ALIASES[v]
    raise e.error(f"{e.where}: unknown mode {e.value!r}; use one of {', '.join(MODES)}")


_ENCODING_ADVICE = "use a text encoding such as utf-8, gbk, cp1252, latin-1, shift_jis"


def encoding_value(e: Entry) -> str:
    """A Python codec name, checked to be a usable *text* encoding.

    Refused: unknown names, names Python cannot look up at all (an embedded
    NUL), binary-to-binary or text-to-text codecs (``hex``, ``zlib``, ``bz2``,
    ``uu``, ``quopri``, ``base64``, ``rot13``: ``_is_text_encoding`` is false)
    and text codecs that cannot decode anything (``undefined``).
    """
    name = str(e.value).strip()
    shown = name if len(name) <= 40 else name[:40] + "..."
    try:
        info = codecs.lookup(name)
    except (LookupError, ValueError, TypeError):  # ValueError: an embedded NUL character
        raise e.error(f"{e.where}: unknown text encoding {shown!r}; {_ENCODING_ADVICE}") from None
    if not getattr(info, "_is_text_encoding", True):
        raise e.error(
            f"{e.where}: {shown!r} is not a text encoding (Python's codec of that name transforms data, it "
            f"does not decode bytes into text); {_ENCODING_ADVICE}"
        )
    try:
        codecs.decode(b"", name)
    except (UnicodeError, LookupError, ValueError, TypeError):
        raise e.error(f"{e.where}: the {info.name!r} codec cannot decode text; {_ENCODING_ADVICE}") from None
    return name


_DECIMAL_COMMA = re.compile(r"^\s*([-+]?\d+),(\d+)(\s*[^\d.,].*)?$", re.S)


def _decimal_comma(e: Entry, decimal: str | None = None) -> Any:
    """A file's own value written with a decimal comma (``30,5 mm``, Bluehill's ``"30,00000",mm`` in a
    European export) with a decimal point. Three digits after the comma are ambiguous (``4,773 mm2``: a
    thousands separator?) unless the file's data write their numbers with a decimal comma (*decimal* is
    ``","``): one file has one convention. Refused otherwise."""
    m = _DECIMAL_COMMA.match(e.value) if e.level == COMMENT and isinstance(e.value, str) else None
    if m is None:
        return e.value
    whole, frac, unit = m.group(1), m.group(2), (m.group(3) or "").strip()
    if len(frac) == 3 and decimal != ",":
        raise e.error(
            f"{e.where}: {e.value!r} is ambiguous (a decimal comma, or a thousands separator?); write it "
            f"with a decimal point and no grouping, e.g. \"{whole}.{frac} {unit}\" or \"{whole}{frac} {unit}\""
        )
    return f"{whole}.{frac} {unit}".strip()


def length_value(e: Entry, kind: str = "length", *, decimal: str | None = None) -> float:
    """A positive dimensional value in SI (``"30 mm" -> 0.03``; in the file's own lines also ``"30,5 mm"``;
    *decimal*: the decimal mark of the file's data, where known)."""
    try:
        v = _units.parse_quantity(_decimal_comma(e, decimal), kind, where=e.where)
    except InputError as exc:
        raise e.error(str(exc)) from None
    if not (v > 0 and math.isfinite(v)):
        raise e.error(f"{e.where}: {e.value!r} must be positive")
    return v


def orientation_value(e: Entry) -> tuple[str, float | None]:
    """``'x'``/``'y'``/``'z'`` or an angle; returns (text, angle in rad or None)."""
    v = e.value
    if isinstance(v, str):
        s = v.strip().lower()
        if s in ("x", "y", "z"):
            return s, None
        m = _ANGLE.match(s)
        if m:
            number = float(m.group(1))
            rad = number if m.group(2).startswith("rad") else math.radians(number)
            unit = "rad" if m.group(2).startswith("rad") else "deg"
            return f"{number:g} {unit}", rad
    raise e.error(
        f"{e.where}: orientation {v!r} not understood; write x, y, z or an angle with its unit, e.g. \"45 deg\""
    )


def list_value(e: Entry) -> list[str]:
    """A list of strings from a TOML array or a comma-separated string."""
    v = e.value
    if isinstance(v, str):
        items = [s.strip().strip("\"'") for s in v.split(",")]
    elif isinstance(v, (list, tuple)):
        items = [str(s).strip() for s in v]
    else:
        raise e.error(f"{e.where}: expected a list such as [\"time\", \"displacement\", \"force\"]")
    return items


def columns_value(e: Entry) -> list[str]:
    """The quantities by position (``'ignore'`` for skipped columns)."""
    items = list_value(e)
    out = []
    for i, item in enumerate(items, 1):
        try:
            out.append(column_keyword(item, where=f"{e.where}: entry {i}"))
        except InputError as exc:
            raise e.error(str(exc)) from None
    return out


def delimiter_value(e: Entry) -> str:
    v = str(e.value)
    table = {",": ",", ";": ";", "\t": "\t", "tab": "\t", "\\t": "\t", "|": "|",
             " ": " ", "space": " ", "spaces": " ", "whitespace": " ", "blank": " ", "blanks": " "}
    key = v if v in table else v.strip().lower()
    if key not in table:
        raise e.error(f"{e.where}: delimiter {v!r} not supported; use ',', ';', '|', 'tab' or 'whitespace' "
                      "(columns aligned by blanks)")
    return table[key]


def decimal_value(e: Entry) -> str:
    v = str(e.value).strip()
    if v not in (".", ","):
        raise e.error(f"{e.where}: decimal must be '.' or ','")
    return v


@dataclass(frozen=True)
class Geometry:
    """Specimen geometry in SI (None where not stated)."""

    gauge_length: float | None
    area: float | None
    width: float | None
    thickness: float | None
    area_from: str | None   # "area", "width x thickness" or "diameter"
    diameter: float | None = None


def geometry(md: Metadata, *, label: str, decimal: str | None = None) -> Geometry:
    """Gauge length and cross-section from the merged metadata.

    The cross-section is ``area``, or ``width`` x ``thickness``, or a circle of
    ``diameter`` (area = pi d^2 / 4). Two of them may both be stated; they must then
    agree within 1 %, otherwise the input is refused (the two cannot both be right).
    *decimal*: the decimal mark of the file's data, where known (its header's values
    are read the same way).
    """
    vals = {k: (length_value(md.entries[k], decimal=decimal) if k in md.entries else None) for k in LENGTH_KEYS}
    w, t, d = vals["width"], vals["thickness"], vals["diameter"]
    if (w is None) != (t is None) and "area" not in md.entries and d is None:
        have, miss = ("width", "thickness") if w is not None else ("thickness", "width")
        raise InputError(
            f"{label}: {have} is given but not {miss}; give both, or give area (e.g. area = \"22 mm2\")"
        )
    stated = []  # (area, how, where) in order of preference
    if "area" in md.entries:
        stated.append((length_value(md.entries["area"], "area", decimal=decimal), "area",
                       md.entries["area"].described))
    if w is not None and t is not None:
        stated.append((w * t, "width x thickness", md.entries["width"].described))
    if d is not None:
        stated.append((math.pi * d * d / 4.0, "diameter", md.entries["diameter"].described))
    area = area_from = None
    if stated:
        area, area_from, where = stated[0]
        for other, how, other_where in stated[1:]:
            if abs(other - area) > 0.01 * area:
                raise InputError(
                    f"{label}: {area_from} ({where}) gives {area * 1e6:.6g} mm2, which disagrees with {how} = "
                    f"{other * 1e6:.6g} mm2 ({other_where}); remove one of them or correct it"
                )
    return Geometry(vals["gauge_length"], area, w, t, area_from, d)


# ---------------------------------------------------------------------------
# metadata a file needs and does not state: all of it in one message

#: What to write for each key a file may miss (sidecar syntax), and what it is needed for.
NEEDED = {
    "encoding": ('"gbk"', "the file is not UTF-8 text"),
    "gauge_length": ('"30 mm"', "stretch from displacement"),
    "area": ('"22 mm2" (or width and thickness, or diameter)', "stress from force"),
}


@dataclass(frozen=True)
class Missing:
    """One key a file needs: its name, why, and an example value in sidecar syntax."""

    key: str
    why: str
    example: str


class MissingMetadataError(InputError):
    """Metadata that files need and do not state, every key of every file at once.

    Attributes
    ----------
    missing : list of (file, sidecar name, list of Missing)
    """

    def __init__(self, missing: list[tuple[str, str, list[Missing]]]):
        self.missing = missing
        super().__init__(self.text(None))

    def text(self, flag_of) -> str:
        """The message; *flag_of(key)* gives the command-line option of a key (None: name no option)."""
        groups: dict[tuple[str, ...], list[tuple[str, str, list[Missing]]]] = {}
        for item in self.missing:
            groups.setdefault(tuple(m.key for m in item[2]), []).append(item)
        parts = []
        for keys, items in groups.items():
            files = [f for f, _, _ in items]
            shown = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
            miss = items[0][2]
            what = ", ".join(f"{m.key} ({m.why})" for m in miss)
            side = ", ".join(f"{m.key} = {m.example}" for m in miss)
            where = f"in the sidecar {items[0][1]}" + (" (one per file)" if len(files) > 1 else "")
            opts = [flag_of(k) for k in keys] if flag_of else []
            also = (" or with " + ", ".join(o for o in opts if o)) if any(opts) else ", or as overrides"
            geometry = [m for m in miss if m.key != "encoding"]
            kind = ("missing geometry" if len(geometry) == len(miss) else
                    "missing metadata and geometry" if geometry else "missing metadata")
            parts.append(f"{shown}: {kind}, {len(miss)} item{'s' if len(miss) > 1 else ''}: {what}; "
                         f"state {'them' if len(miss) > 1 else 'it'} {where}{also}, e.g. {side}")
        return "; ".join(parts)
