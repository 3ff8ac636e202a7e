"""No import cycles among brasidas, platformd and stationd modules.

Every import counts, wherever it is written: at the top, inside a function, or under
``TYPE_CHECKING`` (which only hides a cycle from the interpreter, not from the design).
Importing ``a.b.c`` also runs the packages ``a`` and ``a.b``.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("brasidas", "platformd", "stationd")


def module_files() -> dict[str, Path]:
    modules: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def imports_of(name: str, source: str, is_package: bool, modules: Iterable[str]) -> set[str]:
    """The project modules that importing ``name`` runs first (its direct imports).

    Importing ``a.b.c`` runs ``a`` and ``a.b`` too, except those ``name`` is inside (they are
    already running: a package's ``__init__`` importing its submodules is no cycle)."""
    modules = set(modules)
    package = name if is_package else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                origin = ".".join([*base, node.module] if node.module else base)
            else:
                origin = node.module or ""
            submodules = {f"{origin}.{alias.name}" for alias in node.names} & modules
            targets.update(submodules)
            if len(submodules) < len(node.names):  # a name defined in ``origin`` itself
                targets.add(origin)
    inside = {".".join(name.split(".")[:end]) for end in range(1, name.count(".") + 2)}
    found: set[str] = set()
    for target in targets:
        parts = target.split(".")
        if target in modules and target != name:
            found.add(target)
        for end in range(1, len(parts)):
            parent = ".".join(parts[:end])
            if parent in modules and parent not in inside:
                found.add(parent)
    return found


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for neighbour in sorted(graph[node]):
            if neighbour not in index:
                visit(neighbour)
                low[node] = min(low[node], low[neighbour])
            elif neighbour in on_stack:
                low[node] = min(low[node], index[neighbour])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """Every module's imports (parsed once per process: each parse of the tree took ~2 s of
    CPU, and three tests read it; none changes it)."""
    modules = module_files()
    return {
        name: imports_of(name, path.read_text(), path.name == "__init__.py", modules)
        for name, path in modules.items()
    }


def test_the_checker_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycles(graph) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_every_kind_of_import() -> None:
    graph = import_graph()
    assert "brasidas.bus" in graph["brasidas.topics"]  # from brasidas.bus import Topic
    assert "brasidas.codecs.commands" in graph["brasidas.messages"]
    assert "brasidas" in graph["platformd.sessions"]  # from brasidas import __version__
    assert "brasidas.security" in graph["platformd.sessions"]  # from brasidas import security
    assert "brasidas.codecs" in graph["platformd.signaling"]  # runs the package first
    # A package's __init__ importing its modules is no cycle; a module importing from the
    # package that imports it is one.
    assert "platformd.telemetry" not in graph["platformd.telemetry.aggregator"]
    assert imports_of("p.a", "from p import b", False, ["p", "p.a", "p.b"]) == {"p.b"}
    assert imports_of("p.a", "from p import helper", False, ["p", "p.a"]) == {"p"}
    assert imports_of("q", "import p.b", False, ["p", "p.b", "q"]) == {"p", "p.b"}
    assert "platformd.context" in graph["platformd.signaling"]


def test_no_import_cycles() -> None:
    cycles = find_cycles(import_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


LAYERS = {
    "brasidas": ("platformd", "stationd"),
    "platformd": ("stationd",),
    "stationd": ("platformd",),
}
"""Who may not import whom: the shared library neither daemon; each daemon not the other (a
platform runs without the station's code, and the reverse)."""


def test_the_layers_hold() -> None:
    graph = import_graph()
    crossings = [
        f"{module} imports {target}"
        for module, targets in sorted(graph.items())
        for target in sorted(targets)
        if target.split(".")[0] in LAYERS[module.split(".")[0]]
    ]
    assert not crossings, "; ".join(crossings)
    # The check sees a crossing written anywhere (a function's body too).
    assert "stationd.telemetry" in imports_of(
        "platformd.x",
        "def f():\n    from stationd.telemetry import annunciator\n",
        False,
        ["platformd.x", "stationd", "stationd.telemetry", "stationd.telemetry.annunciator"],
    )
