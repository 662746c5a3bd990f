"""The windowed replan (`planning.window`): the window's terminal target, the plan spliced to
the waypoint, the replan it triggers, refusal of bad settings, and a closed loop flown with it.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import propagate_mean_oe, roe_from_rtn_linear
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus
from art_guidance.optim.scp import TERMINAL_TOL_M
from art_guidance.planning import GuidancePipeline, NavState, PlanRequest
from art_guidance.guidance.replan import Decision, ReplanPolicy, ReplanSettings
from art_guidance.planning.window import window_request
from art_guidance.ros.parameters import NodeParameters
from art_guidance.scenarios import sample_scenario
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance, default_settings

SC = ScenarioConfig()
CHIEF = np.array(SC.chief_oe)
TARGET = np.array(SC.waypoints_rtn["plus_vbar"])
T0_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def pipeline() -> GuidancePipeline:
    return GuidancePipeline()


def _request(seed: int = 1000, **kw) -> PlanRequest:
    roe0 = roe_from_rtn_linear(CHIEF, sample_scenario(SC, seed).rtn0)
    return PlanRequest(CHIEF, roe0, TARGET, warm_start="cvx", **kw)


def test_a_window_ends_at_the_cvx_state_and_the_plan_continues_to_the_waypoint(pipeline):
    request = _request(window_nodes=20, terminal_target="cvx")
    result = pipeline.plan(request)
    transfer = pipeline.transfer(request)
    horizon, n = transfer.horizon, transfer.horizon.n_nodes
    assert result.status.name == "CONVERGED"
    assert result.window.end_node == 20 and result.window.target_source == "cvx"
    assert result.dv_rtn_mps.shape == (n, 3) and result.roe_m.shape == (n, 6)
    np.testing.assert_array_equal(result.epochs_s, horizon.epochs_s)
    cvx = result.cvx
    # the window's post-burn state at node 20 is CVX's there (the hard terminal condition)
    z = horizon.post_burn_nonlinear(result.roe_m, result.dv_rtn_mps)[20]
    z_cvx = horizon.post_burn_nonlinear(cvx.roe_m, cvx.dv_rtn_mps)[20]
    assert np.abs(z - z_cvx).max() <= 10 * TERMINAL_TOL_M
    # beyond the window the plan is CVX's, to the waypoint
    np.testing.assert_array_equal(result.dv_rtn_mps[21:], cvx.dv_rtn_mps[21:])
    assert result.scp.dv_rtn_mps.shape == (21, 3)  # SCVx* solved the window only
    assert result.request is request
    assert result.to_json()["window"]["target_source"] == "cvx"


def test_the_window_request_keeps_the_grid_and_the_switch(pipeline):
    request = _request(window_nodes=20)
    transfer = pipeline.transfer(request)
    w = window_request(request, transfer.horizon.n_nodes, pipeline.scenario)
    assert w.n_nodes == 21 and w.window_nodes == 0 and w.warm_start == "cvx"
    assert w.koz_switch_node == SC.ae_to_koz_node
    np.testing.assert_allclose(pipeline.transfer(w).horizon.epochs_s,
                               transfer.horizon.epochs_s[:21], rtol=1e-12, atol=1e-9)


def test_a_remainder_inside_the_window_is_planned_whole(pipeline):
    request = _request(n_nodes=15, n_orbits=15 * SC.n_orbits / SC.n_nodes, window_nodes=20)
    windowed = pipeline.plan(request)
    whole = pipeline.plan(dataclasses.replace(request, window_nodes=0))
    np.testing.assert_array_equal(windowed.dv_rtn_mps, whole.dv_rtn_mps)
    assert windowed.window.target_source == "waypoint" and windowed.window.end_node == 14


@pytest.mark.parametrize("n_orbits", [0.3, 0.01])
def test_a_window_shorter_than_the_planner_takes_plans_the_whole_remainder(pipeline, n_orbits):
    """Window 2 of 99 intervals at 0.3 orbits spans 0.006 orbits, below the planner's 0.01
    (it was SOLVER_ERROR, "n_orbits ..."): the valid request plans its whole remainder, as
    without a window (bit for bit), and says so."""
    request = _request(window_nodes=2, n_orbits=n_orbits)
    result = pipeline.plan(request)
    whole = pipeline.plan(dataclasses.replace(request, window_nodes=0))
    assert result.status is not ScpStatus.SOLVER_ERROR, result.warm_start_reason
    np.testing.assert_array_equal(result.dv_rtn_mps, whole.dv_rtn_mps)
    assert result.window.target_source == "waypoint" and result.window.window_nodes == 2
    assert "below the planner's 0.01" in result.window.reason, result.window.reason
    assert result.request is request
    if n_orbits == 0.3:
        assert result.scp.feasible, result.status


def test_a_window_that_fails_falls_back_to_the_whole_remainder(pipeline):
    """Window 20 at 0.3 orbits: its plan ends INFEASIBLE where the whole remainder converges;
    the request gets the whole remainder's plan, saying why."""
    request = _request(window_nodes=20, n_orbits=0.3, terminal_target="cvx")
    result = pipeline.plan(request)
    assert result.scp.feasible, (result.status, result.warm_start_reason)
    assert result.window.target_source == "waypoint" and result.window.window_nodes == 20
    assert "the window's plan ended INFEASIBLE" in result.window.reason, result.window.reason


