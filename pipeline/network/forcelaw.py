r"""Reference (pure numpy) spring forces of the ESMM network.

This is the slow, readable implementation that the tests and the virtual
tensile test use; the simulator has its own compiled kernel and is checked
against this one.

For a spring *i-j* with rest length :math:`L_0`, volume :math:`V_{ij}`,
rest-direction weights :math:`\cos^2\theta_d` and current vector
:math:`\mathbf d = P_j - P_i`, :math:`L = |\mathbf d|`,
:math:`\lambda = L/L_0`, :math:`\mathbf u = \mathbf d/L`:

.. math::

    F = \frac{c V_{ij}}{L_0}\sum_d \cos^2\theta_d\, f_d(\lambda), \qquad
    \mathbf F_i = +F\,\mathbf u, \quad \mathbf F_j = -F\,\mathbf u,

with :math:`f_d` the secant (paper Eq. 9: :math:`f = \mu_e(\lambda-1)`, i.e.
:math:`\mathbf F_i = k_{ij}(|P_iP_j|-L_0)\,\mathbf u`) or energy
(:math:`f = W_T'`) law of :mod:`esmm.pipeline.network.tables`. Both are
central forces whose magnitude depends on :math:`L` only, so both derive from
the potential :math:`E = \sum c V_{ij}\sum_d\cos^2\theta_d\,\Phi_d(\lambda)`,
:math:`\Phi_d = \int_1^\lambda f_d`; :func:`spring_energy` returns it and
:func:`tangent_stiffness` its Hessian. Springs of zero current length carry
no force (their direction is undefined).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .tables import StiffnessTables, spring_factors

__all__ = [
    "spring_stretch", "spring_force_magnitudes", "spring_forces", "spring_energy",
    "tangent_stiffness",
]


def _geometry(points, network):
    x = np.asarray(points, dtype=np.float64)
    springs = np.asarray(network.springs)
    L0 = np.asarray(network.rest_length, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"points: expected shape (n, 3), got {x.shape}")
    if springs.size and springs.max() >= x.shape[0]:
        raise InputError(f"points: {x.shape[0]} points but the network references point "
                         f"{int(springs.max())}; pass the network's own point array")
    d = x[springs[:, 1]] - x[springs[:, 0]]
    L = np.sqrt(np.einsum("ij,ij->i", d, d))
    return x, springs, L0, d, L


def spring_stretch(points, network) -> np.ndarray:
    """Stretch :math:`\\lambda = L/L_0` of every spring, shape (s,)."""
    _, _, L0, _, L = _geometry(points, network)
    return L / L0


def spring_force_magnitudes(points, network, tables: StiffnessTables, *,
                            law: str | None = None) -> np.ndarray:
    """Signed force magnitude [N] of every spring (positive = tension), shape (s,)."""
    law = tables.check_law(law)
    _, _, L0, _, L = _geometry(points, network)
    a = spring_factors(tables, network)                     # (s, 3) = c v cos2
    f = tables.force_function(L / L0, law=law)              # (3, s)
    return L0 * np.einsum("sd,ds->s", a, f)


def spring_forces(points, network, tables: StiffnessTables, *, law: str | None = None) -> np.ndarray:
    """Nodal spring forces, shape (n, 3) [N].

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Current positions [m].
    network : SpringNetwork
        ``springs`` (s, 2), ``rest_length`` (s,), ``volume_weight`` (s,),
        ``cos2`` (s, 3).
    tables : StiffnessTables
    law : {"secant", "energy"}, optional
        Default: ``tables.default_law``.
    """
    law = tables.check_law(law)
    x, springs, L0, d, L = _geometry(points, network)
    a = spring_factors(tables, network)
    F = L0 * np.einsum("sd,ds->s", a, tables.force_function(L / L0, law=law))
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(L[:, None] > 0, d / L[:, None], 0.0)
    fu = F[:, None] * u
    out = np.zeros_like(x)
    np.add.at(out, springs[:, 0], fu)
    np.add.at(out, springs[:, 1], -fu)
    return out


def spring_energy(points, network, tables: StiffnessTables, *, law: str | None = None) -> float:
    """Total spring potential [J] whose negative gradient is :func:`spring_forces`.

    For the energy law it is :math:`\\sum c V_{ij} W_T(\\lambda_{ij})` (direction
    weighted); for the secant law it is the potential of the secant force,
    not the paper's :math:`\\sum \\tfrac12 k_{ij}(L-L_0)^2`.
    """
    law = tables.check_law(law)
    _, _, L0, _, L = _geometry(points, network)
    a = spring_factors(tables, network)
    phi = tables.potential(L / L0, law=law)                 # (3, s)
    return float(np.einsum("s,sd,ds->", L0**2, a, phi))


def tangent_stiffness(points, network, tables: StiffnessTables, *, law: str | None = None):
    """Hessian of :func:`spring_energy`, a symmetric sparse (3n, 3n) CSR matrix [N/m].

    Per spring, the block ``K = dF/dL u u^T + F/L (I - u u^T)`` enters
    ``+K`` at (i, i) and (j, j) and ``-K`` at (i, j) and (j, i).
    """
    law = tables.check_law(law)
    x, springs, L0, d, L = _geometry(points, network)
    a = spring_factors(tables, network)
    lam = L / L0
    F = L0 * np.einsum("sd,ds->s", a, tables.force_function(lam, law=law))
    dF = np.einsum("sd,ds->s", a, tables.tangent_function(lam, law=law))  # dF/dL = a.f'/L0 * L0
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(L[:, None] > 0, d / L[:, None], 0.0)
        FoL = np.where(L > 0, F / L, 0.0)
    uu = u[:, :, None] * u[:, None, :]
    K = dF[:, None, None] * uu + FoL[:, None, None] * (np.eye(3)[None] - uu)   # (s, 3, 3)
    n = x.shape[0]
    i, j = springs[:, 0], springs[:, 1]
    r3 = np.arange(3)
    def idx(p, q):
        rows = (3 * p[:, None, None] + r3[None, :, None]).repeat(3, axis=2)
        cols = (3 * q[:, None, None] + r3[None, None, :]).repeat(3, axis=1)
        return rows.ravel(), cols.ravel()
    parts_r, parts_c, parts_v = [], [], []
    for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        r, c = idx(p, q)
        parts_r.append(r)
        parts_c.append(c)
        parts_v.append(sign * K.ravel())
    H = sp.coo_matrix((np.concatenate(parts_v), (np.concatenate(parts_r), np.concatenate(parts_c))),
                      shape=(3 * n, 3 * n))
    return H.tocsr()
