"""Reading organ surfaces (STL, OBJ, PLY, VTK/VTP, legacy gmsh .msh, NIfTI masks)."""

from __future__ import annotations

import os

from .surface import Surface


def read_surface(path: str | os.PathLike, *, unit: str = "mm", label: int | None = None,
                 reporter=None) -> Surface:
    """Read an organ surface and convert it to metres (work in progress)."""
    raise NotImplementedError
