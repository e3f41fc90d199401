r"""Homogeneous load cases beyond the uniaxial test: simple shear and any prescribed deformation.

The virtual tensile test (:mod:`~esmm.pipeline.compensation.virtual_tensile`) leaves the specimen's sides
free, which is what measures the Poisson effect. The tests here prescribe a
homogeneous deformation :math:`\mathbf x = \mathbf F \mathbf X` on *every*
boundary node of a network (any mesh: a specimen or an organ) and let the
interior nodes find their equilibrium. A homogeneous continuum satisfies these
conditions with exactly the homogeneous state, so its answers are the
material's: the stored energy :math:`V_0 W(\mathbf F)` and the average nominal
stress :math:`\mathbf P(\mathbf F)`; everything else is the network's. The
network's average nominal stress comes from the boundary reactions
:math:`\mathbf r_a` (the forces that hold the boundary nodes):

.. math::  \bar{\mathbf P} = \frac{1}{V_0}\sum_{a \in \partial} \mathbf r_a \otimes \mathbf X_a

(the exact identity :math:`\int_{\partial\Omega} \mathbf t \otimes \mathbf X\,dA
= \int_\Omega \mathbf P\,dV` of a body in equilibrium). For simple shear
:math:`\mathbf F = \mathbf I + \gamma\,\mathbf e_x \otimes \mathbf e_z`,
:math:`P_{xz} = 2\gamma W_1` whatever the pressure, the clean measure of the
shear response (:func:`virtual_shear_test`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, SimulationError
from ..materials.loading import energy_density, nominal_stress
from ..network.springs import tet_volumes
from ..network.tables import StiffnessTables
from ..network.volume import VolumeSpec, inverted_tets, volume_elements
from .virtual_tensile import Potential, _newton

__all__ = ["PLANES", "HomogeneousResult", "ShearResult", "boundary_nodes", "homogeneous_test", "shear_deformation",
           "virtual_shear_test"]


def boundary_nodes(network) -> np.ndarray:
    """Nodes on the network's boundary triangles, sorted, shape (b,)."""
    return np.unique(np.asarray(network.surface_faces, dtype=np.int64).ravel())


#: Simple-shear planes: (moving axis, gradient axis). "xz": x moves by gamma z.
PLANES = {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}


def shear_deformation(gamma: float, plane: str = "xz") -> np.ndarray:
    """F = I + gamma e_a (x) e_b for *plane* "ab" (default "xz": x moves by gamma z), shape (3, 3)."""
    a, b = PLANES[plane]
    F = np.eye(3)
    F[a, b] = gamma
    return F


@dataclass(frozen=True, eq=False)
class HomogeneousResult:
    """Outcome of :func:`homogeneous_test`, one entry per prescribed deformation.

    Attributes
    ----------
    F : ndarray, shape (m, 3, 3)
    energy : ndarray, shape (m,)
        Network potential at equilibrium [J] (springs and volume term).
    stress : ndarray, shape (m, 3, 3)
        Average nominal stress from the boundary reactions [Pa].
    volume_ratio : ndarray, shape (m,)
        Mesh volume over rest volume.
    inverted : ndarray of int, shape (m,)
        Tetrahedra with non-positive volume.
    iterations : ndarray of int, shape (m,)
    rest_volume : float
        [m3].
    points : ndarray, shape (n, 3)
        Positions at the last deformation.
    path : ndarray, shape (m, n, 3)
        Positions at every deformation.
    """

    F: np.ndarray
    energy: np.ndarray
    stress: np.ndarray
    volume_ratio: np.ndarray
    inverted: np.ndarray
    iterations: np.ndarray
    rest_volume: float
    points: np.ndarray
    path: np.ndarray | None = None


