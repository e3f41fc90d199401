"""Read one tensile-test file (a testing machine's CSV-like export) into a :class:`TensileTest`.

The input contract, what is accepted, the column synonyms, the precedence of
metadata and every error message are documented in ``docs/reference/tensile-input.md``.

Outline of :func:`read`:

1. the sidecar (``test1.toml``) and the command-line ``overrides`` are read;
2. the bytes are checked to be text and decoded (stated encoding, else a BOM,
   else UTF-8; a legacy encoding must be stated);
3. ``#`` comment lines at the top give metadata; the header line, an optional
   units row and the data rows are found; the delimiter (``,`` ``;`` tab ``|``)
   and the decimal mark are detected;
4. columns are matched to quantities by name (or by position from ``columns``),
   units are taken from the header, a units row, or ``units``;
5. the numbers are parsed with :func:`numpy.loadtxt` (a slow, exact pass runs
   only to locate a bad cell) and converted to SI;
6. stretch (or shear strain) and nominal stress are formed from processed
   columns, or from displacement and force with the specimen geometry.
"""

from __future__ import annotations

import codecs
import csv
import datetime
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import units as _units
from ..errors import InputError
from ..progress import Reporter, ensure
from . import columns as C
from . import metadata as M
from .data import TensileTest

_DELIMITERS = ("\t", ";", "|", ",")
_DELIM_NAME = {"\t": "tab", ";": "';'", ",": "','", "|": "'|'"}
_QUOTED = re.compile(r'"[^"]*"')
_EXCEL_SEP = re.compile(r'^\s*"?sep=(.)"?\s*$', re.I)
_NUMBER = re.compile(r"^[-+]?(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][-+]?\d+)?$|^[-+]?(?:nan|inf|infinity)$"
                     # with thousands separators (1.234,5 or 1,234.5): a number, refused as such by _decimal
                     r"|^[-+]?\d{1,3}(?:\.\d{3})+,\d*$|^[-+]?\d{1,3}(?:,\d{3})+\.\d*$", re.I)
_ENCODING_COMMENT = re.compile(rb"^[ \t]*#+[ \t]*(?:encoding|charset)[ \t]*[:=][ \t]*[\"']?([A-Za-z0-9_.\-]+)", re.M | re.I)
_CONTENT = re.compile(rb"[^ \t\r\n\x00\x1a\xef\xbb\xbf\xff\xfe]")
_CONTROL_BYTES = bytes(c for c in range(32) if c not in (9, 10, 12, 13, 26))
_SIGNATURES = (
    (b"PK\x03\x04", "a zip archive (an Excel .xlsx workbook?); open it and save the sheet as CSV"),
    (b"\xd0\xcf\x11\xe0", "an OLE document (an old Excel .xls workbook?); open it and save the sheet as CSV"),
    (b"%PDF", "a PDF document; export the test data as CSV from the testing software"),
    (b"\x89HDF", "an HDF5 file; export the test data as CSV"),
    (b"\x89PNG", "a PNG image; export the test data as CSV"),
    (b"\xff\xd8\xff", "a JPEG image; export the test data as CSV"),
)


def read(
    path,
    *,
    overrides: Mapping[str, Any] | None = None,
    encoding: str | None = None,
    reporter: Reporter | None = None,
) -> TensileTest:
    """Read one tensile-test file into SI units.

    Parameters
    ----------
    path : str or path-like
        The CSV-like export (``,`` ``;`` tab or ``|`` delimited). A TOML
        sidecar with the same stem is read when present.
    overrides : mapping, optional
        Command-line metadata, the highest precedence: e.g.
        ``{"gauge_length": "30 mm", "area": "22 mm2", "mode": "uniaxial",
        "columns": ["time", "displacement", "force"], "units": ["s", "mm", "N"],
        "orientation": "x"}``. ``None`` values are ignored.
    encoding : str, optional
        Text encoding of the file (the same as ``overrides["encoding"]``, and
        preferred to it).
    reporter : Reporter, optional
        Receives warnings (ignored columns, units replaced by the sidecar).

    Returns
    -------
    TensileTest
        ``stretch`` (n,) is lambda, or gamma for ``simple_shear``; ``stress`` (n,)
        is nominal stress [Pa]; ``time`` (n,) [s] from the first sample, or None;
        ``displacement`` (n,) [m] and ``force`` (n,) [N] when the file has them
        (with units); ``metadata`` as documented in docs/reference/tensile-input.md ("What the reader returns").

    Raises
    ------
    InputError
        One line naming the file, the line/column or key, and what to do.
    ConfigError
        A bad command-line metadata key or value.
    """
    rep = ensure(reporter)
    p = Path(path)
    label = str(path)
    _check_path(p, label)
    side = M.from_sidecar(p)
    over = M.from_overrides(overrides, encoding=encoding)
    pre = side.merged(over)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{label}: cannot be read ({exc.strerror or exc}); check the path and permissions") from None
    text, enc_used = _decode(raw, label, pre.get("encoding"))
    lines = text.split("\n")
    if lines and lines[-1].strip() == "\x1a":  # DOS end-of-file mark
        lines.pop()

    delim_entry = pre.get("delimiter")
    layout = _layout(lines, label, M.delimiter_value(delim_entry) if delim_entry else None)
    md = (M.from_comments(layout.top_comments, label=label)
          .merged(M.from_machine_header(layout.preamble_cells, label=label)).merged(side).merged(over))
    if md.get("delimiter") and not delim_entry:  # stated only in a comment line
        d = M.delimiter_value(md.get("delimiter"))
        if d != layout.delimiter:
            layout = _layout(lines, label, d)
    warnings: list[str] = []
    if layout.trailer:
        (first, text), last = layout.trailer[0], layout.trailer[-1][0]
        warnings.append(f"{label}: lines {first}-{last} after the data (a results summary?) not read as data, "
                        f"starting {text.strip()[:60]!r}")
    return _assemble(p, label, layout, md, enc_used, warnings, rep)


# ---------------------------------------------------------------------------
# bytes -> text


def _check_path(p: Path, label: str) -> None:
    if not p.exists():
        raise InputError(f"{label}: no such file; check the path")
    if p.is_dir():
        raise InputError(f"{label}: is a folder; give the test's CSV file")
    if p.suffix.lower() == ".toml":
        raise InputError(
            f"{label}: is a TOML sidecar, not test data; give the CSV file with the same stem (it is read automatically)"
        )


def _decode(raw: bytes, label: str, enc_entry: M.Entry | None) -> tuple[str, str]:
    """Decode the file's bytes: stated encoding, else a BOM, else a ``# encoding:`` line, else UTF-8."""
    if _CONTENT.search(raw) is None:
        raise InputError(f"{label}: empty file; export the test again (one header line and one row per sample)")
    name, src = _stated_encoding(raw, label, enc_entry)
    wide = name is not None and _codec(name).startswith(("utf-16", "utf-32"))
    if not wide:
        _check_text(raw, label)
    if name is not None:
        text = _decode_as(raw, label, name, src)
    else:
        try:
            text = raw.decode("utf-8")
            name = "utf-8"
        except UnicodeDecodeError as exc:
            line = raw.count(b"\n", 0, exc.start) + 1
            hint = _suggest_encoding(raw)
            raise InputError(
                f"{label}: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}){hint}; state its encoding: "
                f"encoding = \"...\" in the sidecar {M.sidecar_path(Path(label)).name}, "
                f"a '# encoding: ...' first line, or the reader's encoding option", parameter="encoding"
            ) from None
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\r" in text:
        text = text.replace("\r\n", "\n")
        if "\r" in text:
            text = text.replace("\r", "\n")
    return text, _codec(name)


