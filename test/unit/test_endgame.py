"""The end game (`planning.endgame`): a replan the deviation triggers is made only when the
error matters.

A first plan is made and put in force; fixes then arrive at one of its nodes. Held to: the plan
in force flown from its own predicted state is on target and passively safe (the check's
oracle: SCVx*'s own margin and terminal condition); a small offset keeps it in force (the fix
says why, nothing is solved); a fix that makes the plan in force unsafe from it is replanned
however lenient the tolerances; an offset beyond the terminal tolerance is replanned; `none`
replans every deviating fix as before; the cost cap leaves a dear replan out of force only
while the plan in force is safe from the fix.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from art_guidance.config import GuidanceConfig, PlanningConfig, ScenarioConfig
from art_guidance.dynamics import propagate_mean_oe, roe_from_rtn_linear
from art_guidance.errors import ConfigError
from art_guidance.planning import GuidancePipeline, NavState, Target
from art_guidance.planning.endgame import Endgame, InForceCheck, tolerance_scale
from art_guidance.guidance.core import GuidanceCore
from art_guidance.guidance.replan import Action, Decision, ReplanSettings
from art_guidance.scenarios import sample_scenario

T0_NS = 10**18
NODE = 6  # the fixes arrive at this node of the first plan
COV = np.diag([1e-4] * 6)  # a tight fix: any offset below is many sigma off the plan [m^2]


def _pipeline(endgame: str, **extra) -> GuidancePipeline:
    config = GuidanceConfig.load()
    return GuidancePipeline(config.replace(planning=dataclasses.replace(
        config.planning, endgame=endgame, **extra)))


@pytest.fixture(scope="module")
def scenario():
    """(chief elements, the seed's start ROE, its target, the scenario)."""
    sc = ScenarioConfig.from_yaml()
    chief = np.array(sc.chief_oe)
    s = sample_scenario(sc, 3)
    return chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn, sc


def _core(scenario, endgame: str, **extra) -> GuidanceCore:
    """A core with its first plan (chance-constrained, CVX warm start) in force."""
    chief, roe0, target_rtn, _ = scenario
    core = GuidanceCore(_pipeline(endgame, **extra),
                        ReplanSettings(stamp_check="off", replan_sigma_threshold=3.0),
                        Target("custom", target_rtn, True, "cvx", None))
    core.on_nav(NavState(T0_NS, chief, roe0, COV), 0)
    job = core.take_job(wait=False)
    assert core.solve(job).action is Action.ACTIVATED
    return core


def _fix(core: GuidanceCore, offset_m: np.ndarray) -> NavState:
    """The fix at node NODE of the plan in force, `offset_m` off its predicted state."""
    first = core.policy.active.result
    t_s = float(first.epochs_s[NODE])
    return NavState(T0_NS + int(round(t_s * 1e9)), propagate_mean_oe(first.chief_oe, t_s),
                    first.roe_m[NODE] + offset_m, COV)


@pytest.fixture(scope="module")
def keep_core(scenario):
    return _core(scenario, "keep")


def test_the_plan_in_force_from_its_own_state_is_on_target_and_safe(keep_core):
    core = keep_core
    nav = _fix(core, np.zeros(6))
    job = core._job_for(nav, None, "nav")
    check = core.pipeline.check_in_force(job.request, nav.cov_m2)
    assert isinstance(check, InForceCheck)
    # the plan's own model: its predicted states from node NODE on are the carried ones
    assert check.terminal_error_m < 1e-3 and check.terminal_error_mps < 1e-6
    assert check.safe and check.margin_m >= 0.0
    assert check.terminal_sigma < 1e-3
    first = core.policy.active.result
    remaining = float(np.linalg.norm(first.dv_rtn_mps[NODE:], axis=1).sum())
    assert check.remaining_mps == pytest.approx(remaining, rel=1e-12)


def test_a_small_error_keeps_the_plan_in_force_and_says_why(keep_core):
    core = keep_core
    nav = _fix(core, np.array([0.3, -0.2, 0.3, 0.1, -0.1, 0.2]))
    plans = core.stats["plans"]
    decision, deviation = core.on_nav(nav, 0)
    assert deviation > 3.0  # the sigma rule alone would replan
    assert decision is Decision.ON_PLAN
    assert core.why_on_plan.startswith("endgame keep: the error does not matter")
    assert "terminal error" in core.why_on_plan and "margin" in core.why_on_plan
    assert core.take_job(wait=False) is None and core.stats["plans"] == plans
    assert core.stats["kept"] >= 1


def test_an_error_beyond_the_tolerance_is_replanned(scenario):
    core = _core(scenario, "keep", terminal_tolerance_m=0.5)
    decision, _ = core.on_nav(_fix(core, np.array([0.0, 30.0, 0.0, 0.0, 0.0, 0.0])), 0)
    assert decision is Decision.REPLANNING and core.why_on_plan == ""
    assert core.take_job(wait=False) is not None


def test_a_fix_that_makes_the_plan_in_force_unsafe_is_replanned(scenario):
    # tolerances no error exceeds: only safety can refuse the keep
    core = _core(scenario, "keep", terminal_tolerance_m=1e9, terminal_tolerance_mps=1e9)
    first = core.policy.active.result
    nav = _fix(core, -first.roe_m[NODE])  # the fix at the chief: inside every ellipsoid
    job = core._job_for(nav, None, "nav")
    check = core.pipeline.check_in_force(job.request, nav.cov_m2)
    assert not check.safe and check.margin_m < 0.0
    decision, _ = core.on_nav(nav, 0)
    assert decision is Decision.REPLANNING and core.why_on_plan == ""
    assert core.take_job(wait=False) is not None


def test_an_unsafe_fix_on_target_is_replanned_to_the_plan_in_force_s_own_end(scenario):
    # aim_within_tolerance: the replan restores safety and keeps the end the plan in force
    # predicts from the fix (within the tolerances), without nulling the terminal error
    core = _core(scenario, "keep", terminal_tolerance_m=1e9, terminal_tolerance_mps=1e9,
                 aim_within_tolerance=True)
    first = core.policy.active.result
    nav = _fix(core, -first.roe_m[NODE])
    check = core.pipeline.check_in_force(core._job_for(nav, None, "nav").request, nav.cov_m2)
    decision, _ = core.on_nav(nav, 0)
    assert decision is Decision.REPLANNING and core.stats["aimed"] == 1
    job = core.take_job(wait=False)
    np.testing.assert_array_equal(job.request.target_rtn, check.terminal_rtn)
    assert not np.allclose(job.request.target_rtn, scenario[2])


def test_none_replans_every_deviating_fix(scenario):
    core = _core(scenario, "none")
    decision, _ = core.on_nav(_fix(core, np.array([0.3, -0.2, 0.3, 0.1, -0.1, 0.2])), 0)
    assert decision is Decision.REPLANNING and core.why_on_plan == ""
    assert core.stats["kept"] == 0


def test_the_cost_cap_leaves_a_dear_replan_out_of_force_while_the_plan_is_safe(scenario):
    # no keep (zero tolerances): every deviating fix is solved, and any growth is "dear"
    core = _core(scenario, "keep_cap", terminal_tolerance_m=0.0, terminal_tolerance_mps=0.0,
                 endgame_cost_cap_mps=0.0, endgame_cost_per_m=0.0)
    active = core.policy.active_id
    nav = _fix(core, np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]))
    check = core.pipeline.check_in_force(core._job_for(nav, None, "nav").request, nav.cov_m2)
    assert check.safe  # a 1 m offset leaves the plan in force safe (margin ~3 m)
    decision, _ = core.on_nav(nav, 0)
    assert decision is Decision.REPLANNING
    job = core.take_job(wait=False)
    solved = core.solve(job)
    assert float(solved.result.cost_mps) > job.request.carry.remaining_mps  # it grew
    assert solved.action is Action.KEPT_ACTIVE_PLAN and core.policy.active_id == active
    assert "not put in force (endgame keep_cap)" in solved.status_text
    assert core.stats["capped"] == 1


