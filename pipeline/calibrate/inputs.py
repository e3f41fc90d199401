"""How each file was read: the columns used, where stretch and stress came from, the reader's warnings."""

from __future__ import annotations

from typing import Any

from ..tensile.data import TensileTest


def how_read(test: TensileTest) -> dict[str, Any]:
    """How the reader took *test* from its file: the columns used (index, header, unit, factor to SI),
    where stretch and stress came from (and the conversions made, e.g. true to nominal stress), the
    cross-checks against derived columns and the reader's warnings (docs/reference/tensile-input.md: say which
    columns were used, say so in the outputs)."""
    md = test.metadata
    return {"file": str(test.source), "stretch_from": md.get("stretch_from"), "stress_from": md.get("stress_from"),
            "used_columns": md.get("used_columns", {}), "cross_checks": md.get("cross_checks", {}),
            "warnings": list(md.get("warnings", []))}


def columns_text(test: TensileTest) -> str:
    """The columns used, in words: ``4 'Time' [s], 1 'Extension' [mm], 2 'Load' [N]``."""
    return ", ".join(f"{c['index']} '{c['header'] or q}'" + (f" [{c['unit']}]" if c.get("unit") else "")
                     for q, c in how_read(test)["used_columns"].items())
