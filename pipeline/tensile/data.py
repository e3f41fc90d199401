"""The tensile-test data object that the reader produces and the fitters consume."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

MODES = ("uniaxial", "equibiaxial", "pure_shear", "simple_shear")


@dataclass(frozen=True)
class TensileTest:
    """One test on one specimen, in SI units.

    Attributes
    ----------
    source : Path
        The file it was read from.
    mode : str
        One of :data:`MODES`. For ``simple_shear`` :attr:`stretch` holds the
        shear strain gamma and :attr:`stress` the nominal shear stress.
    stretch : ndarray, shape (n,)
        Stretch lambda (dimensionless), or shear strain for simple shear.
    stress : ndarray, shape (n,)
        Nominal (first Piola-Kirchhoff) stress in Pa.
    time : ndarray, shape (n,) or None
        Time in s from the start of the record, when the file has it.
    displacement, force : ndarray, shape (n,) or None
        The raw machine channels in m and N, when the file is raw.
    metadata : dict
        Specimen keys (``specimen``, ``gauge_length`` [m], ``area`` [m2],
        ``orientation``, ``tissue``, ``temperature``, ``notes``) plus
        ``columns``/``units`` as found, ``encoding`` and ``raw`` (bool); the
        full list of keys is in docs/reference/tensile-input.md ("What the reader returns").
    """

    source: Path
    mode: str
    stretch: np.ndarray
    stress: np.ndarray
    time: np.ndarray | None = None
    displacement: np.ndarray | None = None
    force: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = str(self.source)
        if self.mode not in MODES:
            raise InputError(f"{where}: unknown mode {self.mode!r}; use one of {', '.join(MODES)}")
        n = len(self.stretch)
        if n == 0:
            raise InputError(f"{where}: no data rows")
        for name in ("stress", "time", "displacement", "force"):
            arr = getattr(self, name)
            if arr is not None and len(arr) != n:
                raise InputError(f"{where}: {name} has {len(arr)} samples, stretch has {n}")

    @property
    def n(self) -> int:
        return len(self.stretch)

    @property
    def specimen(self) -> str:
        """Specimen id (metadata ``specimen``, else the file stem)."""
        return str(self.metadata.get("specimen") or self.source.stem)

    @property
    def orientation(self) -> str | None:
        """``'x'``, ``'y'``, ``'z'``, an angle as text, or None (untagged)."""
        o = self.metadata.get("orientation")
        return None if o is None else str(o).strip().lower()

    @property
    def name(self) -> str:
        return self.source.name