def test_the_cost_cap_never_holds_a_plan_that_is_unsafe_from_the_fix(scenario):
    core = _core(scenario, "keep_cap", terminal_tolerance_m=0.0, terminal_tolerance_mps=0.0,
                 endgame_cost_cap_mps=0.0)
    first = core.policy.active.result
    core.on_nav(_fix(core, -first.roe_m[NODE]), 0)
    solved = core.solve(core.take_job(wait=False))
    assert core.stats["capped"] == 0
    assert solved.action is (Action.ACTIVATED if solved.result.scp.feasible
                             else Action.KEPT_ACTIVE_PLAN)


def test_the_tolerances_widen_with_the_nodes_left():
    assert tolerance_scale(0, 80) == 1.0
    assert tolerance_scale(10, 5) == 1.0 and tolerance_scale(10, 10) == 1.0
    assert tolerance_scale(10, 40) == 4.0
    check = InForceCheck(1.0, 30.0, 0.01, 1.0, 50.0)
    planning = PlanningConfig(terminal_tolerance_m=10.0, terminal_tolerance_mps=0.02,
                              tolerance_growth_nodes=10)
    assert not check.kept_under(planning, 10) and check.kept_under(planning, 30)
    unsafe = dataclasses.replace(check, margin_m=-0.01)
    assert not unsafe.kept_under(planning, 90) and unsafe.on_target_under(planning, 90)
    # indistinguishable from the fix's navigation error: kept whatever its size
    assert check.on_target(1.0, 0.001, tolerance_sigma=60.0)


def test_a_large_error_is_worth_a_dear_replan():
    planning = PlanningConfig(endgame_cost_cap_mps=0.05, endgame_cost_per_m=0.01)
    near = InForceCheck(1.0, 3.0, 0.001, 1.0)
    far = InForceCheck(1.0, 2000.0, 0.5, 1.0)  # a missed burn's kilometres
    assert near.worth_mps(planning) == pytest.approx(0.08)
    assert far.worth_mps(planning) == pytest.approx(20.05)


def test_settings_are_validated():
    assert Endgame("keep").keeps and not Endgame("keep").caps and Endgame("keep_cap").caps
    assert not Endgame("none").keeps
    with pytest.raises(ConfigError, match="endgame must be one of"):
        PlanningConfig(endgame="hold")
    with pytest.raises(ConfigError, match="tolerance_growth_nodes"):
        PlanningConfig(tolerance_growth_nodes=-1)
    with pytest.raises(ConfigError, match="aim_within_tolerance"):
        PlanningConfig(aim_within_tolerance="yes")
    for name in ("terminal_tolerance_m", "terminal_tolerance_mps", "endgame_cost_cap_mps",
                 "terminal_tolerance_sigma", "endgame_cost_per_m"):
        with pytest.raises(ConfigError, match=name):
            PlanningConfig(**{name: -1.0})
        with pytest.raises(ConfigError, match=name):
            PlanningConfig(**{name: float("nan")})
