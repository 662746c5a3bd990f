"""`GuidancePipeline.plan(request) -> PlanResult`: warm start -> post hoc check -> SCP.

Every stage solves the request's one `Transfer` (`planning.transfer`). The convex TPBVP ("CVX")
is always solved: it is the fallback and the post hoc reference (R_des = -J_CVX). The learned
step (`planning.learned.learned_warm_start`, in line or in the proposal worker process) asks a
`WarmStartProvider` (ART, `art_guidance.art.provider`) for controls, validates them and applies
the post hoc check (`planning.posthoc.check_proposal`: accept when E_R and E_C of the warm start
SCVx* would start from, or of the rollout itself, are inside the configured region); an
accepted (or, with warm_start "art", forced) proposal warm-starts SCVx*, otherwise CVX does.
Every plan says in words which warm start it used and why (`PlanResult.warm_start_reason`).

A replan whose request carries the plan in force (`planning.carry`, `replan_warm_start:
carry`) starts SCVx* from that plan first; the fresh solve above runs only where the carried
run does not converge (the rescue), where the guard against a locked basin fires, or where
there is nothing to carry (`PlanResult.carry` says which).
"""
from __future__ import annotations

import contextlib
import dataclasses
import threading
import time

import numpy as np

from art_guidance import kernels
from art_guidance.config import GuidanceConfig
from art_guidance.deadline import Deadline
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus, Scvx
from art_guidance.optim.problem import REFERENCE_OPTIONS, SubproblemOptions, SubproblemPool
from art_guidance.planning.carry import CarryReport, guard_reason, refusal
from art_guidance.planning.choice import (
    CarryStep, Fresh, choose, keep_first_plan, second_run,
)
from art_guidance.planning.config_record import config_json_sha256
from art_guidance.planning.learned import (
    Learned, cvx_is_safe, error_text, timed_learned_warm_start,
)
from art_guidance.planning.proposal_process import (
    GRACE_S, NO_DEADLINE_TIMEOUT_S, ProposalProcess, model_key,
)
from art_guidance.planning.transfer import Transfer, Transfers
from art_guidance.planning.window import (
    needs_window, plan_window, short_window, waypoint_window,
)
from art_guidance.planning.worker_scvx import WorkerScvx
from art_guidance.planning.types import (
    PlanRequest, PlanResult, ScpAttempt, WarmStart, WarmStartProvider, WarmStartSource,
)
from art_guidance.safety import PassiveSafety

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX


