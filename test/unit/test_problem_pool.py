"""The pooled SCP subproblem: reusing one solver across runs changes no number of any result."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.optim import Scvx, solve_cvx
from art_guidance.optim import problem
from art_guidance.safety import PassiveSafety

SEEDS = (3, 8)


@pytest.fixture(scope="module")
def setup():
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    safety = PassiveSafety(horizon, scenario, UncertaintyConfig.from_yaml())
    problems = []
    for seed in SEEDS:
        s = sample_scenario(scenario, seed)
        x0 = np.linalg.solve(horizon.psi[0], s.rtn0)
        xf = np.linalg.solve(horizon.psi[-1], s.target_rtn)
        problems.append((x0, xf, solve_cvx(horizon, x0, xf).dv_rtn_mps))
    return safety, problems


def _fresh_pool() -> None:
    problem._POOL.subproblems = {}


def _same(a, b) -> bool:
    return (a.status is b.status and a.iterations == b.iterations
            and np.array_equal(a.dv_rtn_mps, b.dv_rtn_mps)
            and np.array_equal(a.roe_m, b.roe_m)
            and [h.cost_mps for h in a.history] == [h.cost_mps for h in b.history])


def test_reused_subproblem_gives_bit_identical_plans(setup):
    """Each run alone on a fresh pool, then all runs through one pooled subproblem (interleaved:
    both solvers are built before either solves) give the same plans to the last bit."""
    safety, problems = setup
    cfg = ScpConfig.from_yaml()
    alone = []
    for x0, xf, warm in problems:
        _fresh_pool()
        alone.append(Scvx(safety, x0, xf, cfg, samples_per_node=3).solve(warm))
    _fresh_pool()
    solvers = [Scvx(safety, x0, xf, cfg, samples_per_node=3) for x0, xf, _ in problems]
    assert solvers[0].sub is solvers[1].sub  # one pooled subproblem, built once
    shared = [s.solve(w) for s, (_, _, w) in zip(solvers[::-1], problems[::-1])][::-1]
    again = solvers[0].solve(problems[0][2])
    for a, b in zip(alone, shared):
        assert _same(a, b)
    assert _same(alone[0], again)


def test_pool_is_per_thread_and_per_horizon(setup):
    safety, problems = setup
    x0, xf, _ = problems[0]
    sub = problem.pooled_subproblem(safety.horizon, x0, xf, samples_per_node=5)
    assert problem.pooled_subproblem(safety.horizon, x0, xf, samples_per_node=5) is sub
    assert problem.pooled_subproblem(safety.horizon, x0, xf, samples_per_node=1) is not sub
    other = Horizon.build(safety.horizon.chief_oe[0], safety.horizon.epochs_s)
    assert problem.pooled_subproblem(other, x0, xf, samples_per_node=5) is not sub
    seen = []
    thread = threading.Thread(target=lambda: seen.append(
        problem.pooled_subproblem(safety.horizon, x0, xf, samples_per_node=5)))
    thread.start()
    thread.join()
    assert seen[0] is not sub
