"""The continuum reference: the load case solved with felupe, quadratic tetrahedra, mixed u-p-J.

Discretisation (docs/design/validation.md, "The continuum reference"):

* the asset's tetrahedra with a node added at the middle of every edge
  (10-node quadratic tetrahedra on the *same* vertices and straight edges,
  so both solvers see the same geometry, and the continuum is compared at
  the vertices);
* felupe's :class:`~felupe.SolidBodyNearlyIncompressible`: the three-field
  Hu-Washizu formulation (displacement, pressure, volume ratio) with the
  pressure and volume ratio constant per element, condensed element by
  element (P2/P0, inf-sup stable: no volumetric locking), with the isochoric
  energy :class:`~.material.IsochoricMaterial` and ``U = K (J̄ − 1)² / 2``;
* a component prescribed at both vertices of an edge is prescribed at its
  middle node too (their mean value): the quadratic interpolation of the
  same boundary data;
* gravity as felupe's consistent body force ``∫ N ρ g dV`` (the network lumps
  the same weight on its nodes).

Load stepping: prescribed displacements and gravity grow together with the
load factor; Newton's method (felupe's, silent) per step; a step that fails
is halved (at most ``max_cuts`` times).
"""

from __future__ import annotations

import time
import warnings
from contextlib import redirect_stdout
from io import StringIO

import numpy as np

from ..errors import ConfigError, SimulationError
from ..mesh.refine import quadratic_tets
from ..progress import ensure
from .cases import LoadCase
from .linear import CondensedMini, NodeDissection
from .material import IsochoricMaterial, bulk_modulus
from .solution import Solution, start_scale

__all__ = ["ELEMENTS", "quadratic_tets", "solve_continuum"]

#: The mixed elements on the asset's tetrahedra (both free of volumetric locking).
ELEMENTS = {
    "p2": "quadratic tetrahedra (a node on every edge), pressure and volume ratio constant per element, "
          "condensed (felupe SolidBodyNearlyIncompressible)",
    "mini": "linear tetrahedra with a cubic bubble (MINI), pressure and volume ratio linear "
            "(felupe ThreeFieldVariation on RegionTetraMINI)",
}

def _quadratic(case: LoadCase) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 10-node mesh of *case*: its own ``quadratic_cells`` (no node added), or :func:`quadratic_tets`."""
    if case.quadratic_cells is None:
        return quadratic_tets(case.points, case.tets)
    return case.points, case.quadratic_cells, np.zeros((0, 2), np.int64)


def _groups(case: LoadCase, edges: np.ndarray, n10: int):
    """Per group, its nodes among the 10-node mesh's; and the prescribed mask and values (n10, 3).

    A middle node gets the components prescribed at both ends of its edge
    (their mean value: the quadratic interpolation of linear boundary data)
    and belongs to the group of its edge's first vertex.
    """
    n = case.n_nodes
    gid = np.full(n, -1)
    for k, c in enumerate(case.constraints):
        gid[c.nodes] = k
    mask_v, u_v = case.prescribed()
    mask = np.zeros((n10, 3), bool)
    u = np.zeros((n10, 3))
    mask[:n], u[:n] = mask_v, u_v
    mask[n:] = mask_v[edges[:, 0]] & mask_v[edges[:, 1]]
    u[n:] = np.where(mask[n:], 0.5 * (u_v[edges[:, 0]] + u_v[edges[:, 1]]), 0.0)
    owner = np.where(mask[n:].any(axis=1), gid[edges[:, 0]], -1)
    members = {c.name: np.concatenate([c.nodes, n + np.flatnonzero(owner == k)])
               for k, c in enumerate(case.constraints)}
    return members, mask, u


class _Check:
    """felupe convergence test: active residual below *rtol* of *scale* (N)."""

    def __init__(self, scale: float, rtol: float):
        self.limit = rtol * scale

    def __call__(self, dx, x, f, xtol, ftol, dof1=None, dof0=None, items=None, **kw):
        fnorm = float(np.max(np.abs(np.asarray(f).ravel()[dof1]))) if len(dof1) else 0.0
        return float(np.max(np.abs(dx))), fnorm, bool(np.isfinite(fnorm) and fnorm <= self.limit)


def _force_scale(case: LoadCase, material, mask: np.ndarray, u: np.ndarray) -> float:
    """A force typical of the case [N]: its weight, and the small-strain force of its prescribed motion."""
    weight = case.density * float(np.linalg.norm(case.gravity)) * float(
        case.node_volumes().sum())
    size = float(np.ptp(case.points, axis=0).max())
    strain = float(np.abs(u[mask]).max()) / size if mask.any() else 0.0
    return max(weight, material.youngs_modulus() * strain * size**2, 1e-12)


def _discretise(fem, case: LoadCase, material, K: float, element: str):
    """felupe's field and solid body of *case*, its constraint groups and prescribed values."""
    if element == "p2":
        p10, cells, edges = _quadratic(case)
        members, mask, u = _groups(case, edges, p10.shape[0])
        region = fem.RegionQuadraticTetra(fem.Mesh(p10, cells, "tetra10"))
        field = fem.FieldContainer([fem.Field(region, dim=3)])
        solid = fem.SolidBodyNearlyIncompressible(IsochoricMaterial(material), field, bulk=K)
    else:  # MINI: a bubble node in every tet (free), u-p-J with p and J linear
        mesh = fem.Mesh(case.points, case.tets, "tetra").add_midpoints_volumes()
        region = fem.RegionTetraMINI(mesh)
        field = fem.FieldsMixed(region, n=3)
        solid = fem.SolidBody(fem.ThreeFieldVariation(IsochoricMaterial(material, bulk=K)), field)
        members = {c.name: c.nodes for c in case.constraints}
        mask_v, u_v = case.prescribed()
        mask = np.zeros((mesh.npoints, 3), bool)
        u = np.zeros((mesh.npoints, 3))
        mask[:case.n_nodes], u[:case.n_nodes] = mask_v, u_v
    return field, solid, members, mask, u, region.mesh.ncells


