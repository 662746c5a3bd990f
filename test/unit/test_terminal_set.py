"""The terminal set (`optim.terminal_set`): a plan may end within a ball of position and one of
velocity about its waypoint instead of on it.

Held to: CVX with the set against an independent cvxpy statement of the same problem (the
states as variables, the set as two norm constraints); a tiny set gives the equality's plan;
SCVx* with the set ends in it on the deputy-aware model, passively safe, no dearer than its
CVX warm start's own cost bound allows; a request carries the set and reads back, one without
it reads as before; the end game puts the set on its last replans only.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from art_guidance.config import PlanningConfig, ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus, TerminalSet, TransferProblem, solve_cvx, terminal_roe
from art_guidance.optim.problem import ScpSubproblem
from art_guidance.planning.endgame import in_set_under
from art_guidance.guidance.replan import Action, Decision
from art_guidance.planning.request import PlanRequest
from art_guidance.safety import PassiveSafety
from art_guidance.scenarios import sample_scenario
from helpers.cvxpy_reference import cvxpy_tpbvp

SET = TerminalSet(10.0, 0.02)


@pytest.fixture(scope="module")
def setup():
    sc = ScenarioConfig.from_yaml()
    chief = np.array(sc.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
    return sc, horizon, PassiveSafety(horizon, sc, UncertaintyConfig.from_yaml())


def _boundary(sc, horizon, seed):
    s = sample_scenario(sc, seed)
    return np.linalg.solve(horizon.psi[0], s.rtn0), terminal_roe(horizon, s.target_rtn)


def _end(horizon, roe_m, dv, linear=True):
    if linear:
        return roe_m[-1] + horizon.b[-1] @ dv[-1]
    return horizon.final_post_burn_nonlinear(roe_m, dv)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("sizes", [(10.0, 0.02), (50.0, 0.05)])
def test_cvx_with_a_set_matches_cvxpy(setup, seed, sizes):
    sc, horizon, _ = setup
    x0, xf = _boundary(sc, horizon, seed)
    sol = solve_cvx(horizon, x0, xf, terminal_set=TerminalSet(*sizes))
    ref_cost, _ = cvxpy_tpbvp(horizon, x0, xf, terminal_set=sizes)
    assert sol.status is ScpStatus.CONVERGED
    assert sol.cost_mps == pytest.approx(ref_cost, rel=1e-6)
    # it ends on the set's boundary (the equality's end is dearer), to 1e-5 relative
    pos, vel = TerminalSet(*sizes).error(horizon.psi[-1], xf,
                                         _end(horizon, sol.roe_m, sol.dv_rtn_mps))
    assert pos <= sizes[0] * (1 + 1e-5) and vel <= sizes[1] * (1 + 1e-5)
    assert sol.cost_mps < solve_cvx(horizon, x0, xf).cost_mps


def test_a_tiny_set_is_the_equality(setup):
    sc, horizon, _ = setup
    x0, xf = _boundary(sc, horizon, 2)
    exact = solve_cvx(horizon, x0, xf)
    tiny = solve_cvx(horizon, x0, xf, terminal_set=TerminalSet(1e-3, 1e-6))
    # the same optimal cost (its burns need not be the same: the optimum is not unique)
    assert tiny.cost_mps == pytest.approx(exact.cost_mps, abs=1e-5)


@pytest.mark.parametrize("seed,mode", [(2, "cc"), (3, "cc"), (2, "det")])
def test_scvx_with_a_set_ends_in_it_passively_safe(setup, seed, mode):
    sc, horizon, safety = setup
    if mode == "det":
        safety = PassiveSafety(horizon, sc, None)
    x0 = _boundary(sc, horizon, seed)[0]
    target = sample_scenario(sc, seed).target_rtn
    problem = TransferProblem.to_target(safety, x0, target, SET)
    cvx = problem.cvx()
    result = problem.scvx(samples_per_node=3).solve(cvx.dv_rtn_mps)
    assert result.status is ScpStatus.CONVERGED
    z_f = _end(horizon, result.roe_m, result.dv_rtn_mps, linear=False)
    assert SET.contains(horizon.psi[-1], problem.roe_f_m, z_f)
    # its states are the deputy-aware model's, and passively safe (SCVx*'s feasibility)
    np.testing.assert_allclose(result.roe_m, horizon.propagate_nonlinear(x0, result.dv_rtn_mps),
                               atol=1e-9)
    assert result.max_violation <= 1e-3
    assert result.cost_mps >= cvx.cost_mps - 1e-6  # CVX with the set: its lower bound


def test_a_tiny_set_gives_the_equality_s_scvx_plan(setup):
    sc, horizon, safety = setup
    x0 = _boundary(sc, horizon, 2)[0]
    target = sample_scenario(sc, 2).target_rtn
    exact = TransferProblem.to_target(safety, x0, target)
    tiny = TransferProblem.to_target(safety, x0, target, TerminalSet(1e-3, 1e-6))
    a = exact.scvx(samples_per_node=3).solve(exact.cvx().dv_rtn_mps)
    b = tiny.scvx(samples_per_node=3).solve(tiny.cvx().dv_rtn_mps)
    assert a.status is b.status is ScpStatus.CONVERGED
    assert b.cost_mps == pytest.approx(a.cost_mps, abs=1e-3)


def test_a_warm_start_ending_in_the_set_is_kept_as_it_is(setup):
    sc, horizon, safety = setup
    x0 = _boundary(sc, horizon, 2)[0]
    target = sample_scenario(sc, 2).target_rtn
    problem = TransferProblem.to_target(safety, x0, target, SET)
    plan = problem.scvx(samples_per_node=3).solve(problem.cvx().dv_rtn_mps)
    again = problem.terminal_warm_start(plan.dv_rtn_mps)
    np.testing.assert_array_equal(again.dv_rtn_mps, plan.dv_rtn_mps)
    # one that ends outside is corrected onto the set's nearest point (its boundary)
    exact = TransferProblem.to_target(safety, x0, target + np.r_[40.0, 0, 0, 0, 0, 0])
    far = problem.terminal_warm_start(exact.terminal_warm_start(plan.dv_rtn_mps).dv_rtn_mps)
    pos, _ = SET.error(horizon.psi[-1], problem.roe_f_m,
                       _end(horizon, far.roe_m, far.dv_rtn_mps, linear=False))
    assert pos == pytest.approx(SET.position_m, rel=1e-5)


def test_the_set_s_own_checks():
    psi = np.eye(6)
    xf = np.zeros(6)
    inside = np.array([3.0, 0, 0, 0.01, 0, 0])
    np.testing.assert_array_equal(SET.aim(psi, xf, inside), inside)
    out = SET.aim(psi, xf, np.array([30.0, 40.0, 0, 0, 0, 0.1]))
    assert np.linalg.norm(out[:3]) == pytest.approx(10.0, rel=1e-5)
    assert np.linalg.norm(out[3:]) == pytest.approx(0.02, rel=1e-5)
    np.testing.assert_allclose(out[:2] / np.linalg.norm(out[:2]), [0.6, 0.8])  # radial
    for bad in ((0.0, 0.02), (10.0, -1.0), (float("inf"), 0.02), (True, 0.02)):
        with pytest.raises(InputError, match="terminal_set"):
            TerminalSet(*bad)
    assert TerminalSet.from_json(SET.to_json()) == SET and TerminalSet.from_json(None) is None


def test_the_subproblem_refuses_a_set_of_another_shape(setup):
    sc, horizon, _ = setup
    x0, xf = _boundary(sc, horizon, 0)
    with pytest.raises(InputError, match="terminal_set"):
        ScpSubproblem(horizon, x0, xf).set_boundary(x0, xf, SET)
    with pytest.raises(InputError, match="OSQP"):
        solve_cvx(horizon, x0, xf, norm="l1", solver="osqp", terminal_set=SET)


def test_a_request_carries_the_set_and_old_records_read_as_before(setup):
    sc, horizon, _ = setup
    chief = np.array(sc.chief_oe)
    s = sample_scenario(sc, 0)
    request = PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn)
    assert "terminal_set" not in request.to_json()  # what older recordings hold
    assert PlanRequest.from_json(request.to_json()).terminal_set is None
    with_set = dataclasses.replace(request, terminal_set=SET)
    assert PlanRequest.from_json(with_set.to_json()).terminal_set == SET
    with pytest.raises(InputError, match="terminal_set"):
        dataclasses.replace(request, terminal_set=(10.0, 0.02))


def test_the_end_game_puts_the_set_on_its_last_replans_only():
    planning = PlanningConfig(terminal_set_nodes=5, terminal_set_share=0.5)
    assert in_set_under(planning, 5) == TerminalSet(5.0, 0.01)
    assert in_set_under(planning, 6) is None and in_set_under(planning, 0) is None
    assert in_set_under(PlanningConfig(terminal_set_nodes=0), 3) is None  # 0: off
    assert in_set_under(dataclasses.replace(planning, endgame="none"), 3) is None
    for bad in ({"terminal_set_nodes": -1}, {"terminal_set_share": 0.0},
                {"terminal_set_share": 1.5}, {"terminal_set_nodes": 2.5}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            PlanningConfig(**bad)


def test_a_replan_in_the_last_nodes_is_planned_into_the_set(setup):
    """An offset beyond a 0.5 m tolerance is replanned; with `terminal_set_nodes` covering
    every node the replan's request carries the set of the tolerances, and its plan, put in
    force, ends in it."""
    from test_endgame import _core, _fix

    sc = setup[0]
    chief = np.array(sc.chief_oe)
    s = sample_scenario(sc, 3)
    scenario = (chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn, sc)
    core = _core(scenario, "keep", terminal_tolerance_m=0.5, terminal_set_nodes=1000,
                 terminal_set_share=1.0)
    decision, _ = core.on_nav(_fix(core, np.array([0.0, 30.0, 0.0, 0.0, 0.0, 0.0])), 0)
    assert decision is Decision.REPLANNING and core.stats["in_set"] == 1
    job = core.take_job(wait=False)
    assert job.request.terminal_set == TerminalSet(0.5, 0.02)
    solved = core.solve(job)
    assert solved.action is Action.ACTIVATED
    res = solved.result
    transfer = core.pipeline.transfer(job.request)
    z_f = transfer.horizon.final_post_burn_nonlinear(res.roe_m, res.dv_rtn_mps)
    assert job.request.terminal_set.contains(transfer.horizon.psi[-1], transfer.roe_f_m, z_f)
