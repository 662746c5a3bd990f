"""The node's replan policy as pure code: stamp checks, decisions, windows, the plan in force."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import propagate_mean_oe, roe_from_rtn_linear
from art_guidance.errors import ConfigError, GuidanceError
from art_guidance.optim import ScpStatus
from art_guidance.planning import GuidancePipeline, NavState, PlanRequest
from art_guidance.guidance.replan import (
    Action, Decision, ReplanPolicy, ReplanSettings, ReplanWindow, check_window, unusable_text,
)

T0_NS = 1_700_000_000_000_000_000
SC = ScenarioConfig()
CHIEF = np.array(SC.chief_oe)


@pytest.fixture(scope="module")
def plan():
    """A real converged plan of the nominal transfer (100 nodes)."""
    roe0 = roe_from_rtn_linear(CHIEF, np.array(SC.rtn0_nominal))
    result = GuidancePipeline().plan(PlanRequest(CHIEF, roe0,
                                                 np.array(SC.waypoints_rtn["plus_vbar"])))
    assert result.scp.feasible
    return result


def _nav(result, k: int, offset_sigma: float = 0.0) -> NavState:
    """The plan's own state at node k (pre-burn), optionally off by `offset_sigma` in da."""
    cov = np.diag([1.0, 25.0, 1.0, 1.0, 1.0, 1.0])
    roe = result.roe_m[k] + np.array([offset_sigma, 0, 0, 0, 0, 0])
    stamp = T0_NS + int(round(result.epochs_s[k] * 1e9))
    return NavState(stamp, propagate_mean_oe(CHIEF, result.epochs_s[k]), roe, cov)


def _policy(**kw) -> ReplanPolicy:
    return ReplanPolicy(ReplanSettings(stamp_check="order", **kw))


def test_stamp_checks():
    p = ReplanPolicy(ReplanSettings(stamp_check="wallclock", max_nav_age_s=5.0,
                                    max_nav_future_s=1.0))
    now = T0_NS
    p.check_stamp(now - 1_000_000_000, now)  # 1 s old: fine
    with pytest.raises(GuidanceError, match="stale stamp: 6.000 s old"):
        p.check_stamp(now - 6_000_000_000, now)
    with pytest.raises(GuidanceError, match="in the future"):
        p.check_stamp(now + 2_000_000_000, now)
    p.accept(NavState(now, CHIEF, np.zeros(6), np.eye(6)))
    with pytest.raises(GuidanceError, match="not newer"):
        p.check_stamp(now, now)
    off = ReplanPolicy(ReplanSettings(stamp_check="off"))
    off.accept(NavState(now, CHIEF, np.zeros(6), np.eye(6)))
    off.check_stamp(now - 10**12, now)  # anything goes
    p.reset()
    p.check_stamp(now - 10, now)  # a new target starts a new stamp sequence


def test_order_check_bounds_the_jump_of_a_stamp():
    """In the stamp-order mode (simulated time, no clock to compare with) a fix far ahead of the
    last accepted one is refused instead of becoming the floor that every later fix would be
    refused against; the jump allowed is max_stamp_jump_s (600 s by default)."""
    p = _policy()
    p.accept(NavState(T0_NS, CHIEF, np.zeros(6), np.eye(6)))
    with pytest.raises(GuidanceError, match="jumps 3600.000 s ahead"):
        p.check_stamp(T0_NS + 3600 * 10**9, 0)
    assert p.stamp_floor_ns == T0_NS
    p.check_stamp(T0_NS + 600 * 10**9, 0)  # at the bound: accepted
    p.reset()
    p.check_stamp(T0_NS + 3600 * 10**9, 0)  # a new target starts a new sequence


@pytest.mark.parametrize("kw", [{"stamp_check": "sometimes"}, {"replan_sigma_threshold": 0},
                                {"min_remaining_nodes": 1}, {"replan_period_s": -1.0},
                                {"max_stamp_jump_s": 0.0}])
def test_invalid_settings_are_refused(kw):
    with pytest.raises(ConfigError):
        ReplanSettings(**kw)


def test_decisions_follow_the_plan_in_force(plan):
    p = _policy(replan_sigma_threshold=3.0)
    nav0 = _nav(plan, 0)
    assert p.decide(nav0, busy=False)[0] is Decision.REPLANNING  # nothing in force
    assert p.on_result("plan-1", nav0.stamp_ns, plan) is Action.ACTIVATED
    assert p.active_id == "plan-1"
    decision, dev = p.decide(_nav(plan, 10), busy=False)
    assert decision is Decision.ON_PLAN and dev < 1e-6  # exactly on the predicted state
    decision, dev = p.decide(_nav(plan, 10, offset_sigma=5.0), busy=False)
    assert decision is Decision.REPLANNING and dev == pytest.approx(5.0, rel=1e-6)
    assert p.decide(_nav(plan, 10), busy=True)[0] is Decision.REPLANNING  # newest state wins
    assert p.decide(_nav(plan, 98, offset_sigma=50.0), busy=False)[0] is Decision.ON_PLAN


def test_periodic_replanning(plan):
    p = _policy(replan_period_s=600.0)
    p.on_result("plan-1", _nav(plan, 0).stamp_ns, plan)
    dt = plan.epochs_s[1] - plan.epochs_s[0]
    k_due = int(np.ceil(600.0 / dt))
    assert p.decide(_nav(plan, k_due - 1), busy=False)[0] is Decision.ON_PLAN
    assert p.decide(_nav(plan, k_due), busy=False)[0] is Decision.REPLANNING


def test_window_covers_the_remaining_nodes_and_keeps_the_switch_epoch(plan):
    p = _policy()
    assert p.window(_nav(plan, 0), None) == ReplanWindow(None, None, None)  # a fresh plan
    p.on_result("plan-1", _nav(plan, 0).stamp_ns, plan)
    w = p.window(_nav(plan, 30), None)
    assert w.n_nodes == 70 and w.koz_switch_node == SC.ae_to_koz_node - 30
    period_s = plan.epochs_s[-1] / SC.n_orbits
    assert w.n_orbits == pytest.approx((plan.epochs_s[-1] - plan.epochs_s[30]) / period_s,
                                       rel=1e-3)
    assert p.window(_nav(plan, 80), None).koz_switch_node == 0  # already past the switch


def test_unusable_result_never_replaces_the_plan_in_force(plan):
    p = _policy()
    bad = dataclasses.replace(plan, status=ScpStatus.INFEASIBLE,
                              scp=dataclasses.replace(plan.scp, status=ScpStatus.INFEASIBLE))
    assert p.on_result("plan-1", T0_NS, bad) is Action.NO_PLAN and p.active is None
    p.on_result("plan-2", T0_NS, plan)
    kept = p.active
    assert p.on_result("plan-3", T0_NS + 10**9, bad) is Action.KEPT_ACTIVE_PLAN
    assert p.active is kept and p.active_id == "plan-2"
    text = unusable_text(bad, p.active_id)
    assert text.startswith("INFEASIBLE: replan not usable") and "plan-2 stays in force" in text
    assert "no plan is in force" in unusable_text(bad, "")


def test_an_unknown_terminal_target_is_a_config_error():
    with pytest.raises(ConfigError, match=re.escape(
            "terminal_target must be one of ('art', 'cvx', 'carry'), got 'nowhere'")):
        check_window(0, "nowhere", 100)
