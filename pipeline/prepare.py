"""``esmm prepare``: an organ surface in, a spring-network asset out.

Stages (each reported with its figures and time through ``reporter``)::

    read -> clean -> mesh (tetra) or skeleton -> quality gate -> network
         -> stiffness tables -> fixed region -> asset (.h5 + .xdmf)

Settings come from, in increasing precedence: the built-in defaults
(:data:`DEFAULTS`), the prepare config (a bundled preset name such as
``"paper"`` or a TOML path; default ``"paper"``), and the keyword arguments.
The resolved configuration is stored in the asset's provenance, so an asset
can be remade from it. The config schema is documented in
docs/prepare-config.md.
"""

from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import config as _config
from .errors import ConfigError, InputError, QualityError
from .network import compensation
from .progress import ensure
from .units import parse_quantity

#: The default prepare preset.
DEFAULT_PRESET = "paper"
#: The default material preset.
DEFAULT_MATERIAL = "porcine_liver_paper"

#: Every section and key a prepare config may have, with its default (None: unset).
DEFAULTS: dict[str, dict[str, Any]] = {
    "prepare": {"structure": "tetra", "material": DEFAULT_MATERIAL, "density": "1060 kg/m3",
                "reorder": "rcm"},
    "input": {"unit": "mm", "label": None},
    "cleaning": {"keep": "largest", "body": None, "smooth_iterations": 20, "smooth_passband": 0.1,
                 "target_faces": None, "target_edge": None},
    "mesh": {"size": None, "nodes": None, "elements": None, "timeout": "120 s"},
    "skeleton": {"n_surface": None, "weight_exponent": 2.0},
    "fibres": {"frame": "identity"},
    "fixed": {"kind": "band", "axis": "longest", "end": "min", "width_fraction": 0.1},
    "quality": {},
    "tables": {"n": 1024, "law": "secant", "lam_min": None, "lam_max": None, "compensate": True},
}

#: Ratio of the mesher's mean tet volume to that of a regular tet whose edge is the
#: requested size. Measured 1.39-1.42 on gmsh cubes, 0.92 on the bundled InVesalius
#: liver and 0.73 on the SOFA liver (surface detail adds tets); 1 is the middle.
MESHER_VOLUME_RATIO = 1.0
#: Relative miss of the tet count beyond which an ``elements`` target is remeshed once.
ELEMENTS_TOLERANCE = 0.2


@dataclass
class PrepareResult:
    """What :func:`prepare` made.

    Attributes
    ----------
    asset : Path
        The ``.h5`` file.
    xdmf : Path
        The ParaView sidecar.
    network : SpringNetwork
    quality : QualityReport or None
        None for the skeleton structure.
    quality_passed : bool
    cleaning : CleaningReport
    tables : StiffnessTables or None
        None when the tables module is not available.
    material : Material or None
    timings : dict
        Stage -> seconds.
    mesher : str
        The meshing path taken (e.g. ``"gmsh"``), or ``"skeleton"``.
    config : dict
        The resolved configuration.
    warnings : list of str
    """

    asset: Path
    xdmf: Path
    network: Any
    quality: Any
    quality_passed: bool
    cleaning: Any
    tables: Any
    material: Any
    timings: dict[str, float]
    mesher: str
    config: dict[str, Any]
    warnings: list[str] = field(default_factory=list)

    def summary_lines(self) -> list[str]:
        """The summary printed by ``esmm prepare``."""
        net = self.network
        lines = [
            f"structure   {net.structure} ({self.mesher})",
            f"nodes       {net.n_nodes}",
            f"springs     {net.n_springs}",
        ]
        if net.tets is not None:
            lines.append(f"tets        {net.n_tets}")
        lines += [
            f"volume      {net.total_volume() * 1e6:.2f} mL, mass {net.total_mass() * 1e3:.1f} g",
            f"rest length {net.rest_length.min() * 1e3:.2f} .. {net.rest_length.max() * 1e3:.2f} mm "
            f"(mean {net.rest_length.mean() * 1e3:.2f})",
            f"fixed       {net.fixed.size} nodes",
        ]
        if self.quality is not None:
            q = self.quality
            verdict = "passes the floors" if self.quality_passed else "BELOW the floors (--force)"
            lines.append(f"quality     min dihedral {getattr(q, 'min_dihedral_deg', float('nan')):.1f} deg, "
                         f"{verdict}")
        if self.tables is not None:
            lines.append(f"tables      {self.tables.n} points, stretch {self.tables.lam_min:.3g}.."
                         f"{self.tables.lam_max:.3g}")
        lines.append("time        " + ", ".join(f"{k} {v:.1f} s" for k, v in self.timings.items())
                     + f" (total {sum(self.timings.values()):.1f} s)")
        lines.append(f"wrote       {self.asset}")
        lines.append(f"            {self.xdmf} (open in ParaView)")
        return lines