def test_the_art_target_is_the_learned_warm_starts_state():
    from art_guidance.art.provider import ArtWarmStart

    pipeline = GuidancePipeline(provider=ArtWarmStart.load(None))
    # warm start "art" flies the proposal whatever the check says: its state is the target
    request = dataclasses.replace(_request(window_nodes=20, terminal_target="art"),
                                  warm_start="art")
    result = pipeline.plan(request)
    assert result.window.target_source == "art", result.warm_start_reason
    assert result.proposal is not None and result.posthoc is not None
    horizon = pipeline.transfer(request).horizon
    warm = result.proposal.warm_start
    z = horizon.post_burn_nonlinear(result.roe_m, result.dv_rtn_mps)[20]
    z_art = horizon.post_burn_nonlinear(warm.roe_m, warm.dv_rtn_mps)[20]
    assert np.abs(z - z_art).max() <= 10 * TERMINAL_TOL_M
    np.testing.assert_array_equal(result.dv_rtn_mps[21:], warm.dv_rtn_mps[21:])


@pytest.mark.parametrize("field,value", [("window_nodes", 1), ("window_nodes", -1),
                                         ("window_nodes", True), ("window_nodes", 2.5),
                                         ("window_nodes", 1001), ("terminal_target", "mpc")])
def test_bad_window_requests_are_refused(field, value):
    with pytest.raises(InputError, match=field):
        _request(**{field: value})


def test_requests_round_trip_with_their_window_and_old_records_have_none():
    request = _request(window_nodes=20, terminal_target="cvx")
    again = PlanRequest.from_json(request.to_json())
    assert again.window_nodes == 20 and again.terminal_target == "cvx"
    old = {k: v for k, v in request.to_json().items()
           if k not in ("window_nodes", "terminal_target")}
    assert PlanRequest.from_json(old).window_nodes == 0


@pytest.mark.parametrize("changes,reason", [
    ({"replan_window_nodes": 1}, "replan_window_nodes must be 0"),
    ({"replan_window_nodes": 100}, r"in \[2, 99\]"),
    ({"replan_window_nodes": -3}, "replan_window_nodes must be >= 0"),
    ({"terminal_target": "waypoint"}, "terminal_target must be one of"),
])
def test_bad_window_parameters_are_refused_with_the_reason(changes, reason):
    from art_guidance.config import GuidanceConfig, node_parameter_defaults
    from art_guidance.ros.parameters import PLANNING_PARAMETERS

    planning = GuidanceConfig.load().planning
    params = NodeParameters.from_values({**node_parameter_defaults(),
                                         **{n: getattr(planning, n) for n in PLANNING_PARAMETERS}})
    with pytest.raises(ConfigError, match=reason):
        params.changed(changes)
    good = params.changed({"replan_window_nodes": 20, "terminal_target": "cvx"})
    assert good.replan_settings().replan_window_nodes == 20
    with pytest.raises(ConfigError, match="in \\[2, 29\\]"):
        ReplanSettings(replan_window_nodes=40, horizon_nodes=30)


def test_a_windowed_plan_is_replanned_before_half_its_window_is_flown(pipeline):
    result = pipeline.plan(_request(window_nodes=20, terminal_target="cvx"))
    policy = ReplanPolicy(ReplanSettings(stamp_check="order", replan_window_nodes=20,
                                         replan_sigma_threshold=1e9))
    policy.on_result("plan-1", T0_NS, result)
    assert policy.active.window_end_ns is not None
    cov = np.eye(6)

    def nav(k: int) -> NavState:
        return NavState(T0_NS + int(round(result.epochs_s[k] * 1e9)),
                        propagate_mean_oe(CHIEF, result.epochs_s[k]), result.roe_m[k], cov)

    assert policy.decide(nav(10), busy=False)[0] is Decision.ON_PLAN  # 10 of 20 left
    assert policy.decide(nav(11), busy=False)[0] is Decision.REPLANNING  # 9 left < 10


def test_a_windowed_closed_loop_reaches_the_waypoint(tmp_path, pipeline):
    settings = dataclasses.replace(default_settings(SC), replan_window_nodes=20,
                                   terminal_target="cvx")
    guidance = InProcessGuidance(pipeline, SIM_EPOCH0_NS, settings)
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=str(tmp_path / "s.json"),
                  seed=3, warm_start="cvx", errors=True)
    loop = ClosedLoop(guidance, params, logging.getLogger("test_window"), settle_s=0.0)
    summary, code = loop.finish(loop.run(), 0.0)
    assert code == 0 and summary["reached"], summary
    windows = [r.window for _, r in guidance.results]
    assert all(w is not None for w in windows)
    assert {w.target_source for w in windows} >= {"cvx", "waypoint"}
