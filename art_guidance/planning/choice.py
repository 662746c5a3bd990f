"""Which SCVx* run a plan keeps: the retry rule (`second_run`) and the comparisons between
two runs (`better_plan`, `keep_first_plan`), shared by the pipeline and the warm-start
analysis (`eval.warmstart`); between the carried run and the fresh solve (`choose`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from art_guidance.optim import ScpResult, ScpStatus
from art_guidance.planning.carry import CarryReport
from art_guidance.planning.learned import Learned
from art_guidance.planning.request import WarmStartSource
from art_guidance.planning.result import ScpAttempt

ART, CVX, CARRIED = WarmStartSource.ART, WarmStartSource.CVX, WarmStartSource.CARRIED


def second_run(first: ScpResult, source: WarmStartSource, other_exists: bool,
               also_from_cvx: bool,
               also_from_art: bool = False) -> tuple[WarmStartSource, str] | None:
    """Whether SCVx* runs a second time after `first` (warm-started from `source`): (the other
    warm start, why), or None.

    A run that did not converge is retried from the other warm start when there is one
    (`other_exists`); a converged run from ART is also solved from CVX when `also_from_cvx`
    (the caller's `also_solve_from_cvx` conditions: warm start "auto", time left); a converged
    run from CVX is also solved from a valid ART proposal the check rejected when
    `also_from_art` (`also_solve_from_art`, the same conditions).
    """
    other = source.other
    if first.status is not ScpStatus.CONVERGED and other_exists:
        return other, (f"SCP from {source.label} ended {first.status.name}, retried from "
                       f"{other.label}")
    if source is ART and also_from_cvx:
        return CVX, "also solved from CVX"
    if source is CVX and other_exists and also_from_art:
        return ART, "also solved from ART"
    return None


def better_plan(a: ScpResult, b: ScpResult) -> bool:
    """True if `a` is at least as good as `b`: feasible first, then the lower cost (feasible)
    or the smaller violation (neither feasible)."""
    if a.feasible != b.feasible:
        return a.feasible
    if a.feasible:
        return a.cost_mps <= b.cost_mps
    return a.max_violation <= b.max_violation


def keep_first_plan(first: ScpResult, second: ScpResult, source: WarmStartSource,
                    min_gain_mps: float) -> bool:
    """Whether the plan of the first SCVx* run (warm-started from `source`) is
    kept over the second's (from the other warm start): the better plan (`better_plan`),
    except that when both are feasible the ART-warm-started plan must be cheaper than the
    CVX-warm-started one by more than `min_gain_mps` [m/s] (`planning.yaml`
    `art_min_gain_mps`). In replanning the two converge to plans of nearly the same cost that
    time their burns differently, and switching between them costs more under the errors
    than the difference saves."""
    art, cvx = (first, second) if source is ART else (second, first)
    if art.feasible and cvx.feasible:
        keep_cvx = not art.cost_mps < cvx.cost_mps - min_gain_mps
    else:
        keep_cvx = better_plan(cvx, art)
    return keep_cvx == (source is CVX)


@dataclass(frozen=True)
class CarryStep:
    """The carried step of a plan (`GuidancePipeline._carry`).

    Attributes:
        report: what it did (`CarryReport`).
        result: SCVx* from the plan in force (None: not run).
        fresh_why: why the fresh solve runs too ("": there is nothing to carry; None: it does
            not run).
    """

    report: CarryReport
    result: ScpResult | None = None
    fresh_why: str | None = None


@dataclass(frozen=True)
class Fresh:
    """The fresh solve of a plan (`GuidancePipeline._fresh`): its kept run and where it
    started, why, the run it replaced, the learned step, its times [ms] (the proposal's
    own, the whole proposal step's, and SCVx* from CVX made meanwhile by the worker's side)
    and the iterations of all its SCVx* runs."""

    result: ScpResult
    source: WarmStartSource
    reason: str
    discarded: ScpAttempt | None
    learned: Learned
    art_ms: float
    propose_ms: float
    early_ms: float
    iterations: int


@dataclass(frozen=True)
class Choice:
    """The run a plan keeps, where it started, why, the run it replaced, the learned step
    (None: not run), the carry's report and the iterations of every SCVx* run."""

    result: ScpResult
    source: WarmStartSource
    reason: str
    discarded: ScpAttempt | None
    learned: Learned | None
    carry: CarryReport
    iterations: int


def keep_carried(carried: ScpResult, fresh: ScpResult, min_gain_mps: float) -> bool:
    """Whether the carried plan is kept over the fresh one: when both are feasible, unless the
    fresh one is cheaper by more than `min_gain_mps` [m/s] (switching between plans of the
    same cost timed differently costs under the errors); else the better plan."""
    if carried.feasible and fresh.feasible:
        return not fresh.cost_mps < carried.cost_mps - min_gain_mps
    return better_plan(carried, fresh)


def choose(step: CarryStep, fresh: Fresh | None, min_gain_mps: float) -> Choice:
    """The plan's run: the carried one alone, the fresh one alone, or the better of the two
    (the rescue and the guard; `keep_carried`). A plan chosen against a fresh solve (the guard,
    or no carry) starts the growth afresh (`CarryReport.excess_mps` 0)."""
    report, carried = step.report, step.result
    if fresh is None:
        return Choice(carried, CARRIED, report.reason, None, None, report, carried.iterations)
    if carried is None:
        return Choice(fresh.result, fresh.source, fresh.reason, fresh.discarded, fresh.learned,
                      report, fresh.iterations)
    keep = keep_carried(carried, fresh.result, min_gain_mps)
    kept, lost = (carried, fresh.result) if keep else (fresh.result, carried)
    source, lost_source = (CARRIED, fresh.source) if keep else (fresh.source, CARRIED)
    excess = 0.0 if report.guard else \
        report.excess_mps + kept.cost_mps - carried.cost_mps
    reason = (f"{report.reason}; {step.fresh_why}: solved fresh ({fresh.reason}): kept the "
              f"{'carried' if keep else 'fresh'} plan")
    return Choice(kept, source, reason,
                  ScpAttempt(lost_source, lost.status, lost.cost_mps, lost.iterations,
                             lost.solve_time_ms), fresh.learned,
                  dataclasses.replace(report, kept=keep, excess_mps=excess),
                  carried.iterations + fresh.iterations)
