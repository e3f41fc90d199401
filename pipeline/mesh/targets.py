"""How fine a tetrahedral mesh is asked for: one rule, and the conversions between targets.

A mesh is asked for by at most one of

* ``size``: the target tetrahedron edge [m];
* ``nodes``: a node count (at least :data:`MIN_NODES`); the size is found from
  the node-count model :func:`expected_nodes` (fitted on gmsh meshes of organs)
  and corrected once if the mesh is more than :data:`NODES_TOLERANCE` off;
* ``elements``: a tetrahedron count; the size is found from the volume
  (:func:`size_for_elements`) and corrected once if the mesh is more than
  :data:`ELEMENTS_TOLERANCE` off;

and by :data:`DEFAULT_NODES` nodes when none is given. The reasons for the
constants are in docs/guide/prepare.md ("Tetrahedra").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..checks import number
from ..errors import ConfigError

#: Fewest nodes a target may ask for (a handful of tetrahedra is not an organ).
MIN_NODES = 10
#: Node count aimed at when no target is given.
DEFAULT_NODES = 5000
#: Node-count model N = a V / h^3 + b A / h^2 (interior + surface nodes), fitted on gmsh
#: Delaunay meshes of three livers at 1 200-18 000 nodes (docs/guide/prepare.md); within ~25 %.
NODES_A, NODES_B = 0.387, 2.44
#: Relative node-count error that triggers one re-run with a corrected size.
NODES_TOLERANCE = 0.25
#: Ratio of the mesher's mean tet volume to that of a regular tet whose edge is the
#: requested size. Measured 1.39-1.42 on gmsh cubes, 0.92 on the bundled InVesalius
#: liver and 0.73 on the SOFA liver (surface detail adds tets); 1 is the middle.
MESHER_VOLUME_RATIO = 1.0
#: Relative miss of the tet count beyond which an ``elements`` target is remeshed once.
ELEMENTS_TOLERANCE = 0.2


@dataclass(frozen=True)
class MeshTarget:
    """At most one of a size [m], a node count or a tetrahedron count (all None: the default).

    Build it with :func:`mesh_target`, which checks the rule.
    """

    size: float | None = None
    nodes: int | None = None
    elements: int | None = None

    def given(self) -> list[str]:
        """The names of the targets set."""
        return [k for k in ("size", "nodes", "elements") if getattr(self, k) is not None]


def mesh_target(*, size=None, nodes=None, elements=None, names: Mapping[str, str] | None = None,
                where: str = "") -> MeshTarget:
    """A checked :class:`MeshTarget`.

    Parameters
    ----------
    size : float, optional
        Tetrahedron edge [m], positive.
    nodes : int, optional
        At least :data:`MIN_NODES`.
    elements : int, optional
        At least 1.
    names : mapping, optional
        The parameter name of each target in messages (default: ``size``,
        ``nodes``, ``elements``; e.g. ``[mesh] nodes`` for a config key).
    where : str
        Where the targets were given, for the message about giving several.

    Raises
    ------
    ConfigError
        More than one target, or a target out of range (naming the parameter).
    """
    names = {k: (names or {}).get(k, k) for k in ("size", "nodes", "elements")}
    given = [k for k, v in (("size", size), ("nodes", nodes), ("elements", elements)) if v is not None]
    if len(given) > 1:
        prefix = f"{where}: " if where else ""
        raise ConfigError(f"{prefix}give one of size, nodes or elements, not several ({' and '.join(given)})",
                          parameter=names[given[0]])
    return MeshTarget(
        size=None if size is None else number(size, names["size"], lo=0.0, lo_open=True),
        nodes=None if nodes is None else number(nodes, names["nodes"], lo=MIN_NODES, integer=True),
        elements=None if elements is None else number(elements, names["elements"], lo=1, integer=True),
    )


def expected_nodes(volume: float, area: float, h: float) -> float:
    """Node count a gmsh mesh of element size *h* [m] is expected to have."""
    return NODES_A * volume / h ** 3 + NODES_B * area / h ** 2


def nodes_exponent(volume: float, area: float, h: float) -> float:
    """-d ln N / d ln h of the node-count model (between 2 and 3)."""
    vi, ar = NODES_A * volume / h ** 3, NODES_B * area / h ** 2
    return (3 * vi + 2 * ar) / (vi + ar)


def size_for_nodes(volume: float, nodes: int, area: float | None = None) -> float:
    """Element size h [m] expected to give about *nodes* nodes.

    Solves ``nodes = a V / h^3 + b A / h^2`` (interior plus surface nodes;
    ``a``, ``b`` fitted on organ meshes, see docs/guide/prepare.md). Without the
    area, a sphere's area for the volume is used.

    Parameters
    ----------
    volume : float
        Enclosed volume [m3].
    nodes : int
        Wanted node count.
    area : float, optional
        Surface area [m2].
    """
    if area is None:
        area = (36.0 * math.pi * volume ** 2) ** (1.0 / 3.0)
    # a V x^3 + b A x^2 - N = 0 for x = 1/h: one positive root (Descartes).
    roots = np.roots([NODES_A * volume, NODES_B * area, 0.0, -float(nodes)])
    x = max(r.real for r in roots if abs(r.imag) < 1e-9 * max(1.0, abs(r.real)) and r.real > 0)
    return 1.0 / x


def size_for_elements(volume: float, elements: int) -> float:
    """Mesh size [m] that gives about *elements* tets in *volume* [m3].

    A regular tet of edge ``h`` has volume ``h**3 / (6 sqrt 2)``; the mesher's
    tets average :data:`MESHER_VOLUME_RATIO` times that.
    """
    return (6.0 * math.sqrt(2.0) * volume / (MESHER_VOLUME_RATIO * elements)) ** (1.0 / 3.0)
