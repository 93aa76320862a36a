"""The benchmark scripts some tests build their scenes with (benchmarks/ is not a package)."""

import importlib.util
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(name, module_name=None):
    """benchmarks/``name``.py as a module (``module_name``: its name in sys.modules' sense, default settle_benchmark
    style ``<name>_benchmark``)."""
    spec = importlib.util.spec_from_file_location(module_name or f"{name}_benchmark", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
