"""Ctrl-C held back while an import runs (esmm.pipeline.interrupts), checked in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys
import textwrap

# The imported module signals its own process half-way through its body: without the guard the
# KeyboardInterrupt lands inside the module (the half-initialised state that made VTK segfault);
# with it, the module finishes and the interrupt is raised right after the import statement.
MODULE = textwrap.dedent("""
    import os, signal
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(200000):
        pass
    COMPLETE = True
""")

DRIVER = textwrap.dedent("""
    import signal, sys
    # Python's own Ctrl-C handler, whatever this process inherited (a shell's background job
    # starts with SIGINT ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sys.path.insert(0, sys.argv[1])
    if sys.argv[2] == "guarded":
        from esmm.pipeline import interrupts
        interrupts.install()
    try:
        import halfway
        print("no interrupt")
    except KeyboardInterrupt:
        print("interrupted; module complete:", getattr(sys.modules.get("halfway"), "COMPLETE", False))
""")


def _run(tmp_path, mode: str) -> str:
    (tmp_path / "halfway.py").write_text(MODULE)
    res = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path), mode], capture_output=True, text=True,
                         timeout=120)
    return res.stdout.strip()


def test_an_interrupt_during_an_import_is_raised_after_it(tmp_path):
    assert _run(tmp_path, "guarded") == "interrupted; module complete: True"


def test_without_the_guard_the_import_is_cut_short(tmp_path):
    """The hazard the guard exists for (if this passes, Python changed and the guard may go)."""
    assert _run(tmp_path, "plain") == "interrupted; module complete: False"
