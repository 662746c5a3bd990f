"""The learned warm-start step of one pipeline, in line or in its proposal worker process.

`Producers.learned` is the planner process's one call site of the learned step
(`planning.learned`): the plan's proposal, its in-line fallback and a window's learned target
all go through it. `Producers.propose` chooses where the plan's proposal is made: in the worker
process (`worker.process`) while this thread solves SCVx* from CVX, or in line.
"""
from __future__ import annotations

from dataclasses import dataclass

from art_guidance.config import GuidanceConfig
from art_guidance.deadline import Deadline
from art_guidance.optim import ConvexSolution, ScpResult, Scvx
from art_guidance.optim.problem import SubproblemOptions
from art_guidance.planning.learned import (
    CvxSafety, Learned, error_text, timed_learned_warm_start,
)
from art_guidance.planning.worker.process import (
    NO_DEADLINE_TIMEOUT_S, ProposalProcess, WorkerScvx, model_key,
)
from art_guidance.planning.transfer import Transfer
from art_guidance.planning.request import WarmStart
from art_guidance.planning.result import WarmStartProvider
from art_guidance.planning.worker.messages import PlanJob


@dataclass(frozen=True)
class Proposed:
    """The learned step of a plan as `Producers.propose` made it.

    Attributes:
        early: SCVx* from CVX, solved meanwhile (None: not solved yet).
        learned: the decision.
        art_ms: the step's own wall time [ms].
        art_run: SCVx* from the proposal as the worker makes it (None: made in line if
            needed).
    """

    early: ScpResult | None
    learned: Learned
    art_ms: float
    art_run: WorkerScvx | None = None


class Producers:
    """The learned step of one pipeline (module docstring).

    Attributes:
        config: the pipeline's configuration.
        provider: the learned warm-start provider, or None (CVX only).
        subproblem: SCVx*'s subproblem options (sent to the worker).
        solve_art_in_worker: the worker also solves SCVx* from its proposal (`propose`).
    """

    def __init__(self, config: GuidanceConfig, provider: WarmStartProvider | None,
                 subproblem: SubproblemOptions, solve_art_in_worker: bool = True) -> None:
        self.config, self.provider, self.subproblem = config, provider, subproblem
        self.solve_art_in_worker = solve_art_in_worker
        self._worker: ProposalProcess | None = None

    def learned(self, transfer: Transfer, cvx: ConvexSolution, deadline: Deadline | None,
                cvx_safe: CvxSafety | None = None) -> tuple[Learned, float]:
        """The learned step in this process (`planning.learned.learned_warm_start`; `cvx_safe`:
        the plan's answer whether CVX is passively safe) and its wall time [ms]."""
        return timed_learned_warm_start(self.provider, transfer, cvx, self.config.planning,
                                        deadline, cvx_safe)

    def concurrent(self, transfer: Transfer, cvx: ConvexSolution, cvx_safe: CvxSafety) -> bool:
        """Whether the plan's proposal goes to the worker: `propose_concurrently`, warm start
        auto and `also_solve_from_cvx` (SCVx* from CVX is solved whatever the check decides),
        a model loaded from a file, and a CVX plan that is feasible but not passively safe
        (otherwise ART is not run)."""
        planning = self.config.planning
        return bool(planning.propose_concurrently and planning.also_solve_from_cvx
                    and model_key(self.provider)
                    and transfer.request.warm_start is WarmStart.AUTO
                    and cvx.status.feasible
                    and not (planning.skip_art_when_cvx_safe and cvx_safe()))

    def propose(self, transfer: Transfer, cvx: ConvexSolution, cvx_safe: CvxSafety, scvx: Scvx,
                deadline: Deadline | None) -> Proposed:
        """The plan's learned step. Where it goes to the worker (`concurrent`), this thread
        solves SCVx* from CVX meanwhile, and right after the proposal the worker also solves
        SCVx* from it (the run the plan needs where the check accepts it, or where SCVx* from
        CVX does not converge), so that run overlaps this one; the plan takes it where it
        needs it and cancels it otherwise. The plan is the one the sequence gives. A worker
        that fails or answers late is stopped and the proposal is made here instead
        (`worker_error` says why)."""
        if not self.concurrent(transfer, cvx, cvx_safe):
            return Proposed(None, *self.learned(transfer, cvx, deadline, cvx_safe))
        planning, early = self.config.planning, None
        worker = self.worker()
        job_id = worker.submit(self._job(transfer, cvx, cvx_safe, deadline),
                               solve_art=self.solve_art_in_worker)
        if job_id is not None:
            try:
                early = scvx.solve(cvx.warm_start, deadline=None if deadline is None
                                   else deadline.share(planning.art_deadline_share))
            except BaseException as exc:  # the worker is freed on every path
                worker.abandon(f"SCVx* from CVX failed meanwhile ({error_text(exc)})")
                raise
            # until the deadline, not past it: a late or stalled worker is given up and the
            # plan is the best at hand (SCVx* from CVX, solved meanwhile)
            wait = NO_DEADLINE_TIMEOUT_S if deadline is None else max(deadline.left_s(), 0.0)
            answer = worker.collect(wait)
            if answer is not None and answer.deadline_hit and deadline is not None:
                deadline.mark_hit()  # the worker's step found it passed: the plan hit it
            if answer is not None:
                return Proposed(early, answer.learned, answer.wall_ms,
                                WorkerScvx(worker, job_id) if self.solve_art_in_worker
                                else None)
        return Proposed(early, *self.learned(transfer, cvx, deadline, cvx_safe))

    def _job(self, transfer: Transfer, cvx: ConvexSolution, cvx_safe: CvxSafety,
             deadline: Deadline | None) -> PlanJob:
        return PlanJob(0, self.config.to_json(), self.config.sha256(),
                       model_key(self.provider), transfer.request, cvx,
                       None if deadline is None else deadline.left_s(),
                       cvx_safe.known, self.subproblem)

    def worker(self) -> ProposalProcess:
        """The worker process (created, not started, on first need)."""
        if self._worker is None:
            self._worker = ProposalProcess()
        return self._worker

    @property
    def worker_error(self) -> str:
        """Why the worker process last failed ("" = it did not, or there is none)."""
        return "" if self._worker is None else self._worker.error

    @property
    def worker_state(self) -> tuple[str, int]:
        """The worker process in words ("" = there is none) and how many times it was found
        dead."""
        return ("", 0) if self._worker is None else (self._worker.state, self._worker.deaths)

    @property
    def worker_scvx_runs(self) -> tuple[int, int]:
        """SCVx* runs from the proposal the worker answered with, and those the plans took."""
        return (0, 0) if self._worker is None else self._worker.scvx_runs

    def start_worker(self) -> bool:
        """Start the worker and load the model in it now (`propose_concurrently` with a model
        loaded from a file): True if it runs; False otherwise (`worker_error` says why)."""
        model = model_key(self.provider)
        if not (self.config.planning.propose_concurrently and model):
            return False
        return self.worker().start(self.config.to_json(), self.config.sha256(), model)

    def close(self) -> None:
        """Stop the worker process, if any (a later concurrent proposal starts it again)."""
        if self._worker is not None:
            self._worker.close()
