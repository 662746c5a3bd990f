"""The caller-owned SCP subproblem pool: reusing one solver across runs changes no number of any
result, and nothing is shared that the caller did not hand over."""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.optim import TransferProblem
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
        transfer = TransferProblem.to_target(safety, x0, s.target_rtn)
        problems.append((x0, transfer.roe_f_m, transfer.cvx().dv_rtn_mps))
    return safety, problems


def _same(a, b) -> bool:
    return (a.status is b.status and a.iterations == b.iterations
            and np.array_equal(a.dv_rtn_mps, b.dv_rtn_mps)
            and np.array_equal(a.roe_m, b.roe_m)
            and [h.cost_mps for h in a.history] == [h.cost_mps for h in b.history])


def test_reused_subproblem_gives_bit_identical_plans(setup):
    """Each run alone with a subproblem of its own, then all runs through one pool's subproblem
    (interleaved: both solvers are built before either solves) give the same plans to the
    last bit."""
    safety, problems = setup
    cfg = ScpConfig.from_yaml()
    alone = [TransferProblem(safety, x0, xf).scvx(cfg, samples_per_node=3).solve(warm)
             for x0, xf, warm in problems]
    pool = problem.SubproblemPool()
    solvers = [TransferProblem(safety, x0, xf).scvx(cfg, samples_per_node=3, pool=pool)
               for x0, xf, _ in problems]
    assert solvers[0].sub is solvers[1].sub and len(pool) == 1  # one subproblem, built once
    shared = [s.solve(w) for s, (_, _, w) in zip(solvers[::-1], problems[::-1])][::-1]
    again = solvers[0].solve(problems[0][2])
    for a, b in zip(alone, shared):
        assert _same(a, b)
    assert _same(alone[0], again)


def test_pool_is_per_caller_and_per_horizon(setup):
    """A pool keeps one subproblem per shape for its last horizon; solvers built without a pool
    share nothing."""
    safety, problems = setup
    x0, xf, _ = problems[0]
    pool = problem.SubproblemPool()
    sub = pool.get(safety.horizon, x0, xf, samples_per_node=5)
    assert pool.get(safety.horizon, x0, xf, samples_per_node=5) is sub
    assert pool.get(safety.horizon, x0, xf, samples_per_node=1) is not sub
    other = Horizon.build(safety.horizon.chief_oe[0], safety.horizon.epochs_s)
    assert pool.get(other, x0, xf, samples_per_node=5) is not sub
    assert problem.SubproblemPool().get(safety.horizon, x0, xf, samples_per_node=5) is not sub
    a, b = (TransferProblem(safety, x0, xf).scvx(samples_per_node=3) for _ in range(2))
    assert a.sub is not b.sub


def test_the_pipeline_plans_on_several_threads_with_subproblems_apart(setup):
    """Two plans at once on one pipeline take two pools; afterwards both are kept for reuse,
    and the plans equal those made one at a time."""
    import threading

    from art_guidance.planning import GuidancePipeline, PlanRequest
    safety, problems = setup
    chief = safety.horizon.chief_oe[0]
    requests = [PlanRequest(chief, x0, safety.horizon.psi[-1] @ xf, chance_constrained=True)
                for x0, xf, _ in problems]
    pipeline = GuidancePipeline()
    one_by_one = [pipeline.plan(r) for r in requests]
    assert len(pipeline._pools) == 1
    barrier, out = threading.Barrier(2), [None, None]

    def run(i: int) -> None:
        barrier.wait()
        out[i] = pipeline.plan(requests[i])
    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert 1 <= len(pipeline._pools) <= 2
    for a, b in zip(one_by_one, out):
        assert np.array_equal(a.dv_rtn_mps, b.dv_rtn_mps) and a.status is b.status
