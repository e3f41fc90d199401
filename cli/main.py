"""The ``esmm`` command: thin subcommands over :mod:`esmm.pipeline`.

``main(argv)`` parses, dispatches and turns library exceptions into a one-line
message on stderr and an exit code; it never raises for a user error.

Exit codes
----------
0 success; 1 unexpected internal error (a bug: please report it with the log);
2 bad input or configuration; 3 fit/meshing/simulation failed; 4 a quality floor
was not met (``--force`` overrides); 5 a batch finished with failures;
130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
from collections.abc import Sequence

from esmm.pipeline import __version__, interrupts
from esmm.pipeline.errors import EsmmError

#: subcommand -> module in esmm.cli implementing ``add_parser(sub)`` and ``run(args, ui)``.
COMMANDS: dict[str, str] = {
    "calibrate": "esmm.cli.calibrate",
    "evaluate": "esmm.cli.evaluate",
    "prepare": "esmm.cli.prepare",
    "info": "esmm.cli.info",
    "tables": "esmm.cli.tables",
    "simulate": "esmm.cli.simulate",
    "validate": "esmm.cli.validate",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="esmm",
        description=(
            "Equivalent Spring-Mass Model pipeline: fit the ESEDF tissue model to tensile "
            "data (calibrate), turn an organ surface into a spring-network asset (prepare), "
            "and replay it in real time (simulate)."
        ),
        epilog="Run 'esmm COMMAND --help' for the options of each command.",
    )
    parser.add_argument("--version", action="version", version=f"esmm {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="count", default=0, help="more detail")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="only errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in COMMANDS.values():
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue  # command not implemented in this build
            raise
        mod.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run esmm with *argv* (default: ``sys.argv[1:]``) and return the exit code."""
    from esmm.cli.ui import UI

    interrupts.install()  # a Ctrl-C during a lazy import of VTK would crash the process
    parser = build_parser()
    try:
        args = parser.parse_args(list(argv) if argv is not None else None)
    except SystemExit as exc:  # argparse: --help, --version or a usage error
        return int(exc.code or 0)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    ui = UI(verbosity=-1 if args.quiet else args.verbose)
    args._argv = list(argv) if argv is not None else sys.argv[1:]
    try:
        return int(args.func(args, ui) or 0)
    except EsmmError as exc:
        ui.error(flag_message(exc, parser, args.command))
        return exc.exit_code
    except KeyboardInterrupt:
        ui.error("interrupted; no partial output was left behind")
        return 130
    except MemoryError:
        ui.error("out of memory; try a coarser target (--size / --nodes) or fewer files at once")
        return 1
    except BrokenPipeError:  # the reader of the output went away (esmm ... | head): not esmm's error
        return 141
    except OSError as exc:   # the system refused a read or write: disk full, permissions, I/O
        where = f" ({exc.filename})" if exc.filename else ""
        ui.error(f"the system refused a read or write{where}: {exc.strerror or exc}; free space or choose a "
                 f"place that can be written, and run the command again")
        return 1


def _flush_stdout(code: int) -> int:
    """Flush standard output now and return the exit code. If it cannot be written (a closed pipe, a
    full disk), say so (a full disk: the output is lost, exit 1; a closed pipe: its reader left, 141)
    and point it at the null device, so that the interpreter's own last flush does not fail again."""
    try:
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        code = code or 141
    except OSError as exc:
        with contextlib.suppress(OSError):
            sys.stderr.write(f"esmm: error: the output could not be written: {exc.strerror or exc}; free space "
                             f"or send it elsewhere, and run the command again\n")
        code = code or 1
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return code


def flag_message(exc: EsmmError, parser: argparse.ArgumentParser, command: str) -> str:
    """The error's message, its leading library parameter name replaced by the command's flag.

    ``nodes: expected a whole number >= 10`` becomes ``--nodes: ...`` when the
    command has a ``--nodes`` option (an argparse ``dest`` equal to the parameter).
    """
    from esmm.pipeline.tensile.metadata import MissingMetadataError

    msg = str(exc)
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    cmd = sub.choices.get(command) if sub is not None else None

    def flag_of(name: str) -> str | None:
        for action in cmd._actions if cmd is not None else ():
            if action.dest == name and action.option_strings:
                return max(action.option_strings, key=len)
        return None

    if isinstance(exc, MissingMetadataError):  # every missing key: its option beside its sidecar key
        return exc.text(flag_of)
    param = getattr(exc, "parameter", None)
    if not param or not msg.startswith(f"{param}:"):
        return msg
    flag = flag_of(param)
    return msg if flag is None else flag + msg[len(param):]


def run() -> None:  # console-script entry point
    try:
        code = main()
    except KeyboardInterrupt:  # between the command's end and here
        code = 130
    code = _flush_stdout(code)
    # The work is done and written: a Ctrl-C during the interpreter's shutdown must not turn
    # the exit status into "killed by SIGINT".
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
