"""The ablation table of docs/art_training.md is the one its results render to."""
from __future__ import annotations

from helpers.benchmarks import load_analysis


def test_documented_table_is_current():
    mod = load_analysis("ablation_table")
    assert mod.in_doc() == mod.render(), "run python benchmarks/analyses/ablation_table.py"
