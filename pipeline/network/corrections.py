r"""Per-spring stiffness corrections: a multiplier on each spring fitted to a reference response.

The network of a coarse first-order mesh is stiff where the displacement field bends
over few elements (docs/design/validation.md, "What the network's errors are, and
why"). This module fits a multiplier :math:`e^{\theta_s}` on each spring's stiffness
(at every stretch) so that the network's *linearised* response to a set of load cases
matches a reference response given on the network's nodes (the second-order continuum's,
computed elsewhere), and measures the result (docs/design/realtime.md, "Per-spring
corrections against the continuum").

The linear network at rest is

.. math::

    \mathbf K(\theta) = \mathbf B^{\mathsf T}\,\mathrm{diag}(k_s e^{\theta_s})\,\mathbf B + \mathbf K_V,

with :math:`\mathbf B` the springs' linearised extensions (row s:
:math:`\mathbf n_s\cdot(\mathbf e_j - \mathbf e_i)`), :math:`k_s` each spring's axial
stiffness at rest and :math:`\mathbf K_V` the volume term's tangent at rest (the term is
not corrected). A load case holds a set of nodes (the anchor) for every case, applies
gravity on the lumped masses and may move a patch of nodes by a prescribed displacement
(a grasp); the patch enters by Lagrange multipliers, so that every case shares one
factor of the anchor-held matrix. The objective, over the cases c,

.. math::

    J(\theta) = \frac{1}{2N}\sum_c\Big[\frac{\sum_i w_i|\mathbf u_{n,i} - \mathbf u_{c,i}|^2}
      {\sum_i w_i\,\max_i|\mathbf u_{c,i}|^2}
      + \beta\frac{|\mathbf R_n - \mathbf R_c|^2}{|\mathbf R_c|^2}\Big]
      + \frac{\alpha}{2}|\theta|^2 + \frac{\gamma}{2}|\mathbf D\theta|^2,

is the squared L2 error of ``esmm validate`` plus the squared force error of a patch's
reaction, with a Tikhonov term and a smoothness term (:math:`\mathbf D\theta`: each
spring's θ minus the mean of the springs at its two nodes). Its gradient is one adjoint
solve per case: :math:`\partial J/\partial\theta_s = -k_s e^{\theta_s}(\mathbf B\mathbf a)_s
(\mathbf B\mathbf u)_s` with :math:`\mathbf a` the adjoint field (tested against finite
differences).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from ..errors import ConfigError
from ..linalg.newton import OrderedFactor, free_order, ldlt
from .tables import spring_factors
from .volume import nodal_volumes, volume_elements

__all__ = ["LinearLoad", "LinearNetwork", "CorrectionObjective", "extension_matrix", "rest_stiffness",
           "smoothing_operator", "fit_corrections", "linear_errors"]


@dataclass(frozen=True, eq=False)
class LinearLoad:
    """One linear load case on top of the held nodes.

    Attributes
    ----------
    name : str
    gravity : ndarray, shape (3,)
        [m/s2] on the lumped masses.
    patch : ndarray of int, shape (k,)
        Nodes moved by *displacement* (all three components; none: a gravity case).
    displacement : ndarray, shape (k, 3)
        [m].
    """

    name: str
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    patch: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    displacement: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def extension_matrix(network) -> sp.csr_matrix:
    """``B``, shape (s, 3n): row s maps nodal displacements to spring s's extension ``n . (u_j - u_i)``."""
    X, S = network.points, network.springs
    d = X[S[:, 1]] - X[S[:, 0]]
    nrm = d / np.linalg.norm(d, axis=1)[:, None]
    s = S.shape[0]
    rows = np.repeat(np.arange(s), 6)
    cols = np.concatenate([3 * S[:, [0]] + np.arange(3), 3 * S[:, [1]] + np.arange(3)], axis=1).ravel()
    return sp.csr_matrix((np.concatenate([-nrm, nrm], axis=1).ravel(), (rows, cols)),
                         shape=(s, 3 * network.n_nodes))


def rest_stiffness(network, tables) -> np.ndarray:
    """Each spring's axial stiffness at rest, dF/dL at L0 [N/m], shape (s,) (the tables' own law)."""
    a = spring_factors(tables, network)
    return np.einsum("sd,ds->s", a, tables.tangent_function(np.ones(network.n_springs), law=tables.default_law))


