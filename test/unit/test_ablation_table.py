"""The ablation table of docs/art_training.md is the one its results render to."""
from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_documented_table_is_current():
    spec = importlib.util.spec_from_file_location("ablation_table",
                                                  ROOT / "benchmarks" / "ablation_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.in_doc() == mod.render(), "run python benchmarks/ablation_table.py"
