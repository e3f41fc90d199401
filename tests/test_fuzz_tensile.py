"""Fuzzing the tensile reader (esmm.pipeline.tensile.read) and ``esmm calibrate`` on bad files.

Property: whatever the bytes, the sidecar or the command-line metadata, the
reader either returns a test with finite values or raises an EsmmError with a
one-line message, and the CLI exits non-zero with ``esmm: error: ...`` and no
traceback. Each input runs in a sandbox process, so a crash (even a segfault)
is recorded as such instead of ending the test session.

Budget: ESMM_FUZZ_EXAMPLES=<n> sets max_examples of every test (default: a
CI-sized number); ESMM_FUZZ_REPORT=<file.jsonl> appends the counts.
"""

from __future__ import annotations

import codecs
import json
import sys
from pathlib import Path

import cloudpickle
import pytest
from fuzzkit import Campaign, crash_of, fuzz
from hypothesis import given, note
from hypothesis import strategies as st

cloudpickle.register_pickle_by_value(sys.modules[__name__])

DATA = Path(__file__).resolve().parent.parent / "data" / "tensile"
REAL = sorted(p for p in DATA.glob("*/*.csv") if p.stat().st_size < 40_000)

#: Known crashes, reported to the reader's owner (each had an xfail regression test below).
#: fixed: non-text codecs named by an encoding statement (regression test below)
CAMPAIGN = Campaign("tensile", known=[])


@pytest.fixture(scope="module")
def sandbox():
    yield from CAMPAIGN.sandbox()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz-tensile")


# ----------------------------------------------------------------------------- sandboxed probes
def probe_read(path: str, kwargs: dict) -> dict:
    import numpy as np
    from esmm.pipeline.errors import EsmmError
    from esmm.pipeline.tensile import read

    try:
        t = read(path, **kwargs)
    except EsmmError as exc:
        return {"outcome": "refused", "type": type(exc).__name__, "message": str(exc), "exit": exc.exit_code}
    except Exception as exc:  # noqa: BLE001 - that is what we are looking for
        return crash_of(exc)
    arrays = [t.stretch, t.stress] + [a for a in (t.time, t.force, t.displacement) if a is not None]
    return {"outcome": "accepted", "n": int(t.n), "finite": all(bool(np.all(np.isfinite(a))) for a in arrays),
            "mode": t.mode}


def check(sandbox, path: Path, kwargs: dict | None = None, *, cli_extra: list[str] | None = None,
          label: str = "") -> str:
    """Read *path* in the sandbox, apply the property, return the outcome."""
    kwargs = kwargs or {}
    case = {"input": label, "file": path.name, "size": path.stat().st_size if path.exists() else -1}
    value = CAMPAIGN.run(sandbox, probe_read, str(path), kwargs, case=case, timeout=120)
    if value is None:
        return "known-crash"
    if value["outcome"] == "accepted":
        CAMPAIGN.stats["accepted"] += 1
        assert value["n"] >= 1 and value["finite"], f"accepted with non-finite or no samples: {value}"
        return "accepted"
    CAMPAIGN.refused(value["message"], exit_code=value["exit"])
    # The CLI: non-zero, the same one line, no traceback.
    CAMPAIGN.cli_fails_cleanly(sandbox, ["calibrate", str(path), *(cli_extra or [])])
    return "refused"


def write(workdir: Path, data: bytes, suffix: str = ".csv") -> Path:
    p = CAMPAIGN.folder(workdir, "c") / f"test{suffix}"
    p.write_bytes(data)
    return p


# ----------------------------------------------------------------------------- strategies
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-10, max_value=10),
    st.sampled_from([0.0, -0.0, 1e-320, 5e-324, 1.7976931348623157e308, -1e308, 1e-300]),
    st.integers(min_value=-(10**30), max_value=10**30),
)


def fmt_number(draw, x) -> str:
    style = draw(st.sampled_from(["repr", "g", "e", "comma", "quoted", "spaces", "pct"]))
    s = repr(x) if style == "repr" else f"{x:g}" if style == "g" else f"{x:e}" if style == "e" else str(x)
    if style == "comma":
        s = s.replace(".", ",")
    elif style == "quoted":
        s = f'"{s}"'
    elif style == "spaces":
        s = f"  {s} "
    elif style == "pct":
        s += "%"
    return s


NAMES = ["time", "t", "displacement", "extension", "position", "force", "load", "stretch", "lambda", "strain",
         "stress", "nominal stress", "engineering stress", "shear strain", "gamma", "shear stress", "Zeit",
         "时间", "位移", "力", "temperature", "", "x", "stress stress"]