# -- configuration ------------------------------------------------------------------------

def _merge(base: dict, over: dict, *, source: str) -> dict:
    out = copy.deepcopy(base)
    for section, table in over.items():
        if section not in DEFAULTS:
            raise ConfigError(f"{source}: unknown section [{section}]; allowed: "
                              f"{', '.join('[' + s + ']' for s in DEFAULTS)}")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: [{section}] must be a table")
        if section in ("fixed",):
            out[section] = copy.deepcopy(table)  # replaced as a whole (its keys depend on kind)
            continue
        if section != "quality":
            unknown = sorted(set(table) - set(DEFAULTS[section]))
            if unknown:
                raise ConfigError(f"{source}: unknown key(s) {', '.join(unknown)} in [{section}]; allowed: "
                                  f"{', '.join(DEFAULTS[section])}")
        if section == "mesh" and any(k in table for k in ("size", "nodes", "elements")):
            for k in ("size", "nodes", "elements"):
                out["mesh"][k] = None
        if section == "cleaning" and "body" in table:
            out["cleaning"]["keep"] = "largest"
        out[section].update(copy.deepcopy(table))
    return out


def load_prepare_config(config: str | os.PathLike | dict | None) -> tuple[dict, str]:
    """The prepare config merged over :data:`DEFAULTS`, and where it came from."""
    if isinstance(config, dict):
        return _merge(DEFAULTS, config, source="config"), "config (dict)"
    name = DEFAULT_PRESET if config is None else config
    data, source = _config.load("prepare", name)
    return _merge(DEFAULTS, data, source=source), source


def _int(v, where: str, *, minimum: int = 0) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ConfigError(f"{where}: expected a whole number >= {minimum}, got {v!r}")
    return int(v)


def _float(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}: expected a number, got {v!r}")
    return float(v)


def _quantity(v, kind: str, where: str) -> float:
    try:
        return parse_quantity(v, kind, where=where)
    except InputError as exc:
        raise ConfigError(str(exc)) from None


@dataclass
class _Settings:
    structure: str
    material: str
    density: float
    reorder: str | None
    unit: str
    label: int | None
    cleaning: dict
    size: float | None
    nodes: int | None
    elements: int | None
    timeout: float
    n_surface: int | None
    weight_exponent: float
    frame: Any
    fixed: Any
    floors: dict
    tables: dict