def _stated_encoding(raw: bytes, label: str, enc_entry: M.Entry | None) -> tuple[str | None, str]:
    """The encoding stated (metadata, else a byte-order mark, else a ``# encoding:`` line), and by whom."""
    name = M.encoding_value(enc_entry) if enc_entry else None
    bom = _bom(raw)
    if name is not None and bom is not None and not _codec(name).startswith(bom.split("-sig")[0]):
        raise InputError(
            f"{label}: starts with a {bom} byte-order mark but {enc_entry.described} says {name}; "
            f"remove the encoding statement (the mark is definitive)"
        )
    src = enc_entry.described if enc_entry else "its byte-order mark"
    if name is None:
        name = bom
    if name is None:
        m = _ENCODING_COMMENT.search(raw[:8192])
        if m:
            line = raw.count(b"\n", 0, m.start(1)) + 1
            src = f"{label} line {line}: encoding"
            name = M.encoding_value(M.Entry(m.group(1).decode("ascii"), src, M.COMMENT))
    return name, src


def _decode_as(raw: bytes, label: str, name: str, src: str) -> str:
    """The bytes decoded with the stated encoding *name* (one-line InputError where they do not decode)."""
    try:
        return raw.decode(name)
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise InputError(
            f"{label}: does not decode as {name} (stated by {src}): byte 0x{raw[exc.start]:02x} "
            f"on line {line}; state the file's real encoding"
        ) from None
    except (UnicodeError, LookupError, ValueError) as exc:
        # Codecs that fail without a position (punycode, idna: "codec failed", label errors).
        why = " ".join(str(exc).split())[:120]
        raise InputError(
            f"{label}: does not decode as {name} (stated by {src}: {why}); state the file's real "
            f"encoding, e.g. utf-8 or gbk"
        ) from None


def _bom(raw: bytes) -> str | None:
    if raw.startswith((b"\xff\xfe\x00\x00", b"\x00\x00\xfe\xff")):
        return "utf-32"
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return "utf-16"
    if raw.startswith(b"\xef\xbb\xbf"):
        return "utf-8-sig"
    return None


def _codec(name: str) -> str:
    return codecs.lookup(name).name


def _check_text(raw: bytes, label: str) -> None:
    for sig, what in _SIGNATURES:
        if raw.startswith(sig):
            raise InputError(f"{label}: is not a text file but {what}")
    head = raw[:65536]
    nul = head.find(b"\x00")
    if nul >= 0:
        even, odd = head[0::2].count(0), head[1::2].count(0)
        if max(even, odd) > 0.4 * len(head) / 2 and min(even, odd) < 0.05 * len(head) / 2:
            guess = "utf-16-le" if odd > even else "utf-16-be"
            raise InputError(
                f"{label}: looks like {guess} text without a byte-order mark; state encoding = \"{guess}\" "
                f"in the sidecar or as the encoding option"
            )
        raise InputError(
            f"{label}: is not a text file (binary data at byte {nul}); export the test as CSV text"
        )
    control = len(head) - len(head.translate(None, _CONTROL_BYTES))
    if control > 0.01 * len(head):
        raise InputError(f"{label}: is not a text file (control bytes); export the test as CSV text")


def _suggest_encoding(raw: bytes) -> str:
    """A hint for the error message; the file is never read with a guessed encoding."""
    head = raw[:4096]
    try:
        t = head.decode("gb18030", errors="strict")
        if any(name in t for name in C.SYNONYMS if any("\u4e00" <= ch <= "\u9fff" for ch in name)):
            return " (its header reads as Chinese GBK: encoding = \"gbk\"?)"
    except UnicodeDecodeError:
        pass
    try:  # Shift-JIS decodes most single Latin-1 bytes (µ ° ²) as half-width katakana: ask for kana or kanji
        if re.search("[\u3040-\u30ff\u4e00-\u9fff]", head.decode("shift_jis")):
            return " (it may be Japanese Shift-JIS)"
    except UnicodeDecodeError:
        pass
    try:
        head.decode("cp1252")
        return " (it may be Windows Western cp1252)"
    except UnicodeDecodeError:
        return ""


# ---------------------------------------------------------------------------
# text -> layout (comments, header, units row, data rows)


@dataclass
class _Layout:
    delimiter: str
    top_comments: list[tuple[int, str]]
    header: tuple[int, list[str]] | None       # (line number, cells)
    units_row: tuple[int, list[str]] | None
    data_lines: list[str]
    data_linenos: list[int]
    n_fields: int                              # fields of the first data row
    preamble: list[str]                        # text lines above the header
    preamble_cells: list[tuple[int, list[str]]]  # the same as (line number, cells): machine header lines
    trailer: list[tuple[int, str]]             # a results block after the data (line number, text): not read


#: The delimiter of columns aligned by blanks (a run of spaces or tabs; fixed-width exports, ``.dat`` files).
WHITESPACE = " "


def _split(line: str, delim: str) -> list[str]:
    if delim == WHITESPACE:
        line = line.replace("\t", " ").strip()
        if '"' not in line:
            return line.split()
    if '"' in line:
        return next(csv.reader([line], delimiter=delim, quotechar='"', skipinitialspace=True))
    return line.split(delim)


def _split_names(line: str, delim: str, n: int) -> list[str]:
    """A header or units line's cells: as a data row's, except that between columns aligned by blanks a name
    may hold single spaces (``Time (s)   Extension (mm)``): where splitting at every blank does not give the
    *n* columns of the data, the line is split at runs of two or more blanks or at tabs."""
    cells = _split(line, delim)
    if delim == WHITESPACE and len(cells) != n and '"' not in line:
        wide = [c for c in re.split(r" {2,}|\t", line.strip()) if c.strip()]
        if len(wide) == n:
            return wide
    return cells


def _is_number(cell: str) -> bool:
    return bool(_NUMBER.match(cell.strip().strip('"').strip()))


def _numeric_row(cells: list[str]) -> bool:
    nonempty = [c for c in cells if c.strip().strip('"').strip()]
    if not nonempty:
        return False
    return sum(_is_number(c) for c in nonempty) * 2 >= len(nonempty)


def _units_row(cells: list[str], *, under_header: bool = False) -> bool:
    """A units row: every cell a unit (``(s),(mm),(N)``); under a header line, also a row with the unit
    of an unused channel that esmm does not know (``s,mm,N,°C``): no numbers, no spaces inside a cell,
    and most cells known units."""
    filled = [C.clean_cell(c) for c in cells if C.clean_cell(c)]
    if not filled:
        return False
    known = sum(C.is_unit_cell(c) for c in filled)
    if known == len(filled):
        return all(C.is_unit_cell(c) for c in cells)
    return (under_header and known * 2 > len(filled)
            and not any(_is_number(c) or len(c.split()) > 1 for c in filled))


def _detect_delimiter(sample: list[str], label: str) -> str:
    """The delimiter that splits the (last) lines into a steady number of fields, most of them numbers.

    Ties go to tab, ``;``, ``|``, ``,`` in this order (a decimal comma makes ``,``
    steady in ``;``- and ``|``-delimited files too, but its fields are not numbers). Where none of them
    splits the rows steadily into numbers alone, runs of blanks that do are the delimiter
    (:data:`WHITESPACE`: columns aligned by spaces).
    """
    stripped = [_QUOTED.sub("x", s) for s in sample]
    best = None
    for rank, d in enumerate(_DELIMITERS):
        counts = [s.count(d) for s in stripped]
        mode = max(set(counts), key=counts.count)
        steady = counts.count(mode) / len(counts)
        if mode < 1 or steady < 0.5:
            continue
        cells = [c for s in sample for c in _split(s, d)]
        numeric = sum(_is_number(c) for c in cells) / max(len(cells), 1)
        score = (steady >= 0.8, numeric, steady, -rank)
        if best is None or score > best[0]:
            best = (score, d)
    blanks = _rows_of_numbers(sample, WHITESPACE)   # columns aligned by blanks: only where they do better
    if blanks >= 0.8 and (best is None or blanks > _rows_of_numbers(sample, best[1])):
        return WHITESPACE
    if best is not None:
        return best[1]
    raise InputError(
        f"{label}: cannot find the column delimiter (',', ';', tab, '|' or aligned blanks) in the data rows; "
        f"a test needs at least two columns (e.g. stretch and stress) - export it as CSV, "
        f"or state delimiter = \"...\" in the sidecar"
    )


