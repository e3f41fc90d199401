"""Terminal output for the CLI: messages, warnings, errors and progress bars (rich)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class UI:
    """The CLI's reporter: implements :class:`esmm.pipeline.progress.Reporter`.

    Normal output goes to stdout; warnings, errors and progress to stderr, so
    that ``--json -`` style output stays clean.
    """

    def __init__(self, verbosity: int = 0):
        self.verbosity = verbosity
        self.out = Console(file=sys.stdout, highlight=False, soft_wrap=True)
        self.err = Console(file=sys.stderr, highlight=False, soft_wrap=True)

    # Reporter protocol -------------------------------------------------
    def step(self, message: str) -> None:
        if self.verbosity >= 0:
            self.err.print(f"  {message}", markup=False)

    def warn(self, message: str) -> None:
        if self.verbosity >= 0:
            self.err.print(f"[yellow]warning:[/yellow] {_escape(message)}")

    @contextlib.contextmanager
    def task(self, description: str, total: float | None = None) -> Iterator[Callable[[float], None]]:
        if self.verbosity < 0:
            yield lambda amount=1.0: None
            return
        progress = Progress(
            TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f}"),
            TimeElapsedColumn(), TimeRemainingColumn(), console=self.err, transient=False,
            disable=not self.err.is_terminal and self.verbosity < 1,
        )
        with progress:
            tid = progress.add_task(description, total=total)

            def advance(amount: float = 1.0) -> None:
                progress.advance(tid, amount)

            yield advance
        if not self.err.is_terminal and self.verbosity >= 0:
            self.err.print(f"  {description}: done", markup=False)

    # CLI helpers ---------------------------------------------------------
    def info(self, message: str) -> None:
        if self.verbosity >= 0:
            self.out.print(message, markup=False)

    def detail(self, message: str) -> None:
        if self.verbosity >= 1:
            self.err.print(message, markup=False)

    def error(self, message: str) -> None:
        self.err.print(f"esmm: error: {message}", markup=False)


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text)
