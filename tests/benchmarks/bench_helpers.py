"""Helpers of the benchmark-script tests: load a script under benchmarks/ as a module."""

from __future__ import annotations

from types import ModuleType

from conftest import REPO, load_script

__all__ = ["REPO", "load_benchmark"]


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` imported as a module (:func:`conftest.load_script`)."""
    return load_script("benchmarks", name)
