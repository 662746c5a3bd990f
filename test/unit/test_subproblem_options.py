"""The SCP subproblem posed faster (`SubproblemOptions`) against the form it replaced
(`REFERENCE_OPTIONS`): the reduced form has the optimum of the full one, and SCVx* converges to
the same plans to its own tolerance eps_opt."""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.errors import InputError
from art_guidance.optim import ScpStatus, TransferProblem
from art_guidance.optim import problem
from art_guidance.optim.problem import REFERENCE_OPTIONS, SubproblemOptions
from art_guidance.safety import PassiveSafety
from art_guidance.scenarios import sample_scenario

SEEDS = (20011, 20033, 20003)  # 7, 10 and 16 SCVx* iterations from CVX
OBJ_TOL = 1e-6  # |objective difference| of the two forms at Clarabel tolerance 1e-8


@pytest.fixture(scope="module")
def setup():
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    safety = {"cc": PassiveSafety(horizon, scenario, UncertaintyConfig.from_yaml()),
              "det": PassiveSafety(horizon, scenario, None)}
    problems = {}
    for seed in SEEDS:
        s = sample_scenario(scenario, seed)
        x0 = roe_from_rtn_linear(chief, s.rtn0)
        transfer = TransferProblem.to_target(safety["cc"], x0, s.target_rtn)
        problems[seed] = (x0, transfer.roe_f_m, transfer.cvx().dv_rtn_mps)
    return safety, problems


def _objective(sol: problem.SubproblemSolution, sub: problem.ScpSubproblem) -> float:
    """sum ||u_i|| + mu' zeta + w/2 ||zeta||^2 of a solution (the subproblem's objective)."""
    mu, w = sub._q[sub.iz], sub._p_diag[sub.iz]
    return sol.cost_mps + float(mu @ sol.zeta) + 0.5 * float(w @ sol.zeta**2)


def test_idle_control_box_leaves_the_optimum_unchanged(setup):
    """Every subproblem of three SCVx* runs solved both ways (Clarabel at 1e-8): the control
    box is judged implied by the state box, the reduced form's optimum equals the full form's,
    and the full form's solution keeps its controls within the implied bound, far inside the
    box."""
    safety, problems = setup
    options = SubproblemOptions(tol=1e-8)
    checked = 0
    for x0, xf, warm in problems.values():
        scvx = TransferProblem(safety["cc"], x0, xf).scvx(ScpConfig.from_yaml(), 3,
                                                          subproblem=options)
        sub, solve = scvx.sub, scvx.sub.solve
        seen = []

        def both(keep_control_box: bool = False, sub=sub, solve=solve, seen=seen):
            full = solve(keep_control_box=True)
            fast = solve()
            seen.append((sub.control_box_idle(), full, fast, sub._ref_u.copy(), sub._radius,
                         _objective(full, sub), _objective(fast, sub)))
            return fast
        sub.solve = both
        try:
            res = scvx.solve(warm)
        finally:
            del sub.solve
        assert res.status is ScpStatus.CONVERGED
        for idle, full, fast, u_ref, radius, l_full, l_fast in seen:
            assert idle and full.output.ok and fast.output.ok
            assert abs(l_fast - l_full) <= OBJ_TOL * (1.0 + abs(l_full))
            assert np.abs(full.dv_rtn_mps - u_ref).max() <= 3.5e-3 * radius
            checked += 1
    assert checked >= 20


def test_control_box_is_kept_when_not_implied(setup):
    """The first subproblem from CVX: implied at any radius while the reference meets the
    dynamics rows; with the terminal rows 100 m off at the reference and a radius of 1 mm, not
    implied and kept (the solve is the full form's)."""
    safety, problems = setup
    x0, xf, warm = problems[SEEDS[0]]
    cfg, horizon = ScpConfig.from_yaml(), safety["cc"].horizon
    dv, roe = TransferProblem(safety["cc"], x0, xf).terminal_warm_start(warm)
    sub = problem.ScpSubproblem(horizon, x0, xf, samples_per_node=3)
    sub.set_dynamics(horizon.linearize_nonlinear(roe, dv))
    a, rhs, _ = safety["cc"].linearize_samples(roe, dv, 3)
    sub.set_safety(a, rhs + cfg.tightening)
    sub.set_penalty(np.zeros(horizon.n_nodes), cfg.w0)
    for radius in (1e-6, 1.0, 5e3):
        sub.set_reference(roe, dv, radius)
        assert sub.control_box_idle()
    sub.set_boundary(x0, xf + 100.0)
    sub.set_dynamics(horizon.linearize_nonlinear(roe, dv))  # the terminal rows take x_f
    sub.set_reference(roe, dv, 1e3)
    assert sub.control_box_idle()  # 100 m of residual: 0.15 m/s, below r / 2
    sub.set_reference(roe, dv, 1e-3)
    assert not sub.control_box_idle()
    auto, full = sub.solve(), sub.solve(keep_control_box=True)
    np.testing.assert_array_equal(auto.dv_rtn_mps, full.dv_rtn_mps)


@pytest.mark.parametrize("mode", ["cc", "det"])
def test_scvx_plans_match_the_reference_form(setup, mode):
    """SCVx* with the shipped options and with the reference form: same status, converged
    costs within eps_opt (paths may differ by an iteration where a ratio sits on a
    threshold; `bench scvx` measures this on 600 problems)."""
    safety, problems = setup
    cfg = ScpConfig.from_yaml()
    for x0, xf, warm in problems.values():
        transfer = TransferProblem(safety[mode], x0, xf)
        fast = transfer.scvx(cfg, samples_per_node=3).solve(warm)
        ref = transfer.scvx(cfg, samples_per_node=3, subproblem=REFERENCE_OPTIONS).solve(warm)
        assert fast.status is ref.status is ScpStatus.CONVERGED
        assert abs(fast.cost_mps - ref.cost_mps) <= cfg.eps_opt
        assert fast.max_violation <= cfg.eps_feas


def test_options_are_validated_and_pooled_apart(setup):
    safety, problems = setup
    with pytest.raises(InputError):
        SubproblemOptions(tol=0.0)
    x0, xf, _ = problems[SEEDS[0]]
    horizon = safety["cc"].horizon
    pool = problem.SubproblemPool()
    a = pool.get(horizon, x0, xf, samples_per_node=3)
    b = pool.get(horizon, x0, xf, samples_per_node=3, options=REFERENCE_OPTIONS)
    assert a is not b and a.options == SubproblemOptions() and b.options == REFERENCE_OPTIONS
    assert pool.get(horizon, x0, xf, samples_per_node=3, options=SubproblemOptions()) is a


def test_the_pipeline_records_its_subproblem_and_replays_older_records_as_solved():
    """`config_json` records the subproblem's options; a record from before they were recorded
    was solved with the reference form, and `from_config_json` rebuilds it so (a log replays as
    it was flown)."""
    from art_guidance.optim.problem import REFERENCE_OPTIONS, SubproblemOptions
    from art_guidance.planning import GuidancePipeline

    record = GuidancePipeline().config_json()
    assert record["scp_subproblem"] == {"tol": 1e-6, "drop_idle_control_box": True}
    assert GuidancePipeline.from_config_json(record).subproblem == SubproblemOptions()
    older = {k: v for k, v in record.items() if k != "scp_subproblem"}
    assert GuidancePipeline.from_config_json(older).subproblem == REFERENCE_OPTIONS
