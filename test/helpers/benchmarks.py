"""The modules of benchmarks/ and benchmarks/analyses/ as the tests read them (neither is a
package)."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def load_benchmark(name: str, folder: Path = BENCHMARKS) -> ModuleType:
    """benchmarks/<name>.py (or `folder`/<name>.py), executed as a module of that name."""
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_analysis(name: str) -> ModuleType:
    """benchmarks/analyses/<name>.py (an analysis of results, not a benchmark)."""
    return load_benchmark(name, BENCHMARKS / "analyses")
