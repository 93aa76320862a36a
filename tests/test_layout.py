"""The layout rules of CONTRIBUTING.md that a machine can check."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SOURCES = sorted([*ROOT.joinpath("src", "polydem").rglob("*.py"), *ROOT.joinpath("kernels").glob("*.py")])


# The standard library's documented names that start with an underscore (os._exit ends a process
# without unwinding, as an MPI rank must after MPI_Abort returns).
STDLIB_DOCUMENTED = {"_exit"}


def _private(name: str) -> bool:
    dunder = name.startswith("__") and name.endswith("__")
    return name.startswith("_") and not dunder and name not in STDLIB_DOCUMENTED


def _defined_here(tree) -> set[str]:
    """Names a file defines: functions, classes, assigned names and attributes (``x._a = ...``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return names


def foreign_private_uses(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    here = _defined_here(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            found += [f"from {node.module} import {a.name}" for a in node.names if _private(a.name)]
        elif isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if any(_private(p) for p in a.name.split("."))]
        elif isinstance(node, ast.Attribute) and _private(node.attr) and node.attr not in here:
            found.append(f"line {node.lineno}: .{node.attr}")
        elif isinstance(node, ast.keyword) and node.arg and _private(node.arg):
            found.append(f"line {node.lineno}: {node.arg}=")
    return found


def test_no_module_uses_another_modules_private_names():
    offenders = {str(p.relative_to(ROOT)): uses for p in SOURCES if (uses := foreign_private_uses(p))}
    assert offenders == {}
