"""Every command of the README's shell blocks runs.

The README's ``bash`` blocks are read as written (continuation lines joined,
comments dropped). The commands it shows for the user's own machine are not
run here, each for its stated reason (:data:`NOT_RUN`); every other command is
an ``esmm`` command. The fast test parses each with esmm's own argument parser;
the slow one runs every block, in order, in a temporary folder beside a link to
the repository's bundled ``data/`` (blocks run two at a time: they do not
depend on each other), and requires exit status 0 of each command.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
#: Command prefix -> why the command is not run by this test.
NOT_RUN = {
    "make demo": "runs every stage on the bundled data; the examples below it run the same stages",
    "make test": "is the test suite this test belongs to",
    "sudo apt-get": "installs system packages (needs root; CI's machine has them)",
}
#: A hang guard per command, generous for a loaded two-core machine (not a speed goal).
HANG_GUARD_S = 3600


def shell_blocks(text: str) -> list[list[str]]:
    """The commands of each ``bash``/``sh``/``shell`` block: continuation lines joined, comments dropped."""
    blocks = []
    for body in re.findall(r"^```(?:bash|sh|shell)\n(.*?)^```", text, flags=re.S | re.M):
        joined = re.sub(r"\\\n\s*", " ", body)
        cmds = []
        for line in joined.splitlines():
            cmd = line.split(" #", 1)[0].strip() if not line.lstrip().startswith("#") else ""
            if cmd:
                cmds.append(cmd)
        blocks.append(cmds)
    return blocks


def runnable(blocks: list[list[str]]) -> list[list[str]]:
    """The blocks without the commands of :data:`NOT_RUN` (blocks left empty dropped)."""
    out = [[c for c in b if not any(c.startswith(p) for p in NOT_RUN)] for b in blocks]
    return [b for b in out if b]


BLOCKS = shell_blocks(README.read_text(encoding="utf-8"))


def test_the_readme_has_commands_and_every_skip_is_listed():
    skipped = {p for b in BLOCKS for c in b for p in NOT_RUN if c.startswith(p)}
    assert skipped == set(NOT_RUN), f"NOT_RUN lists commands the README no longer shows: {set(NOT_RUN) - skipped}"
    assert sum(len(b) for b in runnable(BLOCKS)) >= 5


@pytest.mark.parametrize("cmd", [c for b in runnable(BLOCKS) for c in b])
def test_each_command_parses(cmd):
    from esmm.cli.main import build_parser

    argv = shlex.split(cmd)
    assert argv[0] == "esmm", f"README command {cmd!r}: only esmm commands are run here (or list it in NOT_RUN)"
    try:
        build_parser().parse_args(argv[1:])
    except SystemExit as exc:
        pytest.fail(f"README command {cmd!r}: esmm refuses its options (exit {exc.code})")


def _run_block(cmds: list[str], cwd: Path, env: dict) -> list[str]:
    """Run *cmds* in order; the failures (command, status, the end of its output)."""
    for cmd in cmds:
        p = subprocess.run(cmd, shell=True, executable="/bin/bash", cwd=cwd, env=env, capture_output=True,
                           text=True, timeout=HANG_GUARD_S)
        if p.returncode != 0:
            return [f"{cmd!r} exited {p.returncode}:\n{(p.stdout + p.stderr)[-3000:]}"]
    return []


@pytest.mark.slow
def test_every_readme_command_runs(tmp_path):
    bin_dir = Path(sys.executable).parent
    assert (bin_dir / "esmm").is_file(), f"no esmm beside {sys.executable}: run the tests from the venv"
    (tmp_path / "data").symlink_to(REPO / "data", target_is_directory=True)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    with ThreadPoolExecutor(max_workers=2) as pool:
        failures = [f for fs in pool.map(lambda b: _run_block(b, tmp_path, env), runnable(BLOCKS)) for f in fs]
    assert not failures, "README commands failed:\n" + "\n".join(failures)