def _settings(cfg: dict, source: str) -> _Settings:
    """Check every value of a resolved config (one-line ConfigError naming the key)."""
    p, m, c = cfg["prepare"], cfg["mesh"], cfg["cleaning"]
    structure = p["structure"]
    if structure not in ("tetra", "skeleton"):
        raise ConfigError(f"[prepare] structure: {structure!r} is not \"tetra\" or \"skeleton\"")
    if not isinstance(p["material"], str) or not p["material"]:
        raise ConfigError(f"[prepare] material: expected a preset name or a .toml path, got {p['material']!r}")
    density = p["density"]
    if isinstance(density, str):
        density = _quantity(density, "density", "[prepare] density")
    else:
        density = _float(density, "[prepare] density (kg/m3)")
    if not 100 <= density <= 20000:
        raise ConfigError(f"[prepare] density: {density:g} kg/m3 is not plausible for tissue (about 1000-1100)")
    reorder = p["reorder"]
    if reorder not in ("rcm", "morton", "none", None):
        raise ConfigError(f"[prepare] reorder: {reorder!r} is not \"rcm\", \"morton\" or \"none\"")
    unit = cfg["input"]["unit"]
    from .units import UNITS, normalise_unit

    if not isinstance(unit, str) or normalise_unit(unit) not in UNITS["length"]:
        raise ConfigError(f"[input] unit: {unit!r} is not a length unit (mm, cm, m)")
    label = cfg["input"]["label"]
    if label is not None:
        label = _int(label, "[input] label", minimum=0)
    keep = c["keep"]
    if keep not in ("largest", "all"):
        raise ConfigError(f"[cleaning] keep: {keep!r} is not \"largest\" or \"all\"")
    cleaning = {"keep": keep, "smooth_iterations": _int(c["smooth_iterations"], "[cleaning] smooth_iterations"),
                "smooth_passband": _float(c["smooth_passband"], "[cleaning] smooth_passband"),
                "body": None if c["body"] is None else _int(c["body"], "[cleaning] body"),
                "target_faces": None if c["target_faces"] is None else _int(c["target_faces"], "[cleaning] target_faces", minimum=4),
                "target_edge": None if c["target_edge"] is None else _quantity(c["target_edge"], "length", "[cleaning] target_edge")}
    if not 0 < cleaning["smooth_passband"] <= 2:
        raise ConfigError(f"[cleaning] smooth_passband: expected a number in (0, 2], got {c['smooth_passband']!r}")
    given = [k for k in ("size", "nodes", "elements") if m[k] is not None]
    if len(given) > 1:
        raise ConfigError(f"[mesh]: give one of size, nodes or elements, not {' and '.join(given)}")
    size = None if m["size"] is None else _quantity(m["size"], "length", "[mesh] size")
    if size is not None and size <= 0:
        raise ConfigError(f"[mesh] size: must be positive, got {m['size']!r}")
    nodes = None if m["nodes"] is None else _int(m["nodes"], "[mesh] nodes", minimum=4)
    elements = None if m["elements"] is None else _int(m["elements"], "[mesh] elements", minimum=1)
    timeout = _quantity(m["timeout"], "time", "[mesh] timeout") if isinstance(m["timeout"], str) else \
        _float(m["timeout"], "[mesh] timeout (s)")
    if timeout <= 0:
        raise ConfigError(f"[mesh] timeout: must be positive, got {m['timeout']!r}")
    sk = cfg["skeleton"]
    n_surface = None if sk["n_surface"] is None else _int(sk["n_surface"], "[skeleton] n_surface", minimum=4)
    weight_exponent = _float(sk["weight_exponent"], "[skeleton] weight_exponent")
    from .network.regions import region_from_config
    from .network.springs import fibre_frame_matrix

    frame = cfg["fibres"]["frame"]
    if not (isinstance(frame, str) and frame in ("identity", "principal")):
        try:
            fibre_frame_matrix(frame, where="[fibres] frame")
        except InputError as exc:
            raise ConfigError(str(exc)) from None
    fixed = region_from_config(cfg["fixed"], where="[fixed]")
    floors = {}
    for k, v in cfg["quality"].items():
        floors[k] = _float(v, f"[quality] {k}")
    t = cfg["tables"]
    tables = {"n": _int(t["n"], "[tables] n", minimum=3), "law": t["law"]}
    for k in ("lam_min", "lam_max"):
        if t[k] is not None:
            tables[k] = _float(t[k], f"[tables] {k}")
    if t["law"] not in ("secant", "energy"):
        raise ConfigError(f"[tables] law: {t['law']!r} is not \"secant\" or \"energy\"")
    if not isinstance(t["compensate"], bool):
        raise ConfigError(f"[tables] compensate: expected true or false, got {t['compensate']!r}")
    tables["compensate"] = t["compensate"]
    return _Settings(structure, p["material"], density, None if reorder in ("none", None) else reorder, unit,
                     label, cleaning, size, nodes, elements, timeout, n_surface, weight_exponent, frame,
                     fixed, floors, tables)


def _toml_clean(d):
    """Drop None values (TOML has no null) recursively."""
    if isinstance(d, dict):
        return {k: _toml_clean(v) for k, v in d.items() if v is not None}
    return d


def config_toml(cfg: dict) -> str:
    """The resolved config as TOML text."""
    import tomli_w

    return tomli_w.dumps(_toml_clean(cfg))


# -- stages -------------------------------------------------------------------------------

class _Clock:
    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.started = time.perf_counter()

    def run(self, name: str, fn, *args, **kwargs):
        t0 = self.started = time.perf_counter()
        out = fn(*args, **kwargs)
        self.timings[name] = time.perf_counter() - t0
        return out


def _load_material(name: str):
    try:
        from .materials.material import load_material
    except ImportError:
        return None
    return load_material(name)


def _build_tables(material, opts: dict):
    if material is None:
        return None
    try:
        from .network.tables import build_tables
    except ImportError:
        return None
    return build_tables(material, **{k: v for k, v in opts.items() if k != "compensate"})


