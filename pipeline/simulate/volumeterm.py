r"""The volume force term: the network's volume elements as the kernels read them.

:func:`build_volume_term` turns the volume elements of a network
(:mod:`esmm.pipeline.network.volume`: nodal volumes
:math:`V_a = \sum_{t \ni a} V_t/4`, energy
:math:`U = \sum_a V_{a,0}\,\tfrac{\kappa}{2}(J_a - 1)^2`, docs/design/model.md, "The volume term
(nearly incompressible network)")
into a :class:`VolumeTerm`, a :class:`~.model.ForceTerm` beside the springs:

* its forces are compiled (:func:`~.kernels.volume_forces`: one thread
  scatters over the tets; threads gather per node, race-free);
* :meth:`VolumeTerm.stiffness_rows` bounds its tangent for the explicit step
  (weighted Cauchy-Schwarz rows of the element terms plus the pressures'
  geometric part, :meth:`~esmm.pipeline.network.volume.VolumeElements.stiffness_rows`);
* :meth:`VolumeTerm.tangent` is its exact tangent stiffness
  :math:`K = -\partial \mathbf f/\partial \mathbf x` (sparse, symmetric) for
  an implicit stepper, :meth:`VolumeTerm.tangent_operator` its product and
  :meth:`VolumeTerm.tangent_bound` a sparser matrix above it (the stepper's
  preconditioner).

Only the nodal formulation is compiled (the per-tet one locks; it exists in the
network module for the measurement that shows it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import ConfigError, InputError
from ..network.springs import tet_volumes
from ..network.volume import J_RANGE, VolumeElements, VolumeSpec, volume_elements
from . import kernels as K

# The six edges of a tet (local node pairs).
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


@dataclass(eq=False)
class VolumeTerm:
    """The volume elements of a network, compiled (a :class:`~.model.ForceTerm`).

    Attributes
    ----------
    n_nodes : int
    elements : VolumeElements
        The numpy model (energy, tangent, stiffness rows).
    tets : ndarray, shape (4, t), uint32
        Rows of tet nodes for the kernels.
    s24 : ndarray, shape (n,)
        ``1 / (24 V_a0)``.
    lam_max : float
        Largest stretch of the whole-run stability bound (the tables' grid end).
    """

    n_nodes: int
    elements: VolumeElements
    tets: np.ndarray
    s24: np.ndarray
    lam_max: float
    node_ptr: np.ndarray
    node_tet: np.ndarray
    node_loc: np.ndarray
    rest_edges: np.ndarray
    _scratch: dict = field(default_factory=dict, repr=False)

    @property
    def bulk_modulus(self) -> float:
        return self.elements.bulk_modulus

    @property
    def spec(self) -> VolumeSpec:
        return self.elements.spec

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[1])

    def kernel(self) -> K.VolumeKernel:
        """The kernels' tuple (its scratch arrays are the term's own: one run at a time)."""
        n, t = self.n_nodes, self.n_tets
        if not self._scratch:
            self._scratch.update(dsum=np.zeros(n), q=np.zeros(n), tv=np.zeros(max(t, 1)))
        s = self._scratch
        return K.VolumeKernel(self.tets, self.s24, self.bulk_modulus / 24.0, s["dsum"], s["q"], s["tv"],
                              self.node_ptr, self.node_tet, self.node_loc)

    # -- evaluation ------------------------------------------------------------
    def forces(self, x: np.ndarray, v: np.ndarray | None = None, **options) -> np.ndarray:
        """Nodal forces (n, 3) [N] at positions *x* (compiled, one thread; *v* and options unused)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise InputError(f"x: expected shape ({self.n_nodes}, 3), got {x.shape}")
        f = np.zeros_like(x)
        K.volume_forces_serial(x, f, self.kernel())
        return f

    def energy(self, x: np.ndarray) -> float:
        """Stored energy [J]."""
        return self.elements.energy(x)

    def tangent(self, x: np.ndarray, v: np.ndarray | None = None, *, definite: bool = False) -> sp.csr_matrix:
        """Tangent stiffness ``K = -df/dx`` at positions *x* (n, 3): symmetric CSR (3n, 3n) [N/m].

        Degrees of freedom in the order of ``x.ravel()`` (node-major, xyz). The
        term has no velocity dependence (*v* is accepted for the interface).
        *definite*: the positive semi-definite part only (no pressure geometric
        part), as the implicit stepper's Newton matrix needs (docs/design/simulator.md, "Scheme").
        """
        return self.elements.tangent(np.asarray(x, dtype=np.float64), definite=definite)

    def tangent_operator(self, x: np.ndarray, *, definite: bool = False):
        """``p -> K p`` for :meth:`tangent`'s K at *x*, without forming it (the Newton iteration's products)."""
        return self.elements.tangent_operator(np.asarray(x, dtype=np.float64), definite=definite)

    def tangent_bound(self, x: np.ndarray) -> sp.csr_matrix:
        """A matrix above the definite tangent with the sparsity of the tets (the per-tet Gauss-Newton
        matrix, :meth:`~esmm.pipeline.network.volume.VolumeElements.tangent_bound`): what the implicit
        stepper factors as its preconditioner."""
        return self.elements.tangent_bound(np.asarray(x, dtype=np.float64))

    def tangent_parts(self, x: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """``(B, w)`` with the definite tangent ``B^T diag(w) B``; row a of B is node a's volume
        (:meth:`~esmm.pipeline.network.volume.VolumeElements.gauss_newton_parts`): what the implicit
        stepper's "mixed" factor holds beside the springs."""
        return self.elements.gauss_newton_parts(np.asarray(x, dtype=np.float64))

    def jacobians(self, x: np.ndarray) -> np.ndarray:
        """Nodal volume ratios ``J_a``, shape (n,)."""
        return self.elements.jacobians(x)

    def volume_ratio(self, x: np.ndarray) -> float:
        """Mesh volume at *x* over its rest volume."""
        return float(tet_volumes(x, self.elements.tets).sum() / self.elements.rest_volume.sum())

    # -- stability -------------------------------------------------------------
    def stiffness_rows(self, *, x: np.ndarray | None = None, window: float | None = None) -> np.ndarray:
        """Per node, a bound of the row sums of the tangent [N/m] (Gershgorin, weighted), shape (n,).

        Over the whole run (no *x*): the rest gradients with every edge at the
        tables' largest stretch and ``|J - 1| <= 0.5``. With positions *x* and
        a stretch *window* delta: the gradients at *x* with every edge allowed
        to grow by ``delta L0`` (a factor ``1 + delta / lam_min``, ``lam_min`` the
        smallest edge stretch at *x*) and the nodes' ``|J - 1|`` by the
        corresponding volume change.
        """
        if x is None or window is None:
            return self.elements.stiffness_rows(growth=self.lam_max, j_bound=J_RANGE)
        x = np.asarray(x, dtype=np.float64)
        t = self.elements.tets
        L = np.linalg.norm(x[t[:, _EDGES[:, 1]]] - x[t[:, _EDGES[:, 0]]], axis=2)
        lam_min = float(np.min(L / self.rest_edges)) if L.size else 1.0
        growth = 1.0 + float(window) / max(lam_min, 1e-3)
        j = np.abs(self.elements.jacobians(x) - 1.0) + (growth**3 - 1.0)
        return self.elements.stiffness_rows(x, growth=growth, j_bound=j)

    def damping_rows(self) -> np.ndarray:
        """The term has no damping: zeros, shape (n,)."""
        return np.zeros(self.n_nodes)

    def state_rows(self, state, x: np.ndarray, delta: float) -> np.ndarray | None:
        """The term has no state: None."""
        return None


def build_volume_term(points: np.ndarray, tets: np.ndarray, spec: VolumeSpec, *, lam_max: float) -> VolumeTerm:
    """The :class:`VolumeTerm` of *spec* on a mesh (rest *points* (n, 3) [m], *tets* (t, 4)).

    Raises
    ------
    ConfigError
        A formulation other than "nodal" (the only one compiled).
    InputError
        No tetrahedra, or tetrahedra not positively oriented at rest.
    """
    if spec.formulation != "nodal":
        raise ConfigError(f"volume formulation: the simulator compiles \"nodal\" only, got {spec.formulation!r}",
                          parameter="formulation")
    el = volume_elements(points, tets, spec)
    n = el.n_nodes
    t = el.tets
    if n >= 2**32 - 1:
        raise InputError(f"network has {n} nodes; the simulator supports fewer than 2**32")
    order = np.argsort(t.ravel(), kind="stable")
    node_of = t.ravel()[order]
    node_ptr = np.searchsorted(node_of, np.arange(n + 1)).astype(np.int64)
    rest = el.rest_volume
    x = np.asarray(points, dtype=np.float64)
    rest_edges = np.linalg.norm(x[t[:, _EDGES[:, 1]]] - x[t[:, _EDGES[:, 0]]], axis=2)
    return VolumeTerm(n_nodes=n, elements=el, tets=np.ascontiguousarray(t.T.astype(np.uint32)),
                      s24=np.ascontiguousarray(1.0 / (24.0 * rest)), lam_max=float(lam_max),
                      node_ptr=node_ptr, node_tet=np.ascontiguousarray(order // 4),
                      node_loc=np.ascontiguousarray(order % 4), rest_edges=rest_edges)


def shape_change(rest: np.ndarray, tets: np.ndarray | None, x: np.ndarray, gravity=None) -> dict:
    """How the organ's shape changed from *rest* to *x* (both (n, 3) [m]): volume, inversions, sag.

    Returns a dict: ``volume_ratio`` (tet volume at *x* over rest; None without
    tets), ``inverted_tets`` (tets of non-positive volume), and with *gravity*
    the sag along it (``sag_median_m``, ``sag_p90_m``, ``sag_max_m``: node
    displacements along gravity) and the organ's ``height_m`` along it before
    and after.
    """
    rest = np.asarray(rest, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    out: dict = {"volume_ratio": None, "inverted_tets": None}
    if tets is not None and len(tets):
        v0 = tet_volumes(rest, tets)
        v = tet_volumes(x, tets)
        out["volume_ratio"] = float(v.sum() / v0.sum())
        out["inverted_tets"] = int(np.count_nonzero(v <= 0.0))
    g = None if gravity is None else np.asarray(gravity, dtype=np.float64)
    if g is not None and np.any(g):
        d = g / np.linalg.norm(g)
        sag = (x - rest) @ d
        out.update(sag_median_m=float(np.median(sag)), sag_p90_m=float(np.percentile(sag, 90)),
                   sag_max_m=float(sag.max()), height_m=[float(np.ptp(rest @ d)), float(np.ptp(x @ d))])
    return out