def solve_continuum(case: LoadCase, material, *, bulk: float | None = None, element: str = "p2", steps: int = 8,
                    rtol: float = 1e-8, max_iter: int = 25, max_cuts: int = 10, budget: int = 250,
                    start: Solution | None = None, reporter=None) -> Solution:
    """Solve *case* as a nearly incompressible hyperelastic continuum (felupe).

    Parameters
    ----------
    case : LoadCase
    material : Material
        Isotropic, W(I1) (:class:`~.material.IsochoricMaterial`).
    bulk : float, optional
        Bulk modulus K [Pa]; default :func:`~.material.bulk_modulus`.
    element : {"p2", "mini"}
        :data:`ELEMENTS`.
    steps : int
        Initial load steps (the step doubles after a quick convergence and is
        halved on failure).
    rtol : float
        Newton converges when the largest residual force on a free degree
        of freedom is below *rtol* times the case's force scale.
    max_iter : int
    max_cuts : int
        Halvings of one load step before giving up.
    budget : int
        Newton iterations of the whole solve before giving up (a load the
        material can hardly reach creeps on in tiny steps otherwise).
    start : Solution, optional
        A continuum solution of the same mesh, element and body force (a
        previous round of the floor's active set): the solve starts from its
        state with the body force on and moves the prescribed values from
        where they are there to the case's.

    Returns
    -------
    Solution
        Its ``state`` is the felupe solid's checkpoint (for *start*).

    Raises
    ------
    SimulationError
        No equilibrium after *max_cuts* halvings of a step, or not within
        *budget* Newton iterations.
    """
    import felupe as fem

    rep = ensure(reporter)
    t_start = time.perf_counter()
    if element not in ELEMENTS:
        raise ConfigError(f"element: {element!r} is not one of {', '.join(ELEMENTS)}", parameter="element")
    K = bulk_modulus(material) if bulk is None else float(bulk)
    field, solid, members, mask, u_full, ncells = _discretise(fem, case, material, K, element)
    ndof = int(np.sum(field.fieldsizes))
    dof0 = np.flatnonzero(mask.ravel())
    dof1 = np.setdiff1d(np.arange(ndof), dof0)
    path = _LoadPath(solid, dof0, u_full.ravel()[dof0], start, start_scale(start, case.gravity))
    body = fem.SolidBodyForce(field, values=case.density * np.asarray(case.gravity, dtype=np.float64),
                              scale=path.body(0.0))
    stepper = _Stepper(fem, solid, body, dof0, dof1, _Check(_force_scale(case, material, mask, u_full), rtol),
                       max_iter, _linear_solver(element, dof1, case.n_nodes, field.region.mesh), residual=element == "mini")
    with rep.task(f"continuum {case.name} (felupe, {ncells} tets, {element})", total=1.0) as advance:
        done_steps, cuts = _apply_load(case, stepper, path, steps=steps, max_cuts=max_cuts, budget=budget,
                                       advance=advance)
    return _solution(case, solid, body, stepper.field, members, K, _max_i1(material), {
        "bulk_modulus_Pa": K, "element": element, "elements": ELEMENTS[element], "dofs": ndof,
        "load_steps": done_steps, "step_cuts": cuts, "newton_iterations": stepper.iterations,
        "factorisations": stepper.factorisations, "lu_fallbacks": int(getattr(stepper.solver, "fallbacks", 0)),
        "warm_start": start is not None,
        "seconds": time.perf_counter() - t_start})


