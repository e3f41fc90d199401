"""esmm.pipeline: the library behind the ``esmm`` command.

The library never prints, exits or reads ``sys.argv``; the command-line layer
(:mod:`esmm.cli`) turns its exceptions (:mod:`esmm.pipeline.errors`) into
one-line messages and exit codes.
"""

import functools
import re
from importlib import metadata

try:
    __version__ = metadata.version("esmm")
except metadata.PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

_REQUIREMENT_NAME = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)")


@functools.lru_cache(maxsize=1)
def distributions() -> tuple[str, ...]:
    """esmm and the distributions it requires, from its installed metadata (extras left out).

    The one list of the software that makes esmm's results (its home is pyproject.toml's
    ``dependencies``): their versions are recorded in every asset
    (:func:`esmm.pipeline.asset.provenance.package_versions`) and enter the batch cache
    key (:func:`esmm.pipeline.batch.jobs.code_version`).
    """
    names = ["esmm"]
    try:
        requires = metadata.requires("esmm") or []
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare source tree
        requires = []
    for req in requires:
        requirement, _, marker = req.partition(";")
        m = _REQUIREMENT_NAME.match(requirement)
        if m and "extra" not in marker and m.group(1) not in names:
            names.append(m.group(1))
    return tuple(names)


__all__ = ["__version__", "distributions"]
