"""fastmac_exp/ imports bottom-up: the package's rooms (its subpackages and top-level modules) form an
acyclic graph, in the order docs/development.md's layout table lists them, bottom first. An import inside
a function counts as much as one at the top: a lazy import is a dependency too."""

from __future__ import annotations

import ast
import re
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "fastmac_exp"


def room_of(module: str) -> str:
    """fastmac_exp.run.experiment -> run; fastmac_exp.io -> io."""
    return module.split(".")[1]


def imported_modules(path: Path) -> set[str]:
    """Every fastmac_exp module `path` imports anywhere in its body; `from fastmac_exp import x` gives
    fastmac_exp.x (a room, or a name of the root package such as __version__)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "fastmac_exp":
                out |= {f"fastmac_exp.{a.name}" for a in node.names}
            elif node.module.startswith("fastmac_exp."):
                out.add(node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("fastmac_exp.")}
    return out


def room_graph() -> dict[str, set[str]]:
    """room -> the rooms it imports (the root package's __init__ and __main__ left out: they are the top)."""
    graph: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] in ("__init__.py", "__main__.py"):
            continue
        room = rel.parts[0].removesuffix(".py")
        deps = {room_of(m) for m in imported_modules(path)} - {room}
        graph.setdefault(room, set()).update(deps)
    return graph


def documented_order() -> list[str]:
    """The rooms in the order of docs/development.md's layout table (rows `| `room` | ...`), bottom first."""
    text = (REPO / "docs" / "development.md").read_text()
    section = text.split("## The package's layout", 1)[1]
    return re.findall(r"^\| `([A-Za-z0-9_]+)/?` \|", section, flags=re.M)


def test_room_graph_sees_known_edges():
    graph = room_graph()
    assert "pipeline" in graph["run"] and "geometry" in graph["pipeline"] and "run" in graph["report"]
    assert "core" in graph["geometry"]  # a function-level import (resolution's core call) counts


def test_only_version_is_imported_from_the_root_package():
    graph = room_graph()
    roots = {room: deps & {"__version__", "api", "register"} for room, deps in graph.items()}
    assert all(deps <= {"__version__"} for deps in roots.values()), roots


def test_rooms_import_without_a_cycle():
    graph = {room: deps - {"__version__"} for room, deps in room_graph().items()}
    try:
        order = list(TopologicalSorter(graph).static_order())
    except CycleError as exc:
        cycle = " -> ".join(exc.args[1])
        raise AssertionError(f"import cycle between fastmac_exp's rooms: {cycle}") from None
    assert set(order) >= set(graph)


def test_rooms_import_only_rooms_listed_below_them_in_the_docs():
    graph = {room: deps - {"__version__", "_mac_core"} for room, deps in room_graph().items()}
    order = documented_order()
    missing = sorted(set(graph) - {"_mac_core"} - set(order))
    assert not missing, f"rooms missing from docs/development.md's layout table: {missing}"
    rank = {room: i for i, room in enumerate(order)}
    upward = [f"{room} -> {dep}" for room, deps in graph.items() for dep in deps if rank[dep] > rank[room]]
    assert not upward, f"imports of a room listed above the importer in docs/development.md: {upward}"
