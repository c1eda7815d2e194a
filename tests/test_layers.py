"""The package's imports only point down the layers (no SUMO needed).

    cli -> training, evaluation -> agents, baselines -> env -> physics, distributed -> sim

A module may import its own package, any lower layer, and the shared leaves (the package root for
``__version__``, ``errors``, ``config``, ``io_utils``, ``resources``), which import only each other.
Two packages on one layer (training and evaluation; agents and baselines) must not import each other.
Every import counts, also the lazy ones inside functions and those under ``TYPE_CHECKING``: a lazy
import that points up is a cycle that only shows when that function runs. Inside a layer, no two modules
import each other, directly or round a longer circle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = "idas_sumo"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE

LAYER: dict[str, int] = {
    "sim": 0,
    "physics": 1,
    "distributed": 1,
    "env": 2,
    "agents": 3,
    "baselines": 3,
    "training": 4,
    "evaluation": 4,
    "cosim": 4,
    "cli": 5,
}
SHARED_LEAVES = frozenset({"", "errors", "config", "io_utils", "resources", "stops"})
"""'' is the package root (``from idas_sumo import __version__``)."""
SUMO_MODULES = frozenset({"libsumo", "sumolib", "traci", "sumo"})
"""Only the sim layer talks to SUMO."""


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, at any depth of the tree."""
    package = module if is_package else module.rpartition(".")[0]
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            target = _from_target(node, package)
            found.append((node.lineno, target))
            if target == PACKAGE:  # ``from idas_sumo import errors`` imports a submodule
                found.extend((node.lineno, f"{target}.{a.name}") for a in node.names if _is_submodule(a.name))
    return found


