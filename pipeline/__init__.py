"""esmm.pipeline: the library behind the ``esmm`` command.

The library never prints, exits or reads ``sys.argv``; the command-line layer
(:mod:`esmm.cli`) turns its exceptions (:mod:`esmm.pipeline.errors`) into
one-line messages and exit codes.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("esmm")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = ["__version__"]
