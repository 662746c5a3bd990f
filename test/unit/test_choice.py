"""The choice between a replan's carried run and its fresh runs (`planning.choice.choose`):
the rescue (a carried run that did not converge) and the guard (a carried plan grown far above
a fresh one's) keep the better plan, count every iteration, and carry the growth on or start
it afresh.
"""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.optim import ScpResult, ScpStatus
from art_guidance.planning.carry import CarryReport
from art_guidance.planning.choice import CarryStep, Fresh, choose
from art_guidance.planning.learned import Learned
from art_guidance.planning.request import WarmStartSource

CARRIED, CVX = WarmStartSource.CARRIED, WarmStartSource.CVX


def _run(status: ScpStatus, cost: float, iterations: int = 2) -> ScpResult:
    return ScpResult(status, np.zeros((3, 6)), np.zeros((3, 3)), cost, iterations, 0.0)


def _fresh(result: ScpResult) -> Fresh:
    return Fresh(result, CVX, "CVX warm start requested", None, Learned(CVX, "x"), 0.0, 0.0,
                 0.0, result.iterations)


def test_the_rescue_keeps_the_better_plan_and_the_growth():
    report = CarryReport("carry", True, "carried plan-2", True, "", 0.3, 20)
    step = CarryStep(report, _run(ScpStatus.MAX_ITERATIONS, 2.5, 20), "the carried run ended")
    out = choose(step, _fresh(_run(ScpStatus.CONVERGED, 2.0, 4)), 1e-3)
    assert out.source is CVX and not out.carry.kept and out.iterations == 24
    assert out.carry.excess_mps == pytest.approx(0.3 - 0.5)  # the fresh plan's cost counts
    assert out.discarded.warm_start is CARRIED
    infeasible = CarryStep(report, _run(ScpStatus.INFEASIBLE, 1.0, 20), "ended INFEASIBLE")
    assert choose(infeasible, _fresh(_run(ScpStatus.CONVERGED, 2.0)), 1e-3).source is CVX


def test_the_guard_switches_only_to_a_cheaper_plan_and_starts_the_growth_afresh():
    report = CarryReport("carry", True, "carried plan-2", True, "grew", 0.3, 2)
    step = CarryStep(report, _run(ScpStatus.CONVERGED, 2.4), "guard: grew")
    switched = choose(step, _fresh(_run(ScpStatus.CONVERGED, 1.7)), 1e-3)
    assert switched.source is CVX and switched.carry.excess_mps == 0.0
    kept = choose(step, _fresh(_run(ScpStatus.CONVERGED, 2.3995)), 1e-3)
    assert kept.source is CARRIED and kept.carry.kept and kept.carry.excess_mps == 0.0