def size_for_elements(volume: float, elements: int) -> float:
    """Mesh size [m] that gives about *elements* tets in *volume* [m3].

    A regular tet of edge ``h`` has volume ``h**3 / (6 sqrt 2)``; the mesher's
    tets average :data:`MESHER_VOLUME_RATIO` times that.
    """
    return (6.0 * math.sqrt(2.0) * volume / (MESHER_VOLUME_RATIO * elements)) ** (1.0 / 3.0)


def _mesh(surface, s: _Settings, rep, clock: _Clock):
    from .errors import MeshingError
    from .mesh.volume import mesh_volume

    if s.elements is None:
        return clock.run("mesh", mesh_volume, surface, size=s.size, nodes=s.nodes, timeout=s.timeout,
                         reporter=rep)
    vol = abs(float(surface.volume()))
    size = size_for_elements(vol, s.elements)
    mesh = clock.run("mesh", mesh_volume, surface, size=size, timeout=s.timeout, reporter=rep)
    got = mesh.tets.shape[0]
    if abs(got / s.elements - 1.0) <= ELEMENTS_TOLERANCE:
        return mesh
    # One correction, N ~ h^-3. It is an improvement, not a requirement: its time is
    # bounded and, if the mesher fails at the new size, the first mesh is kept.
    size2 = size * (got / s.elements) ** (1.0 / 3.0)
    first = clock.timings["mesh"]
    rep.step(f"mesh: {got} tets for a target of {s.elements}; remeshing at {size2 * 1e3:.2f} mm "
             f"instead of {size * 1e3:.2f} mm")
    try:
        mesh2 = clock.run("mesh", mesh_volume, surface, size=size2,
                          timeout=min(s.timeout, max(30.0, 4.0 * first)), reporter=rep)
    except MeshingError as exc:
        clock.timings["mesh"] = first + time.perf_counter() - clock.started
        rep.warn(f"mesh: remeshing at {size2 * 1e3:.2f} mm failed ({exc}); keeping the first mesh "
                 f"({got} tets at {size * 1e3:.2f} mm)")
        return mesh
    clock.timings["mesh"] += first
    return mesh2


def _check_floor_names(floors: dict) -> None:
    """Refuse [quality] keys that are not quality figures, before any meshing."""
    from types import SimpleNamespace

    from .mesh.quality import QUALITY_FLOORS, tet_quality

    probe = SimpleNamespace(points=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                            tets=np.array([[0, 1, 2, 3]]))
    report = tet_quality(probe)
    known = set(report.values()) if hasattr(report, "values") else set(QUALITY_FLOORS)
    unknown = sorted(set(floors) - known)
    if unknown:
        raise ConfigError(f"[quality]: unknown figure(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")


def input_stem(path: str | os.PathLike) -> str:
    """The input's name without its extension (``liver.stl`` -> ``liver``, ``seg.nii.gz`` -> ``seg``)."""
    name = Path(path).name
    for compound in (".nii.gz", ".vtk.gz", ".stl.gz"):
        if name.lower().endswith(compound):
            return name[: -len(compound)]
    return Path(name).stem


