"""The warm-up before a process's first timed solve: its one-time costs, paid and measured apart.

A process's first plan would otherwise carry costs that no later plan pays: the compiled
kernels loaded from their cache (~0.4-0.6 s here; compiled on a cold cache) and the model
runtime's first inference (its session and buffers, ~0.1-0.2 s). `warm_up` pays them through
the kernels' one door (`kernels.prepare`, waiting for a compile) and one throwaway proposal, so
that the timings a one-shot command or a benchmark reports are the solve's own (on a cold
cache a one-shot command plans on the numpy path while the kernels compile in the background;
a benchmark waits for them)
(`art-guidance plan` reports the warm-up as `timings_ms.warm_up`).
"""
from __future__ import annotations

import time

import numpy as np

from art_guidance import kernels
from art_guidance.config import PlanningConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.optim import TransferProblem
from art_guidance.planning.request import PlanRequest
from art_guidance.scenarios import sample_scenario


def seed_request(scenario: ScenarioConfig, seed: int = 0, *, chance_constrained: bool = True,
                 warm_start: str = "cvx", target_rtn: np.ndarray | None = None) -> PlanRequest:
    """The request of the scenario's transfer of `seed` (`scenarios.sample_scenario`), as
    `art-guidance plan --seed S` plans it: chance-constrained unless told, warm-started from
    `warm_start`, to the seed's waypoint or `target_rtn` (6,) [m, m/s]. With the defaults, seed
    0: the canned transfer a warm-up plans before the first timed plan."""
    sample = sample_scenario(scenario, seed)
    chief = np.asarray(scenario.chief_oe, float)
    target = sample.target_rtn if target_rtn is None else target_rtn
    return PlanRequest(chief, roe_from_rtn_linear(chief, sample.rtn0), target,
                       chance_constrained=chance_constrained, warm_start=warm_start)


def warm_up(provider: object | None = None, problem: TransferProblem | None = None,
            planning: PlanningConfig | None = None, wait: bool = False) -> float:
    """Load the kernels (numerics as chosen at the process's entry) and, with a `provider`
    and a `problem`, make one proposal of it that nobody uses (ranked under `planning`). On a
    cold cache the kernels compile now with `wait` (a benchmark of the compiled path), else
    in the background while the process plans on the numpy path (`kernels.prepare`). The wall
    time taken [ms]; never raises for the model (the plans report its trouble)."""
    t0 = time.perf_counter()
    kernels.prepare(wait=wait)
    if provider is not None and problem is not None:
        try:
            provider.propose(problem, problem.cvx(), planning)
        except Exception:  # the model's trouble is the plans' to report
            pass
    return 1e3 * (time.perf_counter() - t0)
