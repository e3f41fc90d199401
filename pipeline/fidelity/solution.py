"""What a solver returns for a load case: the field, the reactions, the volume."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..network.springs import tet_volumes

__all__ = ["Solution", "start_scale", "tet_volume_ratios"]


@dataclass(eq=False)
class Solution:
    """A static solution of a :class:`~.cases.LoadCase`.

    Attributes
    ----------
    solver : str
        "continuum" or "network".
    displacement : ndarray, shape (n, 3)
        At the mesh vertices [m].
    reactions : dict of str -> ndarray (3,)
        Per constraint group, the force the body exerts on it [N] (its weight
        and internal forces on the group's nodes; the grasper force of the
        simulator for the grasped nodes).
    volume_ratio : float
        Deformed over rest volume of the whole body.
    element_J : ndarray, shape (t,)
        Per tetrahedron, its volume ratio (continuum: the smallest over its
        quadrature points; network: its deformed/rest volume).
    info : dict
        Solver figures (load steps, iterations, seconds, bulk modulus, ...).
    state : object, optional
        The solver's own state, to start another solve of the same mesh from
        (continuum: the values of its fields).
    gravity : ndarray, shape (3,), optional
        The gravity of the case it solves: a solve started from it ramps the
        body force from there (:func:`start_scale`).
    """

    solver: str
    displacement: np.ndarray
    reactions: dict
    volume_ratio: float
    element_J: np.ndarray
    info: dict = field(default_factory=dict)
    state: object = None
    gravity: np.ndarray | None = None   #: the case's gravity it solves [m/s^2] (None: not recorded)

    @property
    def inverted(self) -> int:
        """Tetrahedra turned inside out (J <= 0)."""
        return int(np.count_nonzero(~(self.element_J > 0)))


def tet_volume_ratios(points: np.ndarray, tets: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Deformed over rest volume of each linear tetrahedron, shape (t,)."""
    return tet_volumes(points + displacement, tets) / tet_volumes(points, tets)


def start_scale(start: Solution | None, gravity) -> float:
    """The body force a solve of a case under *gravity* starts from, as a share of the case's: 0 from rest,
    1 from a solution under the same gravity (a floor round), ``(k-1)/k`` from load level k-1 to k.

    Both solvers ramp their body force from it to 1 over their load steps, so that a step they halve
    halves the body force's increment too (with the start's share taken as 1 whatever it was, the
    continuum met each level's increment of gravity whole in its first Newton iteration and no halving
    could make it smaller: P2 gave up on the bundled liver's gravity case at a load factor of 0.001).
    """
    if start is None:
        return 0.0
    g = np.asarray(gravity, dtype=np.float64)
    gg = float(g @ g)
    if start.gravity is None or gg == 0.0:
        return 1.0
    return float(np.asarray(start.gravity, dtype=np.float64) @ g / gg)
