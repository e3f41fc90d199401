"""``esmm validate``: the network against an independent continuum reference, case by case.

:func:`validate_network` builds the load cases on a network (:mod:`.cases`),
solves each with the continuum (:mod:`.continuum`, felupe) and with the
network (:mod:`.network_solve`), compares them (:mod:`.compare`) and writes
the outputs (:mod:`.report`) when given a folder. :func:`validate_asset` reads
an asset first; :func:`validate_specimen` makes the built-in cube
(:mod:`.specimen`). docs/design/validation.md explains every choice.

The floor of the organ cases is a unilateral sticking contact; both solvers
get it as the same bilateral constraints, found by an active set: solve, pin
every node that went below the plane (either solver) at the point of the plane
under its rest position, solve again, until no node goes below.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..asset import read_asset, record_validation
from ..atomicio import write_json, write_text
from ..checks import choice
from ..errors import AssetError, ConfigError, SimulationError
from ..materials.material import DEFAULT_MATERIAL, load_material
from ..network.volume import volume_elements
from ..progress import ensure
from ..simulate.grasper import plan_grasp
from ..simulate.runsetup import fixed_nodes
from ..simulate.scene import load_scene
from .cases import (
    CASES,
    ORGAN_CASES,
    SPECIMEN_CASES,
    at_load,
    grasp_hold,
    gravity_case,
    lift_case,
    lift_stretch,
    shear_case,
    uniaxial_case,
    with_floor_pins,
)
from .compare import CaseResult, compare
from .continuum import NEAR_LOCKING, solve_continuum
from .html import write_validation_html
from .material import DEFAULT_BULK_RATIO, bulk_modulus, check_continuum
from .network_solve import solve_network
from .report import plot_case, table_markdown, write_fields
from .specimen import cube_specimen
from .workers import map_cases

__all__ = ["VOLUME_TERM", "LoadOptions", "ValidationReport", "default_out_dir", "network_terms", "resolved_volume_term",
           "validate_asset", "validate_network", "validate_specimen"]

#: ``volume_term`` values: the network with its volume term if it has one, with it, without it.
VOLUME_TERM = ("auto", "on", "off")
#: Continuum elements by size: quadratic tetrahedra up to this many tets, MINI above (docs/design/validation.md, "The continuum reference").
#: P2 is the reference: MINI's reaction forces converge at first order and are stiff on organ meshes
#: (the kidney's lift by 29 %). Every organ of the "paper" preset (4 000-6 000 tets) is below; the "fine"
#: liver (29 270 tets: about 141 000 P2 unknowns) is above.
P2_MAX_TETS = 12000


@dataclass(frozen=True)
class LoadOptions:
    """The loads of the cases: specimen stretches and shear, and the scene of the organ cases."""

    tension: float = 1.2
    compression: float = 0.9
    gamma: float = 0.3
    scene: object = None      #: a Scene, a scene name or TOML path; None: the bundled default


@dataclass(eq=False)
class ValidationReport:
    """The outcome of a validation.

    Attributes
    ----------
    label : str
        What was validated (asset path or specimen).
    results : list of CaseResult
    volume_term : str
        "on" or "off": whether the network ran with its volume term.
    files : dict
        Output files by kind (``json``, ``table``, per case ``png`` and ``xdmf``).
    info : dict
        Material, law, bulk modulus, element, timings.
    """

    label: str
    results: list
    volume_term: str
    files: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def table(self) -> str:
        failed = [f"| {name} | no equilibrium: {msg} |" for name, msg in self.info.get("failed", {}).items()]
        return "\n".join([table_markdown(self.results), *failed])

    def figures(self) -> dict:
        """The JSON document of ``--json``."""
        return {"label": self.label, "volume_term": self.volume_term, **self.info,
                "cases": [r.figures() for r in self.results]}

    def worst(self) -> dict:
        """The largest L2 and force errors over the cases."""
        return {"l2_error": max((r.l2_error for r in self.results), default=float("nan")),
                "force_error": max((r.force_error for r in self.results), default=float("nan"))}


def network_terms(network, tables, material, *, volume_term: str = "auto") -> tuple:
    """The terms of the network's potential beside its springs (:func:`~.network_solve.solve_network`).

    The one place that decides them: ``"auto"`` takes the network's own volume
    term (what ``esmm prepare`` stored in the asset's ``/volume``) when it has
    one, ``"on"`` requires it, ``"off"`` leaves it out (the springs alone; the
    tables are still the ones compensated with the term).

    Returns
    -------
    tuple
        ``()`` or ``(VolumeElements,)``.
    """
    if resolved_volume_term(network, volume_term) == "off":
        return ()
    return (volume_elements(network.points, network.tets, network.volume_term),)


def _p2_cells(network) -> int:
    """The P2 continuum's cells: the network's parents when it was split (one per eight tets), else its tets."""
    return network.n_tets if network.quadratic_cells is None else int(network.quadratic_cells.shape[0])


def resolved_volume_term(network, volume_term: str) -> str:
    """``"on"`` or ``"off"``: *volume_term* (:data:`VOLUME_TERM`) for *network*."""
    choice(volume_term, VOLUME_TERM, "volume_term")
    has = getattr(network, "volume_term", None) is not None and network.tets is not None
    if volume_term == "on" and not has:
        raise ConfigError("volume_term: this network has no volume term (an asset prepared without one, or with "
                          "the skeleton structure); use off, or prepare the asset again with the volume term", parameter="volume_term")
    return "on" if volume_term == "on" or (volume_term == "auto" and has) else "off"


def _cases_for(network, names, loads: LoadOptions) -> list:
    """The load cases *names* on *network*'s nodes and tetrahedra (and its quadratic cells, if split); a lift
    records what its grasped nodes hold (:func:`~.cases.grasp_hold`) in its ``load``."""
    out = []
    for c in _cases_on(network, names, loads):
        c = replace(c, quadratic_cells=network.quadratic_cells)
        if c.name == "lift":
            c = replace(c, load={**c.load, "grasp_hold": grasp_hold(c, network.surface_faces)})
        out.append(c)
    return out


def _cases_on(network, names, loads: LoadOptions) -> list:
    pts, tets = network.points, network.tets
    density = float(network.mass.sum()) / float(network.total_volume())
    out = []
    for name in names:
        if name == "tension":
            out.append(uniaxial_case(pts, tets, stretch=loads.tension, density=density))
        elif name == "compression":
            out.append(uniaxial_case(pts, tets, stretch=loads.compression, density=density))
        elif name == "shear":
            out.append(shear_case(pts, tets, gamma=loads.gamma, density=density))
        else:
            out.append(_organ_case(network, name, loads, density))
    return out


def _organ_case(network, name: str, loads: LoadOptions, density: float):
    scene = loads.scene if hasattr(loads.scene, "gravity") else load_scene(loads.scene)
    fixed = fixed_nodes(network, scene)
    weight = float(network.mass.sum() * np.linalg.norm(scene.gravity))
    if name == "gravity":
        return gravity_case(network.points, network.tets, scene=scene, fixed=fixed, density=density, weight=weight)
    if scene.grasper is None:
        raise ConfigError("cases: the lift case needs the scene's grasper; enable it or drop the case",
                          parameter="cases")
    plan = plan_grasp(scene.grasper, network.points, network.surface_faces, fixed, scene.gravity,
                      springs=network.springs)
    return lift_case(network.points, network.tets, scene=scene, fixed=fixed, grasped=plan.nodes,
                     lift=plan.offsets[-1], density=density, weight=weight)


def _below(case, solutions) -> np.ndarray:
    """Nodes that any of *solutions* put below the case's floor (beyond a round-off tolerance)."""
    fl = case.floor
    if fl is None:
        return np.zeros(0, np.int64)
    tol = 1e-6 * float(np.ptp(case.points, axis=0).max())
    out = [np.flatnonzero((case.points + s.displacement) @ fl.normal < fl.height - tol) for s in solutions]
    return np.unique(np.concatenate(out))


#: Load levels of a case on the floor: contacts are looked for after each.
_LEVELS = 8


def _on_the_floor(case, solve, max_rounds: int, rep):
    """*solve* (``solve(case, start) -> Solution``) with the floor as a sticking contact along the load path.

    The load grows in :data:`_LEVELS` levels, each solved from the previous
    one; a node that goes below the floor is pinned at the point of the plane
    under where it was at the previous level (it touched the floor within
    the level; it sticks there), and the level is solved again, until no node
    goes below. A round solves the level again from the previous round's
    equilibrium, with the new pins moved from where that round put them to
    their place: the same equilibrium as from the previous level (the
    problem is elastic, its loads and constraints the same), reached in a few
    Newton iterations instead of the level's whole increment again. Returns the
    solution and the number of pins.
    """
    c, sol = case, None
    for k in range(1, _LEVELS + 1):
        start = sol
        for _ in range(max_rounds):
            trial = solve(at_load(c, k / _LEVELS), start)
            held = c.constraint("floor").nodes if any(g.name == "floor" for g in c.constraints) else []
            new = np.setdiff1d(_below(c, (trial,)), held)
            if new.size == 0:
                break
            c = with_floor_pins(c, new, case.points[new] + (0.0 if sol is None else sol.displacement[new]))
            start = trial     # the level again from this round's equilibrium: only the new pins move
        else:
            rep.warn(f"{case.name}: nodes still reach the floor after {max_rounds} rounds of pins at load level "
                     f"{k}/{_LEVELS}; the figures include a small penetration")
        sol = trial
    pins = len(c.constraint("floor").nodes) if any(g.name == "floor" for g in c.constraints) else 0
    sol.info["floor_pins"] = pins
    return sol, pins


def _reachable(case, material) -> None:
    """Refuse a lift that stretches a segment inside the body past the material's locking
    (:func:`~.cases.lift_stretch`): no continuum has an equilibrium there, and its solvers would spend their
    iteration budgets (25 minutes on a small organ) to say so."""
    lam = material.stretch_range()[1]           # uniaxial locking: λ² + 2/λ = Ī1_lock, increasing in λ > 1
    if case.name != "lift" or not np.isfinite(lam):
        return
    ls = lift_stretch(case)
    if ls.stretch < lam:
        return
    lift = float(np.linalg.norm(case.constraint("grasper").displacement[0]))
    raise SimulationError(
        f"the continuum cannot follow this lift: the grasp moves node {ls.grasped} by {lift * 1e3:.3g} mm while "
        f"anchor node {ls.anchor}, {ls.length * 1e3:.3g} mm away through the organ, is held, so the segment "
        f"between them stretches at least {ls.stretch:.3f} somewhere, past the material's locking stretch "
        f"{lam:.3f}; give a scene (--scene) whose lift stays well below {ls.lift_at(lam) * 1e3:.3g} mm "
        "(where that segment would lock)")


def _solve_case(case, network, tables, material, *, law, terms, bulk, elements, max_rounds: int, rep) -> CaseResult:
    """Both solutions of *case* and their comparison.

    On a floor each solver has its own sticking contact, found along its
    load path (:func:`_on_the_floor`): the contact set is part of the answer.
    The continuum takes the first of *elements* that finds an equilibrium.
    A lift that no continuum can follow is refused first (:func:`_reachable`).
    """
    _reachable(case, material)

    def net(c, start):
        return solve_network(c, network, tables, law=law, terms=terms, start=start, steps=1, reporter=rep)

    def fem(element):
        def solve(c, start):
            return solve_continuum(c, material, bulk=bulk, element=element, start=start, steps=1, reporter=rep)
        return solve

    if case.floor is None:
        nw = solve_network(case, network, tables, law=law, terms=terms, reporter=rep)
        fe, pins = _first_of(elements, lambda el: (solve_continuum(case, material, bulk=bulk, element=el,
                                                                   reporter=rep), 0), case, rep)
    else:
        nw, pins_n = _on_the_floor(case, net, max_rounds, rep)
        fe, pins_c = _first_of(elements, lambda el: _on_the_floor(case, fem(el), max_rounds, rep), case, rep)
        pins = max(pins_n, pins_c)
        rep.step(f"{case.name}: {pins_c} continuum and {pins_n} network nodes on the floor")
    res = compare(case, fe, nw, pins=pins)
    _warn_patch(case, rep)
    if fe.info.get("cells_near_locking"):
        rep.warn(f"{case.name}: the continuum comes within {100 * (1 - NEAR_LOCKING):.0f} % of the material's "
                 f"locking in {fe.info['cells_near_locking']} cell(s) (largest share of the way "
                 f"{fe.info['locking_share']:.4f}): its stiffness there has no bound, so its reaction force depends "
                 "on the mesh; read the force error as the case's, not the network's alone (docs/design/validation.md, 'Error measures')")
    rep.step(f"{case.name}: L2 error {100 * res.l2_error:.2f} %, max {100 * res.max_error:.2f} %, force "
             f"{100 * res.force_error:.2f} % (largest continuum displacement {res.max_displacement_m * 1e3:.3g} mm)")
    return res


def _warn_patch(case, rep) -> None:
    """Warn where P2 on a split network's parents holds another grasp patch than the network
    (:func:`~.cases.grasp_hold`)."""
    hold = case.load.get("grasp_hold", {})
    if hold.get("network_only", 0) > 0:
        rep.warn(f"{case.name}: the network holds {hold['surface_triangles_held']} surface triangles under the "
                 f"grasper, P2 on its parents holds {hold['parent_faces_held']} parent faces whole (the rest at "
                 "the grasped points and edges): the two hold different patches, and the reference's grasper "
                 "force is not converged there (P2 on the split tetrahedra moves it by 5.7 % on the kidney and "
                 "10 % on the liver); read the force error as the case's, not the network's alone "
                 "(docs/design/validation.md, 'Is the reference converged for the grasper force?')")


def _first_of(elements, solve, case, rep):
    """``solve(element)`` (a ``(Solution, pins)`` pair) with the first of *elements* whose continuum finds
    an equilibrium.

    A solution from a later element records why in its ``info["element_fallback"]``.
    """
    for element, following in zip(elements, elements[1:], strict=False):
        try:
            return solve(element)
        except SimulationError as exc:
            rep.warn(f"{case.name}: the {element} continuum found no equilibrium ({exc}); solved with the "
                     f"{following} element instead, whose forces are first order")
            reason = f"{element}: {exc}"
    out = solve(elements[-1])
    if len(elements) > 1:
        out[0].info["element_fallback"] = reason
    return out


def _continuum_elements(network, element: str, rep) -> tuple[str, tuple[str, ...]]:
    """The continuum's element and the elements to try in order ("auto": P2 where it fits, then MINI)."""
    element = choice(element, ("auto", "p2", "mini"), "element")
    elements = (element,)
    if element == "auto":
        element = "p2" if _p2_cells(network) <= P2_MAX_TETS else "mini"
        elements = ("p2", "mini") if element == "p2" else ("mini",)
    if element == "mini":
        rep.warn("the MINI continuum's reaction forces are first order: stiffer than the converged continuum "
                 "on a coarse mesh (docs/design/validation.md, 'The continuum reference'); the P2 element is the reference where it fits in memory")
    return element, elements


def _solve_cases(cases, network, tables, material, *, jobs, rep, **options) -> tuple[list, dict, dict]:
    """:func:`_solve_case` of every case, at once where *jobs* allows (:func:`~.workers.map_cases`):
    ``(results, failed, case_seconds)``, a case without an equilibrium in *failed* with the reason (the
    other cases still run)."""
    def one(c, rep_):
        t_case = time.perf_counter()
        try:
            res = _solve_case(c, network, tables, material, rep=rep_, **options)
        except SimulationError as exc:
            rep_.warn(f"{c.name}: {exc}")
            return c.name, None, str(exc), time.perf_counter() - t_case
        res.continuum.state = None          # felupe's checkpoint: for warm starts within the case only
        return c.name, res, None, time.perf_counter() - t_case

    results, failed, case_seconds = [], {}, {}
    for name, res, err, seconds in map_cases(one, cases, jobs=jobs, reporter=rep, names=[c.name for c in cases]):
        case_seconds[name] = seconds
        if res is None:
            failed[name] = err
        else:
            results.append(res)
    return results, failed, case_seconds


def validate_network(network, tables, material, *, cases=None, label: str = "network", loads: LoadOptions | None = None,
                     volume_term: str = "auto", law: str | None = None, element: str = "auto",
                     bulk_ratio: float = DEFAULT_BULK_RATIO, out_dir=None, max_rounds: int = 10,
                     jobs: int | None = None, reporter=None) -> ValidationReport:
    """Validate *network* with *tables* against the continuum of *material*, case by case.

    Parameters
    ----------
    network : SpringNetwork
        Tetrahedral (the continuum is solved on its tetrahedra).
    tables : StiffnessTables
    material : Material
        Isotropic (:func:`~.material.check_continuum`).
    cases : sequence of str, optional
        From :data:`~.cases.CASES`; default all.
    label : str
    loads : LoadOptions, optional
    volume_term : {"auto", "on", "off"}
        :func:`network_terms` (the report records the resolved "on" or "off").
    law : {"secant", "energy"}, optional
        The network's force law (default: the tables').
    element : {"auto", "p2", "mini"}
        The continuum's element (P2 on a split network's parents, node for node). "auto": P2 up to
        :data:`P2_MAX_TETS` tets (a split network: parents), MINI above; a case
        for which P2 finds no equilibrium is solved with MINI (its ``info["element_fallback"]`` says so).
    bulk_ratio : float
        K over the largest tangent shear modulus (:func:`~.material.bulk_modulus`).
    out_dir : path-like, optional
        Write ``validation.json``, ``validation.md`` and per case ``<case>.png``,
        ``<case>.xdmf`` + ``.h5`` there.
    jobs : int, optional
        Cases solved at once, each in a process of its own (:func:`~.workers.map_cases`); default the
        cores this process may use. The figures do not depend on it.

    Returns
    -------
    ValidationReport

    Raises
    ------
    ConfigError
        A skeleton network, an unknown case, an anisotropic material.
    SimulationError
        A solver found no equilibrium.
    """
    rep = ensure(reporter)
    t0 = time.perf_counter()
    if network.tets is None or network.n_tets == 0:
        raise ConfigError("the continuum reference needs tetrahedra; this network has the skeleton structure "
                          "(prepare it with structure tetra)")
    names = list(CASES) if cases is None else [choice(c, CASES, "cases") for c in cases]
    if not names:
        raise ConfigError("cases: no case to run", parameter="cases")
    check_continuum(material)
    terms = network_terms(network, tables, material, volume_term=volume_term)
    volume_term = resolved_volume_term(network, volume_term)
    element, elements = _continuum_elements(network, element, rep)
    bulk = bulk_modulus(material, ratio=bulk_ratio)
    law = tables.check_law(law)
    loads = LoadOptions() if loads is None else loads
    results, failed, case_seconds = _solve_cases(_cases_for(network, names, loads), network, tables, material,
                                                 jobs=jobs, rep=rep, law=law, terms=terms, bulk=bulk,
                                                 elements=elements, max_rounds=max_rounds)
    info = {"failed": failed, "material": material.name or material.model, "law": law,
            "volume_factor": float(tables.volume_factor),
            "bulk_modulus_Pa": bulk, "bulk_ratio": float(bulk_ratio), "element": element,
            "nodes": network.n_nodes, "springs": network.n_springs, "tets": network.n_tets,
            "seconds": time.perf_counter() - t0, "case_seconds": case_seconds}
    if network.quadratic_cells is not None:     # split: the continuum's P2 cells are these parents
        info["split_from"] = int(network.quadratic_cells.shape[0])
    report = ValidationReport(label=label, results=results, volume_term=volume_term, info=info)
    if out_dir is not None:
        _write(report, Path(out_dir))
    return report


def _write(report: ValidationReport, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for r in report.results:
        report.files[f"{r.case.name}_png"] = str(plot_case(r, out / f"{r.case.name}.png"))
        report.files[f"{r.case.name}_xdmf"] = str(write_fields(r, out / f"{r.case.name}.xdmf"))
    text = (f"# esmm validate: {report.label}\n\nvolume term {report.volume_term}; "
            + ", ".join(f"{k} {v}" for k, v in report.info.items() if k not in ("seconds", "case_seconds", "failed")) + "\n\n"
            + report.table() + "\n\n" + "\n".join(f"* {r.case.name}: {r.case.description}" for r in report.results)
            + "\n")
    report.files["table"] = str(write_text(out / "validation.md", text))
    report.files["json"] = str(write_json(out / "validation.json", report.figures()))
    report.files["html"] = str(write_validation_html(report, out))


def validate_asset(path, *, cases=None, **options) -> ValidationReport:
    """:func:`validate_network` on an asset's network, tables and material (default cases: the organ's);
    the figures are recorded in the asset (``/accuracy/validation``, :func:`~esmm.pipeline.asset.record_validation`)."""
    asset = read_asset(path)
    if asset.tables is None or asset.material is None:
        raise ConfigError(f"{path}: the asset has no stiffness tables or material; rebuild it with 'esmm tables'")
    report = validate_network(asset.network, asset.tables, asset.material, label=str(path),
                              cases=list(ORGAN_CASES) if cases is None else cases, **options)
    scene = getattr(options.get("loads"), "scene", None)
    try:
        record_validation(path, report.figures(), scene=str(getattr(scene, "source", scene) or "default"))
    except AssetError as exc:   # a read-only asset: the figures stay in the validation's own outputs
        ensure(options.get("reporter")).warn(f"the figures are not recorded in the asset: {exc}")
    return report


def validate_specimen(material=None, *, side: float = 20e-3, size: float = 2.5e-3, split: bool = False, cases=None,
                      reporter=None, **options) -> ValidationReport:
    """:func:`validate_network` on the built-in cube (default cases: the specimen's).

    The cube gets a volume term and tables compensated with it, as ``esmm prepare``
    gives an asset, unless ``volume_term="off"`` (then neither). *material*
    defaults to the preset :data:`~esmm.pipeline.materials.material.DEFAULT_MATERIAL`.
    """
    material = load_material(DEFAULT_MATERIAL) if material is None else material
    volume = options.get("volume_term", "auto") != "off"
    spec = cube_specimen(material, side=side, size=size, volume=volume, split=split, reporter=reporter)
    return validate_network(spec.network, spec.tables, material, label=f"specimen: {spec.label}",
                            cases=list(SPECIMEN_CASES) if cases is None else cases, reporter=reporter, **options)


def default_out_dir(asset_path=None) -> Path:
    """Where the validation writes when no folder is given: ``<asset stem>-validate`` beside the asset,
    or ``specimen-validate`` in the current folder for the built-in specimen."""
    if asset_path is None:
        return Path("specimen-validate")
    return Path(asset_path).with_name(Path(asset_path).stem + "-validate")