def homogeneous_test(network, tables: StiffnessTables, deformations, *, law: str | None = None,
                     volume: VolumeSpec | None = None, rtol: float = 1e-9, max_iter: int = 40,
                     substeps: int = 4, predictors=None) -> HomogeneousResult:
    """Prescribe ``x = F X`` on the boundary nodes of *network*, relax the interior, measure.

    Parameters
    ----------
    network : SpringNetwork
        With tetrahedra (the mesh volume and the volume term need them).
    tables : StiffnessTables
    deformations : sequence of array_like (3, 3)
        Deformation gradients, visited in order (each from the previous
        equilibrium, in *substeps* linear steps of F).
    law : {"secant", "energy"}, optional
    volume : VolumeSpec, optional
        The volume term on the network's tets (None: springs only).
    rtol, max_iter
        Newton's tolerance and iterations per step (see
        :func:`~esmm.pipeline.compensation.virtual_tensile.virtual_tensile_test`).
    substeps : int
        Linear steps in F between two deformations (halved on failure, 12 times at most).
    predictors : array_like, shape (m, n, 3), optional
        Positions to start Newton's method from at each deformation (e.g. the
        ``path`` of a test with slightly different tables); the boundary is
        reset to ``F X``. Where Newton fails from one, the walk in F takes over.

    Raises
    ------
    ConfigError
        No deformation, or one that is not a finite 3x3 matrix of positive determinant.
    SimulationError
        No equilibrium found.
    """
    law = tables.check_law(law)
    Fs = [np.asarray(F, dtype=np.float64).reshape(3, 3) for F in deformations]
    if not Fs or any(not np.all(np.isfinite(F)) or np.linalg.det(F) <= 0 for F in Fs):
        raise ConfigError("deformations: need 3x3 finite matrices of positive determinant")
    X = network.points
    bnd = boundary_nodes(network)
    fixed = np.zeros((X.shape[0], 3), bool)
    fixed[bnd] = True
    free = ~fixed.ravel()
    pot = Potential(network, tables, law, None if volume is None else volume_elements(X, network.tets, volume))
    V0 = float(tet_volumes(X, network.tets).sum())
    size = float(np.ptp(X, axis=0).max())
    x = X.copy()
    F_prev = np.eye(3)
    out: dict[str, list] = {k: [] for k in ("energy", "stress", "volume_ratio", "inverted", "iterations", "path")}
    if predictors is not None and np.shape(predictors) != (len(Fs), *X.shape):
        raise ConfigError(f"predictors: need shape ({len(Fs)}, {X.shape[0]}, 3), got {np.shape(predictors)}")
    for k, F in enumerate(Fs):
        ok = False
        if predictors is not None:
            guess = np.array(predictors[k], dtype=np.float64)
            guess[bnd] = X[bnd] @ F.T
            ok, xg, its, _ = _newton(guess, pot, free, size, rtol, max_iter)
            x = xg if ok else x
        if not ok:
            x, its = _walk(x, X, F_prev, F, pot, free, bnd, size, rtol, max_iter, substeps)
        F_prev = F
        r = -pot.forces(x)[bnd]                      # reactions holding the boundary
        out["energy"].append(pot.energy(x))
        out["stress"].append(r.T @ X[bnd] / V0)
        out["volume_ratio"].append(float(tet_volumes(x, network.tets).sum()) / V0)
        out["inverted"].append(inverted_tets(x, network.tets))
        out["iterations"].append(its)
        out["path"].append(x)
    return HomogeneousResult(F=np.asarray(Fs), energy=np.asarray(out["energy"]), stress=np.asarray(out["stress"]),
                             volume_ratio=np.asarray(out["volume_ratio"]), inverted=np.asarray(out["inverted"]),
                             iterations=np.asarray(out["iterations"]), rest_volume=V0, points=x,
                             path=np.asarray(out["path"]))


def _walk(x, X, F0, F1, pot, free, bnd, size, rtol, max_iter, substeps):
    """Equilibrium at F1 from the one at F0, by linear steps in F (cut when Newton fails)."""
    total = 0
    s, ds, cuts = 0.0, 1.0 / max(1, int(substeps)), 0
    while s < 1.0 - 1e-14:
        t = min(1.0, s + ds)
        Fa = F0 + s * (F1 - F0)
        Fb = F0 + t * (F1 - F0)
        trial = x @ (Fb @ np.linalg.inv(Fa)).T          # affine predictor
        trial[bnd] = X[bnd] @ Fb.T
        ok, trial, its, _ = _newton(trial, pot, free, size, rtol, max_iter)
        total += its
        if ok:
            x, s = trial, t
            continue
        cuts += 1
        if cuts > 12:
            raise SimulationError(f"homogeneous test: no equilibrium on the way to F = {F1.tolist()} after 12 "
                                  "step cuts; use smaller deformations")
        ds /= 2.0
    return x, total


