"""Fixed regions: which nodes the simulation holds in place.

A region comes from the ``[fixed]`` table of a prepare config (lengths are
strings with units, as everywhere in esmm configs)::

    [fixed]                      # the default: a band at one end of the longest axis
    kind = "band"
    axis = "longest"             # or a normal vector, e.g. [0, 0, 1]
    end = "min"                  # which end of the longest axis ("min" / "max")
    width_fraction = 0.1         # of the extent along the axis ... or width = "10 mm"

    [fixed]                      # a band between two parallel planes
    kind = "band"
    axis = [0, 0, 1]             # normal (any length)
    offset = "-40 mm"            # plane position: normal . x >= offset (unit normal)
    width = "15 mm"              # ... and normal . x <= offset + width

    [fixed]
    kind = "box"
    lower = ["-10 mm", "-10 mm", "0 mm"]
    upper = ["10 mm", "10 mm", "5 mm"]

    [fixed]
    kind = "nearest"
    point = ["12 mm", "-3 mm", "40 mm"]
    count = 20

    [fixed]
    kind = "none"                # nothing fixed (the scene fixes nodes itself)

``surface_only = true`` restricts any region to surface nodes. The "longest
axis" is the first principal axis of the node cloud, signed so that its
largest component is positive (so ``end = "min"`` is deterministic). A region
that selects no node is an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ConfigError, InputError
from ..units import parse_quantity
from .springs import NODE_SURFACE, principal_axes

REGION_KINDS = ("band", "box", "nearest", "none")
_KEYS = {
    "band": {"kind", "axis", "end", "width", "width_fraction", "offset", "surface_only"},
    "box": {"kind", "lower", "upper", "surface_only"},
    "nearest": {"kind", "point", "count", "surface_only"},
    "none": {"kind"},
}
DEFAULT_WIDTH_FRACTION = 0.1


@dataclass(frozen=True)
class FixedRegion:
    """A fixed-region specification (SI lengths).

    Attributes
    ----------
    kind : {"band", "box", "nearest", "none"}
    axis : "longest" or ndarray (3,)
        Band normal (unit vector once resolved).
    end : {"min", "max"}
        Band at the low or high end of *axis* (when *offset* is None).
    width : float or None
        Band thickness [m].
    width_fraction : float or None
        Band thickness as a fraction of the extent along the axis (when *width* is None).
    offset : float or None
        Band start ``normal . x >= offset`` [m]; None: at the *end* of the organ.
    lower, upper : ndarray (3,) or None
        Box corners [m].
    point : ndarray (3,) or None
        Target point of ``"nearest"`` [m].
    count : int
        Number of nodes of ``"nearest"``.
    surface_only : bool
        Only surface nodes are eligible.
    """

    kind: str = "band"
    axis: Any = "longest"
    end: str = "min"
    width: float | None = None
    width_fraction: float | None = DEFAULT_WIDTH_FRACTION
    offset: float | None = None
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    point: np.ndarray | None = None
    count: int = 0
    surface_only: bool = False

    def describe(self) -> str:
        """One line for reports and provenance."""
        only = ", surface nodes only" if self.surface_only else ""
        if self.kind == "none":
            return "no fixed nodes"
        if self.kind == "box":
            return f"box {_mm(self.lower)} .. {_mm(self.upper)} mm{only}"
        if self.kind == "nearest":
            return f"{self.count} nodes nearest to {_mm(self.point)} mm{only}"
        axis = "longest axis" if isinstance(self.axis, str) else f"normal {np.round(np.asarray(self.axis), 4).tolist()}"
        if self.offset is not None:
            where = f"from {self.offset * 1e3:g} mm"
        else:
            where = f"at the {self.end} end"
        thick = f"{self.width * 1e3:g} mm" if self.width is not None else f"{self.width_fraction:g} of the extent"
        return f"band {where} of the {axis}, {thick} thick{only}"

    def to_config(self) -> dict:
        """The ``[fixed]`` table that reproduces this region (lengths in mm)."""
        if self.kind == "none":
            return {"kind": "none"}
        out: dict[str, Any] = {"kind": self.kind}
        if self.kind == "band":
            out["axis"] = self.axis if isinstance(self.axis, str) else [float(v) for v in self.axis]
            if self.offset is not None:
                out["offset"] = f"{self.offset * 1e3:.17g} mm"
            else:
                out["end"] = self.end
            if self.width is not None:
                out["width"] = f"{self.width * 1e3:.17g} mm"
            else:
                out["width_fraction"] = float(self.width_fraction)
        elif self.kind == "box":
            out["lower"] = [f"{v * 1e3:.17g} mm" for v in self.lower]
            out["upper"] = [f"{v * 1e3:.17g} mm" for v in self.upper]
        else:
            out["point"] = [f"{v * 1e3:.17g} mm" for v in self.point]
            out["count"] = int(self.count)
        if self.surface_only:
            out["surface_only"] = True
        return out


def _mm(v) -> str:
    return "(" + ", ".join(f"{x * 1e3:.4g}" for x in np.asarray(v)) + ")"


def _length(value, where: str) -> float:
    return parse_quantity(value, "length", where=where)


def _vector3(value, where: str, *, lengths: bool) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        example = '["10 mm", "0 mm", "5 mm"]' if lengths else "[0, 0, 1]"
        raise ConfigError(f"{where}: expected a list of 3 {'lengths' if lengths else 'numbers'}, e.g. {example}")
    if lengths:
        try:
            return np.array([_length(v, f"{where}[{k}]") for k, v in enumerate(value)])
        except InputError as exc:  # a config value: report it as a ConfigError
            raise ConfigError(str(exc)) from None
    try:
        out = np.array([float(v) for v in value])
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected 3 numbers, got {value!r}") from None
    if isinstance(value[0], bool) or not np.all(np.isfinite(out)):
        raise ConfigError(f"{where}: expected 3 finite numbers, got {value!r}")
    return out


def region_from_config(table: dict | None, *, where: str = "[fixed]") -> FixedRegion:
    """Parse and check a ``[fixed]`` config table (None: the default band).

    Raises
    ------
    ConfigError
        Unknown kind or key, a length without unit, a non-positive width,
        a degenerate box or normal, a count < 1.
    """
    if table is None:
        return FixedRegion()
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {type(table).__name__}")
    kind = table.get("kind", "band")
    if kind not in REGION_KINDS:
        raise ConfigError(f"{where} kind: {kind!r} is not one of {', '.join(REGION_KINDS)}")
    unknown = sorted(set(table) - _KEYS[kind])
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)} for kind {kind!r}; "
                          f"allowed: {', '.join(sorted(_KEYS[kind]))}")
    surface_only = table.get("surface_only", False)
    if not isinstance(surface_only, bool):
        raise ConfigError(f"{where} surface_only: expected true or false, got {surface_only!r}")
    if kind == "none":
        return FixedRegion(kind="none", width_fraction=None)
    if kind == "band":
        return _band_region(table, where, surface_only)
    if kind == "box":
        return _box_region(table, where, surface_only)
    return _nearest_region(table, where, surface_only)


def _band_region(table: dict, where: str, surface_only: bool) -> FixedRegion:
    """A ``kind = "band"`` table: a slab across *axis* at one *end* or at *offset*."""
    axis = _band_axis(table.get("axis", "longest"), where)
    end = table.get("end", "min")
    if end not in ("min", "max"):
        raise ConfigError(f"{where} end: {end!r} is not \"min\" or \"max\"")
    if "offset" in table and "end" in table:
        raise ConfigError(f"{where}: give either offset (a plane position) or end, not both")
    offset = None
    if "offset" in table:
        try:
            offset = _length(table["offset"], f"{where} offset")
        except InputError as exc:
            raise ConfigError(str(exc)) from None
    width, frac = _band_width(table, where, offset)
    return FixedRegion(kind="band", axis=axis, end=end, width=width, width_fraction=frac,
                       offset=offset, surface_only=surface_only)


def _band_axis(axis, where: str):
    """``"longest"`` or a unit vector (3,) from a non-zero vector."""
    if isinstance(axis, str):
        if axis != "longest":
            raise ConfigError(f"{where} axis: {axis!r} is not \"longest\" or a vector like [0, 0, 1]")
        return axis
    axis = _vector3(axis, f"{where} axis", lengths=False)
    norm = float(np.linalg.norm(axis))
    if norm == 0:
        raise ConfigError(f"{where} axis: the zero vector is not a direction")
    return axis / norm


def _band_width(table: dict, where: str, offset: float | None) -> tuple[float | None, float | None]:
    """``(width [m], None)`` or ``(None, width_fraction)``; a band at an offset needs an absolute width."""
    if "width" in table and "width_fraction" in table:
        raise ConfigError(f"{where}: give either width or width_fraction, not both")
    if "width" in table:
        try:
            width = _length(table["width"], f"{where} width")
        except InputError as exc:
            raise ConfigError(str(exc)) from None
        if width <= 0:
            raise ConfigError(f"{where} width: must be positive, got {table['width']!r}")
        return width, None
    if offset is not None:
        raise ConfigError(f"{where}: a band given by offset needs an absolute width, e.g. width = \"10 mm\"")
    frac = table.get("width_fraction", DEFAULT_WIDTH_FRACTION)
    if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not 0 < frac <= 1:
        raise ConfigError(f"{where} width_fraction: expected a number in (0, 1], got {frac!r}")
    return None, float(frac)


def _box_region(table: dict, where: str, surface_only: bool) -> FixedRegion:
    """A ``kind = "box"`` table: the nodes between *lower* and *upper*."""
    for key in ("lower", "upper"):
        if key not in table:
            raise ConfigError(f"{where}: kind \"box\" needs {key} = [x, y, z] with units, e.g. [\"0 mm\", \"0 mm\", \"0 mm\"]")
    lower = _vector3(table["lower"], f"{where} lower", lengths=True)
    upper = _vector3(table["upper"], f"{where} upper", lengths=True)
    if np.any(upper <= lower):
        raise ConfigError(f"{where}: upper must exceed lower on every axis (got lower {_mm(lower)} mm, "
                          f"upper {_mm(upper)} mm)")
    return FixedRegion(kind="box", lower=lower, upper=upper, width_fraction=None, surface_only=surface_only)


def _nearest_region(table: dict, where: str, surface_only: bool) -> FixedRegion:
    """A ``kind = "nearest"`` table: the *count* nodes nearest *point*."""
    if "point" not in table or "count" not in table:
        raise ConfigError(f"{where}: kind \"nearest\" needs point = [x, y, z] with units and count = N")
    point = _vector3(table["point"], f"{where} point", lengths=True)
    count = table["count"]
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ConfigError(f"{where} count: expected a whole number >= 1, got {count!r}")
    return FixedRegion(kind="nearest", point=point, count=count, width_fraction=None, surface_only=surface_only)


def select_fixed(points: np.ndarray, region: FixedRegion, *, node_kind: np.ndarray | None = None,
                 where: str = "[fixed]") -> np.ndarray:
    """Indices of the nodes inside *region*, sorted, shape (f,).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Node positions [m].
    region : FixedRegion
    node_kind : ndarray, shape (n,), optional
        Needed when ``region.surface_only`` (surface nodes have code ``NODE_SURFACE``).

    Raises
    ------
    ConfigError
        The region selects no node (message gives the organ's extent to help), or
        asks for more nearest nodes than exist.
    """
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    if region.kind == "none":
        return np.zeros(0, np.int64)
    eligible = np.ones(n, bool)
    if region.surface_only:
        if node_kind is None:
            raise ConfigError(f"{where} surface_only: this network has no node kinds")
        eligible = np.asarray(node_kind) == NODE_SURFACE
    lo, hi = p.min(axis=0), p.max(axis=0)
    if region.kind == "band":
        normal = principal_axes(p)[0] if isinstance(region.axis, str) else np.asarray(region.axis, float)
        normal = normal / np.linalg.norm(normal)
        s = p @ normal
        if region.offset is not None:
            a = region.offset
            b = a + region.width
        else:
            thick = region.width if region.width is not None else region.width_fraction * float(s.max() - s.min())
            if region.end == "min":
                a, b = float(s.min()), float(s.min()) + thick
            else:
                a, b = float(s.max()) - thick, float(s.max())
        # A relative tolerance so that a band ending exactly on a node row keeps that row.
        tol = 1e-9 * max(float(s.max() - s.min()), 1e-300)
        inside = (s >= a - tol) & (s <= b + tol)
        sel = np.flatnonzero(inside & eligible)
        if sel.size == 0:
            raise ConfigError(f"{where}: the band {a * 1e3:.4g}..{b * 1e3:.4g} mm along {np.round(normal, 3).tolist()} "
                              f"holds no {'surface ' if region.surface_only else ''}node; the organ spans "
                              f"{s.min() * 1e3:.4g}..{s.max() * 1e3:.4g} mm along it")
        return sel.astype(np.int64)
    if region.kind == "box":
        inside = np.all((p >= region.lower) & (p <= region.upper), axis=1)
        sel = np.flatnonzero(inside & eligible)
        if sel.size == 0:
            raise ConfigError(f"{where}: the box {_mm(region.lower)}..{_mm(region.upper)} mm holds no "
                              f"{'surface ' if region.surface_only else ''}node; the organ's bounding box is "
                              f"{_mm(lo)}..{_mm(hi)} mm")
        return sel.astype(np.int64)
    cand = np.flatnonzero(eligible)
    if region.count > cand.size:
        raise ConfigError(f"{where} count: {region.count} nodes asked for but the network has only {cand.size} "
                          f"{'surface ' if region.surface_only else ''}nodes")
    d = np.linalg.norm(p[cand] - region.point, axis=1)
    pick = cand[np.argsort(d, kind="stable")[: region.count]]
    return np.sort(pick).astype(np.int64)
