"""Progress and step reporting without printing.

Library functions accept ``reporter=`` (keyword-only). They call
``reporter.step(message)`` for each reportable step (e.g. each cleaning step
with its figures) and wrap long loops in ``with reporter.task(name, total) as
advance: ... advance(n)``. The CLI passes a rich-based reporter; tests and
other callers pass nothing and get :data:`SILENT`, or a :class:`ListReporter`
to inspect what was reported.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Protocol


class Reporter(Protocol):
    def step(self, message: str) -> None:
        """Report one completed step (one line, no trailing newline)."""

    def warn(self, message: str) -> None:
        """Report a warning the user should read (one line)."""

    def task(self, description: str, total: float | None = None) -> contextlib.AbstractContextManager[Callable[[float], None]]:
        """Context manager around a long loop; yields ``advance(amount)``."""


class _Silent:
    def step(self, message: str) -> None:
        pass

    def warn(self, message: str) -> None:
        pass

    @contextlib.contextmanager
    def task(self, description: str, total: float | None = None) -> Iterator[Callable[[float], None]]:
        yield lambda amount=1.0: None


SILENT: Reporter = _Silent()


class ListReporter:
    """Collects steps and warnings in lists (for tests and for reports)."""

    def __init__(self) -> None:
        self.steps: list[str] = []
        self.warnings: list[str] = []
        self.tasks: list[str] = []

    def step(self, message: str) -> None:
        self.steps.append(message)

    def warn(self, message: str) -> None:
        self.warnings.append(message)

    @contextlib.contextmanager
    def task(self, description: str, total: float | None = None) -> Iterator[Callable[[float], None]]:
        self.tasks.append(description)
        yield lambda amount=1.0: None


def ensure(reporter: Reporter | None) -> Reporter:
    """Return *reporter*, or the silent reporter when it is None."""
    return SILENT if reporter is None else reporter
