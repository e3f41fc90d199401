"""The blocks of a report: tables whose every number has a unit, figures embedded as images.

A :class:`Table` declares a unit per column (or takes :class:`Quantity` cells that
carry their own); a bare number in a column without a unit is refused, so that no
number reaches a reader without its unit. A figure is embedded in the page as a
``data:`` URI (PNG or SVG): the report is one file that opens anywhere, offline.
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Real
from typing import Any

from .numbers import DIMENSIONLESS, format_number, quantity_text


@dataclass(frozen=True)
class Quantity:
    """A number with its own unit, for a table cell whose column has none (SI value)."""

    value: float | None
    unit: str
    digits: int = 4
    readable: bool = True
    note: str = ""  # e.g. "(at bound)", shown after the unit

    def text(self) -> str:
        if self.value is None:
            return "–"
        t = quantity_text(self.value, self.unit, digits=self.digits, readable=self.readable)
        return f"{t} {self.note}".rstrip()


@dataclass(frozen=True)
class Column:
    """One column: its title, and the unit of its numbers.

    Attributes
    ----------
    title : str
    unit : str or None
        Unit of the column's numbers, shown in the header (``[kPa]``; ``[–]`` for
        :data:`~.numbers.DIMENSIONLESS`, ``[%]`` for percentages given as fractions).
        None: a column of text or of :class:`Quantity` cells.
    scale : float
        The numbers are divided by it before display (SI Pa shown in kPa: 1e3).
    digits : int
        Significant digits.
    """

    title: str
    unit: str | None = None
    scale: float = 1.0
    digits: int = 4

    def header(self) -> str:
        if self.unit is None:
            return self.title
        shown = "–" if self.unit in (DIMENSIONLESS, "", "-") else self.unit
        return f"{self.title} [{shown}]"

    def cell(self, value: Any) -> str:
        """The text of one cell (not escaped)."""
        if value is None:
            return "–"
        if isinstance(value, Quantity):
            return value.text()
        if isinstance(value, Real) and not isinstance(value, bool):
            if self.unit is None:
                raise ValueError(f"table column {self.title!r} holds the number {value!r} but declares no unit; "
                                 f"give Column(unit=...) ('1' for a dimensionless number) or a Quantity cell")
            v = float(value)
            if self.unit == "%":
                v *= 100.0
            return format_number(v / self.scale if math.isfinite(v) else v, self.digits)
        return str(value)


@dataclass
class Table:
    """Rows of cells under :class:`Column` headers; *caption* says what the table is."""

    columns: Sequence[Column]
    rows: Sequence[Sequence[Any]]
    caption: str = ""

    def html(self) -> str:
        head = "".join(f"<th>{html.escape(c.header())}</th>" for c in self.columns)
        body = []
        for r, row in enumerate(self.rows):
            if len(row) != len(self.columns):
                raise ValueError(f"table row {r + 1} has {len(row)} cells for {len(self.columns)} columns")
            cells = "".join(f"<td{NUM if _numeric(v) else ''}>{html.escape(c.cell(v))}</td>"
                            for c, v in zip(self.columns, row))
            body.append(f"<tr>{cells}</tr>")
        cap = f"<caption>{html.escape(self.caption)}</caption>" if self.caption else ""
        return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


NUM = ' class="num"'


def _numeric(v: Any) -> bool:
    return isinstance(v, (Real, Quantity)) and not isinstance(v, bool)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def image_uri(image: Any, *, dpi: int = 100) -> str:
    """A ``data:`` URI of *image*: PNG bytes, SVG text, or a matplotlib figure (saved as PNG).

    Raises
    ------
    TypeError
        *image* is none of these.
    """
    if hasattr(image, "savefig"):
        buf = io.BytesIO()
        image.savefig(buf, format="png", dpi=dpi)
        image = buf.getvalue()
    if isinstance(image, (bytes, bytearray)):
        data = bytes(image)
        if not data.startswith(PNG_SIGNATURE):
            raise TypeError("image bytes are not a PNG; give PNG bytes, SVG text or a matplotlib figure")
        return "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    if isinstance(image, str) and "<svg" in image[:4096]:
        return "data:image/svg+xml;base64," + base64.b64encode(image.encode("utf-8")).decode("ascii")
    raise TypeError(f"cannot embed a {type(image).__name__} as an image; give PNG bytes, SVG text or a "
                    f"matplotlib figure")


@dataclass(frozen=True)
class Figure:
    """An embedded image with its description (*alt*, for a reader who cannot see it) and caption."""

    uri: str
    alt: str
    caption: str = ""

    def html(self) -> str:
        cap = f"<figcaption>{html.escape(self.caption)}</figcaption>" if self.caption else ""
        return f'<figure><img src="{self.uri}" alt="{html.escape(self.alt, quote=True)}">{cap}</figure>'
