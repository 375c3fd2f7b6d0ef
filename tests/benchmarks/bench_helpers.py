"""Helpers of the benchmark-script tests: load a script under benchmarks/ as a module."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` imported as a module (the folder is not a package). The scripts' own imports
    (``from common import ...``, one script from another) resolve through pytest's ``pythonpath`` (pyproject.toml),
    as ``python benchmarks/<name>.py`` resolves them through the script's folder."""
    spec = importlib.util.spec_from_file_location(f"{name}_benchmark", REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
