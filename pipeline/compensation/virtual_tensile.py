r"""Virtual tensile test: does the spring network behave like the tissue?

A cylindrical specimen (the paper's Fig. 3) is meshed with gmsh (in-process),
turned into a spring network with :func:`~esmm.pipeline.network.springs.network_from_tets`
and stretched quasi-statically along its axis (z) with the stiffness tables.

Boundary conditions (frictionless grips): every node of the bottom face has
:math:`z = 0`, every node of the top face :math:`z = \lambda H`; lateral
motion is free everywhere except the rigid modes: the node at the centre of
the bottom face is held in x and y, the node at :math:`(R, 0, 0)` in y. A
homogeneous continuum satisfies these conditions with exactly the uniaxial
state, so the continuum answer is the material's uniaxial nominal stress
:math:`P(\lambda) = W_T'(\lambda)` and any difference is the network's.

Each load step solves static equilibrium :math:`\nabla E(\mathbf x) = 0` of the
spring potential (:func:`~esmm.pipeline.network.forcelaw.spring_energy`;
both force laws are conservative) by Newton's method with the exact sparse
tangent (:func:`~esmm.pipeline.network.forcelaw.tangent_stiffness`), a shift
when the tangent is not positive definite, an Armijo line search on the
energy and automatic step cutting. The measured nominal stress is the axial
reaction of the top face over the reference cross-section
:math:`A_0 = V_{mesh}/H` (the exact mean section of the meshed cylinder).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, MeshingError, SimulationError
from ..linalg.newton import descent_direction, free_order
from ..materials.loading import nominal_stress
from ..mesh.gmsh_model import gmsh_model, tetrahedra
from ..network import forcelaw
from ..network.springs import network_from_tets, tet_volumes
from ..network.tables import StiffnessTables
from ..network.volume import VolumeElements, VolumeSpec, volume_elements
from ..progress import ensure

__all__ = [
    "Potential", "Specimen", "TensileResult", "cylinder_specimen", "virtual_tensile_test", "continuum_stress",
]


@dataclass(frozen=True, eq=False)
class Specimen:
    """A meshed cylinder and its spring network, axis along z from 0 to ``length``.

    Attributes
    ----------
    network : SpringNetwork
        Built with the identity fibre frame (fibre x, y, z = mesh axes).
    radius, length : float
        Geometry [m].
    size : float
        Target element size given to gmsh [m].
    bottom, top : ndarray of int, shape (k,)
        Nodes on the end faces.
    centre, rim : int
        Bottom-face nodes at (0, 0, 0) and (R, 0, 0) (rigid-mode suppression).
    area : float
        Reference cross-section ``A0 = V_mesh / length`` [m2].
    """

    network: Any
    radius: float
    length: float
    size: float
    bottom: np.ndarray
    top: np.ndarray
    centre: int
    rim: int
    area: float

    @property
    def n_nodes(self) -> int:
        return int(self.network.n_nodes)

    def volume_elements(self, spec: VolumeSpec) -> VolumeElements:
        """The volume term *spec* on this specimen's tetrahedra."""
        return volume_elements(self.network.points, self.network.tets, spec)

    def describe(self) -> dict[str, Any]:
        """Plain-data summary (for metadata and reports)."""
        L0 = self.network.rest_length
        return {
            "shape": "cylinder", "radius_m": self.radius, "length_m": self.length,
            "size_m": self.size, "nodes": int(self.network.n_nodes),
            "springs": int(self.network.n_springs), "tets": int(self.network.n_tets),
            "median_rest_length_m": float(np.median(L0)), "area_m2": self.area,
        }


