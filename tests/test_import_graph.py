"""The package's import graph is layered (docs/design.md §2, "Layers"): no import cycle between
modules, and no module imports from a layer above its own.

The graph is read from the source with `ast`, without importing the package: every `import` and
`from ... import` statement counts, at module level or inside a function, relative ones resolved.
Imports under `if TYPE_CHECKING:` count too: they never run, but a module that names a higher layer's
type in its annotations depends on that layer all the same (and a loop through them is a loop).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "cefc_mj"

LAYERS = (
    # (name, the package's top-level modules and subpackages in it), bottom first; "__init__" is
    # cefc_mj/__init__.py itself (make_env and the public re-exports, such as make_world).
    ("foundation", ("errors", "version", "paths", "fileio", "seeds", "jit", "provenance", "executors")),
    ("core", ("task", "control", "sim")),
    ("networks", ("nn",)),
    ("environments", ("env", "hierarchy", "rule_teams", "table3_protocol", "game_protocol")),
    ("baselines", ("baselines",)),
    ("evaluation", ("eval",)),
    ("applications", ("train", "viz")),
    ("deployment", ("deploy",)),
    ("front ends", ("__init__", "pettingzoo_env", "suite", "cli")),
)
"""A module may import from its own layer and the layers below, never from one above."""


@dataclass(frozen=True)
class Edge:
    """One import statement: module `source` imports module `target` at `where` (file:line)."""

    source: str
    target: str
    where: str


# ---------------------------------------------------------------------------------- the checker
def layer_of(module: str, layers=LAYERS) -> int | None:
    """Index into `layers` of a module by its top-level name under the package (None: in no layer)."""
    parts = module.split(".")
    key = parts[1] if len(parts) > 1 else "__init__"
    return next((i for i, (_, names) in enumerate(layers) if key in names), None)


def package_modules(package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> source file of every module of the package (a package by its __init__)."""
    modules = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = path.relative_to(package_dir.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _known(name: str, modules) -> str:
    """The longest prefix of a dotted name that is a module of the package."""
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def imports_in(source: str, module: str, is_package: bool, modules) -> list[tuple[str, int]]:
    """(imported module of the package, line) for every import statement in `source`, the module
    `module`, once per statement and module, those under `if TYPE_CHECKING:` included; imports of
    other packages are left out."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend(
                (_known(alias.name, modules), node.lineno)
                for alias in node.names
                if alias.name.split(".")[0] == PACKAGE
            )
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".") if is_package else module.split(".")[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join(package + ([node.module] if node.module else []))
            if base.split(".")[0] == PACKAGE:
                for alias in node.names:
                    submodule = f"{base}.{alias.name}"
                    found.append((submodule if submodule in modules else _known(base, modules), node.lineno))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(source))
    return list(dict.fromkeys(found))  # `from x import a, b`: one edge


def import_graph(package_dir: Path = ROOT / PACKAGE) -> tuple[dict[str, Path], list[Edge]]:
    """The package's modules and every import edge between two of them (self-imports left out)."""
    modules = package_modules(package_dir)
    edges = []
    for module, path in modules.items():
        where = path.relative_to(package_dir.parent).as_posix()
        for target, line in imports_in(path.read_text(), module, path.name == "__init__.py", modules):
            if target != module:
                edges.append(Edge(module, target, f"{where}:{line}"))
    return modules, edges


def find_cycles(edges: list[Edge]) -> list[list[Edge]]:
    """One cycle (as its edges) per strongly connected group of two or more modules."""
    graph: dict[str, dict[str, Edge]] = {}
    for edge in edges:
        graph.setdefault(edge.source, {}).setdefault(edge.target, edge)
        graph.setdefault(edge.target, {})
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def connect(node: str) -> None:  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph[node]:
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = set()
            while True:
                member = stack.pop()
                group.add(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(group)

    for node in sorted(graph):
        if node not in index:
            connect(node)
    cycles = []
    for group in groups:
        start = min(group)
        came_by: dict[str, Edge] = {}
        queue = [start]
        for node in queue:  # breadth first: the shortest way round from the group's first module
            if start in graph[node]:
                cycle = [graph[node][start]]
                while node != start:
                    cycle.insert(0, came_by[node])
                    node = came_by[node].source
                cycles.append(cycle)
                break
            for nxt in sorted(graph[node]):
                if nxt in group and nxt != start and nxt not in came_by:
                    came_by[nxt] = graph[node][nxt]
                    queue.append(nxt)
    return cycles


def upward_imports(edges: list[Edge], layer=layer_of) -> list[Edge]:
    """The edges that import from a higher layer than the importing module's."""
    return [
        e
        for e in edges
        if layer(e.source) is not None and layer(e.target) is not None and layer(e.target) > layer(e.source)
    ]


def describe_cycle(cycle: list[Edge]) -> str:
    """'a -> b -> a  (where a imports b, where b imports a)'."""
    modules = " -> ".join([cycle[0].source] + [e.target for e in cycle])
    return f"{modules}  ({', '.join(e.where for e in cycle)})"


def describe_upward(edge: Edge, layer=layer_of, layers=LAYERS) -> str:
    """'file:line: module (its layer) imports module (its layer)'."""
    return (
        f"{edge.where}: {edge.source} ({layers[layer(edge.source)][0]}) imports {edge.target} "
        f"({layers[layer(edge.target)][0]})"
    )


# ---------------------------------------------------------------------------------- the package
MODULES, EDGES = import_graph()


def test_every_module_has_a_layer():
    missing = sorted(m for m in MODULES if layer_of(m) is None)
    assert not missing, f"modules in no layer of LAYERS (place them in tests/test_import_graph.py): {missing}"


def test_no_import_cycle():
    cycles = find_cycles(EDGES)
    assert not cycles, "import cycles:\n" + "\n".join(describe_cycle(c) for c in cycles)


def test_no_upward_import():
    upward = upward_imports(EDGES)
    assert not upward, "imports from a higher layer:\n" + "\n".join(describe_upward(e) for e in upward)


def test_the_graph_is_read():
    """The parser sees the package's imports: a few edges that exist today, of each kind."""
    seen = {(e.source, e.target) for e in EDGES}
    assert ("cefc_mj.eval.runner", "cefc_mj.sim.backends") in seen  # module level
    assert ("cefc_mj.cli.eval_common", "cefc_mj.deploy.episode") in seen  # inside a function
    assert ("cefc_mj.provenance", "cefc_mj.paths") in seen  # `from cefc_mj import paths`: the submodule
    assert len(MODULES) > 50 and len(EDGES) > 300


HIGHLEVEL_TRAINING = (
    "cefc_mj.train.highlevel_config",
    "cefc_mj.train.consmac_replay",
    "cefc_mj.train.highlevel_trainer",
    "cefc_mj.train.highlevel_export",
    "cefc_mj.train.highlevel",
)
"""The high level's training, split by job, bottom first: config, replay, learner, export, the run."""


def test_the_high_level_training_modules_import_only_downward():
    rank = {module: i for i, module in enumerate(HIGHLEVEL_TRAINING)}
    assert set(HIGHLEVEL_TRAINING) <= set(MODULES)
    upward = [e for e in EDGES if e.source in rank and e.target in rank and rank[e.target] >= rank[e.source]]
    assert not upward, "\n".join(f"{e.where}: {e.source} imports {e.target}" for e in upward)
    assert all(len(MODULES[m].read_text().splitlines()) <= 600 for m in HIGHLEVEL_TRAINING)


# ---------------------------------------------------------------------------------- the checker itself
def test_checker_reports_a_cycle_and_an_upward_import():
    layers = (("low", ("low",)), ("high", ("high",)))
    edges = [
        Edge("cefc_mj.low.a", "cefc_mj.low.b", "a.py:1"),
        Edge("cefc_mj.low.b", "cefc_mj.low.c", "b.py:2"),
        Edge("cefc_mj.low.c", "cefc_mj.low.a", "c.py:3"),
        Edge("cefc_mj.low.a", "cefc_mj.high.x", "a.py:4"),
        Edge("cefc_mj.high.x", "cefc_mj.low.d", "x.py:5"),
    ]
    cycles = find_cycles(edges)
    assert [describe_cycle(c) for c in cycles] == [
        "cefc_mj.low.a -> cefc_mj.low.b -> cefc_mj.low.c -> cefc_mj.low.a  (a.py:1, b.py:2, c.py:3)"
    ]

    def layer(module):
        return layer_of(module, layers)

    upward = upward_imports(edges, layer)
    assert upward == [Edge("cefc_mj.low.a", "cefc_mj.high.x", "a.py:4")]
    assert describe_upward(upward[0], layer, layers) == "a.py:4: cefc_mj.low.a (low) imports cefc_mj.high.x (high)"
    assert not find_cycles(edges[:2] + edges[3:]) and not upward_imports(edges[:3] + edges[4:], layer)


def test_a_loop_through_annotations_is_a_loop():
    """The last loop the package had: a front end imports a recorder, which named the front end's env
    class under TYPE_CHECKING. Read from source as it was, it is a cycle and an upward import."""
    modules = {"cefc_mj", "cefc_mj.pettingzoo_env", "cefc_mj.viz", "cefc_mj.viz.recorder"}
    sources = {
        "cefc_mj.pettingzoo_env": "from cefc_mj.viz.recorder import RerunRecorder\n",
        "cefc_mj.viz.recorder": (
            "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n"
            "    from cefc_mj.pettingzoo_env import CEFCParallelEnv\n"
        ),
    }
    edges = [
        Edge(module, target, f"{module}:{line}")
        for module, source in sources.items()
        for target, line in imports_in(source, module, False, modules)
    ]
    assert [describe_cycle(c) for c in find_cycles(edges)] == [
        "cefc_mj.pettingzoo_env -> cefc_mj.viz.recorder -> cefc_mj.pettingzoo_env  "
        "(cefc_mj.pettingzoo_env:1, cefc_mj.viz.recorder:3)"
    ]
    assert upward_imports(edges) == [Edge("cefc_mj.viz.recorder", "cefc_mj.pettingzoo_env", "cefc_mj.viz.recorder:3")]


def test_parser_reads_every_kind_of_import():
    modules = {"cefc_mj", "cefc_mj.a", "cefc_mj.a.b", "cefc_mj.a.c", "cefc_mj.d"}
    source = """
from typing import TYPE_CHECKING
import numpy
import cefc_mj.d
from . import c
from .. import d as dee
from cefc_mj.a import SOMETHING, OTHER
if TYPE_CHECKING:
    from cefc_mj import a
else:
    from cefc_mj.a.c import thing

def later():
    from cefc_mj import make_env
"""
    assert imports_in(source, "cefc_mj.a.b", False, modules) == [
        ("cefc_mj.d", 4),
        ("cefc_mj.a.c", 5),
        ("cefc_mj.d", 6),
        ("cefc_mj.a", 7),
        ("cefc_mj.a", 9),  # under TYPE_CHECKING: counted
        ("cefc_mj.a.c", 11),
        ("cefc_mj", 14),
    ]
    assert imports_in("from . import b\nfrom .c import x", "cefc_mj.a", True, modules) == [
        ("cefc_mj.a.b", 1),
        ("cefc_mj.a.c", 2),
    ]
