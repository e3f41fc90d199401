r"""Volume elements: the term that makes the spring network nearly incompressible.

A central-force network has a Poisson ratio near 1/4 whatever its weights
(docs/design/model.md, "The spring network"); tissue is nearly incompressible. The springs keep
carrying the calibrated nonlinear stretch response; this term adds a penalty
on the change of volume of *volume elements* built on the network's
tetrahedra:

.. math::

    U = \sum_e V_{e,0}\,\Psi(J_e), \qquad J_e = V_e / V_{e,0}, \qquad
    \Psi(J) = \tfrac{\kappa}{2}(J - 1)^2,

with :math:`\kappa` the bulk modulus [Pa] (:func:`bulk_modulus`). Two kinds
of element (``formulation``):

* ``"nodal"`` (the default): one element per node, its volume the nodal
  share of the tetrahedra around it, :math:`V_a = \sum_{t \ni a} V_t / 4`
  (the average nodal pressure tetrahedron of Bonet & Burton 1998). One
  volume constraint per node, three degrees of freedom per node: it does not
  lock (docs/design/model.md, "The volume term (nearly incompressible network)", shows it);
* ``"tet"``: one element per tetrahedron, :math:`V_e = V_t`. About five to
  six constraints per node: linear tetrahedra lock (the network becomes far
  too stiff in shear and bending as :math:`\kappa` grows). Kept for the
  measurement that shows it.

Both are sums over tetrahedra through an averaging matrix :math:`A` (elements
by tets; nodal: :math:`A_{at} = 1/4` for :math:`a \in t`; tet: the
identity): :math:`V_e = \sum_t A_{et} V_t`. With the element pressure
:math:`p_e = \Psi'(J_e) = \kappa (J_e - 1)` and the tet pressure
:math:`\bar p_t = \sum_e A_{et} p_e` (nodal: the mean of its four nodes'
pressures),

.. math::

    \mathbf f_b = -\sum_t \bar p_t\, \frac{\partial V_t}{\partial \mathbf x_b},
    \qquad
    K = \sum_e \frac{\kappa}{V_{e,0}}\, \nabla V_e \nabla V_e^T
        + \sum_t \bar p_t\, \nabla^2 V_t ,

with :math:`6V_t = (\mathbf x_1 - \mathbf x_0)\cdot[(\mathbf x_2 - \mathbf x_0)\times(\mathbf x_3 - \mathbf x_0)]`.
The forces are the exact negative gradient of :math:`U`, so the term is
conservative and :math:`K` (its Hessian) symmetric; translations and
rotations change no volume, so they give no force. This module is the
readable numpy reference; the simulator's compiled kernel
(``esmm.pipeline.simulate.volumeterm``) is checked against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numba as nb
import numpy as np
import scipy.sparse as sp

from ..errors import ConfigError, InputError
from .springs import tet_volumes

__all__ = [
    "DEFAULT_POISSON", "FORMULATIONS", "VolumeElements", "VolumeSpec", "bulk_modulus", "bulk_ratio",
    "inverted_tets", "nodal_volumes", "tangent_shear_modulus", "volume_elements",
]

FORMULATIONS = ("nodal", "tet")

#: Poisson ratio of the stiffest calibrated state the volume term is sized for
#: (docs/design/model.md, "The volume term (nearly incompressible network)"):
#: kappa = 9.7 times the liver's tangent shear modulus at stretch 1.3, i.e. Poisson ratio 0.4986 at small
#: strain; the volume changes by at most 0.4 % over the calibration range. A smaller kappa was measured
#: against the continuum and not adopted (docs/design/realtime.md, "The volume term's bulk modulus against
#: the continuum").
DEFAULT_POISSON = 0.45
#: Accepted Poisson ratios (0: no volume stiffness beyond the springs'; 0.5 is the incompressible limit).
POISSON_RANGE = (0.0, 0.4999)
#: Largest |J - 1| the whole-run stability bound assumes (the term keeps J near 1; docs/design/simulator.md).
J_RANGE = 0.5

# For node k of a positively oriented tet (0, 1, 2, 3): an even permutation (p0, k, p2, p3) of it,
# so that d(6V)/dx_k = (x_p2 - x_p0) x (x_p3 - x_p0).
_EVEN = np.array([[1, 0, 3, 2], [0, 1, 2, 3], [0, 2, 3, 1], [0, 3, 1, 2]])
# The three edges of the face opposite each local node (node-major, 4 x 3 pairs).
_FACE_EDGES = np.array([[1, 2], [1, 3], [2, 3], [0, 2], [0, 3], [2, 3], [0, 1], [0, 3], [1, 3], [0, 1], [0, 2], [1, 2]])


def bulk_ratio(poisson: float) -> float:
    r"""Bulk over shear modulus of an isotropic solid, :math:`2(1+\nu)/(3(1-2\nu))`."""
    nu = float(poisson)
    return 2.0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


def tangent_shear_modulus(tables, lo: float, hi: float) -> tuple[float, float]:
    r"""Largest tangent shear modulus :math:`\mu_t = \tfrac13\, dP/d\lambda` of the material over [lo, hi].

    *P* is the material's own uniaxial nominal stress (``tables.material_stress``,
    without any compensation), differentiated on the tables' grid, largest over
    the fibre directions. For an incompressible solid at small strain
    :math:`dP/d\lambda = E = 3\mu`; at finite stretch it is the stiffening
    tissue's tangent (porcine liver: 37 times E at 1.3).

    Returns
    -------
    (mu_t [Pa], the stretch where it is largest)
    """
    lam = tables.lam
    slope = np.diff(np.asarray(tables.material_stress, dtype=np.float64), axis=1) / tables.dlam   # (3, n-1)
    mid = 0.5 * (lam[1:] + lam[:-1])
    inside = (mid >= lo) & (mid <= hi)
    if not inside.any():
        inside = np.abs(mid - 1.0) == np.abs(mid - 1.0).min()
    s = slope[:, inside].max(axis=0)
    k = int(np.argmax(s))
    return float(s[k] / 3.0), float(mid[inside][k])


@dataclass(frozen=True)
class VolumeSpec:
    """The material-level parameters of the volume term (what the asset's ``/volume`` group stores).

    Attributes
    ----------
    bulk_modulus : float
        :math:`\\kappa` [Pa].
    formulation : {"nodal", "tet"}
    poisson_ratio : float or None
        The Poisson ratio *kappa* was sized for (None: given directly).
    shear_modulus : float or None
        The tangent shear modulus it was sized on [Pa] (:func:`tangent_shear_modulus`).
    at_stretch : float or None
        Where that tangent is largest.
    rule : str
        How *kappa* was chosen, one line.
    """

    bulk_modulus: float
    formulation: str = "nodal"
    poisson_ratio: float | None = None
    shear_modulus: float | None = None
    at_stretch: float | None = None
    rule: str = ""

    def __post_init__(self) -> None:
        k = self.bulk_modulus
        if not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
            raise ConfigError(f"bulk_modulus: must be a finite number >= 0 Pa, got {k!r}", parameter="bulk_modulus")
        if self.formulation not in FORMULATIONS:
            raise ConfigError(f"formulation: unknown {self.formulation!r}; use one of {', '.join(FORMULATIONS)}",
                              parameter="formulation")
        object.__setattr__(self, "bulk_modulus", float(k))

    def describe(self) -> dict[str, Any]:
        """Plain data (asset attributes, summaries, the compensation's cache key)."""
        return {"bulk_modulus_pa": self.bulk_modulus, "formulation": self.formulation,
                "poisson_ratio": self.poisson_ratio, "shear_modulus_pa": self.shear_modulus,
                "at_stretch": self.at_stretch, "rule": self.rule}


def bulk_modulus(tables, *, poisson: float = DEFAULT_POISSON, calibration_range=(0.9, 1.3),
                 formulation: str = "nodal") -> VolumeSpec:
    r"""The volume term of a material: :math:`\kappa = \frac{2(1+\nu)}{3(1-2\nu)}\,\mu_t`.

    :math:`\mu_t` is the material's largest tangent shear modulus over the
    calibration range (:func:`tangent_shear_modulus`): a penalty sized on the
    small-strain modulus stops being incompressible once the fibres stiffen
    (the liver's tangent is 6 E at 1.1 and 37 E at 1.3), so it is sized on the
    stiffest state the network is calibrated for. The ratio is the bulk/shear
    ratio of an isotropic solid of Poisson ratio *poisson* (0.45: 9.67; 0.49: 49.7).

    Parameters
    ----------
    tables : StiffnessTables
    poisson : float
        Poisson ratio at that stiffest state, in [0, 0.4999].
    calibration_range : (float, float)
        Stretches the tangent is taken over (clipped to the grid).
    formulation : {"nodal", "tet"}
    """
    nu = float(poisson)
    if not (math.isfinite(nu) and POISSON_RANGE[0] <= nu <= POISSON_RANGE[1]):
        raise ConfigError(f"poisson_ratio: must lie in [{POISSON_RANGE[0]}, {POISSON_RANGE[1]}], got {poisson!r}",
                          parameter="poisson_ratio")
    lo, hi = (float(v) for v in calibration_range)
    mu_t, at = tangent_shear_modulus(tables, max(lo, tables.lam_min), min(hi, tables.lam_max))
    ratio = bulk_ratio(nu)
    rule = (f"kappa = 2(1+nu)/(3(1-2nu)) * mu_t = {ratio:.4g} * {mu_t:.4g} Pa, nu = {nu:g}, mu_t = dP/dlambda / 3 "
            f"of the material, largest over stretch {lo:g}-{hi:g} (at {at:.4g})")
    return VolumeSpec(bulk_modulus=ratio * mu_t, formulation=formulation, poisson_ratio=nu, shear_modulus=mu_t,
                      at_stretch=at, rule=rule)


def nodal_volumes(points: np.ndarray, tets: np.ndarray, n_nodes: int | None = None) -> np.ndarray:
    """Nodal volumes ``V_a = sum_{t containing a} V_t / 4`` [m3], shape (n,)."""
    t = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    n = int(np.asarray(points).shape[0]) if n_nodes is None else int(n_nodes)
    return np.bincount(t.ravel(), weights=np.repeat(tet_volumes(points, t) / 4.0, 4), minlength=n)


def inverted_tets(points: np.ndarray, tets: np.ndarray) -> int:
    """Number of tetrahedra with zero or negative signed volume at *points*."""
    return int(np.count_nonzero(tet_volumes(points, tets) <= 0.0))


def _skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices [w]x of vectors *w* (..., 3), shape (..., 3, 3): [w]x v = w x v."""
    z = np.zeros(w.shape[:-1])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1),
                     np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


@dataclass(frozen=True, eq=False)
class VolumeElements:
    """A :class:`VolumeSpec` on a mesh: the tets, the averaging matrix, the rest element volumes.

    Attributes
    ----------
    spec : VolumeSpec
    tets : ndarray, shape (t, 4), int64
        Positively oriented tetrahedra over the network's nodes.
    rest_volume : ndarray, shape (m,)
        Rest volume of each element [m3] (nodal: per node; tet: per tet).
    n_nodes : int
    """

    spec: VolumeSpec
    tets: np.ndarray
    rest_volume: np.ndarray
    n_nodes: int
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def bulk_modulus(self) -> float:
        return self.spec.bulk_modulus

    @property
    def formulation(self) -> str:
        return self.spec.formulation

    @property
    def n_elements(self) -> int:
        return int(self.rest_volume.shape[0])

    @property
    def force_unit(self) -> float:
        """``kappa`` times the largest rest gradient ``|dV_t/dx_k|`` [N]: the force of a unit pressure ratio."""
        if "force_unit" not in self._cache:
            g = np.linalg.norm(self._gradients(self._cache["rest_points"]), axis=2)
            self._cache["force_unit"] = float(self.bulk_modulus * g.max()) if g.size else 0.0
        return self._cache["force_unit"]

    def averaging(self) -> sp.csr_matrix:
        """The averaging matrix A (m, t): element volume ``V_e = A @ V_t`` (cached)."""
        if "A" not in self._cache:
            t = self.tets.shape[0]
            if self.formulation == "tet":
                A = sp.identity(t, format="csr")
            else:
                rows = self.tets.ravel()
                cols = np.repeat(np.arange(t), 4)
                A = sp.csr_matrix((np.full(rows.size, 0.25), (rows, cols)), shape=(self.n_nodes, t))
            self._cache["A"] = A
        return self._cache["A"]

    # -- evaluation ------------------------------------------------------------
    def _x(self, points) -> np.ndarray:
        x = np.asarray(points, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise InputError(f"points: expected shape ({self.n_nodes}, 3), got {x.shape}")
        return x

    def volumes(self, points) -> np.ndarray:
        """Current element volumes [m3], shape (m,)."""
        return self.averaging() @ tet_volumes(self._x(points), self.tets)

    def jacobians(self, points) -> np.ndarray:
        """Element volume ratios ``J_e = V_e / V_e0``, shape (m,)."""
        return self.volumes(points) / self.rest_volume

    def pressures(self, points) -> np.ndarray:
        """Element pressures ``p_e = kappa (J_e - 1)`` [Pa] (positive in dilatation), shape (m,)."""
        return self.bulk_modulus * (self.jacobians(points) - 1.0)

    def energy(self, points) -> float:
        """``U = sum_e V_e0 kappa/2 (J_e - 1)^2`` [J]."""
        j = self.jacobians(points)
        return float(0.5 * self.bulk_modulus * np.sum(self.rest_volume * (j - 1.0) ** 2))

    def _gradients(self, x: np.ndarray) -> np.ndarray:
        """d V_t / d x_k for every tet and local node k, shape (t, 4, 3) [m2]."""
        p = x[self.tets]                                   # (t, 4, 3)
        g = np.empty_like(p)
        for k in range(4):
            a, _, b, c = _EVEN[k]
            g[:, k] = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]) / 6.0
        return g

    def forces(self, points) -> np.ndarray:
        """Nodal forces ``-dU/dx`` [N], shape (n, 3)."""
        x = self._x(points)
        pbar = self.averaging().T @ self.pressures(x)       # (t,)
        g = self._gradients(x)
        out = np.zeros_like(x)
        np.add.at(out, self.tets.ravel(), (-pbar[:, None, None] * g).reshape(-1, 3))
        return out

    def gradient_matrix(self, points) -> sp.csr_matrix:
        """G (t, 3n): row t is the gradient of V_t (dof order ``x.ravel()``)."""
        x = self._x(points)
        t = self.tets.shape[0]
        if "G_index" not in self._cache:
            cols = (3 * self.tets[:, :, None] + np.arange(3)[None, None, :]).reshape(t, 12)
            self._cache["G_index"] = (np.repeat(np.arange(t), 12), cols.ravel())
        rows, cols = self._cache["G_index"]
        g = self._gradients(x)
        return sp.csr_matrix((g.ravel(), (rows, cols)), shape=(t, 3 * self.n_nodes))

    def tangent(self, points, *, definite: bool = False) -> sp.csr_matrix:
        """Hessian of :meth:`energy` (= -d forces / dx), symmetric sparse (3n, 3n) CSR [N/m].

        *definite*: its positive semi-definite (Gauss-Newton) part ``B^T D B`` only,
        without the pressures' geometric part (Newton's matrix of the implicit stepper).
        """
        x = self._x(points)
        B, w = self.gauss_newton_parts(x)
        K = (B.T @ sp.diags(w) @ B).tocsr()
        if definite:
            return K
        pbar = self.averaging().T @ self.pressures(x)
        return (K + self._geometric(x, pbar)).tocsr()

    def gauss_newton_parts(self, points) -> tuple[sp.csr_matrix, np.ndarray]:
        r"""The definite tangent's factors: ``(B, w)`` with :math:`K = B^T \operatorname{diag}(w) B`.

        :math:`B = A G` (m, 3n) holds the gradients of the element volumes
        :math:`\nabla V_e` (nodal formulation: row a reaches the nodes of the
        tets around node a) and :math:`w_e = \kappa / V_{e,0}` [Pa/m3]. K
        couples nodes two tets apart; B only nodes one tet apart, so the
        saddle-point matrix ``[[A_s, B^T], [B, -diag(1/w)]]`` holds K with the
        sparsity of the tets (the implicit stepper's "mixed" factor).
        """
        x = self._x(points)
        B = (self.averaging() @ self.gradient_matrix(x)).tocsr()
        return B, self.bulk_modulus / self.rest_volume

    def tangent_operator(self, points, *, definite: bool = False):
        """The product ``p -> K p`` of :meth:`tangent` at *points* without forming K.

        ``K = G^T A^T D A G`` (+ the geometric part unless *definite*, which is
        formed: it has the sparsity of the tets): two sparse products with the
        element gradients G (t, 3n) and the averaging A instead of the (3n, 3n)
        matrix, whose node blocks reach every node two tets away (forming K costs
        several times the products).

        Returns
        -------
        callable
            ``p`` (3n,) -> ``K p`` (3n,).
        """
        x = self._x(points)
        A = self.averaging()
        if "AT" not in self._cache:
            self._cache["AT"] = A.T.tocsr()
        AT = self._cache["AT"]
        G = self.gradient_matrix(x)
        w = self.bulk_modulus / self.rest_volume
        Kg = None if definite else self._geometric(x, AT @ self.pressures(x)).tocsr()

        def product(p: np.ndarray) -> np.ndarray:
            y = G.T @ (AT @ (w * (A @ (G @ p))))
            return y if Kg is None else y + Kg @ p

        return product

    def tangent_bound(self, points) -> sp.csr_matrix:
        r"""A sparser matrix above the definite tangent: the per-tet Gauss-Newton matrix (3n, 3n) CSR [N/m].

        .. math::

            K_{tet} = \sum_t \frac{\kappa}{V_{t,0}} \nabla V_t \nabla V_t^T
            \;\succeq\; K = \sum_a \frac{\kappa}{V_{a,0}} \nabla V_a \nabla V_a^T

        for the nodal formulation (:math:`V_a = \sum_{t \ni a} V_t/4`,
        :math:`V_{a,0} = \sum_{t \ni a} V_{t,0}/4`): by Cauchy-Schwarz,
        :math:`(\sum_{t \ni a} \delta V_t/4)^2 \le V_{a,0} \sum_{t \ni a}
        \delta V_t^2/(4 V_{t,0})`, and summing over the nodes counts each tet's
        :math:`\delta V_t^2/V_{t,0}` once. Its node blocks couple only the
        nodes of a tet (K's reach every node two tets away), so its sparse
        factor has about a third of the fill (docs/design/simulator.md,
        "What is factored, and when it is renewed"). For the per-tet
        formulation it is K itself.
        """
        x = self._x(points)
        t, m = self.tets.shape[0], 3 * self.n_nodes
        if "bound_pattern" not in self._cache:
            rest = tet_volumes(self._cache["rest_points"], self.tets)
            self._cache["bound_weight"] = np.broadcast_to(self.bulk_modulus / rest, (t,)).astype(np.float64)
            self._cache["bound_pattern"] = _tet_block_pattern(self.tets, self.n_nodes)
        indptr, indices, pos = self._cache["bound_pattern"]
        data = np.zeros(indices.size)
        _add_outer_products(self._gradients(x).reshape(t, 12), self._cache["bound_weight"], pos, data)
        return sp.csr_matrix((data, indices, indptr), shape=(m, m))

    def _geometric(self, x: np.ndarray, pbar: np.ndarray) -> sp.coo_matrix:
        """``sum_t pbar_t d2 V_t / dx2`` as a sparse (3n, 3n) matrix (off-diagonal node blocks only).

        For node k with the even ordering (a, k, b, c) of its tet,
        ``d(6V)/dx_k = (x_b - x_a) x (x_c - x_a)``, whose derivatives are the
        cross-product matrices ``-[x_c - x_a]``, ``[x_b - x_a]`` and ``[x_c - x_b]``
        with respect to x_b, x_c and x_a.
        """
        p = x[self.tets]                                      # (t, 4, 3)
        m = 3 * self.n_nodes
        t = self.tets.shape[0]
        if t == 0:
            return sp.coo_matrix((m, m))
        a, b, c = _EVEN[:, 0], _EVEN[:, 2], _EVEN[:, 3]        # per local node k
        w = np.stack([-(p[:, c] - p[:, a]), p[:, b] - p[:, a], p[:, c] - p[:, b]], axis=2)   # (t, 4, 3, 3)
        vals = pbar[:, None, None, None, None] * _skew(w) / 6.0                              # (t, 4, 3, 3, 3)
        if "H_index" not in self._cache:
            other = np.stack([b, c, a], axis=1)                                              # (4, 3)
            r3 = np.arange(3)
            node_k = self.tets[:, :, None]                                                   # (t, 4, 1)
            node_o = self.tets[:, other]                                                     # (t, 4, 3)
            rows = np.broadcast_to(3 * node_k[..., None, None] + r3[:, None], (t, 4, 3, 3, 3))
            cols = np.broadcast_to(3 * node_o[..., None, None] + r3[None, :], (t, 4, 3, 3, 3))
            self._cache["H_index"] = (rows.ravel().copy(), cols.ravel().copy())
        rows, cols = self._cache["H_index"]
        return sp.coo_matrix((vals.ravel(), (rows, cols)), shape=(m, m))

    # -- stability (Gershgorin rows) ---------------------------------------------
    def stiffness_rows(self, points=None, *, growth: float = 1.0, j_bound: float | None = None) -> np.ndarray:
        r"""Per node, a bound ``r_i`` with ``x^T K x <= sum_i r_i |x_i|^2`` [N/m], shape (n,).

        For the rank-one element terms :math:`k_e b_e b_e^T`
        (:math:`k_e = \kappa/V_{e,0}`, :math:`b_e = \nabla V_e`, node blocks
        :math:`b_{e,j}`), Cauchy-Schwarz with weights :math:`w_j` gives
        :math:`(b_e \cdot x)^2 \le (\sum_j |b_{e,j}|^2/w_j)(\sum_j w_j |x_j|^2)`,
        hence :math:`r_i = w_i \sum_{e \ni i} k_e \sum_j |b_{e,j}|^2 / w_j`. The
        weights are the rest nodal volumes (proportional to the lumped masses
        of a tet network), so that :math:`r_i/m_i` is the element eigenvalue
        summed over the elements that touch node *i*: 2.8 times the true
        largest eigenvalue on a gmsh cylinder (the unweighted form, 12 times).
        The geometric part adds, per tet, :math:`|\bar p_t|` times the
        perimeter of the face opposite the node over 6 (the node blocks of
        :math:`\nabla^2 V_t` are cross-product matrices of the opposite edges).

        Parameters
        ----------
        points : ndarray, shape (n, 3), optional
            Positions where the gradients and pressures are taken (default: the
            rest shape, pressures from *j_bound*).
        growth : float
            Factor on every length: gradients (face areas) are scaled by
            ``growth**2``, the perimeters by *growth* (the whole run: the
            largest tabulated stretch; a stretch window: ``1 + delta / lam_min``).
        j_bound : float or ndarray of shape (m,), optional
            Bound of ``|J - 1|`` for the pressures, per element or for all
            (default: the current ``|J - 1|`` at *points*; at rest :data:`J_RANGE`).
        """
        rest = self._cache["rest_points"]
        x = rest if points is None else self._x(points)
        kappa = self.bulk_modulus
        A = self.averaging()
        B = (A @ self.gradient_matrix(x)).tocsr()
        n = self.n_nodes
        sum3 = sp.csr_matrix((np.ones(3 * n), (np.arange(3 * n), np.repeat(np.arange(n), 3))), shape=(3 * n, n))
        N2 = (B.multiply(B) @ sum3).tocsr() * float(growth) ** 4          # element x node: |b_ej|^2
        w = self._cache.get("node_weights")
        if w is None:
            w = nodal_volumes(rest, self.tets, n)
            self._cache["node_weights"] = w
        beta = np.asarray(N2 @ (1.0 / w)).ravel()                          # per element sum_j |b_ej|^2 / w_j
        touch = N2.copy()
        touch.data[:] = 1.0
        rows = w * np.asarray(touch.T @ (kappa / self.rest_volume * beta)).ravel()
        if j_bound is None and points is not None:
            jdev = np.abs(self.jacobians(x) - 1.0)
        else:
            jdev = np.broadcast_to(np.asarray(J_RANGE if j_bound is None else j_bound, dtype=np.float64),
                                   (self.n_elements,))
        pbar = kappa * (A.T @ jdev)
        p = x[self.tets]
        d = p[:, _FACE_EDGES[:, 1]] - p[:, _FACE_EDGES[:, 0]]                # (t, 12, 3)
        perim = np.linalg.norm(d, axis=2).reshape(-1, 4, 3).sum(axis=2) * float(growth) / 6.0
        rows += np.bincount(self.tets.ravel(), weights=(pbar[:, None] * perim).ravel(), minlength=n)
        return rows


def volume_elements(points: np.ndarray, tets: np.ndarray, spec: VolumeSpec) -> VolumeElements:
    """The volume elements of *spec* on the mesh (*points* (n, 3) [m] at rest, *tets* (t, 4)).

    Raises
    ------
    InputError
        No tetrahedra, indices out of range, or a tet that is not positively
        oriented (zero or negative volume) at rest.
    """
    x = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    t = np.ascontiguousarray(np.asarray(tets, dtype=np.int64).reshape(-1, 4))
    n = x.shape[0]
    if t.shape[0] == 0:
        raise InputError("volume term: the mesh has no tetrahedra (the skeleton structure has none)")
    if t.min() < 0 or t.max() >= n:
        raise InputError(f"volume term: tetrahedra reference nodes outside 0..{n - 1}")
    vt = tet_volumes(x, t)
    if np.any(vt <= 0):
        raise InputError(f"volume term: {int(np.count_nonzero(vt <= 0))} tetrahedra are not positively oriented "
                         "at rest; rebuild the network")
    rest = np.bincount(t.ravel(), weights=np.repeat(vt / 4.0, 4), minlength=n) if spec.formulation == "nodal" \
        else vt.copy()
    if spec.formulation == "nodal" and np.any(rest <= 0):
        raise InputError("volume term: some nodes belong to no tetrahedron; rebuild the network")
    el = VolumeElements(spec, t, rest, n)
    el._cache["rest_points"] = x.copy()
    return el


def _tet_block_pattern(tets: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CSR pattern (indptr, indices) of the (3n, 3n) matrix whose node blocks couple the nodes of a
    tet, and where each tet's 12 x 12 block goes in its data, ``pos`` (t, 144): entry ``12 a + b`` of
    tet t (its dofs in the order ``3 tets[t] + (0, 1, 2)``) at ``data[pos[t, 12 a + b]]``.

    Found on the nodes (16 pairs a tet) and widened to 3 x 3 blocks: a row of node i's holds, for
    each node j it shares a tet with (ascending), j's three dofs. Sorting the 144 dof pairs of every
    tet instead is far slower on a large mesh, and this runs inside a simulation's first step."""
    t, n = tets.shape[0], n_nodes
    ti = np.repeat(tets, 4, axis=1).ravel().astype(np.int64)
    tj = np.tile(tets, (1, 4)).ravel().astype(np.int64)
    pairs, which = np.unique(ti * n + tj, return_inverse=True)
    row, col = pairs // n, pairs % n
    start = np.searchsorted(row, np.arange(n + 1))              # node i's neighbours: pairs[start[i]:start[i+1]]
    deg = np.diff(start)
    k = np.arange(pairs.size) - start[row]                       # j's rank among i's neighbours
    row_ptr = np.concatenate([[0], np.cumsum(np.repeat(3 * deg, 3))]).astype(np.int64)   # scalar rows
    # each scalar row 3 i + d lists, for each neighbour j of i, the dofs 3 j + (0, 1, 2)
    r_dof = np.repeat(np.arange(3 * n), np.repeat(3 * deg, 3))
    node = r_dof // 3
    within = np.arange(r_dof.size) - row_ptr[r_dof]
    indices = 3 * col[start[node] + within // 3] + within % 3
    # tet t's entry (a, b), a = 3 p + da, b = 3 q + db: row 3 tets[t, p] + da, neighbour rank k of the
    # node pair (p, q), column offset db
    kk = k[which].reshape(t, 4, 4)                               # rank of (tets[t, p], tets[t, q])
    base = row_ptr[3 * tets.astype(np.int64)]                    # (t, 4): row 3 tets[t, p]'s start
    p_, da, q_, db = np.meshgrid(np.arange(4), np.arange(3), np.arange(4), np.arange(3), indexing="ij")
    p_, da, q_, db = (v.reshape(12, 12) for v in (p_, da, q_, db))
    rowlen = (3 * deg[tets])[:, p_]                              # (t, 12, 12): a scalar row's length
    pos = base[:, p_] + da * rowlen + 3 * kk[:, p_, q_] + db
    return row_ptr, indices.astype(np.int64), np.ascontiguousarray(pos.reshape(t, 144), dtype=np.int64)


@nb.njit(cache=True)
def _add_outer_products(g, w, pos, data):
    """``data[pos[t, 12 a + b]] += w[t] g[t, a] g[t, b]`` for every tet t: the per-tet Gauss-Newton
    blocks ``w_t grad V_t grad V_t^T`` summed into a CSR matrix's data (:func:`_tet_block_pattern`)."""
    for t in range(g.shape[0]):
        for a in range(12):
            ga = w[t] * g[t, a]
            for b in range(12):
                data[pos[t, 12 * a + b]] += ga * g[t, b]
