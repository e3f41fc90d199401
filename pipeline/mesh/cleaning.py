"""Cleaning an InVesalius-style surface into one closed, outward, smooth body."""

from __future__ import annotations

from dataclasses import dataclass, field

from .surface import Surface


@dataclass
class CleaningOptions:
    """Options of :func:`clean_surface` (lengths in metres)."""

    keep: str = "largest"
    body: int | None = None
    smooth_iterations: int = 20
    smooth_passband: float = 0.1
    target_faces: int | None = None
    target_edge: float | None = None


@dataclass
class CleaningReport:
    """What each cleaning step did, with figures."""

    steps: list[dict] = field(default_factory=list)
    volume_before: float = 0.0
    volume_after: float = 0.0
    area_before: float = 0.0
    area_after: float = 0.0
    bodies_found: int = 0
    bodies_dropped: list[tuple[int, float]] = field(default_factory=list)
    relative_volume_change: float = 0.0


def clean_surface(surface: Surface, *, options: CleaningOptions | None = None,
                  reporter=None) -> tuple[Surface, CleaningReport]:
    """Clean *surface* (work in progress)."""
    raise NotImplementedError
