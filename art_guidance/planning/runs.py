"""The SCVx* runs of one plan and its record: the carried run (`carried_run`), the fresh runs
(`fresh_runs`: from CVX and, per the request's warm start, from the learned proposal, with the
retry), and the `PlanResult` built from the run the choice kept (`plan_result`)."""
from __future__ import annotations

import contextlib
import dataclasses
import time

from art_guidance.config import PlanningConfig
from art_guidance.deadline import Deadline
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus, Scvx
from art_guidance.planning.carry import CarryReport, guard_reason, refusal
from art_guidance.planning.choice import (
    CarryStep, Choice, Fresh, keep_first_plan, second_run,
)
from art_guidance.planning.learned import CvxSafety
from art_guidance.planning.producers import Producers
from art_guidance.planning.transfer import Transfer
from art_guidance.planning.request import WarmStart, WarmStartSource
from art_guidance.planning.result import PlanResult, ScpAttempt, Timings

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX


def carried_run(transfer: Transfer, cvx: ConvexSolution, cvx_safe: CvxSafety, scvx: Scvx,
                deadline: Deadline | None, planning: PlanningConfig,
                config_sha256: str) -> CarryStep:
    """SCVx* from the plan in force, where the request carries one that this plan can start
    from (`planning.carry`), and whether the fresh solve must run too."""
    request = transfer.request
    why = refusal(request.carry, request.no_carry, planning.replan_warm_start,
                  request.chance_constrained, config_sha256, transfer.horizon.n_nodes)
    if not why and cvx.status.feasible and cvx_safe():
        why = "CVX is passively safe: SCVx* from it is the plan, nothing to carry"
    if why:
        return CarryStep(CarryReport(planning.replan_warm_start, False, why,
                                     config_sha256=config_sha256), fresh_why="")
    carry = request.carry
    warm = transfer.problem.terminal_warm_start(carry.dv_rtn_mps)
    res = scvx.solve(warm, deadline=None if deadline is None
                     else deadline.share(planning.art_deadline_share))
    excess = carry.excess_mps + res.cost_mps - carry.remaining_mps
    text = (f"carried {carry.plan_id}: SCVx* from its burns ended {res.status.name} after "
            f"{res.iterations} iterations ({res.cost_mps:.4f} m/s)")
    report = CarryReport("carry", True, text, True, "", excess, res.iterations, config_sha256)
    if res.status is not ScpStatus.CONVERGED:
        return CarryStep(report, res, fresh_why=f"the carried run ended {res.status.name}")
    guard = guard_reason(excess, res.cost_mps, cvx.cost_mps, planning.carry_guard_mps)
    if guard and not (deadline is not None and deadline.passed()):
        return CarryStep(dataclasses.replace(report, guard=guard), res,
                         fresh_why=f"guard: {guard}")
    return CarryStep(report, res)


