"""The ablation table of docs/art_training.md is the one its results render to."""
from __future__ import annotations

from helpers.benchmarks import load_benchmark


def test_documented_table_is_current():
    mod = load_benchmark("ablation_table")
    assert mod.in_doc() == mod.render(), "run python benchmarks/ablation_table.py"
