"""The messages between a planner and its proposal worker process (`worker.process`), typed.

The planner sends a `WarmUpJob` (load the model) and then one `PlanJob` per plan; the worker
answers each job with a `Proposal` (the learned step's decision) or a `Failure`, and a job with
`solve_art` with a second answer, a `ScvxAnswer` (SCVx* from the proposal) or a `Failure`.
Every answer names its job. A run is cancelled per job: the planner writes the job's id into
the worker's shared cancel slot (`CancelSlot`), and the worker's run of that job stops at its
next iteration; a later job is not touched by it. `None` on the pipe stops the worker.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from multiprocessing.context import BaseContext
from typing import TYPE_CHECKING, NamedTuple

from art_guidance.deadline import Deadline
from art_guidance.optim.problem import SubproblemOptions

if TYPE_CHECKING:  # the envelopes' contents, for the reader and the type checker
    from art_guidance.optim import ConvexSolution, ScpResult
    from art_guidance.planning.learned import Learned
    from art_guidance.planning.request import PlanRequest

WARM_UP_ID = 0  # the id of a warm-up job; plan jobs count from 1


class ModelKey(NamedTuple):
    """What the worker needs to load the planner's model (`worker.process.model_key`)."""

    path: str
    sha256: str
    threads: int
    reward_scales: tuple[float, ...]
    runtime: str


@dataclass(frozen=True)
class WarmUpJob:
    """Load the model (and the kernels) now.

    Attributes:
        config_json: the planner's configuration (`GuidanceConfig.to_json`).
        config_sha256: its checksum (the worker keeps its state per configuration and model).
        model: what loads the model (`worker.process.model_key`).
    """

    config_json: dict
    config_sha256: str
    model: ModelKey
    job_id: int = WARM_UP_ID


@dataclass(frozen=True)
class PlanJob:
    """The learned step of one plan (and, with `solve_art`, SCVx* from its proposal).

    Attributes:
        job_id: the job's id (> 0), named by its answers and by a cancel.
        config_json, config_sha256, model: as `WarmUpJob`'s.
        request: the plan's `PlanRequest`.
        cvx: its convex solution (`ConvexSolution`).
        time_left_s: what is left of the plan's deadline [s] (None: no deadline).
        cvx_safe: whether CVX is passively safe, where the planner asked already (the step
            does not ask again; None: not asked, `planning.learned.CvxSafety`).
        subproblem: SCVx*'s subproblem options (the planner's).
        solve_art: solve SCVx* from a valid proposal after answering (`ScvxAnswer`).
    """

    job_id: int
    config_json: dict
    config_sha256: str
    model: ModelKey
    request: PlanRequest
    cvx: ConvexSolution
    time_left_s: float | None
    cvx_safe: bool | None
    subproblem: SubproblemOptions
    solve_art: bool = False

    def warm_up(self) -> WarmUpJob:
        """The warm-up job of the same configuration and model."""
        return WarmUpJob(self.config_json, self.config_sha256, self.model)

    def numbered(self, job_id: int, solve_art: bool) -> "PlanJob":
        """This job with its id and `solve_art` set."""
        return dataclasses.replace(self, job_id=int(job_id), solve_art=bool(solve_art))


@dataclass(frozen=True)
class Proposal:
    """The learned step's answer to a job.

    Attributes:
        job_id: the job's id (`WARM_UP_ID`: the warm-up is done).
        learned: the decision (`planning.learned.Learned`; None for a warm-up).
        wall_ms: the step's wall time [ms].
        deadline_hit: the step found the plan's deadline passed (`Deadline.hit`, on the
            worker's copy of it; the planner marks its own).
    """

    job_id: int
    learned: Learned | None = None
    wall_ms: float = 0.0
    deadline_hit: bool = False


@dataclass(frozen=True)
class ScvxAnswer:
    """SCVx* from a job's proposal (the job's second answer).

    Attributes:
        job_id: the job's id.
        result: the `ScpResult`, or None: no valid proposal, or the run was cancelled.
    """

    job_id: int
    result: ScpResult | None = None


@dataclass(frozen=True)
class Failure:
    """A job that raised in the worker (the planner then works in line).

    Attributes:
        job_id: the job's id.
        text: the exception, in words.
    """

    job_id: int
    text: str


Answer = Proposal | ScvxAnswer | Failure


class CancelSlot:
    """The worker's shared cancel slot: the id of the job whose run must stop (0: none).

    Built on the spawn context's shared integer, so it is passed to the worker at its start.
    """

    def __init__(self, ctx: BaseContext) -> None:
        self._value = ctx.Value("q", 0, lock=False)

    def cancel(self, job_id: int) -> None:
        """Stop the run of job `job_id` at its next iteration."""
        self._value.value = int(job_id)

    def cancelled(self, job_id: int) -> bool:
        """Whether job `job_id`'s run was cancelled."""
        return self._value.value == int(job_id)


@dataclass(frozen=True)
class CancellableDeadline(Deadline):
    """A deadline that has also passed once the planner cancels job `job_id` (`slot`)."""

    slot: CancelSlot | None = None
    job_id: int = 0

    def passed(self) -> bool:
        return (self.slot is not None and self.slot.cancelled(self.job_id)) \
            or super().passed()