@dataclass(frozen=True, eq=False)
class ShearResult:
    """Outcome of :func:`virtual_shear_test`.

    Attributes
    ----------
    gamma : ndarray, shape (m,)
    stress : ndarray, shape (m,)
        Network shear stress ``P_xz`` from the boundary reactions [Pa].
    reference : ndarray, shape (m,)
        The material's ``P_xz = 2 gamma W_1`` [Pa].
    energy, energy_reference : ndarray, shape (m,)
        Network potential and ``V0 W(gamma)`` [J].
    volume_ratio : ndarray, shape (m,)
    inverted : ndarray of int, shape (m,)
    info : dict
    path : ndarray, shape (m, n, 3) or None
        Positions at every amount of shear.
    """

    gamma: np.ndarray
    stress: np.ndarray
    reference: np.ndarray
    energy: np.ndarray
    energy_reference: np.ndarray
    volume_ratio: np.ndarray
    inverted: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)
    path: np.ndarray | None = None

    @property
    def rel_error(self) -> np.ndarray:
        """``(stress - reference) / |reference|``, shape (m,)."""
        return (self.stress - self.reference) / np.abs(self.reference)

    @property
    def max_abs_rel_error(self) -> float:
        return float(np.max(np.abs(self.rel_error)))

    @property
    def shear_modulus_ratio(self) -> float:
        """Network over material secant shear modulus at the smallest gamma."""
        return float(self.stress[0] / self.reference[0])


def virtual_shear_test(network, tables: StiffnessTables, *, gamma=None, law: str | None = None, material=None,
                       volume: VolumeSpec | None = None, plane: str = "xz", rtol: float = 1e-9,
                       predictors=None) -> ShearResult:
    """Simple shear ``x = X + gamma z e_x`` (*plane* "xz") prescribed on the whole boundary of *network*.

    Parameters
    ----------
    network : SpringNetwork
        Any tet network (a specimen's, an organ's).
    tables : StiffnessTables
    gamma : array_like, shape (m,), optional
        Amounts of shear, increasing from 0 (default 0.05 to 0.4, 8 steps).
    material : Material, optional
        The continuum reference (default: none; then ``reference`` is NaN).
    volume : VolumeSpec, optional
    plane : {"xz", "xy", "yz"}
        The moving and the gradient axis (mesh frame); ``stress`` is ``P_ab``.
    predictors : array_like, shape (m, n, 3), optional
        Starting positions per amount of shear (:func:`homogeneous_test`).
    """
    if plane not in PLANES:
        raise ConfigError(f"plane: unknown {plane!r}; use one of {', '.join(PLANES)}")
    a, b = PLANES[plane]
    g = np.linspace(0.05, 0.4, 8) if gamma is None else np.asarray(gamma, dtype=np.float64).ravel()
    if g.size == 0 or not np.all(np.isfinite(g)) or np.any(np.diff(np.concatenate([[0.0], g])) <= 0):
        raise ConfigError("gamma: need increasing positive amounts of shear")
    res = homogeneous_test(network, tables, [shear_deformation(v, plane) for v in g], law=law, volume=volume,
                           rtol=rtol, predictors=predictors)
    if material is not None:
        params = material.params_for(None if material.is_isotropic else "z")
        ref = np.asarray(nominal_stress(material.model_obj, params, "simple_shear", g), dtype=np.float64)
        eref = res.rest_volume * np.asarray(energy_density(material.model_obj, params, "simple_shear", g))
    else:
        ref = eref = np.full(g.size, np.nan)
    return ShearResult(gamma=g, stress=res.stress[:, a, b], reference=ref, energy=res.energy, energy_reference=eref,
                       volume_ratio=res.volume_ratio, inverted=res.inverted,
                       info={"nodes": int(network.n_nodes), "boundary_nodes": int(boundary_nodes(network).size),
                             "plane": plane}, path=res.path)
