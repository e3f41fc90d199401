"""Self-contained HTML reports: one file per run, the verdict in plain words first.

A small writer with no dependency beyond the standard library (matplotlib figures
are accepted, not required): styles inline, images embedded as ``data:`` URIs, no
script and no link outside the page, so a report opens the same in any browser,
offline. Every number in a table carries its unit (:class:`Column`,
:class:`Quantity`); values are SI and shown in a readable multiple
(:func:`readable_unit`).

Public API
----------
:class:`Document`      build a report: ``verdict``, ``section``, ``text``, ``items``, ``table``,
                       ``facts``, ``figure``, ``preformatted``; ``render`` and ``write``
:data:`LEVELS`         the verdict levels: good, poor, unusable, info
:class:`Column`, :class:`Quantity`   table columns with units; a cell with its own unit
:func:`readable_unit`, :func:`quantity_text`, :func:`interval_text`, :func:`format_number`
:data:`DIMENSIONLESS`  the unit of a dimensionless number (``"1"``)
:func:`image_uri`      the ``data:`` URI of PNG bytes, SVG text or a matplotlib figure
"""

from .content import Column, Quantity, image_uri
from .document import LEVELS, Document, Verdict
from .numbers import DIMENSIONLESS, format_number, interval_text, quantity_text, readable_unit

__all__ = ["DIMENSIONLESS", "LEVELS", "Column", "Document", "Quantity", "Verdict", "format_number",
           "image_uri", "interval_text", "quantity_text", "readable_unit"]
