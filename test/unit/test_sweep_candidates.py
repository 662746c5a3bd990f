"""benchmarks/analyses/sweep_candidates.py: its selection rules on constructed candidates, and the
table of docs/art_training.md is the committed result's rendering."""
from __future__ import annotations

import json

import numpy as np
import pytest

from helpers.benchmarks import load_analysis


@pytest.fixture(scope="module")
def mod():
    return load_analysis("sweep_candidates")


def test_documented_table_is_current(mod):
    assert mod.in_doc() == mod.table(json.loads(mod.RESULT.read_text())), \
        "run python benchmarks/analyses/sweep_candidates.py --table and paste it into the doc"


def test_rules_on_constructed_candidates(mod):
    """Two scenarios, eight candidates. Scenario 0: candidate 2's rollout is inside the region
    but its warm start is not, and SCVx* from it is 0.5 m/s dearer than from CVX; candidate 5's
    warm start is inside and 0.1 m/s cheaper. Scenario 1: nothing inside; candidate 0 is the
    cheapest start."""
    k = mod.SCALES.size
    er = np.full((2, k), 0.2)
    ec = np.full((2, k), 9)
    er_roll, ec_roll = er.copy(), ec.copy()
    er_roll[0, 2], ec_roll[0, 2] = 0.01, 0
    er_ws, ec_ws = er.copy(), ec.copy()
    er_ws[0, 5], ec_ws[0, 5] = 0.02, 0
    j_scp = np.full((2, k), 3.1)
    j_scp[0, 2], j_scp[0, 5], j_scp[1, 0] = 3.5, 2.9, 2.8
    cols = {"j_cvx": np.array([2.8, 2.7]), "c_cvx": np.array([45, 5]),
            "j_scp_cvx": np.array([3.0, 3.0]), "ok_cvx": np.array([True, True]),
            "er_roll": er_roll, "ec_roll": ec_roll, "er_ws": er_ws, "ec_ws": ec_ws,
            "j_scp": j_scp, "ok": np.ones((2, k), bool)}
    s = mod.summarize(cols)
    paper, ours = s["check_rollout"], s["check_warm_start"]
    assert (paper["used"], paper["worst_mmps"], paper["worse"]) == (1, pytest.approx(-500), 1)
    assert (ours["used"], ours["worst_mmps"], ours["better"]) == (1, pytest.approx(0.0), 1)
    assert ours["sum_mmps"] == pytest.approx(100.0)
    best = s["oracle_best_candidate"]
    # picks 5 (gain 0.1 of gap 0.2) and 0 (gain 0.2 of gap 0.3)
    assert best["improvement_all"] == pytest.approx(0.3 / 0.5)
    assert best["improvement_high"] == pytest.approx(0.5)
    assert s["share_any_inside_rollout"] == 0.5 and s["share_any_inside_warm_start"] == 0.5