#: A load step that converged in at most this many Newton iterations doubles the next one.
_QUICK = 4


class _LoadPath:
    """Body-force scale and prescribed values at load factor t: from the start state to the case's
    (the body force from the start's share *s0* of it, :func:`~.solution.start_scale`)."""

    def __init__(self, solid, dof0, target, start: Solution | None, s0: float):
        self.target = np.asarray(target, dtype=np.float64)
        if start is None or start.state is None:
            self.s0, self.u0 = 0.0, np.zeros_like(self.target)
            return
        solid.restore(start.state)
        self.s0 = s0
        self.u0 = np.concatenate([f.values.ravel() for f in solid.field.fields])[dof0]

    def body(self, t: float) -> float:
        return self.s0 + t * (1.0 - self.s0)

    def prescribed(self, t: float) -> np.ndarray:
        return self.u0 + t * (self.target - self.u0)


class _Stepper:
    """Newton's method per load step (felupe's, silenced), restoring the state of a failed step."""

    def __init__(self, fem, solid, body, dof0, dof1, check, max_iter, solver, residual: bool):
        self.fem, self.solid, self.body, self.field = fem, solid, body, solid.field
        self.dof0, self.dof1, self.check, self.max_iter, self.solver = dof0, dof1, check, max_iter, solver
        self.residual = residual
        self.iterations = 0

    @property
    def factorisations(self) -> int:
        return int(getattr(self.solver, "count", 0))

    def step(self, scale: float, ext0: np.ndarray) -> tuple[bool, int]:
        """Equilibrium at body-force *scale* and prescribed values *ext0*; ``(converged, iterations)``."""
        saved = self.solid.checkpoint()
        self.body._update_scale(scale)
        before = self.factorisations
        ok, field, its = _newton(self.fem, self.field, self.solid, self.body, self.dof0, self.dof1, ext0,
                                 self.check, self.max_iter, self.solver, self.residual)
        if hasattr(self.solver, "count"):    # one solve per iteration: what an attempt felupe gave up on
            its = self.factorisations - before  # (an exception) made, not max_iter, counts in the budget
        self.iterations += its
        if ok:
            self.field = field
        else:
            self.solid.restore(saved)
            self.field = self.solid.field
        return ok, its


def _apply_load(case: LoadCase, stepper: _Stepper, path: _LoadPath, *, steps: int, max_cuts: int, budget: int,
                advance) -> tuple[int, int]:
    """Raise the load factor from 0 to 1 in adaptive steps: ``(load steps done, step halvings)``.

    A step is halved when Newton fails (at most *max_cuts* times in a row) and
    doubled after one that converged in at most :data:`_QUICK` iterations.
    """
    t, dt, cuts, run, done_steps = 0.0, 1.0 / max(1, int(steps)), 0, 0, 0
    while t < 1.0 - 1e-12:
        t1 = min(1.0, t + dt)
        ok, its = stepper.step(path.body(t1), path.prescribed(t1))
        if stepper.iterations > budget:
            raise SimulationError(
                f"continuum reference: case {case.name!r} took more than {budget} Newton iterations and "
                f"reached load factor {t:.3g} only; its constraints may go beyond the material's locking "
                "stretch")
        if not ok:
            cuts, run = cuts + 1, run + 1
            if run > max_cuts:
                raise SimulationError(
                    f"continuum reference: no equilibrium for case {case.name!r} at load factor {t1:.4g} "
                    f"after {max_cuts} step halvings; the load may go beyond the material's locking stretch")
            dt /= 2.0
            continue
        advance(t1 - t)
        t, done_steps, run = t1, done_steps + 1, 0
        dt = 2.0 * dt if its <= _QUICK else dt
    return done_steps, cuts


