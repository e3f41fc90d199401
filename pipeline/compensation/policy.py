"""The policy of :func:`~esmm.pipeline.compensation.calibration.compensate`: its defaults and its cache.

The defaults (calibration range, specimen radius) live here, in a module that
imports nothing heavy, so that the command line can show them in its help.

A calibration (virtual tension, compression and shear tests on a cylinder: the
slowest part of ``esmm prepare``) is stored under a content address: everything its result
depends on. The calibration specimen is meshed in units of the organ's median
spring length and a radius of a fixed number of elements, then scaled, so it is
the same mesh, geometrically similar, for every organ, and the spring network's
stress response is scale-free (forces ~ V/L0,
areas ~ L0^2): the result depends on the material, the law, the grid, the
calibration range, the specimen's radius in elements and the code, not on the
organ. The volume term's bulk modulus and formulation are part of it too (the
calibration runs with the term on). The code that computes it is part of the
address, so an edited calibration never serves a stale result.

Where: ``$ESMM_CACHE_DIR``, else ``$XDG_CACHE_HOME/esmm``, else
``~/.cache/esmm`` (subfolder ``compensation``), one JSON file per calibration.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import __version__
from ..atomicio import write_json
from ..cache import folder

if TYPE_CHECKING:  # annotations only: this module stays light to import
    from ..network.tables import StiffnessTables

#: Compression and tension ends of the calibration (clipped to the tables' grid; docs/design/tables.md).
DEFAULT_RANGE = (0.9, 1.3)
#: Radius of the calibration cylinder, in element sizes.
DEFAULT_RADIUS_ELEMENTS = 4.0
#: Accepted radii of the calibration cylinder, in element sizes (larger = slower, closer to the bulk).
RADIUS_ELEMENTS_RANGE = (1.5, 20.0)

#: The modules whose source decides a calibration's result (their bytes enter the key), relative to
#: the library's folder.
CODE = ("compensation/calibration.py", "compensation/virtual_tensile.py", "network/tables.py", "network/forcelaw.py",
        "network/springs.py", "network/volume.py", "compensation/loadcases.py", "linalg/newton.py",
        "compensation/stretch_fit.py")


def cache_dir() -> Path:
    """The folder of cached calibrations (see the module docstring; the root: :func:`esmm.pipeline.cache.root`)."""
    return folder("compensation")


def cache_key(tables: StiffnessTables, law: str, lo: float, hi: float, radius_elements: float, *,
              volume: dict[str, Any] | None = None) -> str:
    """Content address of a calibration of *law* on *tables* over stretches *lo* .. *hi*.

    *volume* is the volume term's description (``VolumeSpec.describe()``; None:
    springs only): its bulk modulus and formulation change the result.
    """
    code = hashlib.sha256()
    here = Path(__file__).resolve().parent.parent
    for name in CODE:
        code.update((here / name).read_bytes())
    blob = json.dumps({
        "code": code.hexdigest(),
        "material": tables.material_toml, "law": law, "n": tables.n,
        "lam": [repr(float(tables.lam_min)), repr(float(tables.lam_max))],
        "range": [repr(float(lo)), repr(float(hi))], "radius_elements": float(radius_elements),
        "esmm": __version__,
        "volume": None if volume is None else {k: volume.get(k) for k in ("bulk_modulus_pa", "formulation")},
    }, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def cache_path(key: str) -> Path:
    """The file of the calibration *key*."""
    return cache_dir() / f"{key}.json"


def load(key: str) -> dict[str, Any] | None:
    """The stored calibration *key* (``factor``, ``knots``, ``g``, ``record``), or None.

    A missing, unreadable or incomplete file is a miss (the calibration runs again).
    """
    try:
        cached = json.loads(cache_path(key).read_text(encoding="utf-8"))
        entry = {"factor": float(cached["factor"]), "knots": list(cached["knots"]), "g": list(cached["g"]),
                 "record": dict(cached["record"])}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return entry


def store(key: str, *, factor: float, knots, g, record: dict[str, Any]) -> None:
    """Keep a calibration under *key*; a cache that cannot be written only costs time."""
    try:
        write_json(cache_path(key), {"factor": factor, "knots": knots, "g": g, "record": record})
    except OSError:
        pass