def _from_target(node: ast.ImportFrom, package: str) -> str:
    """The absolute module ``from TARGET import ...`` names (relative ones resolved against ``package``)."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _is_submodule(name: str) -> bool:
    return (PACKAGE_DIR / name / "__init__.py").exists() or (PACKAGE_DIR / f"{name}.py").exists()


def part_of(module: str) -> str | None:
    """The layer part ('env', 'errors', '' for the root, ...) of a module of this package; None outside."""
    if module != PACKAGE and not module.startswith(PACKAGE + "."):
        return None
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def violation(importer: str, imported: str) -> str | None:
    """Why ``importer`` must not import ``imported`` (both absolute module names), or None if it may."""
    top = imported.split(".")[0]
    src = part_of(importer)
    assert src is not None, importer
    if top in SUMO_MODULES:
        return None if src == "sim" else f"only {PACKAGE}.sim may import {top}"
    dst = part_of(imported)
    if dst is None or dst == src:
        return None
    if dst in SHARED_LEAVES:
        return None
    if src in SHARED_LEAVES:
        return f"the shared leaf {importer} may import only other shared leaves"
    if src not in LAYER or dst not in LAYER:
        return f"{src or dst!r} has no layer: add it to LAYER in tests/test_layers.py"
    if LAYER[dst] > LAYER[src]:
        return "points up"
    if LAYER[dst] == LAYER[src]:
        return "points sideways"
    return None


def layer_violations(root: Path = PACKAGE_DIR) -> tuple[list[str], int, int]:
    """(violations, modules walked, package-internal imports seen)."""
    problems: list[str] = []
    modules = internal = 0
    for path in sorted(root.rglob("*.py")):
        modules += 1
        module = module_name(path)
        for line, imported in imported_modules(path.read_text(), module, path.name == "__init__.py"):
            internal += part_of(imported) is not None
            why = violation(module, imported)
            if why:
                problems.append(f"{path.relative_to(root.parent)}:{line}: {module} imports {imported}: {why}")
    return problems, modules, internal


def test_imports_point_down_the_layers() -> None:
    problems, modules, internal = layer_violations()
    # Guard against walking nothing: the package has dozens of modules and well over 100 internal imports.
    assert modules > 30 and internal > 100, (modules, internal)
    assert not problems, "\n".join(problems)


def test_every_part_of_the_package_has_a_layer() -> None:
    parts = {p.name for p in PACKAGE_DIR.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    parts |= {p.stem for p in PACKAGE_DIR.glob("*.py") if p.name != "__init__.py"}
    assert parts - set(LAYER) - SHARED_LEAVES == set()


@pytest.mark.parametrize(
    ("importer", "imported", "expected"),
    [
        ("idas_sumo.sim.backend", "idas_sumo.env.scenario", "points up"),
        ("idas_sumo.env.engine", "idas_sumo.baselines.idm", "points up"),
        ("idas_sumo.env.engine", "idas_sumo.agents.critic_input", "points up"),
        ("idas_sumo.training.imitation", "idas_sumo.evaluation.policies", "points sideways"),
        ("idas_sumo.evaluation.policies", "idas_sumo.training.checkpoint", "points sideways"),
        ("idas_sumo.agents.rollout", "idas_sumo.baselines.policies", "points sideways"),
        ("idas_sumo.errors", "idas_sumo.env.engine", "the shared leaf idas_sumo.errors may import only"),
        ("idas_sumo.env.engine", "libsumo", "only idas_sumo.sim may import libsumo"),
        ("idas_sumo.env.engine", "idas_sumo.sim.backend", None),
        ("idas_sumo.env.actions", "idas_sumo.physics.idm", None),
        ("idas_sumo.cli", "idas_sumo.training.cli", None),
        ("idas_sumo.training.checkpoint", "idas_sumo", None),
        ("idas_sumo.sim.backend", "libsumo", None),
        ("idas_sumo.env.engine", "numpy", None),
    ],
)
def test_the_rule_itself(importer: str, imported: str, expected: str | None) -> None:
    why = violation(importer, imported)
    assert why == expected if expected is None else why is not None and why.startswith(expected)


def test_lazy_and_relative_imports_are_seen() -> None:
    source = (
        "from . import actions\n"
        "from ..baselines import idm\n"
        "def f():\n"
        "    from idas_sumo.training.checkpoint import load_actor\n"
        "    import libsumo\n"
    )
    found = {m for _, m in imported_modules(source, "idas_sumo.env.engine", is_package=False)}
    assert found == {"idas_sumo.env", "idas_sumo.baselines", "idas_sumo.training.checkpoint", "libsumo"}


# --- no import circle between modules -----------------------------------------------------------------


def import_graph(root: Path = PACKAGE_DIR) -> dict[str, set[str]]:
    """Each module of the package -> the package's modules it imports, with every import counted as
    ``imported_modules`` reads them; ``from package import name`` counts the submodule ``name`` too."""
    paths = {module_name(p): p for p in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        is_package = path.name == "__init__.py"
        package = module if is_package else module.rpartition(".")[0]
        targets = {imported for _, imported in imported_modules(path.read_text(), module, is_package)}
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = _from_target(node, package)
                targets.update(f"{base}.{alias.name}" for alias in node.names)
        graph[module] = {t for t in targets if t in paths and t != module}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` as the modules round it, the first one again at the end; None if
    there is none (a depth-first search: an edge back to a module on the current path closes a circle)."""
    done: set[str] = set()
    path: list[str] = []

    def visit(module: str) -> list[str] | None:
        if module in path:
            return [*path[path.index(module) :], module]
        if module in done:
            return None
        path.append(module)
        for imported in sorted(graph.get(module, ())):
            cycle = visit(imported)
            if cycle:
                return cycle
        path.pop()
        done.add(module)
        return None

    for module in sorted(graph):
        cycle = visit(module)
        if cycle:
            return cycle
    return None


def test_no_import_circle_between_modules() -> None:
    graph = import_graph()
    assert len(graph) > 30 and sum(map(len, graph.values())) > 100, graph
    assert "idas_sumo.sim.backend" in graph["idas_sumo.sim.batch"]  # ``from idas_sumo.sim import backend``
    cycle = find_cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_the_circle_finder_itself() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"x": {"a"}, "a": {"b"}, "b": {"a"}}) == ["a", "b", "a"]
    assert find_cycle({"a": {"a"}}) == ["a", "a"]
