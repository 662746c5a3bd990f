"""The closed loop without DDS: the simulator drives the in-process guidance (policy, pipeline)."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from helpers.benchmarks import load_benchmark

from art_guidance.errors import InputError
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


# ----------------------------------------------------------------- bench closed_loop --configs
def _configs():
    """benchmarks/closed_loop_configs.py, imported by name as `art-guidance bench` does (its
    modules import each other by name; its dataclass needs its module registered)."""
    import importlib
    import sys

    from helpers.benchmarks import BENCHMARKS

    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    return importlib.import_module("closed_loop_configs")


def test_configuration_names_say_what_is_flown():
    c = _configs()
    assert c.parse_configs("default,auto_carry_keep_cap,auto_fresh_late6s5") == [
        "cvx_fresh", "default", "auto_carry_keep_cap", "auto_fresh_late6s5"]
    fc = c.flight_config("auto_carry_keep_cap10m20v3sg10af")
    assert fc.warm_start == "auto" and dict(fc.planning) == {
        "replan_warm_start": "carry", "endgame": "keep_cap", "terminal_tolerance_m": 10.0,
        "terminal_tolerance_mps": 0.02, "terminal_tolerance_sigma": 3.0,
        "tolerance_growth_nodes": 10, "aim_within_tolerance": True,
        "first_plan_from_both": True}
    assert dict(c.flight_config("cvx_fresh").planning) == {  # no third part: as before
        "replan_warm_start": "fresh", "endgame": "none"}
    late = c.flight_config("auto_fresh_late6s8")
    assert dict(late.settings) == {"min_remaining_nodes": 6, "replan_sigma_threshold": 8.0}
    assert dict(late.planning)["endgame"] == "none"
    assert c.flight_config("default") == c.FlightConfig("auto")  # the shipped files'
    c.pipeline_for("cvx_carry_keep5m", None)  # the changed fields make a valid configuration
    for bad in ("auto_carry_hold", "auto_later", "art_fresh", "auto_fresh_keep10x"):
        with pytest.raises(InputError, match="--configs"):
            c.parse_configs(bad)


class _Carry:
    def __init__(self, remaining_mps: float) -> None:
        self.remaining_mps = remaining_mps


class _Request:
    def __init__(self, remaining_mps: float | None) -> None:
        self.carry = None if remaining_mps is None else _Carry(remaining_mps)


class _Result:
    def __init__(self, cost: float, n_nodes: int, remaining: float | None,
                 converged: bool = True) -> None:
        from art_guidance.optim import ScpStatus

        self.cost_mps, self.epochs_s = cost, np.zeros(n_nodes)
        self.request = _Request(remaining)
        self.status = ScpStatus.CONVERGED if converged else ScpStatus.MAX_ITERATIONS


def test_growth_counts_the_plans_put_in_force_by_nodes_left():
    from art_guidance.guidance.replan import Action

    c = _configs()
    put, kept = Action.ACTIVATED, Action.KEPT_ACTIVE_PLAN
    results = [("p1", _Result(3.0, 100, None)),  # the first plan: a fresh target
               ("p2", _Result(2.5, 60, 2.4)),  # mid-flight, +0.1
               ("p3", _Result(0.5, 5, 0.2)),  # end game, +0.3
               ("p4", _Result(0.9, 4, 0.1, converged=False)),  # not put in force
               ("p5", _Result(0.1, 3, 0.15))]  # end game, -0.05
    g = c.growth(results, [put, put, put, kept, put])
    assert g["first_plan_dv_mps"] == 3.0
    assert g["midflight_growth_mps"] == pytest.approx(0.1)
    assert g["endgame_growth_mps"] == pytest.approx(0.25)
    assert g["replan_growth_mps"] == pytest.approx([0.1, 0.3, -0.05])
    assert g["replans_by_nodes_left"] == [3, 1] and g["not_converged"] == [1, 0]


@pytest.mark.slow
def test_a_flight_of_the_defaults_reports_where_its_delta_v_goes():
    c = _configs()
    r = c.fly(0, "default")
    assert r["reached"] and r["kept_in_force"] > 0  # the end game kept the plan in force
    assert r["endgame_growth_mps"] + r["midflight_growth_mps"] == pytest.approx(
        sum(r["replan_growth_mps"]))
    s = c.where_dv_goes([r])
    assert s["flown_minus_first_mps_mean"] == pytest.approx(r["dv_mps"] - r["first_plan_dv_mps"])
    assert s["min_safety_margin_m_min"] == r["min_safety_margin_m"] >= 0.0
    assert s["miss_m_mean"] == r["miss_m"] < 50.0


def test_the_simulator_flies_only_the_plan_the_guidance_puts_in_force(tmp_path):
    """A usable plan that names another plan in force (the end game's cost cap) is counted and
    not flown."""
    from art_guidance.sim.link import LinkPlan

    link = InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS)
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path="", seed=0)
    loop = ClosedLoop(link, params, LOG, settle_s=0.0)
    epochs, dv, rtn = np.array([0.0, 60.0]), np.zeros(6), np.zeros(12)
    from art_guidance.optim import ScpStatus

    for pid, active in (("plan-1", "plan-1"), ("plan-2", "plan-1"), ("plan-3", "")):
        loop.sent.add(SIM_EPOCH0_NS + int(pid[-1]))
        link._plans.append(LinkPlan(SIM_EPOCH0_NS + int(pid[-1]), pid, ScpStatus.CONVERGED,
                                    "CONVERGED", active, epochs, dv, rtn))
        loop._adopt_plans()
        assert loop.active.plan_id == ("plan-1" if pid == "plan-2" else pid)
    assert loop.counts["replans_not_in_force"] == 1 and loop.counts["replans"] == 3
