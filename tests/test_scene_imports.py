"""The scene package's modules import each other without a circle (issue 25).

Every import counts, also one inside a function or under ``if TYPE_CHECKING``: an import moved into a
function only hides a circle from the interpreter, and the modules still depend on each other.
"""

import ast
from pathlib import Path

PACKAGE = "polydem.scene"
ROOT = Path(__file__).resolve().parent.parent / "src" / "polydem" / "scene"


def _imported(node: ast.AST, modules: set[str]) -> set[str]:
    """The modules of the scene package an import statement names (``__init__`` for the package itself)."""
    if isinstance(node, ast.Import):
        names, pairs = [a.name for a in node.names], []
    elif isinstance(node, ast.ImportFrom):
        module = node.module or ""
        if node.level:  # relative to the package the scene modules live in
            base = PACKAGE.rsplit(".", node.level - 1)[0]
            module = f"{base}.{module}" if module else base
        names, pairs = [module], [(module, a.name) for a in node.names]
    else:
        return set()
    found = {name.split(".")[2] for name in names if name.startswith(PACKAGE + ".")}
    found |= {name if name in modules else "__init__" for module, name in pairs if module == PACKAGE}
    if PACKAGE in names and isinstance(node, ast.Import):
        found.add("__init__")
    return {m if m in modules else "__init__" for m in found}


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module name -> the modules of the package it imports, anywhere in its source."""
    modules = {p.stem for p in root.glob("*.py")}
    graph = {}
    for name in sorted(modules):
        tree = ast.parse((root / f"{name}.py").read_text())
        graph[name] = set().union(*(_imported(n, modules) for n in ast.walk(tree))) - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle through each module that lies on one (depth-first search), each as a path a -> ... -> a."""
    found, state = [], {}

    def visit(node, path):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append([*path[path.index(nxt) :], nxt])
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return found


def test_the_scene_package_has_no_import_circle():
    graph = import_graph()
    # The package's __init__ imports its modules; none of them may import the package back.
    assert not [m for m, deps in graph.items() if "__init__" in deps and m != "__init__"]
    assert cycles(graph) == []


def test_the_circle_finder_sees_imports_inside_functions(tmp_path):
    (tmp_path / "a.py").write_text("from polydem.scene.b import f\n")
    (tmp_path / "b.py").write_text("def f():\n    from polydem.scene import a\n")
    (tmp_path / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n")
    graph = import_graph(tmp_path)
    assert graph == {"a": {"b"}, "b": {"a"}, "c": {"a"}}
    assert cycles(graph) == [["a", "b", "a"]]