def _rows_of_numbers(sample: list[str], delim: str) -> float:
    """The share of *sample*'s lines that *delim* splits into the most common number (two or more) of fields,
    every one a number."""
    rows = [_split(s, delim) for s in sample]
    counts = [len(r) for r in rows]
    mode = max(set(counts), key=counts.count)
    if mode < 2:
        return 0.0
    return sum(len(r) == mode and all(_is_number(c) for c in r) for r in rows) / len(rows)


def _skip(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("#")


_BLANK_LINE = re.compile(r"\n[ \t]+(?:\n|$)")


def _layout(lines: list[str], label: str, delimiter: str | None) -> _Layout:
    """Find the top comments, the header, a units row and the data rows of the file."""
    lines, delimiter = _excel_separator(lines, delimiter)
    delim = delimiter or _detect_delimiter(_last_rows(lines, label), label)
    head, first = _head(lines, delim, label)
    data_lines, linenos = _data_rows(lines, first, delim)
    width = len(_split(data_lines[0], delim))           # the data's fields (its first row is lines[first])
    header = units = None
    j = len(head) - 1
    if j >= 0:
        cells = _split_names(head[j][1], delim, width)
        if _units_row(cells, under_header=j >= 1):
            units = (head[j][0], cells)
            j -= 1
    if j >= 0:
        header = (head[j][0], _split_names(head[j][1], delim, width))
    head_end = header[0] if header else (units[0] if units else first + 1)
    top = [(i, lines[i - 1]) for i in range(1, head_end) if lines[i - 1].lstrip().startswith("#")]
    data_lines, linenos, trailer = _trailer(data_lines, linenos, delim, header)
    return _Layout(
        delimiter=delim,
        top_comments=top,
        header=header,
        units_row=units,
        data_lines=data_lines,
        data_linenos=linenos,
        n_fields=width,
        preamble=[ln.strip() for _, ln in head[: max(j, 0)]],
        preamble_cells=[(i, _split(ln, delim)) for i, ln in head[: max(j, 0)]],
        trailer=trailer,
    )


def _excel_separator(lines: list[str], delimiter: str | None) -> tuple[list[str], str | None]:
    """Excel's ``sep=;`` first line: its delimiter (unless one is stated), and the line blanked."""
    for k, ln in enumerate(lines):
        if ln.strip():
            m = _EXCEL_SEP.match(ln)
            if m:
                return [""] * (k + 1) + lines[k + 1:], delimiter or m.group(1)
            break
    return lines, delimiter


def _tail(lines: list[str]) -> list[str]:
    """The last 50 non-blank, non-comment lines, in file order."""
    tail: list[str] = []
    for ln in reversed(lines):
        if not _skip(ln):
            tail.append(ln)
            if len(tail) == 50:
                break
    return tail[::-1]


def _last_rows(lines: list[str], label: str) -> list[str]:
    """The last 50 non-blank, non-comment lines (where the delimiter is looked for), in file order."""
    tail = _tail(lines)
    if not tail:
        raise InputError(
            f"{label}: no numeric rows (only comments or blank lines); export the test data with one row per sample"
        )
    return tail


def _head(lines: list[str], delim: str, label: str) -> tuple[list[tuple[int, str]], int]:
    """The text lines (line number, text) before the first numeric row, and that row's index."""
    head: list[tuple[int, str]] = []   # non-blank, non-comment lines before the first numeric row
    counts = [_filled(_split(ln, delim)) for ln in _tail(lines)]
    width = max(set(counts), key=counts.count) if counts else 0   # filled cells of a typical data row
    for i, ln in enumerate(lines):
        if _skip(ln):
            continue
        cells = _split(ln, delim)
        if _numeric_row(cells) and not _labelled_value(cells, lines, i, delim, width):
            return head, i
        if any(C.clean_cell(c) for c in cells):  # a row of bare delimiters is blank
            head.append((i + 1, ln))
    if not head:
        raise InputError(
            f"{label}: no numeric rows (only comments or blank lines); export the test data with one row per sample"
        )
    raise InputError(
        f"{label}: no numeric rows (found {len(head)} text line(s), the last on line {head[-1][0]}); "
        f"the file must hold one row of numbers per sample"
    )


def _filled(cells: list[str]) -> int:
    return sum(1 for c in cells if c.strip().strip('"').strip())


def _labelled_value(cells: list[str], lines: list[str], i: int, delim: str, width: int) -> bool:
    """A preamble line that counts as a numeric row: a label and a number (``Batch,1``, Bluehill's
    ``Specimen properties : Specimen label,"1"``), narrower than the data rows (*width* filled cells)
    or followed by a text line (the header, more preamble)."""
    first = next((c for c in cells if c.strip().strip('"').strip()), "")
    if _is_number(first):
        return False
    if _filled(cells) < width:
        return True
    nxt = next((lines[j] for j in range(i + 1, len(lines)) if not _skip(lines[j])), None)
    return nxt is not None and not _numeric_row(_split(nxt, delim))


def _data_rows(lines: list[str], first: int, delim: str) -> tuple[list[str], list[int]]:
    """The data rows from index *first* on (comments, blank lines and rows of bare delimiters, which
    Excel leaves where rows were cleared, dropped), and their line numbers."""
    bare = re.compile(r'[ \t"' + re.escape(delim) + r"]*")
    region = lines[first:]
    while region and bare.fullmatch(region[-1]):
        region.pop()
    joined = "\n".join(region)
    if ("#" not in joined and "\n\n" not in joined and _BLANK_LINE.search(joined) is None
            and re.search(r'\n[ \t"' + re.escape(delim) + r"]*(?:\n|$)", joined) is None):
        return region, list(range(first + 1, first + 1 + len(region)))
    pairs = [(i, ln) for i, ln in enumerate(region, first + 1) if not (_skip(ln) or bare.fullmatch(ln))]
    return [ln for _, ln in pairs], [i for i, _ in pairs]


#: Most lines of a results block after the data (``Max load,12.3``, ``Modulus,0.3``) that is set aside.
TRAILER_MAX_LINES = 30


#: First cells of the summary rows a spreadsheet appends right under its columns (``Max,,12.3``).
SUMMARY_LABELS = frozenset({"max", "maximum", "min", "minimum", "mean", "average", "avg", "median", "std", "sd",
                            "stdev", "std dev", "standard deviation", "sum", "total", "count", "range"})


def _summary_rows(data: list[str], delim: str) -> int:
    """How many of the last rows (at most :data:`TRAILER_MAX_LINES`) are a spreadsheet's summary: each starts with a
    statistic's name (:data:`SUMMARY_LABELS`, a colon allowed)."""
    n = 0
    for ln in reversed(data[-TRAILER_MAX_LINES:]):
        first = C.clean_cell((_split(ln, delim) or [""])[0]).rstrip(":").strip().lower()
        if first not in SUMMARY_LABELS:
            break
        n += 1
    return n if n < len(data) else 0


def _trailer(data: list[str], linenos: list[int], delim: str, header: tuple[int, list[str]] | None):
    """Split off a results block that machine software writes after the data: it follows a blank
    line, starts with a row that is text or narrower than the data, is short, and does not repeat
    the header (that would be a second test); or, right under the data, the summary rows a
    spreadsheet appends (:func:`_summary_rows`). Returns (data rows, their line numbers, the block)."""
    n = _summary_rows(data, delim)
    if n:
        return data[:-n], linenos[:-n], list(zip(linenos[-n:], data[-n:]))
    width = _filled(_split(data[0], delim))
    for k in range(max(1, len(data) - TRAILER_MAX_LINES), len(data)):
        if linenos[k] - linenos[k - 1] < 2:   # not after a blank (or comment) line
            continue
        cells = _split(data[k], delim)
        if _numeric_row(cells) and _filled(cells) == width:
            continue
        block = data[k:]
        if header and any(_repeats_header(ln, delim, header) for ln in block):
            break
        return data[:k], linenos[:k], list(zip(linenos[k:], block))
    return data, linenos, []


def _repeats_header(line: str, delim: str, header: tuple[int, list[str]]) -> bool:
    cells = [C.clean_cell(c) for c in _split(line, delim)]
    want = [C.clean_cell(c) for c in header[1]]
    return [c for c in cells if c] == [c for c in want if c]


# ---------------------------------------------------------------------------
# columns


@dataclass
class _Column:
    index: int            # 0-based
    header: str | None    # header text (name part) or None
    quantity: str | None  # C.QUANTITIES key, "true_stress", C.IGNORE, or None (unknown name)
    unit: str | None      # as stated (None: not stated)
    absolute: bool = False

    def where(self, label: str) -> str:
        name = f"'{self.header}'" if self.header else (self.quantity or "?")
        return f"{label}: column {self.index + 1} {name}"


def _columns(label: str, layout: _Layout, md: M.Metadata, warnings: list[str]) -> list[_Column]:
    """The columns: names and units from the header and units row, quantities and units as stated."""
    hdr_cells = [C.clean_cell(c) for c in layout.header[1]] if layout.header else None
    n = _column_count(label, layout, hdr_cells)
    names, file_units = _header_units(label, layout, hdr_cells, n)
    qs = _quantities(label, layout, md, names, hdr_cells is not None, n)
    absolute = [bool(nm) and C.normalise_name(nm) in C.ABSOLUTE_POSITION for nm in names]
    units = _stated_units(label, md, file_units, n, warnings)
    return [_Column(i, names[i] or None, qs[i], units[i], absolute[i]) for i in range(n)]


def _column_count(label: str, layout: _Layout, hdr_cells: list[str] | None) -> int:
    """The number of columns; trailing empty cells (a trailing delimiter) do not make columns."""
    n = layout.n_fields
    if hdr_cells is None:
        first = _split(layout.data_lines[0], layout.delimiter)
        while n > 1 and not first[n - 1].strip():
            n -= 1
        return n
    while len(hdr_cells) > 1 and not hdr_cells[-1]:
        hdr_cells.pop()
    if len(hdr_cells) != n:
        extra = _split(layout.data_lines[0], layout.delimiter)[len(hdr_cells):]
        if len(hdr_cells) < n and not any(c.strip() for c in extra):
            return len(hdr_cells)
        raise InputError(
            f"{label}: the header on line {layout.header[0]} has {len(hdr_cells)} columns but the data row "
            f"on line {layout.data_linenos[0]} has {n}; make them match"
        )
    return n


def _header_units(label: str, layout: _Layout, hdr_cells: list[str] | None, n: int,
                  ) -> tuple[list[str | None], list[str | None]]:
    """Column names and units from the header (``stress [kPa]``) and the units row."""
    names: list[str | None] = [None] * n
    file_units: list[str | None] = [None] * n
    if hdr_cells is not None:
        for i, cell in enumerate(hdr_cells):
            names[i], file_units[i] = C.split_header(cell)
    unit_cells = [C.clean_cell(c) for c in layout.units_row[1]] if layout.units_row else None
    for i, cell in enumerate((unit_cells or [])[:n]):
        u = cell.strip().strip("()[]{}").strip() if cell else ""
        if not u:
            continue
        if file_units[i] is not None and not _same_unit(file_units[i], u):
            raise InputError(
                f"{label}: column {i + 1}: the header says unit {file_units[i]!r} but the units row on line "
                f"{layout.units_row[0]} says {u!r}; keep one"
            )
        file_units[i] = u
    return names, file_units


def _quantities(label: str, layout: _Layout, md: M.Metadata, names: list[str | None], has_header: bool,
                n: int) -> list[str | None]:
    """The quantity of each column: as stated (``columns = [...]``), else from the header names."""
    col_entry = md.get("columns")
    if col_entry is not None:
        qs = M.columns_value(col_entry)
        if len(qs) != n:
            raise col_entry.error(
                f"{col_entry.where}: lists {len(qs)} columns but the file has {n} (data line "
                f"{layout.data_linenos[0]}); list one quantity per column, 'ignore' for those to skip"
            )
        return qs
    if not has_header:
        raise InputError(
            f"{label}: no header line naming the columns (data start on line {layout.data_linenos[0]}); "
            f"add one such as 'stretch,nominal stress [kPa]', or give columns = [...] and units = [...] "
            f"in the sidecar {M.sidecar_path(Path(label)).name}"
        )
    return [C.quantity_of(nm) if nm else None for nm in names]


def _stated_units(label: str, md: M.Metadata, file_units: list[str | None], n: int,
                  warnings: list[str]) -> list[str | None]:
    """The units of the file, replaced by those stated (``units = [...]``) with a warning where they differ."""
    units: list[str | None] = list(file_units)
    unit_entry = md.get("units")
    if unit_entry is None:
        return units
    given = M.list_value(unit_entry)
    if len(given) != n:
        raise unit_entry.error(
            f"{unit_entry.where}: lists {len(given)} units but the file has {n} columns; "
            f"list one unit per column (\"\" for dimensionless ones)"
        )
    for i, u in enumerate(given):
        u = u.strip().strip("()[]{}").strip()
        if file_units[i] is not None and not _same_unit(file_units[i], u):
            warnings.append(
                f"{label}: column {i + 1}: unit {file_units[i]!r} in the file replaced by {u!r} from {unit_entry.described}"
            )
        units[i] = u
    return units


def _same_unit(a: str, b: str) -> bool:
    na, nb = (_units.normalise_unit(C.clean_cell(x)) for x in (a, b))
    none = ("", "-", "1")
    return na == nb or (na in none and nb in none)


def _need_unit(col: _Column, label: str, md: M.Metadata) -> float:
    """SI factor of a used column; a dimensional column without a unit is refused."""
    kind = C.QUANTITIES[col.quantity]
    unit = col.unit
    if unit is not None and unit.strip() in ("", "-") and kind != "dimensionless":
        unit = None
    if unit is None and kind != "dimensionless":
        side = M.sidecar_path(Path(label)).name
        example = {"time": "s", "length": "mm", "force": "N", "stress": "kPa"}[kind]
        name = col.header or col.quantity.replace("_", " ")
        raise InputError(
            f"{col.where(label)} has no unit; units are never guessed: write it in the header "
            f"('{name} [{example}]'), in a units row under the header, or as units = [...] in the sidecar {side}"
        )
    return C.unit_factor(unit, col.quantity, where=col.where(label))


# ---------------------------------------------------------------------------
# numbers


_CLOCK = re.compile(r"^\s*\"?\s*(?:(\d{4})-(\d{2})-(\d{2})[T ]\s*)?(\d+):([0-5]?\d):([0-5]?\d(?:[.,]\d*)?)"
                    r"\s*(Z|[+-]\d{2}:?\d{2})?\s*\"?\s*$")


#: Where date-and-time stamps count their seconds from.
_EPOCH = datetime.datetime(2000, 1, 1)


def _clock_seconds(cell: str) -> float:
    """``"01:02:03.5"`` (hours:minutes:seconds, a clock time or an elapsed time) in seconds; with an ISO 8601
    date before it (``"YYYY-MM-DD hh:mm:ss.s"``, ``T`` or a space between, a ``Z`` or UTC offset after), in
    seconds from :data:`_EPOCH` by :meth:`datetime.datetime.fromisoformat` (the calendar and the offset are
    the standard library's), so that a record across midnight keeps its order (the time is used from its
    first sample on; float64 resolves 0.2 µs at that size)."""
    m = _CLOCK.match(cell)
    if m is None:
        raise ValueError(f"not a clock time: {cell!r}")
    y, mo, d, h, mi, sec, tz = m.groups()
    if y is None:
        return int(h) * 3600.0 + int(mi) * 60.0 + float(sec.replace(",", "."))
    whole, _, frac = sec.replace(",", ".").partition(".")
    stamp = datetime.datetime.fromisoformat(
        f"{y}-{mo}-{d}T{int(h):02d}:{int(mi):02d}:{int(whole):02d}{'.' + frac if frac else ''}{tz or ''}")
    if stamp.tzinfo is not None:
        stamp = stamp.astimezone(datetime.UTC).replace(tzinfo=None)
    return (stamp - _EPOCH).total_seconds()


def _clock_columns(layout: _Layout, cols: list[_Column]) -> frozenset[int]:
    """The time columns written as hh:mm:ss(.sss) (their first data cell is): read as seconds."""
    first = _split(layout.data_lines[0], layout.delimiter)
    return frozenset(c.index for c in cols if c.quantity == "time" and c.index < len(first)
                     and _CLOCK.match(first[c.index]))


def _parse(layout: _Layout, cols: list[_Column], decimal: str, label: str, *,
           clock: frozenset[int] = frozenset()) -> np.ndarray:
    """The used columns as floats, shape (n_rows, len(cols)); exact error location on failure.
    Columns of *clock* hold hh:mm:ss(.sss) times and are read in seconds."""
    lines, delim = layout.data_lines, layout.delimiter
    use = [c.index for c in cols]
    if not (decimal == "," and delim == ","):
        src = [ln.replace(",", ".") for ln in lines] if decimal == "," else lines
        try:
            arr = np.loadtxt(src, delimiter=None if delim == WHITESPACE else delim, quotechar='"', usecols=use,
                             ndmin=2, comments=None,
                             dtype=np.float64, encoding=None, converters=dict.fromkeys(clock, _clock_seconds))
        except (ValueError, IndexError):
            arr = None
    else:
        arr = None
    if arr is None:
        arr = _parse_slow(layout, cols, decimal, label, clock=clock)
    bad = ~np.isfinite(arr)
    if bad.any():
        r, k = np.argwhere(bad)[0]
        raw = _split(lines[r], delim)[cols[k].index].strip()
        raise InputError(
            f"{cols[k].where(label)}, line {layout.data_linenos[r]}: {raw!r} is not a finite number; "
            f"fix or delete that row (or comment it out with #)"
        )
    return arr


def _parse_slow(layout: _Layout, cols: list[_Column], decimal: str, label: str, *,
                clock: frozenset[int] = frozenset()) -> np.ndarray:
    delim = layout.delimiter
    need = max(c.index for c in cols) + 1
    out = np.empty((len(layout.data_lines), len(cols)))
    reader = ((_split(ln, delim) for ln in layout.data_lines) if delim == WHITESPACE else
              csv.reader(layout.data_lines, delimiter=delim, quotechar='"', skipinitialspace=True))
    for r, row in enumerate(reader):
        if len(row) < need:
            raise InputError(
                f"{label}: line {layout.data_linenos[r]} has {len(row)} field(s), the file has {layout.n_fields} "
                f"columns; complete or delete that row"
            )
        for k, c in enumerate(cols):
            cell = row[c.index].strip()
            try:
                if c.index in clock:
                    out[r, k] = _clock_seconds(cell)
                else:
                    out[r, k] = _number(cell, decimal)
            except ValueError:
                _refuse_repeated_header(layout, r, label)
                what = "is empty" if not cell else f"has text {cell!r}"
                if c.index in clock:
                    what += " (the column holds hh:mm:ss or date-and-time stamps)"
                if decimal == "." and re.fullmatch(r"[-+]?\d*,\d+", cell):
                    what += " (a decimal comma where the file uses '.'?)"
                raise InputError(
                    f"{c.where(label)}, line {layout.data_linenos[r]} {what} where a number is expected; "
                    f"fix or delete that row (or comment it out with #)"
                ) from None
    return out


def _refuse_repeated_header(layout: _Layout, r: int, label: str) -> None:
    """A data row that repeats the header: several records joined, or an export's page break."""
    if layout.header and _repeats_header(layout.data_lines[r], layout.delimiter, layout.header):
        raise InputError(
            f"{label}: line {layout.data_linenos[r]} repeats the header of line {layout.header[0]} (a second "
            f"test, or a page break of the export?); a file holds one test: split it into one file per test, "
            f"or delete the repeated header line"
        )


def _data_decimal(layout: _Layout, cols: list[_Column], md: M.Metadata, label: str) -> str | None:
    """The decimal mark the data's numbers use (:func:`_decimal`), None where they mix both: the
    header's values are then read without it, and the data's own reading reports the mix."""
    try:
        return _decimal(layout, cols, md, label)
    except InputError:
        return None


#: A number with its thousands grouped, by the decimal mark: ``1,002.83`` (a spreadsheet's export in English),
#: ``1.002,83`` (in German); the grouping mark is dropped. Only with the decimal mark after the groups: ``1,002``
#: or ``1.002`` alone may be either reading, and stays an error.
_GROUPED = {".": re.compile(r"[-+]?\d{1,3}(?:,\d{3})+\.\d*(?:[eE][-+]?\d+)?"),
            ",": re.compile(r"[-+]?\d{1,3}(?:\.\d{3})+,\d*(?:[eE][-+]?\d+)?")}


def _number(cell: str, decimal: str) -> float:
    """A data cell as a float, in the file's decimal mark, its thousands grouping (:data:`_GROUPED`) dropped."""
    if _GROUPED[decimal].fullmatch(cell):
        cell = cell.replace("," if decimal == "." else ".", "")
    return float(cell.replace(",", ".") if decimal == "," else cell)


def _used_cells(layout: _Layout, cols: list[_Column], rows: list[int]):
    """(row, cell) of the used columns in data rows *rows*, unquoted."""
    for r in rows:
        cells = _split(layout.data_lines[r], layout.delimiter)
        for c in cols:
            if c.index < len(cells):
                yield r, cells[c.index].strip().strip('"').strip()


def _decimal(layout: _Layout, cols: list[_Column], md: M.Metadata, label: str) -> str:
    """The data's decimal mark: as stated (``decimal``), else the one its numbers use. Numbers with both marks
    are read where every one that has the other mark groups thousands with it (``1,002.83``)."""
    e = md.get("decimal")
    if e is not None:
        return M.decimal_value(e)
    lines = layout.data_lines
    idx = list(range(len(lines))) if len(lines) <= 400 else list(range(200)) + list(range(len(lines) - 200, len(lines)))
    first: dict[str, int] = {}
    for r, v in _used_cells(layout, cols, idx):
        for mark in ",.":
            if mark in v:
                first.setdefault(mark, r)
    if len(first) < 2:
        return "," if "," in first else "."
    for mark, other in ((".", ","), (",", ".")):        # both marks: rare; the cells read again
        if all(_GROUPED[mark].fullmatch(v) for _, v in _used_cells(layout, cols, idx) if other in v):
            return mark
    raise InputError(
        f"{label}: numbers mix '.' (line {layout.data_linenos[first['.']]}) and ',' (line "
        f"{layout.data_linenos[first[',']]}) as decimal mark; export without thousands separators, "
        f"or state decimal = \".\" or \",\" in the sidecar"
    )


# ---------------------------------------------------------------------------
# assembly


@dataclass
class _Plan:
    """Which columns make the test: the processed ones, or the raw channels and the geometry."""

    mode: str
    mode_from: str
    x_q: str | None            # processed x quantity used ("stretch", "strain", ...) or None (raw)
    x_col: _Column | None
    s_q: str | None            # processed stress quantity used ("stress", "true_stress", ...) or None (raw)
    s_col: _Column | None
    d_col: _Column | None
    f_col: _Column | None
    t_col: _Column | None
    checks: dict[str, _Column]  # derived columns kept to cross-check the raw path: "x", "s"

    @property
    def x_name(self) -> str:
        return "shear strain" if self.mode == "simple_shear" else "stretch"


def _by_quantity(cols: list[_Column], label: str) -> tuple[dict[str, _Column], list[str]]:
    """One column per quantity; a derived duplicate (:data:`columns.DERIVED`) gives way to the raw channel."""
    groups: dict[str, list[_Column]] = {}
    for c in cols:
        if c.quantity not in (None, C.IGNORE):
            groups.setdefault(c.quantity, []).append(c)
    by_q: dict[str, _Column] = {}
    notes: list[str] = []
    for q, group in groups.items():
        raw = [c for c in group if not (c.header and C.normalise_name(c.header) in C.DERIVED)]
        if len(group) == 1 or len(raw) == 1:
            by_q[q] = group[0] if len(group) == 1 else raw[0]
            for c in group:
                if c is not by_q[q]:
                    notes.append(f"column {c.index + 1} '{c.header}' not used: the raw channel column "
                                 f"{by_q[q].index + 1} '{by_q[q].header}' is")
            continue
        o, c = (raw or group)[:2]
        raise InputError(
            f"{label}: two {q.replace('_', ' ')} columns, {o.index + 1} '{o.header}' and "
            f"{c.index + 1} '{c.header}'; keep one, or give columns = [...] with 'ignore' for the other"
        )
    return by_q, notes


def _mode(md: M.Metadata, by_q: dict[str, _Column]) -> tuple[str, str]:
    mode_e = md.get("mode")
    shear = any(q in by_q for q in ("shear_strain", "shear_stress"))
    axial = any(q in by_q for q in ("stretch", "strain", "true_strain", "stress", "true_stress"))
    if mode_e is not None:
        return M.mode_value(mode_e), mode_e.described
    if shear and not axial:
        return "simple_shear", "columns"
    return "uniaxial", "default"


def _has_unit(col: _Column | None) -> bool:
    return col is not None and (col.unit not in (None, "", "-"))


def _plan(label: str, layout: _Layout, md: M.Metadata, cols: list[_Column], by_q: dict[str, _Column],
          geo: M.Geometry) -> _Plan:
    """Decide the columns: the raw channels when the file has them with units and the geometry is
    known (the machine's own measurement; derived columns are then cross-checked), else the
    processed stretch/strain and stress columns."""
    mode, mode_from = _mode(md, by_q)
    shear_cols = [q for q in ("shear_strain", "shear_stress") if q in by_q]
    hdr_line = f" (header line {layout.header[0]})" if layout.header else ""
    if mode == "simple_shear":
        bad = [q for q in ("stretch", "strain", "true_strain", "stress") if q in by_q and not shear_cols]
        if bad:
            raise InputError(
                f"{label}: mode simple_shear ({mode_from}) needs 'shear strain' and 'shear stress' columns but "
                f"the file has {', '.join(bad)}{hdr_line}; rename the columns or correct the mode"
            )
        x_q, s_q = "shear_strain", "shear_stress"
    else:
        if shear_cols:
            raise InputError(
                f"{label}: the file has {' and '.join(q.replace('_', ' ') for q in shear_cols)} columns but the "
                f"mode is {mode} ({mode_from}); state mode = \"simple_shear\""
            )
        x_q = next((q for q in ("stretch", "strain", "true_strain") if q in by_q), None)
        s_q = next((q for q in ("stress", "true_stress") if q in by_q), None)
    d_col, f_col, t_col = by_q.get("displacement"), by_q.get("force"), by_q.get("time")
    x_col = by_q.get(x_q) if x_q else None
    s_col = by_q.get(s_q) if s_q else None
    _require_columns(label, mode, cols, x_col, s_col, d_col, f_col, hdr_line)
    area_ok = geo.area is not None and (mode != "simple_shear" or "area" in md.entries)
    raw = _has_unit(d_col) and _has_unit(f_col) and geo.gauge_length is not None and area_ok
    checks: dict[str, _Column] = {}
    if raw and (x_col is not None or s_col is not None):
        checks = {k: c for k, c in (("x", x_col), ("s", s_col))
                  if c is not None and (_has_unit(c) or C.QUANTITIES.get(c.quantity) == "dimensionless")}
        x_col = s_col = None
        x_q = s_q = None
    plan = _Plan(mode, mode_from, x_q if x_col else None, x_col, s_q if s_col else None, s_col,
                 d_col, f_col, t_col, checks)
    side = M.sidecar_path(Path(label)).name

    def missing_geometry(key: str, why: str) -> InputError:
        example = '"30 mm"' if key == "gauge_length" else '"22 mm2" (or width and thickness, or diameter)'
        return InputError(
            f"{key}: missing geometry for {label}: {why} needs {key}; give {key} = {example} in the sidecar "
            f"{side}, a '# {key}: ...' line at the top of the file, or this option", parameter=key
        )

    if x_col is None and geo.gauge_length is None:
        raise missing_geometry("gauge_length", f"{plan.x_name} from displacement")
    if s_col is None:
        if mode == "simple_shear" and "area" not in md.entries:
            raise missing_geometry("area", "shear stress from force (area = the sheared face)")
        if geo.area is None:
            raise missing_geometry("area", "stress from force")
    return plan


class NotATestError(InputError):
    """A text table none of whose columns names a test quantity: another kind of file, not a test."""


def _require_columns(label: str, mode: str, cols: list[_Column], x_col, s_col, d_col, f_col,
                     hdr_line: str) -> None:
    """Refuse a file that has neither the processed nor the raw column of x or of stress."""
    x_missing = x_col is None and d_col is None
    s_missing = s_col is None and f_col is None
    if not (x_missing or s_missing):
        return
    x_name = "shear strain" if mode == "simple_shear" else "stretch"
    x_need = ("a 'shear strain' (gamma) column or a displacement column" if mode == "simple_shear"
              else "a stretch or strain column, or a displacement column")
    s_need = ("a 'shear stress' column or a force column" if mode == "simple_shear"
              else "a stress column or a force column")
    found = ", ".join(f"'{c.header}'" for c in cols if c.header) or "none named"
    unknown = [c for c in cols if c.quantity is None]
    side = M.sidecar_path(Path(label)).name
    if unknown and len(unknown) == len(cols):
        names = ", ".join(f"'{c.header}'" for c in unknown if c.header)
        raise NotATestError(
            f"{label}: unknown column names {names}{hdr_line}: none names a quantity of a tensile test, so this "
            "is not a test record (a table of specimen measurements?); leave it out, or rename the columns (time, "
            "displacement, force, stretch, strain, stress, ...) or give columns = [...] in the sidecar "
            f"{M.sidecar_path(Path(label)).name}")
    if unknown:
        names = ", ".join(f"'{c.header}'" for c in unknown if c.header)
        raise InputError(
            f"{label}: unknown column names {names}{hdr_line}; the test needs "
            f"{x_need if x_missing else s_need}: rename the columns (time, displacement, force, stretch, "
            f"strain, stress, shear strain, shear stress, or a synonym in docs/reference/tensile-input.md) or give "
            f"columns = [...] in the sidecar {side}"
        )
    if x_missing:
        have = "stress" if not s_missing else "neither stretch nor stress"
        raise InputError(
            f"{label}: the file has {have} but no {x_name}: it needs {x_need} (columns found{hdr_line}: "
            f"{found}); add the column or name it in the header"
        )
    raise InputError(
        f"{label}: the file has {x_name} but no stress: it needs {s_need} (columns found{hdr_line}: "
        f"{found}); add the column or name it in the header"
    )


def _used(plan: _Plan) -> dict[str, _Column]:
    """The columns to parse: those used, time, raw channels that have units, and cross-checks."""
    used: dict[str, _Column] = {}
    for key, col in (("x", plan.x_col), ("s", plan.s_col), ("time", plan.t_col)):
        if col is not None:
            used[key] = col
    for key, col, needed in (("displacement", plan.d_col, plan.x_col is None),
                             ("force", plan.f_col, plan.s_col is None)):
        if col is not None and (needed or col.unit not in (None, "", "-")):
            used[key] = col
    for key, col in plan.checks.items():
        used[f"check_{key}"] = col
    return used


def _time(t_col: _Column, t: np.ndarray | None, factor: float, linenos: list[int], label: str, *,
          layout: _Layout | None = None, decimal: str = ".", warnings: list[str] | None = None):
    """Time from the first sample; refuse time that goes backwards.

    A time column whose decimals were written without their leading zeros
    (``40.9, 40.10, 40.11`` for 40.09, 40.10, 40.11 s: a spreadsheet's
    number format) is read as meant where that reading, and only it, runs
    forward (:func:`_digits_time`); a warning says so.
    """
    if t is None:
        return None
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size and layout is not None:
        fixed = _digits_time(layout, t_col, decimal)
        if fixed is not None:
            t, note = fixed[0] * factor, fixed[1]
            back = np.flatnonzero(np.diff(t) < 0)
            if warnings is not None and not back.size:
                warnings.append(f"{t_col.where(label)}: {note}")
    if back.size:
        i = back[0] + 1
        u = t_col.unit or "s"
        raise InputError(
            f"{t_col.where(label)}, line {linenos[i]}: time goes backwards ({t[i] / factor:g} {u} after "
            f"{t[i - 1] / factor:g} {u} on line {linenos[i - 1]}); a file must hold one test in time order - "
            f"split joined records into separate files"
        )
    return t - t[0]


_DIGITS = re.compile(r'^\s*"?\s*(\d+)(?:[.,](\d*))?\s*"?\s*$')


def _digits_time(layout: _Layout, t_col: _Column, decimal: str) -> tuple[np.ndarray, str] | None:
    """The time column read with its decimals' leading zeros restored, or None where that is not the pattern.

    Every cell is ``I.F`` (digits only); with *d* the most decimal digits of
    any cell, the time is ``I + F / 10**d`` (a cell with *d* decimals keeps
    its value). The reading is taken only where it explains the file: some
    cells have fewer than *d* decimals (the zeros lost) and the time so read
    never goes backwards, while the numbers as written do. Records joined
    into one file, or times out of order, stay backwards and are refused.
    """
    ints, fracs = [], []
    for line in layout.data_lines:
        cells = _split(line, layout.delimiter)
        m = _DIGITS.match(cells[t_col.index]) if t_col.index < len(cells) else None
        if m is None or (decimal == "." and "," in cells[t_col.index]):
            return None
        ints.append(m.group(1))
        fracs.append(m.group(2) or "")
    d = max(len(f) for f in fracs)
    changed = [k for k, f in enumerate(fracs) if len(f) < d and int(f or "0")]
    if d < 2 or not changed:
        return None
    # the number as meant, written out and parsed (the value a correct export gives, to the last bit)
    meant = [f"{i}.{int(f or '0'):0{d}d}" for i, f in zip(ints, fracs)]
    t = np.array([float(v) for v in meant])
    if np.any(np.diff(t) < 0):
        return None
    step = float(np.median(np.diff(t)))
    k = changed[0]
    sep = "," if decimal == "," else "."
    note = (f"time repaired: {len(changed)} of {len(t)} cells were written without the leading zeros of their "
            f"{d} decimals, as a spreadsheet's number format writes them (e.g. {ints[k]}{sep}{fracs[k]} on line "
            f"{layout.data_linenos[k]} is read as {meant[k]}); so read, the time runs forward in steps of "
            f"{step:.{d}g} (median); check the export's number format")
    return t, note


def _x_of(q: str, v: np.ndarray) -> tuple[np.ndarray, str]:
    """Stretch (or gamma) from a processed column of quantity *q*."""
    if q == "strain":
        return 1.0 + v, "strain column (stretch = 1 + strain)"
    if q == "true_strain":
        with np.errstate(over="ignore"):
            return np.exp(v), "true strain column (stretch = exp(strain))"
    return v, f"{q.replace('_', ' ')} column"


def _stress_of(q: str, v: np.ndarray, x: np.ndarray, mode: str) -> tuple[np.ndarray, str]:
    """Nominal stress from a processed column; true (Cauchy) stress is divided by the stretch."""
    if q == "true_stress":
        # Incompressible, deformation diagonal in the loading frame (uniaxial, equibiaxial, pure
        # shear): P = sigma F^-T gives P = sigma / lambda along the loading direction.
        return v / x, "true stress column (nominal stress = true stress / stretch, incompressible)"
    return v, f"{q.replace('_', ' ')} column"


def _stretch_and_stress(plan: _Plan, col_of: dict[str, np.ndarray], disp, force, geo: M.Geometry,
                        linenos: list[int], label: str):
    """x (stretch or gamma), nominal stress, and where each came from."""
    if plan.x_col is not None:
        x, x_from = _x_of(plan.x_q, col_of["x"])
        xc = plan.x_col
    else:
        x = disp / geo.gauge_length
        if plan.mode != "simple_shear":
            x = 1.0 + x
        x_from, xc = "displacement / gauge_length", plan.d_col
    if plan.mode != "simple_shear":
        bad = np.flatnonzero(x <= 0)
        if bad.size:
            i = bad[0]
            raise InputError(
                f"{xc.where(label)}, line {linenos[i]}: gives stretch {x[i]:.4g} <= 0; check the column's unit, "
                f"the gauge length and that strain is engineering strain"
            )
    if plan.s_col is not None:
        stress, s_from = _stress_of(plan.s_q, col_of["s"], x, plan.mode)
    else:
        stress, s_from = force / geo.area, "force / area"
    for arr, col, what in ((x, xc, plan.x_name), (stress, plan.s_col or plan.f_col, "stress")):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:  # e.g. exp() of an absurd true strain
            raise InputError(
                f"{col.where(label)}, line {linenos[bad[0]]}: gives a {what} that is not finite; check the value"
            )
    return x, x_from, stress, s_from


def _check_response(plan: _Plan, x: np.ndarray, stress: np.ndarray, linenos: list[int], label: str) -> None:
    """Refuse a stress that cannot be a response to the deformation: one value on every row (a dead
    load channel), or the opposite sign to it on most rows away from the reference state (tension
    with compressive stress: a channel recorded compression-positive)."""
    col = plan.s_col or plan.f_col
    if len(stress) > 2 and np.ptp(stress) == 0:  # (of two rows, the fitter refuses too few samples)
        raise InputError(
            f"{col.where(label)}: the stress is {stress[0]:.4g} Pa on every row ({len(stress)} rows): the load "
            f"channel recorded nothing; check the column and the load cell, and export the test again"
        )
    dx = x - (0.0 if plan.mode == "simple_shear" else 1.0)
    loaded = (np.abs(dx) > 0.05 * np.max(np.abs(dx))) & (np.abs(stress) > 0.05 * np.max(np.abs(stress)))
    opposite = loaded & (np.sign(dx) != np.sign(stress))
    n, bad = int(loaded.sum()), int(opposite.sum())
    if n >= 3 and bad * 2 > n:
        i = int(np.flatnonzero(opposite)[0])
        _refuse_saturated(col.where(label), stress[opposite], n)
        which = "the stress column" if plan.s_col is not None else "the force (or the displacement) column"
        raise InputError(
            f"{col.where(label)}, line {linenos[i]}: {plan.x_name} {x[i]:.4g} with stress {stress[i]:.4g} Pa; on "
            f"{bad} of {n} loaded rows the stress has the opposite sign to the deformation (tension must give "
            f"positive stress): {which} is recorded compression-positive; change its sign and read again"
        )


def _refuse_saturated(where: str, wrong: np.ndarray, n: int) -> None:
    """A stress of the wrong sign that sits at one value on most of its rows is a saturated channel (the
    converter or the amplifier at the end of its range, or a zero far off), not a sign convention: say so."""
    values, counts = np.unique(wrong, return_counts=True)
    j = int(np.argmax(counts))
    if counts[j] * 2 > wrong.size and counts[j] >= 3:
        raise InputError(
            f"{where}: the stress sits at {values[j]:.4g} Pa on {int(counts[j])} of {n} loaded rows, opposite to "
            f"the deformation: the load channel is saturated (its converter or amplifier at the end of its range, "
            f"or its zero far off); test again with a load range that covers the test and the channel zeroed"
        )


#: Largest relative disagreement (of the column's range) between the stress (or strain) computed
#: from the raw channels and a derived column of the same file before a warning is given.
CROSS_CHECK_TOLERANCE = 0.01


def _cross_check(plan: _Plan, col_of: dict[str, np.ndarray], x: np.ndarray, stress: np.ndarray,
                 label: str, warnings: list[str]) -> dict[str, dict[str, Any]]:
    """Compare the raw-channel stretch and stress with the file's derived columns."""
    out: dict[str, dict[str, Any]] = {}
    for key, ours, what in (("x", x, plan.x_name), ("s", stress, "stress")):
        col = plan.checks.get(key)
        if col is None:
            continue
        v = col_of[f"check_{key}"]
        theirs, _ = _x_of(col.quantity, v) if key == "x" else _stress_of(col.quantity, v, x, plan.mode)
        scale = float(np.ptp(theirs)) or 1.0
        rel = float(np.max(np.abs(ours - theirs)) / scale)
        out[what] = {"column": col.index + 1, "header": col.header, "max_difference": rel}
        if rel > CROSS_CHECK_TOLERANCE:
            warnings.append(
                f"{col.where(label)}: the {what} computed from the raw channels and the geometry differs from "
                f"this column by up to {rel * 100:.1f} % of its range; check the specimen geometry"
            )
    return out


def _assemble(p: Path, label: str, layout: _Layout, md: M.Metadata, enc: str,
              warnings: list[str], rep: Reporter) -> TensileTest:
    cols = _columns(label, layout, md, warnings)
    by_q, notes = _by_quantity(cols, label)
    geo = M.geometry(md, label=label, decimal=_data_decimal(layout, cols, md, label))
    plan = _plan(label, layout, md, cols, by_q, geo)
    used = _used(plan)
    clock = _clock_columns(layout, list(used.values()))
    factors = {k: 1.0 if c.index in clock else _need_unit(c, label, md) for k, c in used.items()}
    order = list(used)
    decimal = _decimal(layout, [used[k] for k in order], md, label)
    arr = _parse(layout, [used[k] for k in order], decimal, label, clock=clock)
    col_of = {k: arr[:, i] * factors[k] for i, k in enumerate(order)}
    linenos = layout.data_linenos
    meta_extra: dict[str, Any] = {}
    time = _time(plan.t_col, col_of.get("time"), factors.get("time", 1.0), linenos, label,
                 layout=None if plan.t_col is None or plan.t_col.index in clock else layout, decimal=decimal,
                 warnings=warnings)
    if time is not None:
        meta_extra["time_start"] = float(col_of["time"][0])
        if plan.t_col.index in clock:
            first = _CLOCK.match(_split(layout.data_lines[0], layout.delimiter)[plan.t_col.index])
            meta_extra["time_format"] = "date and time" if first.group(1) else "hh:mm:ss"
    disp = col_of.get("displacement")
    if disp is not None and plan.d_col.absolute:
        meta_extra["displacement_start"] = float(disp[0])
        disp = disp - disp[0]
    force = col_of.get("force")
    x, x_from, stress, s_from = _stretch_and_stress(plan, col_of, disp, force, geo, linenos, label)
    _check_response(plan, x, stress, linenos, label)
    checks = _cross_check(plan, col_of, x, stress, label, warnings)
    for c in cols:
        if c.quantity is None and c.header:
            known = C.KNOWN_UNUSED.get(C.normalise_name(c.header))
            if known:
                notes.append(f"column {c.index + 1} '{c.header}' not used: {known}")
            else:
                warnings.append(f"{c.where(label)}: unknown column name, ignored")
    for w in warnings:
        rep.warn(w)
    metadata = _metadata(md, geo, plan, layout, cols, used, factors, enc, decimal, linenos, warnings)
    metadata.update(stretch_from=x_from, stress_from=s_from, raw=plan.x_col is None or plan.s_col is None,
                    n_rows=int(len(x)), cross_checks=checks, column_notes=notes, **meta_extra)
    x_c, s_c = plan.x_col or plan.d_col, plan.s_col or plan.f_col
    rep.step(  # the columns used and the conversions made (docs/reference/tensile-input.md: say which, say so)
        f"read {label}: {len(x)} rows, {plan.mode}; {plan.x_name} {np.min(x):.4g}..{np.max(x):.4g} from {x_from}, "
        f"column {x_c.index + 1} '{x_c.header or x_c.quantity}'; stress {np.min(stress):.4g}..{np.max(stress):.4g} "
        f"Pa from {s_from}, column {s_c.index + 1} '{s_c.header or s_c.quantity}'"
    )
    return TensileTest(
        source=p,
        mode=plan.mode,
        stretch=np.ascontiguousarray(x, dtype=np.float64),
        stress=np.ascontiguousarray(stress, dtype=np.float64),
        time=time,
        displacement=disp,
        force=force,
        metadata=metadata,
    )


def _metadata(md: M.Metadata, geo: M.Geometry, plan: _Plan, layout: _Layout, cols: list[_Column],
              used: dict[str, _Column], factors: dict[str, float], enc: str, decimal: str,
              linenos: list[int], warnings: list[str]) -> dict[str, Any]:
    """The metadata record of docs/reference/tensile-input.md (without the figures of the numbers)."""

    def text(key):
        e = md.get(key)
        return None if e is None else M.text_value(e)

    orient = orient_rad = None
    if md.get("orientation") is not None:
        orient, orient_rad = M.orientation_value(md.get("orientation"))
    return {
        "specimen": text("specimen"),
        "gauge_length": geo.gauge_length,
        "area": geo.area,
        "width": geo.width,
        "thickness": geo.thickness,
        "diameter": geo.diameter,
        "area_from": geo.area_from,
        "orientation": orient,
        "orientation_rad": orient_rad,
        "tissue": text("tissue"),
        "temperature": text("temperature"),
        "notes": text("notes"),
        "mode": plan.mode,
        "mode_from": plan.mode_from,
        "encoding": enc,
        "delimiter": "whitespace" if layout.delimiter == WHITESPACE else layout.delimiter,
        "decimal": decimal,
        "columns": [c.quantity or C.IGNORE for c in cols],
        "units": [c.unit or "" for c in cols],
        "headers": [c.header for c in cols],
        "used_columns": {
            c.quantity: {"index": c.index + 1, "header": c.header, "unit": c.unit or "", "factor": factors[k]}
            for k, c in used.items() if not k.startswith("check_")
        },
        "header_row": layout.header[0] if layout.header else None,
        "units_row": layout.units_row[0] if layout.units_row else None,
        "first_data_row": linenos[0],
        "last_data_row": linenos[-1],
        "sidecar": str(md.sidecar) if md.sidecar else None,
        "sources": {k: md.source(k) for k in md.entries},
        "extra": dict(md.extra),
        "preamble": layout.preamble,
        "trailer": [text.strip() for _, text in layout.trailer],
        "warnings": list(warnings),
    }
