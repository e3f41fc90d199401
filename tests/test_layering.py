"""The import structure of esmm, enforced: a house a newcomer can read bottom-up.

The library is two stacks on a common ground, with the stages that combine
them, the batch runner and the command line on top::

    cli
    batch, api (the public Python API)
    prepare, retable (the stages), fidelity (the validation)
    discover            simulate        compensation
    calibrate           asset
    materials   <-      network
    tensile             mesh
    ground: errors, progress, atomicio, blas, interrupts, cache, units, config, checks, linalg,
            htmlreport

Checked from the source text (no import is run):

* every package of ``pipeline/`` has a place in :data:`ALLOWED`, and imports only
  the packages listed there for it (its own modules and the ground are always allowed);
* no circle of imports between modules, anywhere;
* no private name (``_x``) imported from another package;
* inside ``pipeline/``, esmm's own modules are imported at the top of a module, so
  the graph is what the top of each file says (third-party imports may be local, to
  keep start-up fast).
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
TOPS = {"cli": "esmm.cli", "pipeline": "esmm.pipeline"}

#: The ground: small modules every package may use. Among themselves they import downwards only.
GROUND = {"pipeline": set(), "errors": set(), "progress": set(), "atomicio": set(), "blas": set(), "interrupts": set(),
          "cache": set(),
          "units": {"errors"}, "config": {"errors"}, "checks": {"errors", "units"},
          # the sparse linear algebra: a ground package (supernodal LDLT, Newton helpers, solves, L-BFGS)
          "linalg": {"errors", "blas"},
          # the self-contained HTML report writer every stage's report uses
          "htmlreport": {"atomicio"}}

#: package -> the packages (above the ground) it may import.
ALLOWED: dict[str, set[str]] = {
    "tensile": set(),
    "materials": set(),
    "calibrate": {"tensile", "materials"},
    "discover": {"tensile", "materials", "calibrate"},
    "mesh": set(),
    "network": {"mesh", "materials"},
    "asset": {"mesh", "network", "materials"},
    "simulate": {"mesh", "network", "asset", "materials"},
    "compensation": {"mesh", "network", "materials"},
    "prepare": {"mesh", "network", "compensation", "asset", "materials"},
    "retable": {"network", "compensation", "asset", "materials"},
    "fidelity": {"mesh", "network", "compensation", "asset", "simulate", "materials"},
    "batch": {"tensile", "materials", "calibrate", "discover", "mesh", "network", "compensation", "asset",
              "simulate", "prepare"},
    # the public Python API (what `import esmm` gives): thin over the stages
    "api": {"tensile", "materials", "calibrate", "mesh", "network", "compensation", "asset", "simulate",
            "prepare"},
    "cli": None,  # on top: anything of the library
}


def _modules() -> dict[str, Path]:
    out = {}
    for top, name in TOPS.items():
        for p in (REPO / top).rglob("*.py"):
            rel = list(p.relative_to(REPO / top).with_suffix("").parts)
            if rel[-1] == "__init__":
                rel = rel[:-1]
            out[".".join([name, *rel])] = p
    return out


MODULES = _modules()


def package(module: str) -> str:
    """``esmm.pipeline.mesh.volume`` -> ``mesh``; ``esmm.pipeline.units`` -> ``units``; cli -> ``cli``."""
    parts = module.split(".")
    if parts[1] == "cli":
        return "cli"
    return parts[2] if len(parts) > 2 else "pipeline"


def _target(module: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _resolve(name: str) -> str | None:
    """The esmm module an import names (a name imported from a package may be a module)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports() -> list[tuple[str, str, str, bool]]:
    """(importer, imported module, imported name or '', at module top) for every esmm import."""
    out = []
    for mod, path in MODULES.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top_level = {id(n) for n in tree.body}
        top_level |= {id(n) for stmt in tree.body if isinstance(stmt, ast.If | ast.Try)
                      for n in ast.walk(stmt)}
        for node in ast.walk(tree):
            at_top = id(node) in top_level
            if isinstance(node, ast.ImportFrom):
                tgt = _target(mod, path, node)
                if not tgt.startswith("esmm."):
                    continue
                for alias in node.names:
                    sub = _resolve(f"{tgt}.{alias.name}")
                    if sub is not None and sub != _resolve(tgt) and sub in MODULES:
                        out.append((mod, sub, "", at_top))
                    else:
                        out.append((mod, _resolve(tgt) or tgt, alias.name, at_top))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("esmm."):
                        out.append((mod, _resolve(alias.name) or alias.name, "", at_top))
    return out


IMPORTS = imports()


def test_every_package_has_a_place():
    pkgs = {package(m) for m in MODULES}
    missing = sorted(p for p in pkgs if p not in ALLOWED and p not in GROUND)
    assert not missing, f"packages without a place in the layering (add them to ALLOWED): {missing}"


def test_imports_run_downwards_only():
    bad = set()
    for a, b, _name, _top in IMPORTS:
        pa, pb = package(a), package(b)
        if pa == pb or pa == "cli":
            continue
        if pa in GROUND:
            ok = pb in GROUND[pa]
        else:
            ok = pb in GROUND or pb in ALLOWED.get(pa, set())
        if not ok:
            bad.add(f"{a} imports {b} ({pa} -> {pb})")
    assert not bad, "imports against the layering:\n" + "\n".join(sorted(bad))


def test_no_circle_of_imports():
    graph = defaultdict(set)
    for a, b, _name, _top in IMPORTS:
        if a != b and b in MODULES:
            graph[a].add(b)
    # Tarjan's strongly connected components.
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in list(MODULES):
        if v not in index:
            visit(v)
    assert not comps, "import circles:\n" + "\n".join(" <-> ".join(c) for c in comps)


def test_no_private_name_crosses_a_package():
    bad = sorted({f"{a} imports {name} from {b}" for a, b, name, _top in IMPORTS
                  if name.startswith("_") and not name.startswith("__") and package(a) != package(b)})
    assert not bad, "private names used across packages:\n" + "\n".join(bad)


def test_library_imports_its_own_modules_at_the_top():
    bad = sorted({f"{a} imports {b} inside a function" for a, b, _name, top in IMPORTS
                  if not top and package(a) != "cli"})
    assert not bad, "esmm imports hidden in functions (move them to the top):\n" + "\n".join(bad)


@pytest.mark.parametrize("module", ["esmm.pipeline.asset.read", "esmm.pipeline.calibrate.fit"])
def test_the_checker_sees_imports(module):
    """The checks above would pass on nothing: make sure they read real imports."""
    assert any(a == module for a, *_ in IMPORTS)
