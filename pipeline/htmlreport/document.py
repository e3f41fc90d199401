"""One self-contained HTML report: the verdict in plain words first, then sections.

A :class:`Document` collects blocks (text, lists, tables, figures, key facts) under
section headings and renders one HTML5 file: styles inline, images as ``data:``
URIs, no script, no link to anything outside the file. It opens the same in any
browser, offline, attached to an e-mail or archived beside the data.

Example
-------
>>> doc = Document("Calibration of tendon sample 1", producer="esmm calibrate")
>>> doc.verdict("poor", "Usable with care: two parameters are not determined by the data.",
...             reasons=["N and A2 are not identifiable"], advice=["fit fewer parameters"])
>>> doc.section("Errors")
>>> doc.facts([("RMSE", 1.2e6, "Pa"), ("R²", 0.93, "1")])
>>> html_text = doc.render()
"""

from __future__ import annotations

import html
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..atomicio import write_text
from .content import Column, Figure, Quantity, Table, image_uri
from .style import CSS

#: Verdict levels and what each says to a reader; the colour of the verdict box follows the level.
LEVELS: dict[str, str] = {
    "good": "the result can be used as it is",
    "poor": "the result can be used with the care its reasons say",
    "unusable": "the result must not be used",
    "info": "a statement, not a judgement",
}


@dataclass(frozen=True)
class Verdict:
    """The report's judgement: a level of :data:`LEVELS`, one sentence, its reasons and what to do."""

    level: str
    headline: str
    reasons: tuple[str, ...] = ()
    advice: tuple[str, ...] = ()

    def html(self) -> str:
        parts = [f'<section class="verdict {self.level}" id="verdict">',
                 f'<p class="level">{html.escape(self.level.upper())}</p>',
                 f'<p class="headline">{html.escape(self.headline)}</p>']
        if self.reasons:
            parts.append("<p>Why:</p>" + _list_html(self.reasons))
        if self.advice:
            parts.append("<p>What to do:</p>" + _list_html(self.advice))
        parts.append("</section>")
        return "".join(parts)


def _list_html(items: Iterable[str]) -> str:
    return "<ul>" + "".join(f"<li>{html.escape(str(i))}</li>" for i in items) + "</ul>"


@dataclass
class _Section:
    title: str
    blocks: list[str] = field(default_factory=list)
    collapsed: bool = False


class Document:
    """A report under construction (see the module's example).

    Parameters
    ----------
    title : str
        The page's heading and title.
    producer : str
        What wrote it, shown under the title (``"esmm 0.1.0 calibrate"``).
    subtitle : str
        One more line under the title (the inputs, the time).
    """

    def __init__(self, title: str, *, producer: str = "", subtitle: str = ""):
        self.title = title
        self.producer = producer
        self.subtitle = subtitle
        self._verdict: Verdict | None = None
        self._sections: list[_Section] = [_Section("")]

    # ------------------------------------------------------------------ content
    def verdict(self, level: str, headline: str, *, reasons: Sequence[str] = (),
                advice: Sequence[str] = ()) -> None:
        """Set the verdict, shown first whatever the order of the calls.

        Raises
        ------
        ValueError
            *level* is not one of :data:`LEVELS`.
        """
        if level not in LEVELS:
            raise ValueError(f"verdict level {level!r}: use one of {', '.join(LEVELS)}")
        self._verdict = Verdict(level, headline, tuple(reasons), tuple(advice))

    def section(self, title: str, *, collapsed: bool = False) -> None:
        """Start a section; the blocks added next go under it. *collapsed*: folded until clicked."""
        self._sections.append(_Section(title, collapsed=collapsed))

    def text(self, paragraph: str) -> None:
        """A paragraph of plain text (escaped; no markup)."""
        self._add(f"<p>{html.escape(paragraph)}</p>")

    def items(self, items: Sequence[str]) -> None:
        """A bulleted list of plain-text items."""
        if items:
            self._add(_list_html(items))

    def preformatted(self, text: str) -> None:
        """Text shown as typed (a command line, a log excerpt)."""
        self._add(f"<pre>{html.escape(text)}</pre>")

    def table(self, columns: Sequence[Column], rows: Sequence[Sequence[Any]], *, caption: str = "") -> None:
        """A table (:class:`~.content.Table`: a unit per column or per :class:`~.content.Quantity` cell)."""
        self._add(Table(columns, rows, caption).html())

    def facts(self, facts: Sequence[tuple[str, Any, str | None]], *, caption: str = "") -> None:
        """A two-column table of named values: (name, SI value or text, SI unit or None for text)."""
        rows = [[name, Quantity(v, unit) if unit is not None and v is not None and not isinstance(v, str) else v]
                for name, v, unit in facts]
        self.table([Column("quantity"), Column("value")], rows, caption=caption)

    def figure(self, image: Any, *, alt: str, caption: str = "") -> None:
        """An image embedded in the page: PNG bytes, SVG text or a matplotlib figure.

        *alt* describes what it shows for a reader who cannot see it; it is required.
        """
        if not alt.strip():
            raise ValueError("a figure needs alt text: say what it shows")
        self._add(Figure(image_uri(image), alt, caption).html())

    def _add(self, block: str) -> None:
        self._sections[-1].blocks.append(block)

    # ------------------------------------------------------------------ output
    def render(self) -> str:
        """The whole page as HTML text.

        Raises
        ------
        ValueError
            No verdict was given: a report says first, in plain words, how far to trust it.
        """
        if self._verdict is None:
            raise ValueError("a report states its verdict first: call Document.verdict(...) before render()")
        head = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
                f'<meta name="viewport" content="width=device-width, initial-scale=1">'
                f"<title>{html.escape(self.title)}</title><style>{CSS}</style></head><body><main>")
        top = [f"<h1>{html.escape(self.title)}</h1>"]
        meta = " · ".join(x for x in (self.producer, self.subtitle) if x)
        if meta:
            top.append(f'<p class="meta">{html.escape(meta)}</p>')
        top.append(self._verdict.html())
        return head + "".join(top) + "".join(self._section_html(s) for s in self._sections) + "</main></body></html>\n"

    @staticmethod
    def _section_html(s: _Section) -> str:
        if not s.title:
            return "".join(s.blocks)
        if s.collapsed:
            return f"<details><summary>{html.escape(s.title)}</summary>{''.join(s.blocks)}</details>"
        return f"<section><h2>{html.escape(s.title)}</h2>{''.join(s.blocks)}</section>"

    def write(self, path: str | os.PathLike) -> Path:
        """Render and write atomically to *path* (UTF-8); returns the path."""
        return write_text(path, self.render())
