"""The exceptions of esmm.

Every error a user can cause is an :class:`EsmmError` whose message is one line
that says *what* is wrong, *where* (file, row, column, parameter) and *what to
do*. The CLI prints ``esmm: error: <message>`` and exits with :attr:`exit_code`.
"""

from __future__ import annotations


class EsmmError(Exception):
    """Base class: a user-facing failure with a one-line message."""

    exit_code = 1

    def __init__(self, message: str, *, parameter: str | None = None):
        # Keep messages on one line whatever the caller passed.
        super().__init__(" ".join(str(message).split()))
        #: The library parameter the message is about (it starts the message), or None.
        #: The CLI replaces it by the command-line flag that sets it, where there is one.
        self.parameter = parameter


class InputError(EsmmError):
    """An input file cannot be used as it is (bad format, units, values)."""

    exit_code = 2


class ConfigError(EsmmError):
    """A configuration file or command-line option is invalid."""

    exit_code = 2


class FitError(EsmmError):
    """A fit could not be carried out (no data, no convergence)."""

    exit_code = 3


class MeshingError(EsmmError):
    """Surface repair or volume meshing failed on every path tried."""

    exit_code = 3


class QualityError(EsmmError):
    """A result is below a documented quality floor (override with --force)."""

    exit_code = 4


class AssetError(EsmmError):
    """An asset file is missing, truncated, tampered with or of another schema."""

    exit_code = 2


class SimulationError(EsmmError):
    """The simulation cannot run (unstable, bad scene)."""

    exit_code = 3
