"""The carried warm start (`planning.carry`): a replan starts from the plan in force.

A first plan is made, a fix arrives at one of its nodes off its predicted state, and the
replan's request carries the plan in force's burns there (`ReplanPolicy.carry_at`). Held to:
the carried run starts on the terminal condition and needs fewer iterations than the fresh
solve; `replan_warm_start: fresh` is the fresh solve bit for bit; the request round-trips
through JSON and replays bit for bit; every refusal says why (the choice between the carried
and the fresh run: `test_choice.py`).
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from art_guidance.config import GuidanceConfig, PlanningConfig, ScenarioConfig
from art_guidance.dynamics import propagate_mean_oe, roe_from_rtn_linear
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus
from art_guidance.planning import GuidancePipeline, NavState, PlanRequest, Target
from art_guidance.planning.carry import CarriedPlan, guard_reason, refusal
from art_guidance.guidance.replan import ReplanPolicy, ReplanSettings, request_for
from art_guidance.planning.request import WarmStartSource
from art_guidance.scenarios import sample_scenario

CARRIED, CVX = WarmStartSource.CARRIED, WarmStartSource.CVX
T0_NS = 10**18
NODE = 6  # the replan's fix is at this node of the first plan
OFFSET_M = np.array([3.0, -2.0, 4.0, 1.0, -1.5, 2.0])  # the fix off the plan's prediction [m]


def _pipeline(policy: str = "carry") -> GuidancePipeline:
    config = GuidanceConfig.load()
    return GuidancePipeline(config.replace(planning=dataclasses.replace(
        config.planning, replan_warm_start=policy)))


@pytest.fixture(scope="module")
def flight():
    """(pipeline, policy, target, the first plan, the replan's fix, its request)."""
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    s = sample_scenario(scenario, 3)
    pipeline = _pipeline()
    target = Target("custom", s.target_rtn, False, "cvx", None)
    settings = ReplanSettings(stamp_check="off")
    policy = ReplanPolicy(settings)
    nav0 = NavState(T0_NS, chief, roe_from_rtn_linear(chief, s.rtn0), np.eye(6))
    window0 = policy.window(nav0, None)
    first = pipeline.plan(request_for(nav0, target, window0, settings, None,
                                      *policy.carry_at(nav0, window0)))
    policy.on_result("plan-1", T0_NS, first)
    t_s = float(first.epochs_s[NODE])
    nav = NavState(T0_NS + int(round(t_s * 1e9)), propagate_mean_oe(chief, t_s),
                   first.roe_m[NODE] + OFFSET_M, np.eye(6))
    window = policy.window(nav, None)
    request = request_for(nav, target, window, settings, None, *policy.carry_at(nav, window))
    return pipeline, policy, target, first, nav, request


def test_the_first_plan_has_nothing_to_carry(flight):
    _, _, _, first, _, _ = flight
    assert first.carry is not None and not first.carry.carried
    assert first.carry.reason == "no plan in force" and first.carry.excess_mps == 0.0
    assert first.warm_start is CVX


def test_the_replan_carries_the_plan_in_force_at_its_nodes(flight):
    _, _, _, first, _, request = flight
    carry = request.carry
    assert carry is not None and request.no_carry == ""
    assert carry.plan_id == "plan-1"
    np.testing.assert_array_equal(carry.dv_rtn_mps, first.dv_rtn_mps[NODE:])
    np.testing.assert_array_equal(carry.roe_m, first.roe_m[NODE:])
    assert request.n_nodes == len(first.epochs_s) - NODE
    assert carry.config_sha256 == GuidanceConfig.load().replace(planning=dataclasses.replace(
        GuidanceConfig.load().planning, replan_warm_start="carry")).sha256()


def test_the_carried_run_needs_fewer_iterations_than_the_fresh_solve(flight):
    pipeline, _, _, _, _, request = flight
    carried = pipeline.plan(request)
    fresh = _pipeline("fresh").plan(request)
    assert carried.warm_start is CARRIED and carried.carry.carried and carried.carry.kept
    assert carried.status is ScpStatus.CONVERGED and carried.constraint_margin_m >= -1e-6
    assert carried.scp_iterations_all < fresh.scp_iterations_all
    # the same optimum within SCVx*'s own tolerance (eps_opt 1 mm/s) or cheaper
    assert carried.cost_mps <= fresh.cost_mps + 2e-3
    assert "carried plan-1" in carried.warm_start_reason
    # the growth since the first plan: this plan's cost above the plan in force's remainder
    remaining = float(np.linalg.norm(request.carry.dv_rtn_mps, axis=1).sum())
    assert carried.carry.excess_mps == pytest.approx(carried.cost_mps - remaining, abs=1e-12)
    assert carried.to_json()["carry"]["kept"] is True


def test_fresh_is_the_plan_without_a_carry_bit_for_bit(flight):
    _, _, _, _, _, request = flight
    fresh = _pipeline("fresh").plan(request)
    alone = _pipeline("carry").plan(dataclasses.replace(request, carry=None))
    np.testing.assert_array_equal(fresh.dv_rtn_mps, alone.dv_rtn_mps)
    assert fresh.carry.reason == "replan_warm_start fresh" and not fresh.carry.carried
    assert alone.carry.reason == "no plan in force"


def test_a_carried_request_replays_bit_for_bit_from_its_json(flight):
    pipeline, _, _, _, _, request = flight
    again = PlanRequest.from_json(json.loads(json.dumps(request.to_json())))
    np.testing.assert_array_equal(again.carry.dv_rtn_mps, request.carry.dv_rtn_mps)
    np.testing.assert_array_equal(pipeline.plan(again).dv_rtn_mps,
                                  pipeline.plan(request).dv_rtn_mps)
    old = {k: v for k, v in request.to_json().items() if k not in ("carry", "no_carry")}
    assert PlanRequest.from_json(old).carry is None  # a record from before the carry


def test_a_fix_off_the_node_grid_or_near_the_end_carries_nothing(flight):
    _, policy, _, first, nav, _ = flight
    off = dataclasses.replace(nav, stamp_ns=nav.stamp_ns + int(0.3 * 1e9 * (
        first.epochs_s[1] - first.epochs_s[0])))
    carry, why = policy.carry_at(off, policy.window(off, None))
    assert carry is None and "off the plan in force's node grid" in why
    end_s = float(first.epochs_s[-1])
    late = dataclasses.replace(nav, stamp_ns=T0_NS + int(round(end_s * 1e9)))
    carry, why = policy.carry_at(late, policy.window(late, None))
    assert carry is None and "raised to its minimum of 3 nodes" in why


def test_a_new_target_carries_nothing_and_says_so(flight):
    pipeline, _, target, first, nav, _ = flight
    policy = ReplanPolicy(ReplanSettings(stamp_check="off"))
    policy.on_result("plan-1", T0_NS, first)
    policy.reset()
    carry, why = policy.carry_at(nav, policy.window(nav, None))
    assert carry is None and why == "a new target"
    window = policy.window(nav, None)
    plan = pipeline.plan(request_for(nav, target, window, policy.settings, None,
                                     *policy.carry_at(nav, window)))
    assert plan.carry.reason == "a new target" and plan.warm_start is not CARRIED


def test_every_refusal_names_its_reason():
    dv = np.ones((5, 3))
    carry = CarriedPlan("plan-3", dv, np.zeros((5, 6)), 0.0, True, "abc")
    assert refusal(carry, "", "fresh", True, "abc", 5) == "replan_warm_start fresh"
    assert refusal(None, "", "carry", True, "abc", 5) == "no plan in force"
    assert refusal(None, "a new target", "carry", True, "abc", 5) == "a new target"
    assert "other mode" in refusal(carry, "", "carry", False, "abc", 5)
    assert "configuration changed" in refusal(carry, "", "carry", True, "xyz", 5)
    assert "5 nodes left, the replan 4" in refusal(carry, "", "carry", True, "abc", 4)
    bad = dataclasses.replace(carry, dv_rtn_mps=np.full((5, 3), np.nan))
    assert "not finite" in refusal(bad, "", "carry", True, "abc", 5)
    assert refusal(carry, "", "carry", True, "abc", 5) == ""


def test_a_malformed_carry_is_refused_with_its_field():
    with pytest.raises(InputError, match="carry dv_rtn_mps"):
        CarriedPlan("p", np.ones((1, 3)), np.zeros((1, 6)), 0.0, True, "")
    with pytest.raises(InputError, match="carry roe_m"):
        CarriedPlan("p", np.ones((4, 3)), np.zeros((3, 6)), 0.0, True, "")
    with pytest.raises(InputError, match="carry excess_mps"):
        CarriedPlan("p", np.ones((4, 3)), np.zeros((4, 6)), np.inf, True, "")
    with pytest.raises(ConfigError, match="replan_warm_start"):
        PlanningConfig(replan_warm_start="shift")
    with pytest.raises(ConfigError, match="carry_guard_mps"):
        PlanningConfig(carry_guard_mps=-1.0)


def test_the_guard_needs_both_growth_and_a_gap_to_j_cvx():
    assert guard_reason(0.2, 3.0, 2.0, 0.05) != ""
    assert guard_reason(0.04, 3.0, 2.0, 0.05) == ""   # grew little since it was checked
    assert guard_reason(0.2, 2.03, 2.0, 0.05) == ""   # at the lower bound: nothing to gain
    assert "grew 200 mm/s" in guard_reason(0.2, 3.0, 2.0, 0.05)


def test_a_windowed_replan_tracks_the_plan_in_force(flight):
    pipeline, _, _, _, _, request = flight
    windowed = dataclasses.replace(request, window_nodes=10, terminal_target="carry")
    plan = pipeline.plan(windowed)
    assert plan.window.target_source == "carry" and plan.window.end_node == 10
    # the window's SCVx* starts from the plan in force's burns, unless its CVX is already safe
    assert plan.warm_start is CARRIED or plan.carry.reason.startswith("CVX is passively safe")
    # past the window the plan in force's burns, as it planned them
    np.testing.assert_array_equal(plan.dv_rtn_mps[11:], request.carry.dv_rtn_mps[11:])
    whole = pipeline.plan(dataclasses.replace(windowed, carry=None, no_carry="a new target"))
    assert whole.window.target_source == "waypoint"
    assert "no plan in force to track (a new target)" in whole.window.reason
    assert whole.window.end_node == len(whole.epochs_s) - 1


def test_whether_cvx_is_passively_safe_is_asked_once_a_plan(flight, monkeypatch):
    """The carried run, the proposal's routing and the learned step read one answer
    (`planning.learned.CvxSafety`): the passive-safety evaluation of CVX's plan runs once a
    plan, for a carried replan whose guard sends it to the fresh solve too (warm start auto, a
    learned model: each step would ask) as for a first plan; the plans are as before."""
    from art_guidance.art.provider import ArtWarmStart
    from art_guidance.planning import learned

    pipeline, _, _, _, _, request = flight
    config = pipeline.config.replace(planning=dataclasses.replace(
        pipeline.config.planning, carry_guard_mps=0.0))
    auto = GuidancePipeline(config, provider=ArtWarmStart.load())
    grown = dataclasses.replace(request.carry, excess_mps=10.0,  # the guard fires
                                config_sha256=config.sha256())
    asked, calls = learned.cvx_is_safe, []

    def counted(cvx, safety):
        calls.append(1)
        return asked(cvx, safety)

    for name, req in (("carried", dataclasses.replace(request, carry=grown)),
                      ("first", dataclasses.replace(request, carry=None,
                                                    no_carry="a new target"))):
        req = dataclasses.replace(req, warm_start="auto")
        plan = auto.plan(req)
        monkeypatch.setattr(learned, "cvx_is_safe", counted)
        calls.clear()
        again = auto.plan(req)
        monkeypatch.setattr(learned, "cvx_is_safe", asked)
        assert len(calls) == 1, (name, len(calls), again.warm_start_reason)
        assert np.array_equal(again.dv_rtn_mps, plan.dv_rtn_mps)
        assert again.warm_start_reason == plan.warm_start_reason
        if name == "carried":
            assert plan.carry.guard and plan.proposal is not None, plan.warm_start_reason
