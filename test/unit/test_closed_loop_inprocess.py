"""The closed loop without DDS: the simulator drives the in-process guidance (policy, pipeline)."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from helpers.benchmarks import load_benchmark

from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance

LOG = logging.getLogger("test_closed_loop_inprocess")


def _run(tmp_path, **overrides) -> tuple[dict, int, InProcessGuidance]:
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=str(tmp_path / "s.json"),
                  **overrides)
    link = InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS)
    loop = ClosedLoop(link, params, LOG, settle_s=0.0)
    outcome = loop.run()
    summary, code = loop.finish(outcome, 0.0)
    return summary, code, link


@pytest.mark.slow
def test_in_process_closed_loop_reaches_the_waypoint(tmp_path):
    summary, code, link = _run(tmp_path, seed=0)
    assert code == 0 and summary["outcome"] == "final_epoch"
    assert summary["miss_m"] < 50.0 and summary["min_safety_margin_m"] > 0.0
    assert summary["n_plans_failed"] == 0 and summary["n_burns"] == 100
    # every replan the loop counted was solved here, and the first one planned all 100 nodes
    assert summary["n_replans"] == len(link.results) >= 1
    assert link.results[0][1].epochs_s.size == 100
    assert (tmp_path / "s.json").is_file()


def test_fixes_before_a_request_or_out_of_order_are_rejected():
    link = InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS)
    chief = np.array(GuidancePipeline().scenario.chief_oe)
    link.publish_nav(SIM_EPOCH0_NS, chief, np.zeros(6), np.eye(6))
    assert link.wait_decision(SIM_EPOCH0_NS, 0.0)["decision"] == "rejected"
    assert link.take_plans(0)[0].rejection
    link.publish_request("plus_vbar", True, "cvx")
    roe = np.array([0.0, -17_500.0, 0.0, 4000.0, 0.0, 0.0])
    link.publish_nav(SIM_EPOCH0_NS + 1, chief, roe, np.eye(6))
    assert link.wait_decision(SIM_EPOCH0_NS + 1, 0.0)["decision"] == "replanning"
    assert link.wait_plan(SIM_EPOCH0_NS + 1, 0.0)
    link.publish_nav(SIM_EPOCH0_NS, chief, roe, np.eye(6))  # older than the last fix
    last = link.take_plans(0)[-1]
    assert last.rejection and "not newer" in last.status_text
    assert last.active_plan_id == "plan-1"  # the plan in force is unchanged
    with pytest.raises(Exception, match="waypoint"):
        link.publish_request("nowhere", True, "cvx")
    # a new target replans from the newest accepted fix at once, as the node does
    link.publish_request("minus_vbar", True, "cvx")
    replan = link.take_plans(0)[-1]
    assert replan.stamp_ns == SIM_EPOCH0_NS + 1 and not replan.rejection
    assert replan.plan_id == "plan-2" == replan.active_plan_id
    assert np.allclose(link.results[-1][1].rtn[-1, :3], [0.0, -750.0, 0.0], atol=1.0)


def test_the_hard_family_is_the_seeds_whose_cvx_warm_start_violates_most():
    """bench closed_loop --min-c-cvx N screens seeds by their initial CVX warm start's C_CVX
    (the first replan's transfer without navigation error)."""

    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.planning import PlanRequest
    from art_guidance.scenarios import sample_scenario

    bench = load_benchmark("bench_closed_loop")
    pipeline = GuidancePipeline()
    seeds, c_cvx, screened = bench.hard_seeds(pipeline, 0, 2, 40)
    assert len(seeds) == 2 and min(c_cvx) >= 40 and screened == seeds[-1] + 1
    sc = pipeline.scenario
    chief = np.array(sc.chief_oe)
    target = np.asarray(sc.waypoints_rtn[PARAMETERS["waypoint"]], float)
    for seed in range(seeds[0]):  # the skipped ones are below the threshold or infeasible
        req = PlanRequest(chief, roe_from_rtn_linear(chief, sample_scenario(sc, seed).rtn0),
                          target, chance_constrained=True)
        tr = pipeline.transfer(req)
        cvx = tr.problem.cvx()
        assert not cvx.status.feasible or \
            tr.safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0] < 40
