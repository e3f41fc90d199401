"""``esmm prepare``: an organ surface in, a spring-network asset out.

Stages (each reported with its figures and time through ``reporter``)::

    read -> clean -> mesh (tetra) or skeleton -> quality gate -> network
         -> stiffness tables -> compensation -> fixed region -> asset (.h5 + .xdmf)

Settings come from, in increasing precedence: the built-in defaults
(:data:`DEFAULTS`), the prepare config (a bundled preset name such as
``"paper"`` or a TOML path; default ``"paper"``), and the keyword arguments.
They are parsed and checked once, before any work, into a frozen
:class:`PrepareConfig` (:func:`prepare_config`); a message names the config key
(``[mesh] nodes``) or the keyword (``nodes``) the bad value came from. The
resolved configuration is stored in the asset's provenance, so an asset can be
remade from it. The config schema is documented in docs/reference/configuration.md ("Prepare config").
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import config as _config
from .asset.accuracy import fit_record
from .asset.material import material_effects, storable_effects
from .asset.provenance import collect_provenance
from .asset.report import report_path, write_asset_report
from .asset.write import write_asset
from .asset.xdmf import sidecar_path
from .atomicio import unwritable_file
from .checks import boolean, choice, number, quantity
from .compensation import calibration as compensation
from .errors import ConfigError, InputError, QualityError
from .materials.material import DEFAULT_MATERIAL, Material, load_material
from .mesh.cleaning import CleaningOptions, CleaningReport, clean_surface
from .mesh.quality import QUALITY_FLOORS, QualityReport, check_floors, tet_quality
from .mesh.readers import read_surface
from .mesh.refine import split_mesh
from .mesh.skeleton import check_n_surface, skeleton_structure
from .mesh.targets import MeshTarget, mesh_target
from .mesh.volume import mesh_volume
from .network.regions import FixedRegion, region_from_config, select_fixed
from .network.springs import (
    NODE_SKELETON,
    NODE_SURFACE,
    STRUCTURES,
    SpringNetwork,
    check_density,
    check_reorder,
    fibre_frame_matrix,
    network_from_skeleton,
    network_from_tets,
)
from .network.tables import GridOptions, StiffnessTables, build_tables, grid_note, grid_options
from .network.volume import DEFAULT_POISSON, POISSON_RANGE, VolumeSpec, bulk_modulus
from .progress import ensure
from .units import factor

#: The default prepare preset.
DEFAULT_PRESET = "paper"

#: Every section and key a prepare config may have, with its default (None: unset).
DEFAULTS: dict[str, dict[str, Any]] = {
    "prepare": {"structure": "tetra", "material": DEFAULT_MATERIAL, "density": "1060 kg/m3",
                "reorder": "rcm"},
    "input": {"unit": None, "label": None},
    "cleaning": {"keep": "largest", "body": None, "smooth_iterations": 20, "smooth_passband": 0.1,
                 "target_faces": None, "target_edge": None},
    "mesh": {"size": None, "nodes": None, "elements": None, "timeout": "120 s", "split": False},
    "skeleton": {"n_surface": None, "weight_exponent": 2.0},
    "fibres": {"frame": "identity"},
    "fixed": {"kind": "band", "axis": "longest", "end": "min", "width_fraction": 0.1},
    "quality": {},
    "tables": {"n": 1024, "law": "secant", "lam_min": None, "lam_max": None, "compensate": True},
    "volume": {"enabled": True, "poisson_ratio": DEFAULT_POISSON},
}

#: Keyword option of :func:`prepare` -> the (section, key) of the config it sets.
KEYWORDS: dict[str, tuple[str, str]] = {
    "size": ("mesh", "size"), "nodes": ("mesh", "nodes"), "elements": ("mesh", "elements"),
    "structure": ("prepare", "structure"), "material": ("prepare", "material"),
    "density": ("prepare", "density"), "unit": ("input", "unit"), "label": ("input", "label"),
    "keep_all": ("cleaning", "keep"), "body": ("cleaning", "body"), "compensate": ("tables", "compensate"),
    "volume": ("volume", "enabled"), "split": ("mesh", "split"),
}


@dataclass(frozen=True)
class PrepareConfig:
    """The settings of one prepare run, parsed and checked (:func:`prepare_config`).

    Attributes
    ----------
    structure : {"tetra", "skeleton"}
    material : str
        Material preset name or TOML path.
    density : float
        Tissue density [kg/m3].
    reorder : {"rcm", "morton"} or None
        Node numbering.
    unit : str or None
        Length unit of the input file; None: mm, or a NIfTI header's own unit.
    label : int or None
        Label to extract from a mask input.
    cleaning : CleaningOptions
    target : MeshTarget
        Size [m], node or tetrahedron count of the tet mesh.
    timeout : float
        Time limit of each meshing attempt [s].
    split : bool
        Split every tetrahedron of the mesh in eight (tetra structure; the
        target is the mesh before the split).
    n_surface : int or None
        Surface vertices of the skeleton structure.
    weight_exponent : float
        Volume-sharing exponent of the skeleton structure.
    fibre_frame : str or tuple
        ``"identity"``, ``"principal"`` or three rows.
    fixed : FixedRegion
    floors : mapping
        Quality floors set by the config (over :data:`~esmm.pipeline.mesh.quality.QUALITY_FLOORS`).
    grid : GridOptions
        The stiffness tables' grid and default law.
    compensate : bool
        Calibrate the volumetric compensation.
    volume : bool
        Give the network its volume term (tet structure; docs/design/model.md, "The volume term (nearly incompressible network)").
    poisson_ratio : float
        The Poisson ratio the volume term's bulk modulus is sized for.
    source : str
        Where the config came from.
    toml : str
        The resolved configuration as TOML text (stored in the asset's provenance).
    """

    structure: str
    material: str
    density: float
    reorder: str | None
    unit: str | None
    label: int | None
    cleaning: CleaningOptions
    target: MeshTarget
    timeout: float
    split: bool
    n_surface: int | None
    weight_exponent: float
    fibre_frame: Any
    fixed: FixedRegion
    floors: Mapping[str, float]
    grid: GridOptions
    compensate: bool
    volume: bool
    poisson_ratio: float
    source: str
    toml: str


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
    tables : StiffnessTables
    material : Material
    timings : dict
        Stage -> seconds.
    mesher : str
        The meshing path taken (e.g. ``"gmsh"``), or ``"skeleton"``.
    config : PrepareConfig
        The resolved configuration.
    warnings : list of str
    report : Path or None
        The asset's HTML report (``NAME.report.html``: how far to trust it, quality, material).
    """

    asset: Path
    xdmf: Path
    network: SpringNetwork
    quality: QualityReport | None
    quality_passed: bool
    cleaning: CleaningReport
    tables: StiffnessTables
    material: Material
    timings: dict[str, float]
    mesher: str
    config: PrepareConfig
    warnings: list[str] = field(default_factory=list)
    report: Path | None = None


# -- configuration ------------------------------------------------------------------------

def _merge(base: dict, over: dict, *, source: str) -> dict:
    out = copy.deepcopy(base)
    for section, table in over.items():
        if section not in DEFAULTS:
            raise ConfigError(f"{source}: unknown section [{section}]; allowed: "
                              f"{', '.join('[' + s + ']' for s in DEFAULTS)}")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: [{section}] must be a table")
        if section == "fixed":
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


def _keyword_table(kw: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The keyword options given (not None) as a config layer, their values in config form.

    Lengths and densities become quantities with their unit (``size`` is in metres,
    ``density`` in kg/m3), so the resolved config reads as a TOML file would.
    """
    mesh_target(size=kw.get("size"), nodes=kw.get("nodes"), elements=kw.get("elements"))  # one of them
    if kw.get("keep_all") and kw.get("body") is not None:
        raise ConfigError("keep_all: keep every body or one body, not both (keep_all and body)", parameter="keep_all")
    layer: dict[str, dict[str, Any]] = {}
    for name, value in kw.items():
        if value is None or (name == "keep_all" and not value):
            continue
        if name == "size":  # checked by mesh_target above
            value = f"{value * 1e3:.12g} mm"
        elif name == "density":
            value = f"{number(value, 'density'):.12g} kg/m3"
        section, key = KEYWORDS[name]
        if name == "keep_all":
            layer.setdefault("cleaning", {}).update(keep="all", body=None)
            continue
        layer.setdefault(section, {})[key] = value
    return layer


def _toml_clean(d):
    """Drop None values (TOML has no null) recursively."""
    if isinstance(d, dict):
        return {k: _toml_clean(v) for k, v in d.items() if v is not None}
    return d


def config_toml(cfg: dict) -> str:
    """The resolved config as TOML text."""
    import tomli_w

    return tomli_w.dumps(_toml_clean(cfg))


def prepare_config(config: str | os.PathLike | dict | None = None, **keywords: Any) -> PrepareConfig:
    """Load, merge and check a prepare configuration.

    Parameters
    ----------
    config
        Prepare preset name (``coarse``, ``paper``, ``fine``), a TOML path, or
        a dict; default ``"paper"``.
    **keywords
        The keyword options of :func:`prepare` that override it (see
        :data:`KEYWORDS`); None means "not given".

    Raises
    ------
    ConfigError
        An unknown section, key or keyword, or a bad value (one line naming the
        config key, or the keyword it came from).
    """
    unknown = sorted(set(keywords) - set(KEYWORDS))
    if unknown:
        raise ConfigError(f"{unknown[0]}: not an option of prepare; known: {', '.join(KEYWORDS)}",
                          parameter=unknown[0])
    layer = _keyword_table(keywords)
    cfg, source = load_prepare_config(config)
    cfg = _merge(cfg, layer, source="options")
    from_keywords = {KEYWORDS[k]: k for k, v in keywords.items() if v is not None and v is not False}
    if cfg["prepare"]["structure"] == "skeleton":
        given = [k for k in ("size", "nodes", "elements") if keywords.get(k) is not None] + \
            (["split"] if keywords.get("split") else [])
        if given:
            raise ConfigError(f"{given[0]}: sets the tet mesh; for the skeleton structure set "
                              f"[skeleton] n_surface in the config", parameter=given[0])
    return parse_prepare_config(cfg, source, names=from_keywords)


@contextlib.contextmanager
def _as_config_error(parameter: str | None = None) -> Iterator[None]:
    """A value of the config refused by a stage's own rule (an InputError) is a ConfigError."""
    try:
        yield
    except InputError as exc:
        raise ConfigError(str(exc), parameter=exc.parameter or parameter) from None


def parse_prepare_config(cfg: dict, source: str, *, names: Mapping[tuple[str, str], str] | None = None
                         ) -> PrepareConfig:
    """Check every value of a resolved config (:func:`load_prepare_config`) into a :class:`PrepareConfig`.

    Each value is checked by the rule of the stage that uses it. *names* maps a
    ``(section, key)`` to the parameter name for messages (the keyword option it
    came from); other values are named ``[section] key``.

    Raises
    ------
    ConfigError
        One line naming the key.
    """
    def name(section: str, key: str) -> str:
        return (names or {}).get((section, key)) or f"[{section}] {key}"

    fields: dict[str, Any] = {"source": source, "toml": config_toml(cfg)}
    for part in (_prepare_part, _input_part, _cleaning_part, _mesh_part, _skeleton_part, _network_part,
                 _tables_part, _volume_part):
        fields.update(part(cfg, name))
    return PrepareConfig(**fields)


def _prepare_part(cfg: dict, name) -> dict[str, Any]:
    p = cfg["prepare"]
    material = p["material"]
    if not isinstance(material, str) or not material:
        raise ConfigError(f"{name('prepare', 'material')}: expected a preset name or a .toml path, "
                          f"got {material!r}", parameter=name("prepare", "material"))
    density = p["density"]
    where = name("prepare", "density")
    density = quantity(density, "density", where) if isinstance(density, str) else number(density, where)
    with _as_config_error():
        return {"structure": choice(p["structure"], STRUCTURES, name("prepare", "structure")),
                "material": material, "density": check_density(density, where),
                "reorder": check_reorder(p["reorder"], name("prepare", "reorder"))}


def _input_part(cfg: dict, name) -> dict[str, Any]:
    unit, label = cfg["input"]["unit"], cfg["input"]["label"]
    where = name("input", "unit")
    if unit is None:
        return {"unit": None, "label": _label(label, name)}
    if not isinstance(unit, str):
        raise ConfigError(f"{where}: {unit!r} is not a length unit (mm, cm, m)", parameter=where)
    with _as_config_error(where):
        factor(unit, "length", where=where)
    return {"unit": unit, "label": _label(label, name)}


def _label(label, name) -> int | None:
    return None if label is None else number(label, name("input", "label"), lo=0, integer=True)


def _cleaning_part(cfg: dict, name) -> dict[str, Any]:
    c = dict(cfg["cleaning"])
    if c["target_edge"] is not None:
        c["target_edge"] = quantity(c["target_edge"], "length", name("cleaning", "target_edge"))
    options = CleaningOptions(**c)
    options.validate(names={k: name("cleaning", k) for k in c})
    return {"cleaning": options}


def _mesh_part(cfg: dict, name) -> dict[str, Any]:
    m = cfg["mesh"]
    size = None if m["size"] is None else quantity(m["size"], "length", name("mesh", "size"))
    target = mesh_target(size=size, nodes=m["nodes"], elements=m["elements"], where="[mesh]",
                         names={k: name("mesh", k) for k in ("size", "nodes", "elements")})
    where = name("mesh", "timeout")
    timeout = quantity(m["timeout"], "time", where) if isinstance(m["timeout"], str) else m["timeout"]
    return {"target": target, "timeout": number(timeout, where, lo=0.0, lo_open=True),
            "split": boolean(m["split"], name("mesh", "split"))}


def _skeleton_part(cfg: dict, name) -> dict[str, Any]:
    sk = cfg["skeleton"]
    return {"n_surface": check_n_surface(sk["n_surface"], name("skeleton", "n_surface")),
            "weight_exponent": number(sk["weight_exponent"], name("skeleton", "weight_exponent"))}


def _network_part(cfg: dict, name) -> dict[str, Any]:
    frame = cfg["fibres"]["frame"]
    if not (isinstance(frame, str) and frame in ("identity", "principal")):
        with _as_config_error(name("fibres", "frame")):
            fibre_frame_matrix(frame, where=name("fibres", "frame"))
        frame = tuple(tuple(float(x) for x in row) for row in frame)
    return {"fibre_frame": frame, "fixed": region_from_config(cfg["fixed"], where="[fixed]"),
            "floors": check_floors(cfg["quality"], "[quality]")}


def _tables_part(cfg: dict, name) -> dict[str, Any]:
    t = cfg["tables"]
    grid = grid_options(n=t["n"], law=t["law"], lam_min=t["lam_min"], lam_max=t["lam_max"],
                        names={k: name("tables", k) for k in ("n", "law", "lam_min", "lam_max")})
    return {"grid": grid, "compensate": boolean(t["compensate"], name("tables", "compensate"))}


def _volume_part(cfg: dict, name) -> dict[str, Any]:
    v = cfg["volume"]
    nu = number(v["poisson_ratio"], name("volume", "poisson_ratio"), lo=POISSON_RANGE[0], hi=POISSON_RANGE[1])
    return {"volume": boolean(v["enabled"], name("volume", "enabled")), "poisson_ratio": nu}


# -- stages -------------------------------------------------------------------------------

class _Run:
    """The timings, warnings and reporter of one prepare run."""

    def __init__(self, reporter) -> None:
        self.rep = ensure(reporter)
        self.timings: dict[str, float] = {}
        self.warnings: list[str] = []

    def stage(self, name: str, fn, *args, **kwargs):
        """Run ``fn(*args, **kwargs)`` and record its time under *name*."""
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self.timings[name] = time.perf_counter() - t0
        return out

    def warn(self, msg: str) -> None:
        self.warnings.append(msg)
        self.rep.warn(msg)


@dataclass(frozen=True)
class _Structure:
    """The spring network and what its meshing left to record."""

    network: SpringNetwork
    mesher: str
    log: list[str]
    quality: QualityReport | None = None
    passed: bool = True
    floors: dict[str, float] | None = None


def input_stem(path: str | os.PathLike) -> str:
    """The input's name without its extension (``liver.stl`` -> ``liver``, ``seg.nii.gz`` -> ``seg``)."""
    name = Path(path).name
    for compound in (".nii.gz", ".vtk.gz", ".stl.gz"):
        if name.lower().endswith(compound):
            return name[: -len(compound)]
    return Path(name).stem


def asset_paths(input_path: str | os.PathLike, output: str | os.PathLike | None) -> tuple[Path, Path]:
    """The input file and the asset to write (default ``<input stem>.h5`` in the current folder).

    Raises
    ------
    InputError
        The input is missing or a folder.
    ConfigError
        The output does not end in ``.h5``, is the input, is a folder (or its
        sidecar is), or cannot be written (parameter ``output``).
    """
    inp = Path(input_path)
    if not inp.exists():
        raise InputError(f"{inp}: no such file")
    if inp.is_dir():
        raise InputError(f"{inp}: is a folder; give the organ surface file (STL, OBJ, PLY, VTK, NIfTI)")
    out = Path(output) if output is not None else Path.cwd() / (input_stem(inp) + ".h5")
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ConfigError(f"output: {out}: the asset file name must end in .h5", parameter="output")
    if out.resolve() == inp.resolve():
        raise ConfigError(f"output: {out}: would overwrite the input; choose another name", parameter="output")
    _check_writable(out)
    return inp, out


def _check_writable(out: Path) -> None:
    """Refuse, before any work, an asset path that cannot be written: a folder, under a file, not writable."""
    problem = unwritable_file(out, "organ.h5")
    if problem:
        raise ConfigError(f"output: {problem}", parameter="output")
    if sidecar_path(out).is_dir():
        raise ConfigError(f"output: {out}: its ParaView sidecar {sidecar_path(out)} is a folder; "
                          "give another name", parameter="output")


def _material(cfg: PrepareConfig, run: _Run) -> Material:
    """The material, loaded before any meshing (a bad material or effects table fails fast)."""
    mat = run.stage("material", load_material, cfg.material)
    run.rep.step(f"config: {cfg.source}; structure {cfg.structure}; material {cfg.material}")
    fx, dropped = storable_effects(material_effects(mat))
    if fx is not None:
        run.rep.step(f"material effects {', '.join(fx.names)}: written to /material/effects, applied by "
                     "'esmm simulate' (the material's parameters are the instantaneous response)")
    for note in dropped:
        run.rep.warn(f"material {cfg.material}: not stored in the asset, so not simulated: {note}; the "
                     f"simulation will differ from the tissue there")
    return mat


def _surface(inp: Path, cfg: PrepareConfig, run: _Run):
    """Read and clean the organ surface: (surface, CleaningReport)."""
    surface = run.stage("read", read_surface, inp, unit=cfg.unit, label=cfg.label, reporter=run.rep)
    run.rep.step(f"read: {surface.summary()} ({run.timings['read']:.1f} s)")
    clean, cleaning = run.stage("clean", clean_surface, surface, options=cfg.cleaning, reporter=run.rep)
    run.rep.step(f"clean: {clean.summary()} ({run.timings['clean']:.1f} s)")
    return clean, cleaning


def _tetra(clean, cfg: PrepareConfig, run: _Run, *, force: bool, name: str) -> _Structure:
    """Tet mesh, quality gate, network on the tet edges."""
    t = cfg.target
    mesh = run.stage("mesh", mesh_volume, clean, size=t.size, nodes=t.nodes, elements=t.elements,
                     timeout=cfg.timeout, reporter=run.rep)
    run.rep.step(f"mesh: {mesh.n_nodes} nodes, {mesh.n_tets} tets via {mesh.path} ({run.timings['mesh']:.1f} s)")
    if cfg.split:
        mesh = run.stage("split", split_mesh, mesh)
        run.rep.step(f"split: every tet in eight, {mesh.n_nodes} nodes, {mesh.n_tets} tets "
                     "(the network on the quadratic tets' nodes)")
    floors = {**QUALITY_FLOORS, **cfg.floors}
    quality = run.stage("quality", tet_quality, mesh)
    passed, problems = quality.passes(floors)
    if passed:
        run.rep.step(f"quality: min dihedral {quality.min_dihedral_deg:.1f} deg, passes the floors")
    elif force:
        for pr in problems:
            run.warn(f"quality below floor (written anyway, forced): {pr}")
    else:
        raise QualityError(f"{name}: mesh quality below the floors: {'; '.join(problems)}; "
                           "try another mesh size or node count, lower the floor in the config's [quality] "
                           "table, or force the write")
    net = run.stage("network", network_from_tets, mesh, density=cfg.density, fibre_frame=cfg.fibre_frame,
                    reorder=cfg.reorder, reporter=run.rep)
    return _Structure(net, mesh.path, list(mesh.log), quality, passed, floors)


def _skeleton(clean, cfg: PrepareConfig, run: _Run) -> _Structure:
    """Surface + skeleton structure, the organ volume shared over its springs."""
    sk = run.stage("mesh", skeleton_structure, clean, n_surface=cfg.n_surface, reporter=run.rep)
    kind = np.where(np.asarray(sk.kind) == 0, NODE_SURFACE, NODE_SKELETON).astype(np.uint8)
    net = run.stage("network", network_from_skeleton, sk.points, sk.edges, volume=abs(clean.volume()),
                    surface_faces=sk.surface_faces, node_kind=kind, density=cfg.density,
                    fibre_frame=cfg.fibre_frame, reorder=cfg.reorder, weight_exponent=cfg.weight_exponent)
    return _Structure(net, "skeleton", list(sk.log))


def _volume(tables: StiffnessTables, net: SpringNetwork, cfg: PrepareConfig, run: _Run) -> VolumeSpec | None:
    """The network's volume term (bulk modulus from the material), or None (disabled, or no tets)."""
    if not cfg.volume:
        run.warn("no volume term: the network is compressible (Poisson ratio ~1/4) and loses volume under "
                 "load (docs/design/model.md, 'The volume term')")
        return None
    if net.tets is None:
        run.warn("the skeleton structure has no tetrahedra, so it gets no volume term: it does not keep the "
                 "organ's volume (use the tetra structure for that; docs/design/model.md, 'The volume term')")
        return None
    spec = bulk_modulus(tables, poisson=cfg.poisson_ratio,
                        calibration_range=compensation.calibration_stretches(tables))
    run.rep.step(f"volume term: bulk modulus {spec.bulk_modulus / 1e3:.4g} kPa (Poisson ratio {spec.poisson_ratio:g} "
                 f"at the material's stiffest tangent, {spec.shear_modulus / 1e3:.4g} kPa at stretch "
                 f"{spec.at_stretch:.3g})")
    return spec


def _tables(mat: Material, cfg: PrepareConfig, run: _Run) -> StiffnessTables:
    """Stiffness tables of the material (uncompensated)."""
    g = cfg.grid
    tables = run.stage("tables", build_tables, mat, n=g.n, law=g.law, lam_min=g.lam_min, lam_max=g.lam_max)
    run.rep.step(f"tables: {tables.n} points on stretch {tables.lam_min:.3g}..{tables.lam_max:.3g} "
                 f"({run.timings['tables']:.2f} s; {grid_note(tables)})")
    if tables.metadata["grid"].get("warning"):
        run.warn(tables.metadata["grid"]["warning"])
    return tables


def _compensated(tables: StiffnessTables, mat: Material, net: SpringNetwork, cfg: PrepareConfig,
                 run: _Run) -> StiffnessTables:
    """*tables* compensated for the network (with its volume term) unless disabled."""
    if not cfg.compensate:
        run.warn("no volumetric compensation: the raw network is several times softer than the tissue "
                 "(docs/design/tables.md); compensate the asset later with 'esmm tables'")
        return tables
    comp = run.stage("compensation", compensation.compensate, tables, net, material=mat, reporter=run.rep,
                     volume=net.volume_term)
    run.rep.step(f"compensation: volume factor c = {comp.tables.volume_factor:.3f} and a stretch "
                 f"correction; error of the virtual tests (uniaxial max; shear max) {comp.summary()} "
                 f"({run.timings['compensation']:.1f} s)")
    return comp.tables


def _fix(net: SpringNetwork, cfg: PrepareConfig, run: _Run) -> SpringNetwork:
    """The network with its fixed nodes (the config's region)."""
    fixed = select_fixed(net.points, cfg.fixed, node_kind=net.node_kind)
    run.rep.step(f"fixed: {fixed.size} nodes ({cfg.fixed.describe()})")
    return net.with_fixed(fixed)


def _structure(clean, cfg: PrepareConfig, run: _Run, *, force: bool, name: str) -> _Structure:
    """The config's structure (tetra or skeleton) of the cleaned surface, its network reported."""
    shape = _tetra(clean, cfg, run, force=force, name=name) if cfg.structure == "tetra" else \
        _skeleton(clean, cfg, run)
    net = shape.network
    run.rep.step(f"network: {net.summary()}, bandwidth {net.bandwidth()} ({run.timings['network']:.2f} s)")
    return shape


def _spring_model(net: SpringNetwork, mat: Material, cfg: PrepareConfig,
                  run: _Run) -> tuple[SpringNetwork, StiffnessTables]:
    """The network with its volume term and fixed nodes, and its (compensated) stiffness tables."""
    tables = _tables(mat, cfg, run)
    net = dataclasses.replace(net, volume_term=_volume(tables, net, cfg, run))
    tables = _compensated(tables, mat, net, cfg, run)
    net = _fix(net, cfg, run)
    return net, tables


def _write(out: Path, inp: Path, net: SpringNetwork, mat: Material, tables: StiffnessTables,
           structure: _Structure, cleaning: CleaningReport, cfg: PrepareConfig, run: _Run,
           argv: list[str] | None) -> None:
    """The asset and its sidecar, with the provenance of this run."""
    prov = collect_provenance(inp, config_toml=cfg.toml, argv=argv,
                              extra={"config_source": cfg.source, "timings_s": dict(run.timings),
                                     "mesher": structure.mesher, "warnings": run.warnings,
                                     "mesh_log": [str(x) for x in structure.log[-50:]]})
    run.stage("write", write_asset, out, net, material=mat, tables=tables, quality=structure.quality,
              cleaning=cleaning, provenance=prov, quality_floors=structure.floors,
              fixed_region=cfg.fixed.describe(), fit=fit_record(cfg.material, loaded=mat))
    run.rep.step(f"write: {out} ({run.timings['write']:.2f} s)")
    run.rep.step(f"report: {run.stage('report', write_asset_report, out)}")


def prepare(input_path: str | os.PathLike, *, output: str | os.PathLike | None = None,
            config: str | os.PathLike | dict | None = None, size: float | None = None,
            nodes: int | None = None, elements: int | None = None, structure: str | None = None,
            unit: str | None = None, label: int | None = None, keep_all: bool = False,
            body: int | None = None, material: str | None = None, density: float | None = None,
            force: bool = False, compensate: bool | None = None, volume: bool | None = None,
            split: bool | None = None, reporter=None, argv: list[str] | None = None) -> PrepareResult:
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
        Length unit of the input file (mm, cm, m); default mm, or a NIfTI
        header's own unit (a unit given wins over the header).
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
    compensate : bool, optional
        Calibrate the volumetric compensation (default: the config's, true).
    volume : bool, optional
        Give the network its volume term (default: the config's, true; the tet
        structure only).
    split : bool, optional
        Split every tet of the mesh in eight (default: the config's, false; the
        tet structure only): the network on the nodes of the quadratic tets.
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
    inp, out = asset_paths(input_path, output)
    cfg = prepare_config(config, size=size, nodes=nodes, elements=elements, structure=structure, unit=unit,
                         label=label, keep_all=keep_all, body=body, material=material, density=density,
                         compensate=compensate, volume=volume, split=split)
    run = _Run(reporter)
    mat = _material(cfg, run)
    clean, cleaning = _surface(inp, cfg, run)
    shape = _structure(clean, cfg, run, force=force, name=inp.name)
    net, tables = _spring_model(shape.network, mat, cfg, run)
    _write(out, inp, net, mat, tables, shape, cleaning, cfg, run, argv)
    return PrepareResult(asset=out, xdmf=sidecar_path(out), network=net, quality=shape.quality,
                         quality_passed=shape.passed, cleaning=cleaning, tables=tables, material=mat,
                         timings=run.timings, mesher=shape.mesher, config=cfg, warnings=run.warnings,
                         report=report_path(out))
