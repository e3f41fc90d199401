"""What a solver returns for a load case: the field, the reactions, the volume."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..network.springs import tet_volumes

__all__ = ["Solution", "tet_volume_ratios"]


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
    """

    solver: str
    displacement: np.ndarray
    reactions: dict
    volume_ratio: float
    element_J: np.ndarray
    info: dict = field(default_factory=dict)
    state: object = None

    @property
    def inverted(self) -> int:
        """Tetrahedra turned inside out (J <= 0)."""
        return int(np.count_nonzero(~(self.element_J > 0)))


def tet_volume_ratios(points: np.ndarray, tets: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Deformed over rest volume of each linear tetrahedron, shape (t,)."""
    return tet_volumes(points + displacement, tets) / tet_volumes(points, tets)
