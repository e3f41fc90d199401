"""The harness the fuzz tests share (tests/test_fuzz_*.py): one copy of the machinery.

A fuzz module states its *property* (what a reader must do with any input) and
its input strategies; this module holds what they have in common:

* :func:`fuzz` — hypothesis settings with the budget ``ESMM_FUZZ_EXAMPLES=<n>``
  (default: each test's CI-sized number, with the examples derandomized so that
  ``make test`` tries the same inputs every time; a run with a budget explores
  new random inputs, and what it finds becomes a regression test);
* :class:`Campaign` — one per module: runs probes in a :class:`Sandbox`
  process (a segfault or a hang is recorded, not fatal), tells known crashes
  from new ones (a new one fails the test), counts outcomes, checks refusals are
  one line and that the CLI fails cleanly, and appends the counts to
  ``ESMM_FUZZ_REPORT=<file.jsonl>`` at the end;
* :func:`probe_cli` — ``esmm`` run in-process, its stderr captured.

The probes run in another process: this module and the calling test module are
pickled by value (cloudpickle), as neither is importable there.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import os
import sys
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest
from esmm.pipeline.batch.local import Sandbox
from hypothesis import HealthCheck, note, settings

cloudpickle.register_pickle_by_value(sys.modules[__name__])

EXAMPLES = int(os.environ.get("ESMM_FUZZ_EXAMPLES", "0") or 0)


def fuzz(default: int):
    """Hypothesis settings: *default* examples unless ESMM_FUZZ_EXAMPLES says otherwise; no deadline.

    Derandomized at the default budget: the suite must decide the same way on every run
    (a random new finding in CI would block work that did not cause it).
    """
    return settings(max_examples=EXAMPLES or default, deadline=None, database=None, derandomize=not EXAMPLES,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


def probe_cli(argv: list[str]) -> dict:
    """Run ``esmm ARGV`` in this process; its exit code and stderr (or what it raised)."""
    from esmm.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except BaseException as exc:  # noqa: BLE001 - a raise out of main is what we look for
            return {"code": None, "stderr": err.getvalue(), "raised": f"{type(exc).__name__}: {exc}"}
    return {"code": code, "stderr": err.getvalue()}


def crash_of(exc: BaseException, **extra) -> dict:
    """A probe's crash record: exception type, message and the innermost frame."""
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    return {"outcome": "crash", **extra, "type": type(exc).__name__, "message": str(exc)[:300],
            "where": f"{Path(frame.filename).name}:{frame.lineno}" if frame else ""}


class Campaign:
    """The fuzzing of one reader: sandbox, counts, crash records.

    Parameters
    ----------
    reader : str
        Its name in the report (``"mesh"``, ``"tensile"``, ``"asset"``).
    known : list of (name, predicate)
        Crashes reported to the reader's owner: a crash record matching a
        predicate is counted as known and does not fail the test.
    """

    def __init__(self, reader: str, known: list[tuple[str, Callable[[dict], bool]]] | None = None):
        self.reader = reader
        self.known = list(known or [])
        self.stats: Counter = Counter()
        self.crashes: list[dict] = []
        self._counter = itertools.count()

    def sandbox(self) -> Iterator[Sandbox]:
        """Body of a module-scoped ``sandbox`` fixture (``yield from campaign.sandbox()``)."""
        with Sandbox() as sb:
            yield sb
        report = os.environ.get("ESMM_FUZZ_REPORT")
        if report:
            with open(report, "a", encoding="utf-8") as fh:
                fh.write(json.dumps({"reader": self.reader, **self.stats,
                                     "crash_samples": self.crashes[:20]}) + "\n")

    def folder(self, workdir: Path, prefix: str) -> Path:
        """A new empty folder under *workdir* for one input."""
        d = workdir / f"{prefix}{next(self._counter)}"
        d.mkdir()
        return d

    def run(self, sandbox: Sandbox, probe: Callable, *args: Any, case: dict, timeout: float) -> dict | None:
        """Run *probe* in the sandbox: its result, or None for a known crash.

        A new crash (an exception the probe reports as ``outcome == "crash"``, an
        error, a dead or hung worker) fails the test with its record.
        """
        self.stats["tried"] += 1
        kind, value = sandbox.call(probe, *args, timeout=timeout)
        if kind == "result" and value.get("outcome") != "crash":
            return value
        if kind == "died":
            c = {**case, "type": "died", "message": value[0], "where": value[1][-400:]}
        elif kind == "error":
            c = {**case, "type": "error", "message": value.strip().splitlines()[-1], "where": ""}
        else:
            c = {**case, **{k: value.get(k, "") for k in ("fn", "type", "message", "where")}}
        known = next((name for name, pred in self.known if pred(c)), None)
        self.stats["crashes_known" if known else "crashes_new"] += 1
        self.crashes.append({**c, "known": known})
        note(f"crash record: {c}")
        if known:
            return None
        where = f"{c['fn']}: " if c.get("fn") else ""
        pytest.fail(f"{self.reader} reader crash: {where}{c['type']}: {c['message']} at {c['where']} "
                    f"(input {case.get('input', '')})")

    def refused(self, message: str, *, exit_code: int, expected_exit: int = 2, max_len: int = 800) -> None:
        """A refusal is one line, not too long, with the input-error exit code."""
        self.stats["refused"] += 1
        assert message and "\n" not in message and "\r" not in message, repr(message)
        assert len(message) <= max_len, f"message of {len(message)} characters"
        assert exit_code == expected_exit, (exit_code, message)

    def cli_fails_cleanly(self, sandbox: Sandbox, argv: list[str], *, codes=(2,), timeout: float = 120) -> list[str]:
        """``esmm ARGV`` exits with one of *codes*, ``esmm: error: ...`` last, no traceback; its stderr lines."""
        kind, r = sandbox.call(probe_cli, argv, timeout=timeout)
        assert kind == "result", f"CLI crashed: {(kind, r)}"
        assert r.get("raised") is None, f"CLI raised {r['raised']}"
        assert r["code"] in codes and "Traceback" not in r["stderr"], r
        lines = [ln for ln in r["stderr"].splitlines() if ln.strip()]
        assert lines and lines[-1].startswith("esmm: error: "), lines[-3:]
        self.stats["cli_checked"] += 1
        return lines