def smoothing_operator(network) -> sp.csr_matrix:
    """``D``, shape (s, s): each spring's value minus the mean, over its two nodes, of the springs at each node."""
    s, n = network.n_springs, network.n_nodes
    S = network.springs
    inc = sp.csr_matrix((np.ones(2 * s), (S.ravel(), np.repeat(np.arange(s), 2))), shape=(n, s))
    deg = np.asarray(inc.sum(axis=1)).ravel()
    mean_at_node = sp.diags(1.0 / np.maximum(deg, 1.0)) @ inc
    half = sp.csr_matrix((np.full(2 * s, 0.5), (np.repeat(np.arange(s), 2), S.ravel())), shape=(s, n))
    return (sp.identity(s) - half @ mean_at_node).tocsr()


class _Factor:
    """The anchor-held matrix K_ff(θ) factored once, and the solves of every case on it."""

    def __init__(self, K, free: np.ndarray, order: np.ndarray):
        self.K, self.free = K, free
        A = K[free][:, free]
        try:                 # K_ff is positive definite: an LDLT without pivoting in a nested-dissection order
            self.fac = OrderedFactor(order, ldlt(A, order))
        except RuntimeError:
            self.fac = spl.splu(A.tocsc(), permc_spec="COLAMD")

    def solve(self, b_full: np.ndarray) -> np.ndarray:
        """``K_ff^-1 b`` on the free dofs (held ones zero) of *b_full* (3n,) or (3n, k)."""
        out = np.zeros(b_full.shape)
        out[self.free] = self.fac.solve(np.ascontiguousarray(b_full[self.free]))
        return out

    def patch_columns(self, dofs: np.ndarray):
        """``Z = K^-1 C^T`` (3n, m) and ``S = C Z`` (m, m) for the patch's dofs."""
        E = np.zeros((self.K.shape[0], dofs.size))
        E[dofs, np.arange(dofs.size)] = 1.0
        Z = self.solve(E)
        return Z, Z[dofs]


class LinearNetwork:
    """The network linearised at rest with its *held* nodes clamped (module doc)."""

    def __init__(self, network, tables, held, *, volume: bool = True):
        self.network = network
        self.B = extension_matrix(network)
        self.BT = self.B.T.tocsr()
        self.k0 = rest_stiffness(network, tables)
        n = network.n_nodes
        if volume and network.volume_term is not None and network.tets is not None:
            self.Kv = volume_elements(network.points, network.tets, network.volume_term).tangent(network.points)
        else:
            self.Kv = sp.csr_matrix((3 * n, 3 * n))
        held = np.unique(np.asarray(held, dtype=np.int64))
        if held.size == 0:
            raise ConfigError("held: the linear network needs held nodes (an anchor) to be solvable",
                              parameter="held")
        mask = np.zeros((n, 3), bool)
        mask[held] = True
        self.held = held
        self.free = np.flatnonzero(~mask.ravel())
        self._order = None

    def matrix(self, theta: np.ndarray):
        return (self.BT @ sp.diags(self.k0 * np.exp(theta)) @ self.B + self.Kv).tocsr()

    def factor(self, theta: np.ndarray) -> _Factor:
        """K(θ) on the free dofs, factored (the fill-reducing order found once: the pattern stays)."""
        K = self.matrix(theta)
        if self._order is None:
            free = np.zeros(K.shape[0], bool)
            free[self.free] = True
            self._order = free_order(K, free)
        return _Factor(K, self.free, self._order)

    def solve(self, fac: _Factor, load: LinearLoad, cols=None):
        """``(u (3n,), R (3,), (Z, S, dofs))``: displacements and the patch's reaction (zeros without a patch)."""
        f = (self.network.mass[:, None] * np.asarray(load.gravity, dtype=np.float64)[None, :]).ravel()
        u0 = fac.solve(f)
        if load.patch.size == 0:
            return u0, np.zeros(3), None
        keep = ~np.isin(load.patch, self.held)           # a held node stays held
        dofs = (3 * load.patch[keep][:, None] + np.arange(3)).ravel()
        Z, S = fac.patch_columns(dofs) if cols is None else cols[:2]
        mu = np.linalg.solve(S, u0[dofs] - np.asarray(load.displacement)[keep].ravel())
        u = u0 - Z @ mu
        return u, mu.reshape(-1, 3).sum(axis=0), (Z, S, dofs)