def cylinder_specimen(*, radius: float = 5e-3, length: float = 20e-3, size: float = 2.5e-3,
                      algorithm: int = 1, reporter=None) -> Specimen:
    """Mesh a cylinder with gmsh and build its spring network.

    Parameters
    ----------
    radius, length : float
        Cylinder radius and height [m].
    size : float
        Target tetrahedron edge length [m] (gmsh ``MeshSizeMin = MeshSizeMax``).
    algorithm : int
        gmsh ``Mesh.Algorithm3D`` (1 = Delaunay, the mesher of ``esmm prepare``).

    Returns
    -------
    Specimen

    Raises
    ------
    ConfigError
        Non-positive geometry, or a size that gives fewer than 2 elements across
        the radius or more than ~200 000 nodes.
    MeshingError
        gmsh produced no tetrahedra.
    """
    rep = ensure(reporter)
    for name, v in (("radius", radius), ("length", length), ("size", size)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ConfigError(f"{name}: must be a positive length in metres, got {v!r}")
    if size > radius:
        raise ConfigError(f"size: {size:g} m is larger than the radius {radius:g} m; use a size "
                          "of at most radius/2")
    est_nodes = math.pi * radius**2 * length / size**3 * 1.2
    if est_nodes > 2e5:
        raise ConfigError(f"size: {size:g} m would give about {est_nodes:.0f} nodes; use a larger size")
    # Meshed in units of the element size, then scaled: cylinders of the same shape in elements are
    # then similar (gmsh's tolerances are absolute), so the scale-free calibration does not depend on
    # the organ's element size (the compensation's cache key holds none).
    points, tets = _gmsh_cylinder(radius / size, length / size, 1.0, algorithm)
    points = points * size
    if tets.shape[0] == 0:
        raise MeshingError(f"gmsh made no tetrahedra for a cylinder R={radius:g} m, H={length:g} m "
                           f"at size {size:g} m; try another size")

    class _Mesh:  # what network_from_tets reads
        pass

    mesh = _Mesh()
    mesh.points, mesh.tets = points, tets
    net = network_from_tets(mesh, fibre_frame=None, reorder="rcm")
    X = net.points
    tol = 1e-7 * length
    bottom = np.flatnonzero(np.abs(X[:, 2]) <= tol)
    top = np.flatnonzero(np.abs(X[:, 2] - length) <= tol)
    centre = int(bottom[np.argmin(np.linalg.norm(X[bottom, :2], axis=1))])
    rim = int(bottom[np.argmin(np.linalg.norm(X[bottom, :2] - [radius, 0.0], axis=1))])
    if (np.linalg.norm(X[centre, :2]) > 1e-9 * radius
            or np.linalg.norm(X[rim, :2] - [radius, 0.0]) > 1e-9 * radius):
        raise MeshingError("the specimen mesh has no node at the bottom centre or at (R, 0, 0); "
                           "this gmsh build does not honour embedded points")
    area = net.total_volume() / length
    spec = Specimen(network=net, radius=float(radius), length=float(length), size=float(size),
                    bottom=bottom, top=top, centre=centre, rim=rim, area=float(area))
    rep.step(f"specimen: cylinder R={radius * 1e3:g} mm, H={length * 1e3:g} mm, size "
             f"{size * 1e3:g} mm: {net.n_nodes} nodes, {net.n_springs} springs, {net.n_tets} tets")
    return spec


def _gmsh_cylinder(radius: float, length: float, size: float, algorithm: int):
    """Tetrahedra of a cylinder with nodes at the bottom centre and at (R, 0, 0)."""
    with gmsh_model("the specimen") as gmsh:
        occ = gmsh.model.occ
        vol = occ.addCylinder(0.0, 0.0, 0.0, 0.0, 0.0, length, radius)
        centre = occ.addPoint(0.0, 0.0, 0.0)
        occ.synchronize()
        # The bottom face is the plane surface at z = 0.
        bottom = None
        for dim, tag in gmsh.model.getBoundary([(3, vol)], oriented=False):
            com = occ.getCenterOfMass(dim, tag)
            if abs(com[2]) < 1e-9 * length and gmsh.model.getType(dim, tag) == "Plane":
                bottom = tag
        if bottom is None:  # pragma: no cover - OCC always makes a plane bottom face
            raise MeshingError("gmsh: cannot find the bottom face of the cylinder")
        gmsh.model.mesh.embed(0, [centre], 2, bottom)
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", int(algorithm))
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        return tetrahedra(gmsh)


# ---------------------------------------------------------------------------
# Solver
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class TensileResult:
    """Outcome of :func:`virtual_tensile_test`.

    Attributes
    ----------
    stretch : ndarray, shape (m,)
        Imposed axial stretches.
    stress : ndarray, shape (m,)
        Network nominal stress: top reaction / A0 [Pa].
    reference : ndarray, shape (m,)
        Continuum uniaxial nominal stress at the same stretches [Pa].
    lateral_stretch : ndarray, shape (m,)
        Mean radial stretch of the side-surface nodes in the middle third.
    iterations : ndarray of int, shape (m,)
        Newton iterations of each step (summed over sub-steps).
    law : str
    volume_factor : float
    residual : float
        Largest relative equilibrium residual at convergence.
    points : ndarray, shape (n, 3)
        Node positions at the last stretch [m].
    path : ndarray, shape (m, n, 3) or None
        Positions at every stretch (``keep_path=True``).
    info : dict
        The specimen's :meth:`Specimen.describe`.
    volume_ratio : ndarray, shape (m,) or None
        Specimen volume over its rest volume at each stretch (the tets' volume).
    """

    stretch: np.ndarray
    stress: np.ndarray
    reference: np.ndarray
    lateral_stretch: np.ndarray
    iterations: np.ndarray
    law: str
    volume_factor: float
    residual: float
    points: np.ndarray | None = None
    path: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)
    volume_ratio: np.ndarray | None = None

    @property
    def rel_error(self) -> np.ndarray:
        """``(stress - reference) / |reference|`` per stretch, shape (m,)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return (self.stress - self.reference) / np.abs(self.reference)

    @property
    def max_abs_rel_error(self) -> float:
        """Largest ``|rel_error|`` over the stretches."""
        return float(np.nanmax(np.abs(self.rel_error)))

    @property
    def rms_rel_error(self) -> float:
        """Root mean square of ``rel_error``."""
        return float(np.sqrt(np.nanmean(self.rel_error**2)))

    def summary(self) -> dict[str, Any]:
        """Plain-data summary."""
        return {
            "law": self.law, "volume_factor": self.volume_factor,
            "stretch": [float(self.stretch.min()), float(self.stretch.max())],
            "points": int(self.stretch.size),
            "max_abs_rel_error": self.max_abs_rel_error, "rms_rel_error": self.rms_rel_error,
            "residual": self.residual,
        }


def continuum_stress(material, stretch, *, direction: str | None = "z") -> np.ndarray:
    """Uniaxial nominal stress of *material* along *direction* [Pa], shape of *stretch*."""
    if getattr(material, "is_isotropic", True):
        direction = None
    return np.asarray(nominal_stress(material.model_obj, material.params_for(direction), "uniaxial",
                                     np.asarray(stretch, dtype=np.float64)), dtype=np.float64)


def virtual_tensile_test(specimen: Specimen, tables: StiffnessTables, *, stretch=None,
                         law: str | None = None, material=None, rtol: float = 1e-9,
                         max_iter: int = 40, predictors=None, keep_path: bool = False,
                         volume: VolumeSpec | None = None, reporter=None) -> TensileResult:
    """Stretch *specimen* quasi-statically and measure its nominal stress.

    Parameters
    ----------
    specimen : Specimen
    tables : StiffnessTables
        Used with their ``volume_factor``.
    stretch : array_like, shape (m,), optional
        Axial stretches, visited in order from 1 (all > 1, or all < 1, monotonic);
        default 30 steps from 1.01 to 1.30.
    law : {"secant", "energy"}, optional
        Default: the tables' default law.
    material : Material, optional
        Continuum reference; default: the tables' own uniaxial stress along z
        (``tables.stress[2]``, the material's W' to interpolation accuracy).
    rtol : float
        Convergence: largest free-node force residual below ``rtol`` times the
        largest spring force.
    max_iter : int
        Newton iterations per (sub-)step before the step is halved.
    predictors : sequence of ndarray, shape (m, n, 3), optional
        Initial guesses of the node positions at each stretch (e.g. the
        ``path`` of an earlier test with slightly different tables); the grip
        coordinates are reset exactly. A step whose guess does not converge
        falls back to continuation from the previous stretch.
    keep_path : bool
        Keep the equilibrium positions of every stretch in ``result.path``.
    volume : VolumeSpec, optional
        The volume term (:mod:`~esmm.pipeline.network.volume`) on the
        specimen's tetrahedra; None: springs only. The measured stress is
        then the reaction of both.

    Returns
    -------
    TensileResult

    Raises
    ------
    ConfigError
        Bad stretch list.
    SimulationError
        Equilibrium not found even after cutting the step 12 times.
    """
    rep = ensure(reporter)
    law = tables.check_law(law)
    lam_list = _check_stretches(stretch)
    if predictors is not None and len(predictors) != lam_list.size:
        raise ConfigError(f"predictors: need one position array per stretch ({lam_list.size}), "
                          f"got {len(predictors)}")
    net = specimen.network
    pot = Potential(net, tables, law, None if volume is None else specimen.volume_elements(volume))
    with rep.task(f"virtual tensile test ({law} law)", total=lam_list.size) as advance:
        x, worst, out_P, out_lat, out_it, out_J, path = _stretch_path(
            specimen, pot, lam_list, predictors, rtol=rtol, max_iter=max_iter, keep_path=keep_path,
            advance=advance)
    stress = np.asarray(out_P)
    if material is not None:
        ref = continuum_stress(material, lam_list)
    else:
        ref = tables.force_function(lam_list, law="energy")[2] * 1.0
    res = TensileResult(stretch=lam_list, stress=stress, reference=ref,
                        lateral_stretch=np.asarray(out_lat), iterations=np.asarray(out_it),
                        law=law, volume_factor=tables.volume_factor, residual=worst, points=x,
                        path=np.asarray(path) if keep_path else None,
                        info={"specimen": specimen.describe()}, volume_ratio=np.asarray(out_J))
    rep.step(f"virtual tensile test ({law}, c={tables.volume_factor:.4g}): max |error| "
             f"{100 * res.max_abs_rel_error:.2f} % over stretch {lam_list.min():.3g}-{lam_list.max():.3g}")
    return res


def _stretch_path(specimen: Specimen, pot: Potential, lam_list, predictors, *, rtol: float, max_iter: int,
                  keep_path: bool, advance):
    """Visit the stretches in order and measure each equilibrium.

    Returns the last positions, the largest residual, and per stretch the
    nominal stress on the top grip [Pa], the mean lateral stretch of the side,
    the Newton iterations, the volume ratio J and (if *keep_path*) the positions.
    """
    net = specimen.network
    X = net.points
    free = _free_dofs(specimen)
    side = _side_nodes(specimen)
    r0 = np.linalg.norm(X[side, :2], axis=1)
    V0 = net.total_volume()
    x = X.copy()
    lam_prev = 1.0
    out_P, out_lat, out_it, out_J, path = [], [], [], [], []
    worst = 0.0
    for k, lam in enumerate(lam_list):
        predictor = None if predictors is None else predictors[k]
        x, its, res = _equilibrium(specimen, pot, free, x, lam_prev, lam, predictor, rtol, max_iter)
        worst = max(worst, res)
        lam_prev = lam
        f = pot.forces(x)
        out_P.append(-f[specimen.top, 2].sum() / specimen.area)
        out_J.append(float(tet_volumes(x, net.tets).sum()) / V0)
        out_lat.append(float(np.mean(np.linalg.norm(x[side, :2], axis=1) / r0)))
        out_it.append(its)
        if keep_path:
            path.append(x.copy())
        advance(1)
    return x, worst, out_P, out_lat, out_it, out_J, path


def _check_stretches(stretch) -> np.ndarray:
    """The axial stretches to visit, shape (m,): default 30 from 1.01 to 1.30; monotonic away from 1."""
    lam_list = np.linspace(1.01, 1.30, 30) if stretch is None else np.asarray(stretch, dtype=np.float64).ravel()
    if lam_list.size == 0 or not np.all(np.isfinite(lam_list)) or np.any(lam_list <= 0):
        raise ConfigError("stretch: need a non-empty list of positive finite stretches")
    steps = np.diff(np.concatenate([[1.0], lam_list]))
    if not (np.all(steps > 0) or np.all(steps < 0)):
        raise ConfigError("stretch: must move monotonically away from 1 (all increasing above 1 "
                          "or all decreasing below 1)")
    return lam_list


def _free_dofs(specimen: Specimen) -> np.ndarray:
    """Free coordinates, shape (3 n,): the grips hold z at both ends; the centre line and rim stop rigid motion."""
    fixed = np.zeros((specimen.network.points.shape[0], 3), bool)
    fixed[specimen.bottom, 2] = True
    fixed[specimen.top, 2] = True
    fixed[specimen.centre, :2] = True
    fixed[specimen.rim, 1] = True
    return ~fixed.ravel()


def _equilibrium(specimen: Specimen, pot: Potential, free, x, lam_prev: float, lam: float, predictor,
                 rtol: float, max_iter: int):
    """Equilibrium positions at stretch *lam*: ``(x, iterations, residual)``.

    Newton from the *predictor* (grip coordinates reset exactly) if one of the
    right shape is given and it converges; otherwise continuation from the
    equilibrium *x* at *lam_prev*.
    """
    H = specimen.length
    if predictor is not None and np.shape(predictor) == x.shape:
        guess = np.array(predictor, dtype=np.float64)
        guess[specimen.bottom, 2] = 0.0
        guess[specimen.top, 2] = lam * H
        guess[specimen.centre, :2] = 0.0
        guess[specimen.rim, 1] = 0.0
        ok, xg, its, res = _newton(guess, pot, free, H, rtol, max_iter)
        if ok:
            return xg, its, res
    return _advance(x, lam_prev, lam, pot, free, H, rtol, max_iter)


def _side_nodes(specimen: Specimen) -> np.ndarray:
    X = specimen.network.points
    r = np.linalg.norm(X[:, :2], axis=1)
    z = X[:, 2]
    H = specimen.length
    mask = (np.abs(r - specimen.radius) <= 1e-6 * specimen.radius) & (z > H / 3) & (z < 2 * H / 3)
    if not np.any(mask):
        mask = np.abs(r - specimen.radius) <= 1e-6 * specimen.radius
    return np.flatnonzero(mask)


def _advance(x, lam_from, lam_to, pot: Potential, free, H, rtol, max_iter):
    """Move the grips from lam_from to lam_to, cutting the step when Newton fails."""
    total_its = 0
    worst = 0.0
    lam_cur = lam_from
    dlam = lam_to - lam_from
    cuts = 0
    while (lam_to - lam_cur) * np.sign(dlam) > 1e-14:
        target = lam_cur + dlam
        if (lam_to - target) * np.sign(dlam) < 0:
            target = lam_to
        trial = x.copy()
        trial[:, 2] *= target / lam_cur         # affine predictor; satisfies the grip conditions
        if pot.volume is not None:              # ... and keeps the volume (the term is stiff)
            trial[:, :2] *= math.sqrt(lam_cur / target)
        ok, trial, its, res = _newton(trial, pot, free, H, rtol, max_iter)
        total_its += its
        if ok:
            x, lam_cur = trial, target
            worst = max(worst, res)
            continue
        cuts += 1
        if cuts > 12:
            raise SimulationError(
                f"virtual tensile test: no equilibrium at stretch {target:.5g} ({pot.law} law) after "
                "12 step cuts; use a finer mesh, smaller stretch steps or a grid further from locking"
            )
        dlam /= 2.0
    return x, total_its, worst


@dataclass(frozen=True, eq=False)
class Potential:
    """The network's potential: springs with their tables and law, plus the volume term (optional).

    What Newton's method needs: :meth:`energy`, :meth:`forces`, :meth:`tangent`
    and a force scale for the convergence test.
    """

    network: Any
    tables: StiffnessTables
    law: str
    volume: VolumeElements | None = None
    factor: dict = field(default_factory=dict, repr=False)     #: a kept factorization and dof order (:func:`_newton`)

    def energy(self, x: np.ndarray) -> float:
        e = forcelaw.spring_energy(x, self.network, self.tables, law=self.law)
        return e if self.volume is None else e + self.volume.energy(x)

    def forces(self, x: np.ndarray) -> np.ndarray:
        f = forcelaw.spring_forces(x, self.network, self.tables, law=self.law)
        return f if self.volume is None else f + self.volume.forces(x)

    def tangent(self, x: np.ndarray):
        K = forcelaw.tangent_stiffness(x, self.network, self.tables, law=self.law)
        return K if self.volume is None else (K + self.volume.tangent(x)).tocsr()

    def force_scale(self, x: np.ndarray) -> float:
        """The residual's reference [N]: the largest spring force, or the volume term's round-off.

        The volume forces carry the round-off of volumes (``kappa`` times about
        1e-16 of a tet's face area); with a stiff term and a small strain that
        exceeds ``rtol`` times the spring forces, so the reference is at least
        1e-4 of ``kappa`` times the largest face area over 3 (a tolerance of 1e-13 of it with ``rtol = 1e-9``).
        """
        mags = forcelaw.spring_force_magnitudes(x, self.network, self.tables, law=self.law)
        floor = 0.0 if self.volume is None else 1e-4 * self.volume.force_unit
        return max(float(np.max(np.abs(mags))), floor, 1e-300)


def _order(pot: Potential, K, free) -> np.ndarray:
    """The free tangent's fill-reducing order (:func:`~.newton.free_order`), kept in ``pot.factor`` per *free*."""
    kept = pot.factor.get("order")
    if kept is None or not np.array_equal(kept[0], free):
        kept = pot.factor["order"] = (np.array(free, copy=True), free_order(K, free))
    return kept[1]


def _newton(x, pot: Potential, free, H, rtol, max_iter):
    """Newton's method on the potential, from *x*: (converged, x, iterations, residual).

    With the volume term the tangent is costly to factor, so a factorization
    is kept (``pot.factor``) and reused, for the next iterations and the next
    load step, as long as each step it gives cuts the residual at least
    threefold with a full step (a modified Newton method); otherwise the
    tangent is factored anew.
    """
    x = x.copy()
    xf = x.ravel()
    E = pot.energy(x)
    if not math.isfinite(E):
        return False, x, 0, math.inf
    res = math.inf
    frozen = None                                  # residual before a step taken with a kept factorization
    for it in range(1, max_iter + 1):
        g = -pot.forces(x).ravel()[free]
        gmax = float(np.max(np.abs(g))) if g.size else 0.0
        res = gmax / pot.force_scale(x) if g.size else 0.0
        if res <= rtol:
            return True, x, it - 1, res
        if frozen is not None and gmax > frozen / 3.0:
            pot.factor.pop("lu", None)              # the kept factorization no longer converges fast
        d, frozen = None, None
        lu = pot.factor.get("lu")
        if lu is not None:
            d = -lu.solve(g)
            if np.all(np.isfinite(d)) and float(g @ d) < 0:
                frozen = gmax
            else:
                d = None
        if d is None:
            K = pot.tangent(x)
            d, lu = descent_direction(K[free][:, free].tocsc(), g, order=_order(pot, K, free))
            if d is None:
                return False, x, it, res
            if pot.volume is not None:
                pot.factor["lu"] = lu
        slope = float(g @ d)
        a = 1.0
        while True:
            xt = xf.copy()
            xt[free] += a * d
            xt = xt.reshape(-1, 3)
            Et = pot.energy(xt)
            if math.isfinite(Et) and Et <= E + 1e-4 * a * slope:
                break
            # Energy differences drown in round-off near convergence: accept a full
            # step that reduces the residual.
            if a == 1.0 and math.isfinite(Et) and abs(Et - E) <= 1e-12 * max(abs(E), 1e-300):
                gt = -pot.forces(xt).ravel()[free]
                if np.max(np.abs(gt)) < np.max(np.abs(g)):
                    break
            a *= 0.5
            if a < 1e-8:
                pot.factor.pop("lu", None)
                return False, x, it, res
        if a < 1.0:
            pot.factor.pop("lu", None)
        x, xf, E = xt, xt.ravel(), Et
        if a * float(np.max(np.abs(d))) <= 1e-13 * H:
            g = -pot.forces(x).ravel()[free]
            res = float(np.max(np.abs(g))) / pot.force_scale(x)
            return res <= max(rtol, 1e-7), x, it, res
    return False, x, max_iter, res
