"""Validation of option values, shared by every stage (one home for the rules).

Every function takes the value and the *name* of the parameter it is for, and
returns the value converted (a float in SI, an int, a bool, a choice) or raises
:class:`~esmm.pipeline.errors.ConfigError` whose message starts with that name
and whose ``parameter`` attribute is it. The library names its own parameters
(``nodes``, ``[mesh] size``); the command line maps a parameter to its flag
(``--nodes``) where it has one, so a library message never names a CLI flag.

>>> number(5000, "nodes", lo=10, integer=True)
5000
>>> quantity("30 mm", "length", "gauge_length")
0.03
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from .errors import ConfigError, InputError
from .units import parse_quantity


def _range_text(lo, hi, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is None:
        return f"> {lo:g}" if lo_open else f">= {lo:g}"
    if hi is not None and lo is None:
        return f"< {hi:g}" if hi_open else f"<= {hi:g}"
    return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def _in_range(v: float, lo, hi, lo_open: bool, hi_open: bool) -> bool:
    if lo is not None and (v < lo or (lo_open and v == lo)):
        return False
    return not (hi is not None and (v > hi or (hi_open and v == hi)))


def _wanted(integer: bool, lo, hi, lo_open: bool, hi_open: bool) -> str:
    """``a number >= 3``, ``a whole number in [1, 6]``, ``a positive number`` (> 0 alone)."""
    kind = "whole number" if integer else "number"
    if lo == 0 and lo_open and hi is None:
        return f"a positive {kind}"
    bound = f" {_range_text(lo, hi, lo_open, hi_open)}" if (lo is not None or hi is not None) else ""
    return f"a {kind}{bound}"


def number(value: Any, name: str, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False, integer: bool = False) -> float | int:
    """A finite number (an ``int`` if *integer*) within the given bounds.

    Booleans are refused (``True`` is not a count); with *integer*, a float is
    refused too (``5000.5`` nodes). Strings are refused: text from a command
    line goes through :func:`number_text`.
    """
    ok_types = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, bool) or not isinstance(value, ok_types):
        raise ConfigError(f"{name}: expected {_wanted(integer, lo, hi, lo_open, hi_open)}, got {value!r}",
                          parameter=name)
    v = int(value) if integer else float(value)
    if not math.isfinite(v) or not _in_range(v, lo, hi, lo_open, hi_open):
        raise ConfigError(f"{name}: expected {_wanted(integer, lo, hi, lo_open, hi_open)}, got {value!r}",
                          parameter=name)
    return v


def number_text(text: Any, name: str, **bounds) -> float | int:
    """:func:`number` of a value that may be text (a command-line argument, a TOML string)."""
    if isinstance(text, str):
        s = text.strip()
        try:
            value: Any = _whole(s) if bounds.get("integer") else float(s)
        except ValueError:
            kind = "a whole number" if bounds.get("integer") else "a number"
            raise ConfigError(f"{name}: expected {kind}, got {text!r}", parameter=name) from None
        return number(value, name, **bounds)
    return number(text, name, **bounds)


def _whole(s: str) -> int:
    """A whole number written as one: ``"5000"``, or in exponent form ``"1e6"`` (the way a range is
    printed); ``"1.5"`` and ``"1e-3"`` raise ValueError."""
    try:
        return int(s)
    except ValueError:
        f = float(s)
        if not (math.isfinite(f) and f == int(f)):
            raise ValueError(s) from None
        return int(f)


def quantity(value: Any, kind: str, name: str, *, lo: float | None = None, hi: float | None = None,
             lo_open: bool = False, hi_open: bool = False) -> float:
    """A dimensional value with its unit (``"30 mm"``), in SI, within the given bounds [SI].

    *kind* is a key of :data:`esmm.pipeline.units.UNITS` (``"length"``, ``"time"``,
    ``"density"``, ...). A bare number is refused: units are never guessed.
    """
    try:
        v = parse_quantity(value, kind, where=name)
    except InputError as exc:
        raise ConfigError(str(exc), parameter=name) from None
    if not math.isfinite(v) or not _in_range(v, lo, hi, lo_open, hi_open):
        raise ConfigError(f"{name}: {value!r} is out of range ({_range_text(lo, hi, lo_open, hi_open)} in SI)",
                          parameter=name)
    return v


def boolean(value: Any, name: str) -> bool:
    """``true`` or ``false`` (not 0/1, not text)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{name}: expected true or false, got {value!r}", parameter=name)
    return value


def choice(value: Any, options: Iterable[str], name: str) -> str:
    """One of *options* (the closest one is suggested for a typo)."""
    opts = list(options)
    if isinstance(value, str) and value in opts:
        return value
    close = difflib.get_close_matches(str(value), opts, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ConfigError(f"{name}: {value!r} is not one of {', '.join(opts)}{hint}", parameter=name)


def table(value: Any, name: str) -> dict:
    """A TOML table (a dict)."""
    if not isinstance(value, Mapping):
        raise ConfigError(f"{name}: expected a table, got {type(value).__name__}", parameter=name)
    return dict(value)


def keys(mapping: Mapping, allowed: Iterable[str], where: str) -> None:
    """Refuse keys of *mapping* that are not *allowed*, naming them and the nearest allowed key."""
    allowed = list(allowed)
    unknown = sorted(str(k) for k in mapping if k not in allowed)
    if not unknown:
        return
    close = difflib.get_close_matches(unknown[0], allowed, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}{hint}; allowed: {', '.join(allowed)}",
                      parameter=where)


def exclusive(given: Mapping[str, Any], where: str = "") -> None:
    """At most one of the *given* options may be set (not None)."""
    set_ = [k for k, v in given.items() if v is not None]
    if len(set_) > 1:
        prefix = f"{where}: " if where else ""
        raise ConfigError(f"{prefix}give one of {', '.join(set_)}, not several", parameter=set_[0])