def prepare(input_path: str | os.PathLike, *, output: str | os.PathLike | None = None,
            config: str | os.PathLike | dict | None = None, size: float | None = None,
            nodes: int | None = None, elements: int | None = None, structure: str | None = None,
            unit: str | None = None, label: int | None = None, keep_all: bool = False,
            body: int | None = None, material: str | None = None, density: float | None = None,
            force: bool = False, compensate: bool | None = None, reporter=None,
            argv: list[str] | None = None) -> PrepareResult:
    """Turn an organ surface into a spring-network asset.

    Parameters
    ----------
    input_path
        Organ surface (STL, OBJ, PLY, VTK, legacy .msh) or a label mask (NIfTI).
    output
        The asset ``.h5``; default ``<input stem>.h5`` in the current folder.
        The XDMF sidecar is written beside it.
    config
        Prepare preset name (``coarse``, ``paper``, ``fine``), a TOML path, or
        a dict; default ``"paper"``. Keyword options below override it.
    size : float, optional
        Target mesh size [m] (tetra).
    nodes : int, optional
        Target number of mesh nodes (tetra).
    elements : int, optional
        Target number of tets; the size is estimated from the cleaned volume,
        with one remeshing pass if off by more than 20 %.
    structure : {"tetra", "skeleton"}, optional
    unit : str, optional
        Length unit of the input file (mm, cm, m).
    label : int, optional
        Label to extract from a mask input.
    keep_all : bool
        Keep every body of the surface (default: the largest).
    body : int, optional
        Keep this body (0-based, by decreasing volume).
    material : str, optional
        Material preset name or TOML path (default ``porcine_liver_paper``).
    density : float, optional
        Tissue density [kg/m3].
    force : bool
        Write the asset even when the mesh is below the quality floors.
    reporter
        Progress reporter (:mod:`esmm.pipeline.progress`).
    argv : list of str, optional
        The command line, for provenance.

    Returns
    -------
    PrepareResult

    Raises
    ------
    ConfigError, InputError, MeshingError
        Bad options, unreadable input, meshing failure (nothing is written).
    QualityError
        The tet mesh is below the quality floors and *force* is False.
    """
    rep = ensure(reporter)
    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        rep.warn(msg)

    inp = Path(input_path)
    if not inp.exists():
        raise InputError(f"{inp}: no such file")
    if inp.is_dir():
        raise InputError(f"{inp}: is a folder; give the organ surface file (STL, OBJ, PLY, VTK, NIfTI)")
    out = Path(output) if output is not None else Path.cwd() / (input_stem(inp) + ".h5")
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ConfigError(f"-o {out}: the asset file name must end in .h5")
    if out.resolve() == inp.resolve():
        raise ConfigError(f"-o {out}: would overwrite the input; choose another name")

    cfg, source = load_prepare_config(config)
    # Keyword options override the config.
    over = [(size, "mesh", "size"), (nodes, "mesh", "nodes"), (elements, "mesh", "elements")]
    given = [k for v, _, k in over if v is not None]
    if len(given) > 1:
        raise ConfigError(f"give one of size, nodes or elements, not {' and '.join(given)}")
    if given:
        cfg["mesh"].update(size=None, nodes=None, elements=None)
        if size is not None:
            if isinstance(size, bool) or not isinstance(size, (int, float)) or not size > 0 or not math.isfinite(size):
                raise ConfigError(f"size: must be a positive length in metres, got {size!r}")
            cfg["mesh"]["size"] = f"{size * 1e3:.12g} mm"
        elif nodes is not None:
            cfg["mesh"]["nodes"] = nodes
        else:
            cfg["mesh"]["elements"] = elements
    if keep_all and body is not None:
        raise ConfigError("give either keep_all (--keep-all) or body (--body), not both")
    if keep_all:
        cfg["cleaning"].update(keep="all", body=None)
    if body is not None:
        cfg["cleaning"].update(keep="largest", body=body)
    for value, section, key in ((structure, "prepare", "structure"), (unit, "input", "unit"),
                                (label, "input", "label"), (material, "prepare", "material")):
        if value is not None:
            cfg[section][key] = value
    if density is not None:
        if isinstance(density, bool) or not isinstance(density, (int, float)):
            raise ConfigError(f"density: expected a number of kg/m3, got {density!r}")
        cfg["prepare"]["density"] = f"{float(density):.12g} kg/m3"
    s = _settings(cfg, source)
    if s.structure == "skeleton" and given:
        raise ConfigError(f"{given[0]} sets the tet mesh; for the skeleton structure set "
                          f"[skeleton] n_surface in the config")
    if s.structure == "tetra" and s.floors:
        _check_floor_names(s.floors)
    clock = _Clock()
    # Fail fast on the material before any meshing.
    mat = clock.run("material", _load_material, s.material)
    rep.step(f"config: {source}; structure {s.structure}; material {s.material}")
    if mat is None:
        warn("the materials module is not available: the asset has no /material or /tables")
    else:
        from .asset.material import material_effects

        fx = material_effects(mat)       # ConfigError before any meshing if [material.effects] is malformed
        if fx is not None:
            rep.step(f"material effects {', '.join(fx.names)}: written to /material/effects, applied by "
                     "'esmm simulate' (the material's parameters are the instantaneous response)")

    # read
    from .mesh.cleaning import CleaningOptions, clean_surface
    from .mesh.readers import read_surface

    surface = clock.run("read", read_surface, inp, unit=s.unit, label=s.label, reporter=rep)
    rep.step(f"read: {surface.summary()} ({clock.timings['read']:.1f} s)")

    opts = CleaningOptions(keep=s.cleaning["keep"], body=s.cleaning["body"],
                           smooth_iterations=s.cleaning["smooth_iterations"],
                           smooth_passband=s.cleaning["smooth_passband"],
                           target_faces=s.cleaning["target_faces"], target_edge=s.cleaning["target_edge"])
    clean, cleaning = clock.run("clean", clean_surface, surface, options=opts, reporter=rep)
    rep.step(f"clean: {clean.summary()} ({clock.timings['clean']:.1f} s)")

    from .network.springs import network_from_skeleton, network_from_tets

    quality, passed, mesher, mesh_log, floors = None, True, "skeleton", [], None
    if s.structure == "tetra":
        mesh = _mesh(clean, s, rep, clock)
        mesher = getattr(mesh, "path", "gmsh")
        mesh_log = list(getattr(mesh, "log", []) or [])
        rep.step(f"mesh: {mesh.points.shape[0]} nodes, {mesh.tets.shape[0]} tets via {mesher} "
                 f"({clock.timings['mesh']:.1f} s)")
        from .mesh.quality import QUALITY_FLOORS, tet_quality

        floors = {**QUALITY_FLOORS, **s.floors}
        quality = clock.run("quality", tet_quality, mesh)
        passed, problems = quality.passes(floors)
        if passed:
            rep.step(f"quality: min dihedral {quality.min_dihedral_deg:.1f} deg, passes the floors")
        elif force:
            for pr in problems:
                warn(f"quality below floor (written anyway, --force): {pr}")
        else:
            raise QualityError(f"{inp.name}: mesh quality below the floors: {'; '.join(problems)}; "
                               f"try another --size/--nodes, or --force to write it anyway")
        net = clock.run("network", network_from_tets, mesh, density=s.density, fibre_frame=s.frame,
                        reorder=s.reorder, reporter=rep)
    else:
        from .mesh.skeleton import skeleton_structure

        sk = clock.run("mesh", skeleton_structure, clean, n_surface=s.n_surface, reporter=rep)
        mesh_log = list(getattr(sk, "log", []) or [])
        from .network.springs import NODE_SKELETON, NODE_SURFACE

        kind = np.where(np.asarray(sk.kind) == 0, NODE_SURFACE, NODE_SKELETON).astype(np.uint8)
        net = clock.run("network", network_from_skeleton, sk.points, sk.edges, volume=abs(clean.volume()),
                        surface_faces=sk.surface_faces, node_kind=kind, density=s.density,
                        fibre_frame=s.frame, reorder=s.reorder, weight_exponent=s.weight_exponent)
    rep.step(f"network: {net.summary()}, bandwidth {net.bandwidth()} ({clock.timings['network']:.2f} s)")

    tables = clock.run("tables", _build_tables, mat, s.tables)
    if tables is not None:
        rep.step(f"tables: {tables.n} points on stretch {tables.lam_min:.3g}..{tables.lam_max:.3g} "
                 f"({clock.timings['tables']:.2f} s)")
        do_comp = s.tables.get("compensate", True) if compensate is None else compensate
        if do_comp:
            comp = clock.run("compensation", compensation.compensate, tables, net, material=mat, reporter=rep)
            tables = comp.tables
            rep.step(f"compensation: volume factor c = {tables.volume_factor:.3f} and a stretch "
                     f"correction; virtual tensile test error {comp.summary()} "
                     f"({clock.timings['compensation']:.1f} s)")
        else:
            warnings.append("no volumetric compensation: the raw network is several times softer "
                            "than the tissue (docs/model.md); run 'esmm tables ASSET --compensate'")
            rep.warn(warnings[-1])

    from .network.regions import select_fixed

    fixed = select_fixed(net.points, s.fixed, node_kind=net.node_kind)
    net = net.with_fixed(fixed)
    rep.step(f"fixed: {fixed.size} nodes ({s.fixed.describe()})")

    from .asset.provenance import collect_provenance
    from .asset.write import write_asset
    from .asset.xdmf import sidecar_path

    prov = collect_provenance(inp, config_toml=config_toml(cfg), argv=argv,
                              extra={"config_source": source, "timings_s": dict(clock.timings),
                                     "mesher": mesher, "warnings": warnings,
                                     "mesh_log": [str(x) for x in mesh_log[-50:]]})
    clock.run("write", write_asset, out, net, material=mat, tables=tables, quality=quality,
              cleaning=cleaning, provenance=prov, quality_floors=floors, fixed_region=s.fixed.describe())
    rep.step(f"write: {out} ({clock.timings['write']:.2f} s)")
    return PrepareResult(asset=out, xdmf=sidecar_path(out), network=net, quality=quality, quality_passed=passed,
                         cleaning=cleaning, tables=tables, material=mat, timings=clock.timings,
                         mesher=mesher, config=cfg, warnings=warnings)