UNITS = ["s", "ms", "min", "mm", "m", "um", "µm", "N", "kN", "mN", "kPa", "MPa", "Pa", "%", "", "furlong", "mPa",
         "N/mm2", "MN/m2", "kgf", "in", "lbf", "psi", "1", "-", "mm/mm"]
META_KEYS = ["specimen", "mode", "gauge_length", "area", "width", "thickness", "orientation", "encoding",
             "delimiter", "temperature", "tissue", "columns", "units", "notes", "colour", "decimal"]
META_VALUES = ["30 mm", "0 mm", "-1 mm", "nan mm", "1e999 mm", "inf mm", "22 mm2", "30", "abc", "", "uniaxial",
               "equibiaxial", "pure_shear", "simple_shear", "sideways", "x", "y", "q", "30 deg", "1e308 deg",
               "utf-8", "gbk", "latin-1", "utf-16", "klingon", ";", "tab", "time, displacement, force",
               "s, mm, N", "s, mm", "a" * 300, "\t", "0.0001 um"]


@st.composite
def csv_files(draw) -> tuple[bytes, str]:
    """A CSV-like tensile export with random (often broken) metadata, header, units and numbers."""
    lines: list[str] = []
    for _ in range(draw(st.integers(0, 4))):
        k = draw(st.sampled_from(META_KEYS))
        v = draw(st.one_of(st.sampled_from(META_VALUES), st.text(max_size=12)))
        lines.append(f"# {k}: {v}")
    ncol = draw(st.integers(1, 4))
    delim = draw(st.sampled_from([",", ";", "\t", "|", " "]))
    bracket = draw(st.sampled_from(["[{}]", "({})", " {}", "", "[{}"]))
    names = [draw(st.sampled_from(NAMES)) for _ in range(ncol)]
    units = [draw(st.sampled_from(UNITS)) for _ in range(ncol)]
    units_row = draw(st.booleans())
    if units_row:
        lines.append(delim.join(names))
        lines.append(delim.join(f"({u})" if u else "" for u in units))
    else:
        lines.append(delim.join(f"{n} {bracket.format(u)}".strip() if u else n for n, u in zip(names, units)))
    for _ in range(draw(st.integers(0, 25))):
        width = draw(st.sampled_from([ncol, ncol, ncol, ncol - 1, ncol + 1]))
        cells = [fmt_number(draw, draw(NUMBERS)) if draw(st.integers(0, 20)) else draw(st.sampled_from(
            ["", "abc", "NaN", "-", "1.2.3", "1e", "--5", "0x1F", "∞"])) for _ in range(max(width, 0))]
        lines.append(delim.join(cells))
    eol = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    text = eol.join(lines) + draw(st.sampled_from([eol, "", eol + "\x1a"]))
    enc = draw(st.sampled_from(["utf-8", "utf-8", "utf-8-sig", "utf-16", "utf-16-le", "latin-1", "gbk", "cp1252",
                                "utf-32", "shift_jis"]))
    data = text.encode(enc, errors="replace")
    return data, enc


REAL_BYTES = [p.read_bytes() for p in REAL]
TOKENS = [b"nan", b"inf", b"-1e308", b"1e400", b",", b";", b"\t", b"\n", b"\r", b"#", b'"', b" [kPa]", b"\x00",
          b"# mode: simple_shear\n", b"# gauge_length: 0 mm\n", b"# area: -1 mm2\n", b"# encoding: utf-16\n",
          b"\xef\xbb\xbf", b"\xff\xfe", b"\xc3", b"\xe6\x97\xb6", b"1e-320", b"# columns: time, force\n",
          b"# orientation: 1e999 deg\n", b"# specimen:\n", b"\x1a"]


