"""The layout rules of CONTRIBUTING.md that a machine can check."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SOURCES = sorted([*ROOT.joinpath("src", "polydem").rglob("*.py"), *ROOT.joinpath("kernels").glob("*.py")])


# The standard library's documented names that start with an underscore (os._exit ends a process
# without unwinding, as an MPI rank must after MPI_Abort returns).
STDLIB_DOCUMENTED = {"_exit"}

# Reading or writing an attribute by its name in a string is a use of it all the same.
BY_NAME = {"getattr", "setattr", "hasattr", "delattr"}

# Known exceptions, by file: cli/device.py reads Warp's runtime by name, with a fallback where Warp's
# internals differ, to keep the native library's warning of a missing CUDA driver off stderr.
ALLOWED = {"src/polydem/cli/device.py": ["line 27: getattr(..., '_src')"]}


def _private(name: str) -> bool:
    dunder = name.startswith("__") and name.endswith("__")
    return name.startswith("_") and not dunder and name not in STDLIB_DOCUMENTED


def _owner_is_here(target: ast.expr, classes: set[str]) -> bool:
    """Whether ``target`` (what an attribute is set on) is this module's own: ``self``, ``cls`` or one of
    its classes. A private name set on anything else (``other._n = 0``) belongs to that object's module."""
    return isinstance(target, ast.Name) and (target.id in ("self", "cls") or target.id in classes)


def _defined_here(tree: ast.Module) -> set[str]:
    """Names a file defines: functions, classes, assigned names, arguments, and attributes set on
    ``self``, ``cls`` or its own classes (``self._a = ...``)."""
    classes = {node.name for node in ast.walk(tree) if isinstance(node, ast.ClassDef)}
    names = set(classes)
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            if _owner_is_here(node.value, classes):
                names.add(node.attr)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return names


def private_uses(source: str) -> list[str]:
    """The uses of other modules' private names in the Python ``source`` of one module."""
    tree = ast.parse(source)
    here = _defined_here(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            found += [f"from {node.module} import {a.name}" for a in node.names if _private(a.name)]
        elif isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if any(_private(p) for p in a.name.split("."))]
        elif isinstance(node, ast.Attribute) and _private(node.attr) and node.attr not in here:
            found.append(f"line {node.lineno}: .{node.attr}" + (" =" if isinstance(node.ctx, ast.Store) else ""))
        elif isinstance(node, ast.keyword) and node.arg and _private(node.arg):
            found.append(f"line {node.lineno}: {node.arg}=")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in BY_NAME:
            name = node.args[1] if len(node.args) > 1 else None
            if isinstance(name, ast.Constant) and isinstance(name.value, str) and _private(name.value):
                if name.value not in here:
                    found.append(f"line {node.lineno}: {node.func.id}(..., {name.value!r})")
    return found


def test_no_module_uses_another_modules_private_names():
    offenders = {}
    for p in SOURCES:
        name = str(p.relative_to(ROOT))
        uses = [u for u in private_uses(p.read_text()) if u not in ALLOWED.get(name, [])]
        if uses:
            offenders[name] = uses
    assert offenders == {}


def test_setting_another_objects_private_attribute_is_a_use():
    # What distributed/simulation.py once did to give a rank its bodies: copy a Scene and set its
    # private arrays. Setting a name on another object does not make it this module's.
    source = """
import copy

def local_scene(scene, index):
    sub = copy.copy(scene)
    sub._arrays = {k: a[index] for k, a in scene.body_arrays().items()}
    sub._n = sub._cap = len(index)
    walls = list(getattr(scene, "_mesh_walls", []))
    return sub, walls
"""
    assert private_uses(source) == [
        "line 6: ._arrays =",
        "line 7: ._n =",
        "line 7: ._cap =",
        "line 8: getattr(..., '_mesh_walls')",
    ]


def test_a_modules_own_private_attributes_are_its_own():
    source = """
class Box:
    _count = 0

    def __init__(self):
        self._items = []
        Box._count += 1

    def copy(self):
        new = Box.__new__(Box)
        new._items = list(self._items)
        return new

    @classmethod
    def reset(cls):
        cls._count = 0
"""
    assert private_uses(source) == []