class CorrectionObjective:
    """:math:`J(\\theta)` and its gradient on *loads* with reference displacements and reactions (module doc).

    Parameters
    ----------
    linear : LinearNetwork
    loads : sequence of LinearLoad
    references : sequence of (ndarray (n, 3), ndarray (3,))
        The reference's displacements on the network's nodes [m] and the patch's reaction [N].
    alpha, gamma, beta : float
        Tikhonov, smoothness and force weights.
    """

    def __init__(self, linear: LinearNetwork, loads, references, *, alpha: float = 1e-4, gamma: float = 1e-3,
                 beta: float = 1.0):
        self.linear, self.loads, self.references = linear, list(loads), list(references)
        net = linear.network
        self.w = nodal_volumes(net.points, net.tets, net.n_nodes) if net.tets is not None else net.mass
        self.alpha, self.gamma, self.beta = float(alpha), float(gamma), float(beta)
        self.D = smoothing_operator(net)
        self.DtD = (self.D.T @ self.D).tocsr()
        self.evaluations = 0

    def _case(self, theta, fac, load, ref, cache):
        lin = self.linear
        u_c, R_c = ref
        key = tuple(load.patch.tolist())
        u, R, cols = lin.solve(fac, load, cache.get(key))
        if cols is not None:
            cache[key] = cols
        umax2 = float(np.max(np.sum(np.asarray(u_c) ** 2, axis=1)))
        wd = np.repeat(self.w, 3) / (np.sum(self.w) * umax2)
        r = u - np.asarray(u_c).ravel()
        J = 0.5 * float(np.sum(wd * r * r))
        g_u = wd * r
        g_u[lin.held.repeat(3) * 3 + np.tile(np.arange(3), lin.held.size)] = 0.0
        if cols is None:
            a = fac.solve(g_u)
        else:
            Z, S, dofs = cols
            scale = float(np.dot(R_c, R_c))
            J += 0.5 * self.beta * float(np.dot(R - R_c, R - R_c)) / scale
            g_R = self.beta * (R - R_c) / scale
            g_u[dofs] = 0.0
            a0 = fac.solve(g_u)
            a_mu = np.linalg.solve(S, a0[dofs] - np.tile(g_R, dofs.size // 3))
            a = a0 - Z @ a_mu
        k = lin.k0 * np.exp(theta)
        return J, -k * (lin.B @ a) * (lin.B @ u)

    def __call__(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        self.evaluations += 1
        fac = self.linear.factor(theta)
        J, grad, cache = 0.0, np.zeros_like(theta), {}
        for load, ref in zip(self.loads, self.references, strict=True):
            j, g = self._case(theta, fac, load, ref, cache)
            J, grad = J + j, grad + g
        J, grad = J / len(self.loads), grad / len(self.loads)
        Dt = self.D @ theta
        J += 0.5 * self.alpha * float(theta @ theta) + 0.5 * self.gamma * float(Dt @ Dt)
        return J, grad + self.alpha * theta + self.gamma * (self.DtD @ theta)


def fit_corrections(objective: CorrectionObjective, *, bound: float = 4.0, max_iter: int = 200,
                    theta0: np.ndarray | None = None):
    """θ minimising *objective* within ``|θ| <= log(bound)`` (L-BFGS-B); ``(theta, scipy result)``."""
    from scipy.optimize import minimize

    if not (np.isfinite(bound) and bound > 1.0):
        raise ConfigError(f"bound: must be a factor above 1, got {bound!r}", parameter="bound")
    s = objective.linear.network.n_springs
    x0 = np.zeros(s) if theta0 is None else np.asarray(theta0, dtype=np.float64)
    b = float(np.log(bound))
    _, g0 = objective(x0)
    res = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=[(-b, b)] * s,
                   options={"maxiter": int(max_iter), "maxfun": 2 * int(max_iter), "ftol": 1e-14,
                            "gtol": 1e-9 * max(float(np.abs(g0).max()), 1e-300), "maxcor": 30})
    return res.x, res


def linear_errors(u, R, reference, weights, *, force_scale: float | None = None) -> tuple[float, float]:
    """``(L2 error, force error)`` of a linear solution against its reference, as ``esmm validate`` defines them.

    *force_scale* divides the force error (default: the reference reaction's magnitude).
    """
    u_c, R_c = reference
    diff = np.linalg.norm(np.asarray(u).reshape(-1, 3) - u_c, axis=1)
    umax = float(np.linalg.norm(u_c, axis=1).max())
    l2 = float(np.sqrt(np.sum(weights * diff**2) / np.sum(weights))) / umax
    fs = float(np.linalg.norm(R_c)) if force_scale is None else float(force_scale)
    return l2, (float(np.linalg.norm(np.asarray(R) - R_c) / fs) if fs > 0 else 0.0)
