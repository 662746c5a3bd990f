"""The choice between runs (`planning.choice`): between a replan's carried run and its fresh
runs (`choose`: the rescue, a carried run that did not converge, and the guard, a carried plan
grown far above a fresh one's, keep the better plan, count every iteration, and carry the
growth on or start it afresh); between the fresh runs from ART and from CVX
(`keep_first_plan`: the margin ART must win by); and between two plans (`better_plan`:
feasible first, then the smaller violation or the lower cost).
"""
from __future__ import annotations

import types

import numpy as np
import pytest

from art_guidance.optim import ScpResult, ScpStatus
from art_guidance.planning.carry import CarryReport
from art_guidance.planning.choice import CarryStep, Fresh, better_plan, choose, keep_first_plan
from art_guidance.planning.learned import Learned
from art_guidance.planning.request import WarmStartSource

ART, CARRIED, CVX = WarmStartSource.ART, WarmStartSource.CARRIED, WarmStartSource.CVX


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


def _outcome(feasible: bool, cost_mps: float, violation: float = 0.0):
    return types.SimpleNamespace(feasible=feasible, cost_mps=cost_mps, max_violation=violation)


@pytest.mark.parametrize("source", [ART, CVX])
def test_art_plan_is_flown_only_when_cheaper_by_the_margin(source):
    """`art_min_gain_mps`: both plans feasible, the ART-warm-started one is kept only when it is
    cheaper than the CVX-warm-started one by more than the margin, whichever ran first; an
    infeasible plan never beats a feasible one, and 0 keeps the cheaper (ties: CVX)."""
    def kept(art, cvx, margin):
        first, second = (art, cvx) if source is ART else (cvx, art)
        return source if keep_first_plan(first, second, source, margin) else source.other
    assert kept(_outcome(True, 1.000), _outcome(True, 1.0005), 0.001) == CVX
    assert kept(_outcome(True, 1.000), _outcome(True, 1.0015), 0.001) == ART
    assert kept(_outcome(True, 1.000), _outcome(True, 1.0005), 0.0) == ART
    assert kept(_outcome(True, 1.000), _outcome(True, 1.000), 0.0) == CVX
    assert kept(_outcome(True, 1.2), _outcome(False, 1.0, 0.5), 0.001) == ART
    assert kept(_outcome(False, 0.9, 0.5), _outcome(True, 1.0), 0.001) == CVX
    assert kept(_outcome(False, 0.9, 0.1), _outcome(False, 1.0, 0.5), 0.001) == ART


def test_of_two_failed_runs_the_smaller_violation_is_better():
    def run(feasible, cost_mps, violation):
        return types.SimpleNamespace(feasible=feasible, cost_mps=cost_mps,
                                     max_violation=violation, status=ScpStatus.MAX_ITERATIONS)

    assert better_plan(run(False, 9.0, 0.1), run(False, 1.0, 0.2))
    assert not better_plan(run(False, 1.0, 0.3), run(False, 9.0, 0.2))
    assert better_plan(run(True, 9.0, 0.0), run(False, 1.0, 0.1))  # feasible first
    assert better_plan(run(True, 1.0, 0.0), run(True, 1.5, 0.0))  # then the lower cost
