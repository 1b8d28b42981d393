"""studies/ imports top-down: no module of studies/ imports, at module level or inside a function, a
module that imports it back (make_results renders the study modules; they share studies.common, never
make_results)."""

from __future__ import annotations

import ast
from pathlib import Path

STUDIES = Path(__file__).resolve().parents[1] / "studies"


def _imports(path: Path, names: set[str]) -> set[str]:
    """The studies modules that `path` imports anywhere in its body (function-level imports included)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            mod = node.module
            if mod == "studies":
                out |= {a.name for a in node.names if a.name in names}
            elif mod.startswith("studies."):
                out.add(mod.split(".")[1])
        elif isinstance(node, ast.Import):
            out |= {a.name.split(".")[1] for a in node.names if a.name.startswith("studies.")}
    return out & names


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of `graph` as a path [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [node, nxt] if nxt in path else [node, nxt]
            if nxt not in state and (found := visit(nxt, path + [node])):
                return found
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start, [])):
            return found
    return None


def test_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) is not None
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_studies_import_graph_has_no_cycle():
    names = {p.stem for p in STUDIES.glob("*.py")}
    graph = {n: _imports(STUDIES / f"{n}.py", names) - {n} for n in names}
    assert "make_results" in graph and "descriptor_robustness" in graph["make_results"]
    assert _cycle(graph) is None, f"import cycle in studies/: {' -> '.join(_cycle(graph))}"


def test_replace_section_replaces_in_place_or_adds_before_notes(tmp_path):
    from studies.common import replace_section

    page = tmp_path / "results.md"
    page.write_text("# R\n\n## 1. A\n\nold\n\n## 2. B\n\nkeep\n\n## Notes\n\nn\n")
    replace_section(page, "## 1. A", "## 1. A\n\nnew\n\n")
    assert page.read_text() == "# R\n\n## 1. A\n\nnew\n\n## 2. B\n\nkeep\n\n## Notes\n\nn\n"
    replace_section(page, "## 3. C", "## 3. C\n\nc\n")
    assert page.read_text() == "# R\n\n## 1. A\n\nnew\n\n## 2. B\n\nkeep\n\n## 3. C\n\nc\n\n## Notes\n\nn\n"