def _linear_solver(element: str, dof1: np.ndarray, n_vertices: int, mesh):
    """The sparse solver of a Newton step (:mod:`.linear`): MINI with its bubbles condensed, P2 by an LDLᵀ
    in the nested-dissection order of *mesh*'s node graph."""
    if element == "mini":
        return CondensedMini(dof1, n_vertices, mesh.ncells)
    return NodeDissection(dof1, mesh.cells, mesh.npoints)


def _newton(fem, field, solid, body, dof0, dof1, ext0, check, max_iter, solver, residual):
    """One load step; ``(converged, field, iterations)`` (felupe's solver silenced).

    felupe's backtracking line search rejects a trial with an inverted element
    and, if *residual*, one whose residual does not decrease. The latter is
    off for P2: its condensed pressure and volume ratio take the whole Newton
    update whatever the step length, so the residuals of a shortened step are
    not Newton's (felupe's ``LinesearchPlugin`` notes this): on an organ under
    gravity it can reject every halving of the first update where plain
    Newton converges (docs/design/validation.md, "The continuum reference").
    """
    # The library never prints: verbose=0 asks felupe so; its warnings (a singular matrix) mean failure here.
    with redirect_stdout(StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with np.errstate(all="ignore"):
                res = fem.newtonraphson(field, items=[solid, body], dof1=dof1, dof0=dof0, ext0=ext0,
                                        verbose=0, maxiter=max_iter, check=check, solver=solver,
                                        plugins=[fem.LinesearchPlugin(residual=residual, max_halvings=6)])
        except (fem.tools.NewtonConvergenceError, ValueError, RuntimeError, FloatingPointError,
                np.linalg.LinAlgError):
            return False, field, max_iter
    ok = bool(res.success) and np.all(np.isfinite(res.x[0].values))
    return ok, res.x, int(res.iterations)


#: Share of the way from rest to the material's locking invariant, ``(Ī1 - 3) / (I1_lock - 3)``, from which a
#: cell counts as locking: within 1 % of it. The eight-chain energy's curvature grows without bound there (the
#: bundled liver's material: 2.7x its small-strain value at 0.99, 16 600x at 0.9999; docs/design/validation.md, "Error measures").
NEAR_LOCKING = 0.99


def _max_i1(material) -> float:
    """The material's locking value of Ī1 (inf for a material that does not lock)."""
    return float(material.model_obj.max_I1(material.params_for(None)))


def _locking(F: np.ndarray, J: np.ndarray, i1_lock: float) -> dict:
    """How far the field *F* (3, 3, q, c), of determinant *J* (q, c), goes towards locking: the largest share of
    the way from rest to the locking invariant over the quadrature points, and the cells with a point at
    :data:`NEAR_LOCKING` or beyond; {} for a material that does not lock."""
    if not np.isfinite(i1_lock):
        return {}
    share = (np.einsum("ij...,ij...->...", F, F) / np.cbrt(J) ** 2 - 3.0) / (i1_lock - 3.0)    # (q, c)
    return {"locking_share": float(np.max(share)),
            "cells_near_locking": int(np.count_nonzero(np.any(share >= NEAR_LOCKING, axis=0)))}


def _solution(case: LoadCase, solid, body, field, members, K: float, i1_lock: float, info: dict) -> Solution:
    n = case.n_nodes
    nu = field[0].values.size
    fint = np.asarray(solid.assemble.vector(field).todense()).ravel()[:nu].reshape(-1, 3)
    fext = np.asarray(body.assemble.vector(field).todense()).ravel()[:nu].reshape(-1, 3)
    on_body = fext - fint                       # what the supports take: -(residual)
    reactions = {name: on_body[nodes].sum(axis=0) for name, nodes in members.items()}
    F = field[0].extract()
    J = np.linalg.det(np.moveaxis(F, (0, 1), (-2, -1)))   # (q, c)
    dV = field.region.dV
    return Solution(solver="continuum", displacement=field[0].values[:n].copy(), reactions=reactions,
                    volume_ratio=float((J * dV).sum() / dV.sum()), element_J=J.min(axis=0),
                    info={**info, **_locking(F, J, i1_lock)},
                    state=solid.checkpoint(), gravity=np.asarray(case.gravity, dtype=np.float64).copy())