class GuidancePipeline:
    """Plans with CVX -> (optional learned warm start + post hoc) -> SCVx*.

    Attributes:
        solve_art_in_worker: with `propose_concurrently`, the worker process also solves SCVx*
            from its proposal while this one solves SCVx* from CVX (`_propose`); False keeps
            every SCVx* run here (the same plans, later: the reference of
            `bench plan_auto`).
    """

    solve_art_in_worker = True

    def __init__(self, config: GuidanceConfig | None = None,
                 provider: WarmStartProvider | None = None,
                 deadline_s: float | None = None,
                 subproblem: SubproblemOptions | None = None) -> None:
        """Args:
            config: the configuration bundle (default: the packaged YAML files).
            provider: a learned warm-start provider, or None (CVX only).
            deadline_s: the default wall-clock budget of one whole plan [s] (CVX, the learned
                proposal and every SCVx* run, counted from the call of `plan`) for a `plan`
                given no deadline, or None (recorded with the configuration).
            subproblem: how SCVx*'s subproblem is posed (`optim.problem.SubproblemOptions`;
                None: the default); recorded with the configuration (`config_json`).
        """
        self.config = config or GuidanceConfig.load()
        self._config_sha256 = self.config.sha256()
        kernels.set_numerics(self.config.planning.numerics)  # process-wide (`kernels`)
        self.scenario = self.config.scenario
        self.uncertainty = self.config.uncertainty
        self.scp_config = self.config.scp
        self.samples_per_node = self.config.planning.samples_per_node
        self.provider = provider
        self.deadline_s = deadline_s
        self.subproblem = subproblem or SubproblemOptions()
        self._worker: ProposalProcess | None = None
        self._transfers = Transfers(self.scenario, self.uncertainty)
        # SCVx*'s subproblems, set up once per horizon and shape and updated run after run;
        # one pool per plan in progress (plans on several threads never share one)
        self._pools: list[SubproblemPool] = []
        self._pools_lock = threading.Lock()

    def config_json(self) -> dict:
        """The configuration this pipeline plans with (recorded with every run), sealed by
        `record_sha256` (`config_json_sha256`: the recording keeps it outside any CRC)."""
        data = {**self.config.to_json(), "deadline_s": self.deadline_s,
                "config_sha256": self.config.sha256(),
                "scp_subproblem": dataclasses.asdict(self.subproblem)}
        return {**data, "record_sha256": config_json_sha256(data)}

    @classmethod
    def from_config_json(cls, data: dict, provider: WarmStartProvider | None = None,
                         time_boxed: bool = True) -> "GuidancePipeline":
        """Rebuild a pipeline from `config_json` output (for replay), with `provider`; with
        `time_boxed` False its plans have no default deadline (the recorded one is dropped).
        A record from before the subproblem's options were recorded was solved with
        `REFERENCE_OPTIONS`, and is replayed with them."""
        try:
            sub = data.get("scp_subproblem")
            options = REFERENCE_OPTIONS if sub is None else SubproblemOptions(**sub)
            deadline_s = data["deadline_s"] if time_boxed else None
            return cls(GuidanceConfig.from_json(data), provider, deadline_s=deadline_s,
                       subproblem=options)
        except (KeyError, TypeError, ConfigError, InputError) as exc:
            raise InputError("config", f"recorded configuration is malformed: {exc!r}") from exc

    def transfer(self, request: PlanRequest) -> Transfer:
        """The problem every stage of a plan of `request` solves (horizon and passive-safety
        model cached)."""
        return self._transfers.get(request)

    def safety_model(self, request: PlanRequest) -> PassiveSafety:
        """The passive-safety model a request is planned with (cached with its horizon)."""
        return self.transfer(request).safety

    def plan(self, request: PlanRequest, deadline: Deadline | None = None) -> PlanResult:
        """Plan one transfer; never raises for solver or model trouble (see
        `PlanResult.status` and `PlanResult.warm_start_reason`).

        When the first SCVx* run (from the chosen warm start) does not converge and the other
        warm start exists (CVX always; ART when the model proposed valid controls, even if the
        post hoc check rejected them), SCVx* is retried from the other one in the time left and
        the better feasible plan (then the lower cost) is kept.

        `deadline` bounds the whole plan (None: `deadline_s` from now, the pipeline's default
        budget, if it has one): the learned proposal is not started once it has passed and
        stops at the first rollout step after it (the plan is then warm-started from CVX), each
        SCVx* run gets what is left of it (the first run `art_deadline_share` of that when a
        retry is possible) and returns its best feasible iterate on expiry (status TIMEOUT).
        It is overrun by at most one SCVx* iteration, one rollout step and the final safety
        evaluation.
        """
        if request.window_nodes:  # optimised over its window (`planning.window`)
            transfer = self.transfer(request)
            n_nodes = transfer.horizon.n_nodes
            why = self._no_window_target(request, n_nodes) \
                or short_window(request, n_nodes, self.scenario.n_orbits)
            if needs_window(request, n_nodes) and not why:
                if deadline is None and self.deadline_s is not None:
                    deadline = Deadline(time.perf_counter() + self.deadline_s)
                windowed = plan_window(self, transfer, deadline)
                if windowed.scp.feasible:
                    return windowed
                why = (f"the window's plan ended {windowed.status.name}: the whole remainder "
                       "is planned")
                whole = self._whole(request, n_nodes, why, deadline)
                return whole if whole.scp.feasible else windowed
            return self._whole(request, n_nodes, why, deadline)
        with self._pools_lock:
            pool = self._pools.pop() if self._pools else SubproblemPool()
        try:
            return self._plan(request, deadline, pool)
        finally:
            with self._pools_lock:
                self._pools.append(pool)

    def _whole(self, request: PlanRequest, n_nodes: int, why: str,
               deadline: Deadline | None) -> PlanResult:
        """A windowed request planned over its whole remainder, its window saying `why`."""
        whole = self.plan(dataclasses.replace(request, window_nodes=0), deadline)
        return dataclasses.replace(whole, request=request,
                                   window=waypoint_window(request, n_nodes, why))

    def _no_window_target(self, request: PlanRequest, n_nodes: int) -> str:
        """Why a windowed request has no target and is planned whole ("" = it has one): with
        `terminal_target` carry, nothing to carry."""
        if request.terminal_target != "carry":
            return ""
        why = refusal(request.carry, request.no_carry, "carry", request.chance_constrained,
                      self._config_sha256, n_nodes)
        return why and f"no plan in force to track ({why}): the whole remainder is planned"

    def _plan(self, request: PlanRequest, deadline: Deadline | None,
              pool: SubproblemPool) -> PlanResult:
        """`plan` with the caller's SCVx* subproblems: setup, CVX, the carried run (where
        there is a plan in force to carry), the fresh runs (where it is needed), the choice,
        the result."""
        t0 = time.perf_counter()
        if deadline is None and self.deadline_s is not None:
            deadline = Deadline(t0 + self.deadline_s)
        transfer = self.transfer(request)
        t_setup = time.perf_counter()
        cvx = transfer.problem.cvx()
        t_cvx = time.perf_counter()
        scvx = transfer.scvx(self.config, self.subproblem, pool)
        step = self._carry(transfer, cvx, scvx, deadline)
        fresh = None
        if step.fresh_why is not None:
            fresh = self._fresh(transfer, cvx, scvx, deadline)
        run = choose(step, fresh, self.config.planning.art_min_gain_mps)
        t_end = time.perf_counter()
        # with the concurrent proposal, "art" (its own wall time) overlaps "scp" (every
        # SCVx* run, the one from CVX made meanwhile included): their sum then exceeds the
        # total
        art_ms, propose_ms, early_ms = (0.0, 0.0, 0.0) if fresh is None else (
            fresh.art_ms, fresh.propose_ms, fresh.early_ms)
        timings = {"setup": 1e3 * (t_setup - t0), "cvx": 1e3 * (t_cvx - t_setup),
                   "art": art_ms, "scp": 1e3 * (t_end - t_cvx) - propose_ms + early_ms,
                   "total": 1e3 * (t_end - t0)}
        res, learned = run.result, run.learned
        margin = float(transfer.safety.evaluate(res.roe_m, res.dv_rtn_mps).margin_m.min())
        horizon = transfer.horizon
        return PlanResult(
            status=res.status, chief_oe=request.chief_oe, epochs_s=horizon.epochs_s,
            dv_rtn_mps=res.dv_rtn_mps, roe_m=res.roe_m, rtn=horizon.to_rtn(res.roe_m),
            cost_mps=res.cost_mps, scp=res, cvx=cvx, warm_start=run.source,
            posthoc=None if learned is None else learned.posthoc,
            constraint_margin_m=margin, timings_ms=timings, request=request,
            proposal=None if learned is None else learned.proposal,
            warm_start_reason=run.reason, discarded=run.discarded,
            carry=run.carry, scp_iterations_all=run.iterations)

    def _carry(self, transfer: Transfer, cvx: ConvexSolution, scvx: Scvx,
               deadline: Deadline | None) -> CarryStep:
        """SCVx* from the plan in force, where the request carries one that this plan can
        start from (`planning.carry`), and whether the fresh solve must run too."""
        planning, request = self.config.planning, transfer.request
        why = refusal(request.carry, request.no_carry, planning.replan_warm_start,
                      request.chance_constrained, self._config_sha256,
                      transfer.horizon.n_nodes)
        if not why and cvx.status.feasible and cvx_is_safe(cvx, transfer.safety):
            why = "CVX is passively safe: SCVx* from it is the plan, nothing to carry"
        if why:
            return CarryStep(CarryReport(planning.replan_warm_start, False, why,
                                         config_sha256=self._config_sha256), fresh_why="")
        carry = request.carry
        warm = transfer.problem.terminal_warm_start(carry.dv_rtn_mps)
        res = scvx.solve(warm.dv_rtn_mps, projected=warm, deadline=None if deadline is None
                         else deadline.share(planning.art_deadline_share))
        excess = carry.excess_mps + res.cost_mps - carry.remaining_mps
        text = (f"carried {carry.plan_id}: SCVx* from its burns ended {res.status.name} after "
                f"{res.iterations} iterations ({res.cost_mps:.4f} m/s)")
        report = CarryReport("carry", True, text, True, "", excess, res.iterations,
                             self._config_sha256)
        if res.status is not ScpStatus.CONVERGED:
            return CarryStep(report, res, fresh_why=f"the carried run ended {res.status.name}")
        guard = guard_reason(excess, res.cost_mps, cvx.cost_mps, planning.carry_guard_mps)
        if guard and not (deadline is not None and deadline.passed()):
            return CarryStep(dataclasses.replace(report, guard=guard), res,
                             fresh_why=f"guard: {guard}")
        return CarryStep(report, res)

    def _fresh(self, transfer: Transfer, cvx: ConvexSolution, scvx: Scvx,
               deadline: Deadline | None) -> Fresh:
        """SCVx* from CVX and, per the request's warm start, from the learned proposal (a
        plan with no plan in force to carry, the carried run's rescue and its guard)."""
        request = transfer.request
        t_start = time.perf_counter()
        cvx_dv = cvx.dv_rtn_mps if np.all(np.isfinite(cvx.dv_rtn_mps)) \
            else np.zeros((transfer.horizon.n_nodes, 3))
        early, learned, art_ms, art_run = self._propose(transfer, cvx, cvx_dv, scvx, deadline)
        # the worker's run from ART, if any, is cancelled on every path that does not take it
        with art_run or contextlib.nullcontext():
            t_art = time.perf_counter()
            source, reason, discarded = learned.source, learned.reason, None
            iterations = 0
            warm = {CVX: cvx_dv, ART: learned.dv}
            projected = {CVX: None, ART: learned.warm_start}  # ART's terminal warm start

            def solve(src: WarmStartSource, until: Deadline | None) -> ScpResult:
                """SCVx* from a warm start (the runs the worker made meanwhile, if any)."""
                if src is CVX and early is not None:
                    return early
                if src is ART and art_run is not None:
                    made = art_run.result(deadline)
                    if made is not None:
                        return made
                return scvx.solve(warm[src], deadline=until, projected=projected[src])

            other = source.other
            first = deadline
            if warm[other] is not None and deadline is not None:  # leave time for the retry
                first = deadline.share(self.config.planning.art_deadline_share)
            res = solve(source, first)
            iterations = res.iterations
            auto = request.warm_start == WarmStart.AUTO.value and not (
                deadline is not None and deadline.passed())
            second = second_run(res, source, warm[other] is not None,
                                auto and self.config.planning.also_solve_from_cvx,
                                auto and self.config.planning.also_solve_from_art)
            if art_run is not None and ART not in (source, second and second[0]):
                art_run.dismiss()  # the worker's run from ART is not needed: stop it now
            if second is not None:
                alt_source, why = second
                alt = solve(alt_source, deadline)
                iterations += alt.iterations
                keep_first = keep_first_plan(res, alt, source,
                                             self.config.planning.art_min_gain_mps)
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
        return Fresh(res, source, reason, discarded, learned, art_ms,
                     1e3 * (t_art - t_start), 0.0 if early is None else early.solve_time_ms,
                     iterations)

    def _propose(self, transfer: Transfer, cvx: ConvexSolution, cvx_dv: np.ndarray,
                 scvx: Scvx, deadline: Deadline | None
                 ) -> tuple[ScpResult | None, Learned, float, "WorkerScvx | None"]:
        """The learned warm start step (`planning.learned`): (SCVx* from CVX if it was solved
        meanwhile, else None; the decision; the proposal's wall time [ms]; SCVx* from the
        proposal as the worker makes it, else None).

        With `propose_concurrently`, warm start auto and `also_solve_from_cvx` (so that SCVx*
        from CVX is solved whatever the check decides), a model loaded from a file, and a CVX
        plan that is feasible but not passively safe (otherwise ART is not run), the proposal
        is made in the pipeline's worker process (`proposal_process`) while this thread solves
        SCVx* from CVX. Right after the proposal the worker also solves SCVx* from it (the
        run the plan needs where the check accepts it, or where SCVx* from CVX does not
        converge), so that run overlaps this one; `_plan` takes it where the plan needs it
        and cancels it otherwise. The plan is the one the sequence gives. A worker that fails
        or answers late is stopped and the proposal (or SCVx* from it) is made here instead
        (`proposal_worker_error` says why).
        """
        planning, early, request = self.config.planning, None, transfer.request
        model = model_key(self.provider)
        if planning.propose_concurrently and planning.also_solve_from_cvx and model \
                and request.warm_start == WarmStart.AUTO.value and cvx.status.feasible \
                and not (planning.skip_art_when_cvx_safe and cvx_is_safe(cvx, transfer.safety)):
            worker = self._proposal_worker()
            left = None if deadline is None else deadline.left_s()
            job = {"config": self.config.to_json(), "config_sha256": self.config.sha256(),
                   "model": model, "request": request, "cvx": cvx,
                   "time_left_s": left, "cvx_unsafe": planning.skip_art_when_cvx_safe,
                   "subproblem": dataclasses.asdict(self.subproblem)}
            job_id = worker.submit(job, solve_art=self.solve_art_in_worker)
            if job_id is not None:
                try:
                    early = scvx.solve(cvx_dv, deadline=None if deadline is None
                                       else deadline.share(planning.art_deadline_share))
                except BaseException as exc:  # the worker is freed on every path
                    worker.abandon(f"SCVx* from CVX failed meanwhile ({error_text(exc)})")
                    raise
                wait = NO_DEADLINE_TIMEOUT_S if deadline is None \
                    else deadline.left_s() + GRACE_S
                answer = worker.collect(wait)
                if answer is not None:
                    return (early, *answer, WorkerScvx(worker, job_id)
                            if self.solve_art_in_worker else None)
            # CVX was found not passively safe above: the in-line proposal does not ask again
            return (early, *timed_learned_warm_start(self.provider, transfer, cvx, planning,
                                                     deadline,
                                                     planning.skip_art_when_cvx_safe), None)
        return (early, *timed_learned_warm_start(self.provider, transfer, cvx, planning,
                                                 deadline), None)

    def _proposal_worker(self) -> ProposalProcess:
        if self._worker is None:
            self._worker = ProposalProcess()
        return self._worker

    @property
    def proposal_worker_error(self) -> str:
        """Why the worker process last failed ("" = it did not, or there is none)."""
        return "" if self._worker is None else self._worker.error

    @property
    def proposal_worker_state(self) -> tuple[str, int]:
        """The worker process in words (running, loading, stopped and when it starts again;
        "" = there is none) and how many times it was found dead."""
        if self._worker is None:
            return "", 0
        return self._worker.state, self._worker.deaths

    @property
    def proposal_worker_scvx_runs(self) -> tuple[int, int]:
        """SCVx* runs from the proposal the worker process answered with, and those of them the
        plans took (they needed that run: the check accepted ART, or the retry); (0, 0) with no
        worker."""
        return (0, 0) if self._worker is None else self._worker.scvx_runs

    def start_proposal_worker(self) -> bool:
        """Start the worker process and load the model in it now, not in the first plan
        (`propose_concurrently` with a model loaded from a file; True if it runs, False and
        `proposal_worker_error` if it could not start; a no-op returning False otherwise)."""
        model = model_key(self.provider)
        if not (self.config.planning.propose_concurrently and model):
            return False
        return self._proposal_worker().start(self.config.to_json(), self.config.sha256(),
                                             model)

    def close(self) -> None:
        """Stop the proposal worker process, if any (the pipeline stays usable: a later
        concurrent proposal starts it again)."""
        if self._worker is not None:
            self._worker.close()