def fresh_runs(transfer: Transfer, cvx: ConvexSolution, cvx_safe: CvxSafety, scvx: Scvx,
               deadline: Deadline | None, planning: PlanningConfig,
               producers: Producers) -> Fresh:
    """SCVx* from CVX and, per the request's warm start, from the learned proposal (a plan with
    no plan in force to carry, the carried run's rescue and its guard).

    When the first run (from the chosen warm start) does not converge and the other warm start
    exists, SCVx* is retried from the other one in the time left and the better feasible plan
    (then the lower cost) is kept; with warm start auto a converged run is also solved from
    the other where `also_solve_from_cvx` / `also_solve_from_art` say so (`choice.second_run`).
    """
    t_start = time.perf_counter()
    made = producers.propose(transfer, cvx, cvx_safe, scvx, deadline)
    learned, art_run = made.learned, made.art_run
    # the worker's run from ART, if any, is cancelled on every path that does not take it
    with art_run or contextlib.nullcontext():
        t_art = time.perf_counter()
        source, reason, discarded = learned.source, learned.reason, None
        warm = {CVX: cvx.warm_start, ART: learned.scvx_start}

        def solve(src: WarmStartSource, until: Deadline | None) -> ScpResult:
            """SCVx* from a warm start (the runs the worker made meanwhile, if any)."""
            if src is CVX and made.early is not None:
                return made.early
            if src is ART and art_run is not None:
                worker_made = art_run.result(deadline)
                if worker_made is not None:
                    return worker_made
            return scvx.solve(warm[src], deadline=until)

        other = source.other
        first = deadline
        if warm[other] is not None and deadline is not None:  # leave time for the retry
            first = deadline.share(planning.art_deadline_share)
        res = solve(source, first)
        iterations = res.iterations
        request = transfer.request
        auto = request.warm_start is WarmStart.AUTO and not (
            deadline is not None and deadline.passed())
        # the first plan of a target (nothing to carry): the plan later replans carry
        from_art = planning.also_solve_from_art or (planning.first_plan_from_both
                                                    and request.carry is None)
        second = second_run(res, source, warm[other] is not None,
                            auto and planning.also_solve_from_cvx, auto and from_art)
        if art_run is not None and ART not in (source, second and second[0]):
            art_run.dismiss()  # the worker's run from ART is not needed: stop it now
        if second is not None:
            alt_source, why = second
            alt = solve(alt_source, deadline)
            iterations += alt.iterations
            keep_first = keep_first_plan(res, alt, source, planning.art_min_gain_mps)
            kept, lost = (res, alt) if keep_first else (alt, res)
            discarded = ScpAttempt(alt_source if keep_first else source, lost.status,
                                   lost.cost_mps, lost.iterations, lost.solve_time_ms)
            source = source if keep_first else alt_source
            reason += (f"; {why} ({alt.status.name}, {alt.cost_mps:.4f} m/s): kept the "
                       f"{source.label}-warm-started plan")
            art_plan, cvx_plan = (kept, lost) if source is ART else (lost, kept)
            if source is CVX and art_plan.feasible and cvx_plan.feasible \
                    and art_plan.cost_mps < cvx_plan.cost_mps:
                reason += (f" (the ART-warm-started one is only "
                           f"{1e3 * (cvx_plan.cost_mps - art_plan.cost_mps):.2f} mm/s "
                           f"cheaper, not more than art_min_gain_mps)")
            res = kept
    return Fresh(res, source, reason, discarded, learned, made.art_ms,
                 1e3 * (t_art - t_start),
                 0.0 if made.early is None else made.early.solve_time_ms, iterations)


def plan_result(transfer: Transfer, cvx: ConvexSolution, run: Choice, fresh: Fresh | None,
                marks_s: tuple[float, float, float, float]) -> PlanResult:
    """The plan's record of the run the choice kept; `marks_s` are the `perf_counter` instants
    [s] of the plan's start, its transfer built, its CVX solved and its runs ended.

    With the concurrent proposal, "art" (its own wall time) overlaps "scp" (every SCVx* run,
    the one from CVX made meanwhile included): their sum then exceeds the total."""
    t0, t_setup, t_cvx, t_end = marks_s
    art_ms, propose_ms, early_ms = (0.0, 0.0, 0.0) if fresh is None else (
        fresh.art_ms, fresh.propose_ms, fresh.early_ms)
    timings = Timings(setup=1e3 * (t_setup - t0), cvx=1e3 * (t_cvx - t_setup), art=art_ms,
                      scp=1e3 * (t_end - t_cvx) - propose_ms + early_ms,
                      total=1e3 * (t_end - t0))
    res, learned, request, horizon = run.result, run.learned, transfer.request, transfer.horizon
    margin = float(transfer.safety.evaluate(res.roe_m, res.dv_rtn_mps).margin_m.min())
    return PlanResult(
        status=res.status, chief_oe=request.chief_oe, epochs_s=horizon.epochs_s,
        dv_rtn_mps=res.dv_rtn_mps, roe_m=res.roe_m, rtn=horizon.to_rtn(res.roe_m),
        cost_mps=res.cost_mps, scp=res, cvx=cvx, warm_start=run.source,
        posthoc=None if learned is None else learned.posthoc,
        constraint_margin_m=margin, timings=timings, request=request,
        proposal=None if learned is None else learned.proposal,
        warm_start_reason=run.reason, discarded=run.discarded,
        carry=run.carry, scp_iterations_all=run.iterations)
