"""Replay re-solves each solve on the numerics path it ran on, and knows a deadline hit from
the record's flag, not its text.

A cold kernel cache plans on the numpy path while the kernels compile (the same decisions, not
the same floats): such a solve is recorded as `numerics: numpy` and replayed there, whatever
the recorded configuration says; one recorded while the kernels became ready (`mixed`) is not
compared; `--numerics` replays every solve on one path; a record from before the field
replays on the configuration's path. A plan whose deadline a stage found passed
(`deadline_hit`: the learned step skipped, a retry cut) is not compared, whatever its status
and reason say.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from art_guidance import kernels
from art_guidance.cli import main as cli_main
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.record.recorder import McapRecorder
from art_guidance.record.replay import DEADLINE_HIT, EXIT_OK, MIXED_NUMERICS, replay
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg
from art_guidance.scenarios import sample_scenario

STAMP0 = 1_800_000_000_000_000_000


@pytest.fixture(scope="module")
def results():
    """Three CVX-warm-started plans: seed 3 on the numpy path, seed 5 compiled, seed 9
    compiled (recorded below as mixed, or as a deadline hit)."""
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load())
    chief = np.array(scenario.chief_oe)
    out = {}
    for seed, path in ((3, "numpy"), (5, "compiled"), (9, "compiled")):
        s = sample_scenario(scenario, seed)
        kernels.prepare(path, wait=True)
        try:
            out[seed] = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0),
                                                  s.target_rtn, warm_start="cvx"))
        finally:
            kernels.prepare("compiled", wait=True)
        assert out[seed].numerics == path and not out[seed].deadline_hit
    return pipeline, out


def _bag(tmp_path: Path, pipeline: GuidancePipeline, results: list) -> Path:
    bag = tmp_path / "bag"
    with McapRecorder(bag, {"config": pipeline.config_json()}) as rec:
        for k, result in enumerate(results):
            stamp = STAMP0 + k * 1_000_000_000
            assert rec.record_solve([
                ("/guidance/solve_record", solve_record_msg(result, stamp, f"plan-{k}", "test")),
                ("/guidance/maneuver_plan", plan_to_msg(result, stamp, f"plan-{k}"))], stamp)
    return bag


def test_each_solve_replays_on_the_path_it_ran_on(tmp_path, results):
    pipeline, plans = results
    bag = _bag(tmp_path, pipeline, [plans[3], plans[5],
                                    dataclasses.replace(plans[9], numerics="mixed")])
    report = replay(bag)
    rows = report["per_solve"]
    assert [r.get("numerics") for r in rows] == ["numpy", "compiled", None]
    assert rows[0]["match"] and rows[1]["match"]
    # the numpy path's floats, replayed on numpy: the same to rounding, not to the tolerance
    assert rows[0]["dv_max_abs_diff_mps"] == 0.0
    assert rows[2]["match"] is None and rows[2]["reason"] == MIXED_NUMERICS
    assert report["exit_code"] == EXIT_OK and report["compared"] == 2
    # --numerics replays every solve on that path
    forced = replay(bag, numerics="numpy")["per_solve"]
    assert [r.get("numerics") for r in forced] == ["numpy"] * 3
    kernels.prepare("compiled", wait=True)


def test_a_deadline_hit_is_not_compared_whatever_the_texts_say(tmp_path, results, capsys):
    """A CONVERGED plan whose deadline passed before the learned step (its reason says so,
    no TIMEOUT anywhere): the record's flag keeps it out of the comparison, exit 0."""
    pipeline, plans = results
    hit = dataclasses.replace(plans[9], deadline_hit=True,
                              warm_start_reason="the plan's deadline (solve_deadline_s) passed "
                              "before ART: CVX warm start")
    assert hit.status.name == "CONVERGED"
    bag = _bag(tmp_path, pipeline, [plans[5], hit])
    assert cli_main(["replay", str(bag)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "1/1 matched" in out and "1 hit their deadline" in out
    rows = replay(bag)["per_solve"]
    assert rows[1]["match"] is None and rows[1]["reason"] == DEADLINE_HIT


def test_replay_leaves_the_process_numerics_as_it_found_them(tmp_path, results):
    """`replay` is a library call: each solve on its recorded path, then the caller's path
    again (here numpy, with a compiled solve replayed in between)."""
    pipeline, plans = results
    bag = _bag(tmp_path, pipeline, [plans[5]])
    kernels.prepare("numpy")
    try:
        rows = replay(bag)["per_solve"]
        assert rows[0]["numerics"] == "compiled" and rows[0]["match"]
        assert not kernels.compiled() and kernels.status().startswith("numpy (as configured)")
    finally:
        kernels.prepare("compiled", wait=True)
