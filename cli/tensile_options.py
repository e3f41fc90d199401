"""Specimen-metadata options shared by the commands that read tensile files."""

from __future__ import annotations

from typing import Any

_PLAIN = ("gauge_length", "area", "width", "thickness", "mode", "orientation", "specimen", "encoding")
_LISTS = ("columns", "units")


def add_metadata_options(parser, *, specimen: bool = True) -> None:
    """Add the ``specimen metadata`` option group (overrides comments and sidecars)."""
    g = parser.add_argument_group("specimen metadata (overrides the file's comments and sidecar)")
    g.add_argument("--gauge-length", metavar="LEN", help='initial gauge length, e.g. "30 mm"')
    g.add_argument("--area", metavar="AREA", help='cross-section area, e.g. "22 mm2"')
    g.add_argument("--width", metavar="LEN", help="cross-section width")
    g.add_argument("--thickness", metavar="LEN", help="cross-section thickness")
    g.add_argument("--mode", help="uniaxial, equibiaxial, pure_shear or simple_shear")
    g.add_argument("--orientation", help='loading direction in the fibre frame: x, y, z (or an angle, "45 deg")')
    if specimen:
        g.add_argument("--specimen", help="specimen id")
    g.add_argument("--columns", help='quantities by position, e.g. "time,displacement,force"')
    g.add_argument("--units", help='units by position, e.g. "s,mm,N"')
    g.add_argument("--encoding", help="text encoding of the files, e.g. gbk")


def metadata_overrides(args) -> dict[str, Any]:
    """The metadata options given on the command line, as reader overrides."""
    out: dict[str, Any] = {}
    for key in _PLAIN:
        v = getattr(args, key, None)
        if v is not None:
            out[key] = v
    for key in _LISTS:
        v = getattr(args, key, None)
        if v is not None:
            out[key] = [s.strip() for s in v.split(",")]
    return out