@st.composite
def mutated_real(draw) -> bytes:
    b = bytearray(draw(st.sampled_from(REAL_BYTES)))
    for _ in range(draw(st.integers(1, 5))):
        op = draw(st.integers(0, 6))
        n = len(b)
        if op == 0:
            b = b[: draw(st.integers(0, n))]
        elif op == 1 and n:
            b[draw(st.integers(0, n - 1))] = draw(st.integers(0, 255))
        elif op == 2:
            i = draw(st.integers(0, n))
            b[i:i] = draw(st.sampled_from(TOKENS))
        elif op == 3 and n:
            i = draw(st.integers(0, n - 1))
            del b[i: i + draw(st.integers(1, 80))]
        elif op == 4:
            lines = bytes(b).split(b"\n")
            lines = draw(st.permutations(lines)) if len(lines) < 60 else lines[::-1]
            b = bytearray(b"\n".join(lines))
        elif op == 5:
            i = draw(st.integers(0, n))
            b[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif op == 6:
            codec = draw(st.sampled_from(["utf-16", "utf-32", "latin-1", "gbk", "cp1252", "utf-16-be"]))
            b = bytearray(bytes(b).decode("utf-8", "replace").encode(codec, "replace"))
    return bytes(b)


# ----------------------------------------------------------------------------- properties
@fuzz(150)
@given(data=st.binary(max_size=600))
def test_arbitrary_bytes(sandbox, workdir, data):
    check(sandbox, write(workdir, data), label=f"bytes {data[:60]!r}")


@fuzz(150)
@given(case=csv_files())
def test_generated_exports(sandbox, workdir, case):
    data, enc = case
    note(f"encoding {enc}: {data[:300]!r}")
    check(sandbox, write(workdir, data), label=f"generated ({enc})")


@fuzz(150)
@given(data=mutated_real())
def test_mutated_real_files(sandbox, workdir, data):
    note(repr(data[:300]))
    check(sandbox, write(workdir, data), label="mutated real file")


SIDE_VALUES = st.one_of(st.sampled_from(META_VALUES).map(json.dumps), st.integers().map(str),
                        st.floats(allow_nan=False).map(repr), st.just("[1, 2]"), st.just("{a = 1}"),
                        st.just("true"), st.just('["time", "displacement", "force"]'), st.just('["s", "mm", "N"]'),
                        st.just('"""\nmulti\nline"""'), st.just("nan"), st.just("inf"), st.just("= ="),
                        st.text(max_size=10))


@fuzz(120)
@given(pairs=st.lists(st.tuples(st.sampled_from([*META_KEYS, "gauge length", "Area", "", "a.b"]), SIDE_VALUES),
                      max_size=5),
       raw=st.booleans())
def test_sidecars(sandbox, workdir, pairs, raw):
    body = ("time [s],displacement [mm],force [N]\n0,0,0\n1,0.5,0.2\n2,1.0,0.5\n" if raw
            else "stretch,stress [kPa]\n1,0\n1.1,1\n1.2,2.5\n")
    p = write(workdir, body.encode())
    side = "\n".join(f"{k} = {v}" if k else f"= {v}" for k, v in pairs)
    p.with_suffix(".toml").write_text(side, encoding="utf-8")
    note(side)
    check(sandbox, p, label=f"sidecar {side[:100]!r}")


OVERRIDE_VALUES = st.one_of(st.sampled_from(META_VALUES), st.text(max_size=8), st.integers(), st.floats(),
                            st.lists(st.sampled_from(["time", "displacement", "force", "s", "mm", "N", "", "x"]),
                                     max_size=4), st.none(), st.booleans())


@fuzz(120)
@given(over=st.dictionaries(st.sampled_from([*META_KEYS, "Gauge-Length", "bogus"]), OVERRIDE_VALUES, max_size=4),
       enc=st.one_of(st.none(), st.sampled_from(["utf-8", "gbk", "klingon", "utf-16", "latin-1", ""])))
def test_command_line_metadata(sandbox, workdir, over, enc):
    p = write(workdir, b"time [s],displacement [mm],force [N]\n0,0,0\n1,0.5,0.2\n2,1.0,0.5\n")
    note(f"overrides {over!r} encoding {enc!r}")
    value = CAMPAIGN.run(sandbox, probe_read, str(p), {"overrides": over, "encoding": enc},
                         case={"input": f"overrides {over!r}"}, timeout=60)
    assert value is not None, "a known crash with command-line metadata"
    if value["outcome"] == "accepted":
        CAMPAIGN.stats["accepted"] += 1
        assert value["finite"]
    else:
        CAMPAIGN.refused(value["message"], exit_code=value["exit"])
        assert value["type"] in ("ConfigError", "InputError")


# ----------------------------------------------------------------------------- known crashes (regressions)
@pytest.mark.parametrize("codec", ["hex", "zlib", "bz2", "uu", "quopri", "punycode", "undefined"])
def test_known_crash_non_text_codec(tmp_path, codec):
    from esmm.pipeline.errors import EsmmError
    from esmm.pipeline.tensile import read

    assert codecs.lookup(codec)  # a real codec, but not a text encoding (or one that cannot decode)
    p = tmp_path / "t.csv"
    p.write_text(f"# encoding: {codec}\nstretch,stress [kPa]\n1,0\n1.1,1\n")
    with pytest.raises(EsmmError):
        read(p)
