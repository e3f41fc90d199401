"""The figures of merit: how far the network's solution is from the continuum's.

For a case solved by both (:class:`~.solution.Solution`), with ``u_c`` the
continuum's and ``u_n`` the network's vertex displacements and ``w_i`` the
lumped nodal volumes:

* **L2 error** ``sqrt(Σ w_i |u_n − u_c|² / Σ w_i) / max_i |u_c|``: the
  volume-weighted RMS of the difference, relative to the continuum's largest
  displacement (the headline figure);
* **max error** ``max_i |u_n − u_c| / max_i |u_c|``;
* **force error** ``|R_n − R_c| / s`` for the case's compared reaction (vector
  difference), with ``s = |R_c|`` or the case's ``force_scale`` (gravity: the
  weight, since the supports carry it whole in both);
* the volume change ``V/V0 − 1`` of each, the largest local one
  ``max |J − 1|`` and the tetrahedra inverted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cases import LoadCase
from .solution import Solution

__all__ = ["CaseResult", "compare"]


@dataclass(eq=False)
class CaseResult:
    """One case of a validation: the two solutions and the figures (see the module doc)."""

    case: LoadCase
    continuum: Solution
    network: Solution
    l2_error: float
    max_error: float
    force_error: float
    max_displacement_m: float
    error_field: np.ndarray = field(repr=False, default=None)
    pins: int = 0

    def figures(self) -> dict:
        """Plain-data summary (the JSON report's entry)."""
        c, n = self.continuum, self.network
        g = self.case.force_group
        return {
            "case": self.case.name, "boundary_conditions": self.case.description, "load": self.case.load,
            "l2_error": self.l2_error, "max_error": self.max_error, "force_error": self.force_error,
            "force_group": g, "reaction_continuum_N": c.reactions[g].tolist(),
            "reaction_network_N": n.reactions[g].tolist(),
            "max_displacement_continuum_m": self.max_displacement_m,
            "max_displacement_network_m": float(np.linalg.norm(n.displacement, axis=1).max()),
            "volume_change_continuum": c.volume_ratio - 1.0, "volume_change_network": n.volume_ratio - 1.0,
            "max_local_volume_change_continuum": float(np.abs(c.element_J - 1.0).max()),
            "max_local_volume_change_network": float(np.abs(n.element_J - 1.0).max()),
            "inverted_continuum": c.inverted, "inverted_network": n.inverted, "floor_pins": self.pins,
            "continuum": c.info, "network": n.info,
        }


def compare(case: LoadCase, continuum: Solution, network: Solution, *, pins: int = 0) -> CaseResult:
    """The figures of merit of *network* against *continuum* on *case*."""
    uc, un = continuum.displacement, network.displacement
    err = un - uc
    w = case.node_volumes()
    umax = float(np.linalg.norm(uc, axis=1).max())
    scale = umax if umax > 0 else 1.0
    e = np.linalg.norm(err, axis=1)
    g = case.force_group
    rc, rn = np.asarray(continuum.reactions[g]), np.asarray(network.reactions[g])
    fs = case.force_scale if case.force_scale is not None else float(np.linalg.norm(rc))
    return CaseResult(case=case, continuum=continuum, network=network,
                      l2_error=float(np.sqrt(np.sum(w * e**2) / np.sum(w)) / scale),
                      max_error=float(e.max() / scale),
                      force_error=float(np.linalg.norm(rn - rc) / fs) if fs > 0 else float("nan"),
                      max_displacement_m=umax, error_field=err, pins=int(pins))
