"""The proposal worker process's side (`worker.process` starts it): one job in, its answers
out (`worker.messages`), until the pipe closes or None comes.

The worker chooses its numerics once, at its warm-up (`kernels.prepare` with the planner's
`numerics`), where it also runs the model once on a canned transfer (`planning.warm_up`: the
runtime's first inference is not the first plan's). It rebuilds the planner's transfer problem
(`planning.transfer.Transfers`) and runs the planner's learned step
(`planning.learned.timed_learned_warm_start`) and, for a job with `solve_art`, the planner's
SCVx* run from the proposal, so its answers are the in-line ones bit for bit (tested).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from art_guidance import kernels
from art_guidance.deadline import Deadline
from art_guidance.planning.worker.messages import (
    CancellableDeadline, CancelSlot, Failure, ModelKey, PlanJob, Proposal, ScvxAnswer,
    WarmUpJob,
)

if TYPE_CHECKING:
    from art_guidance.config import GuidanceConfig
    from art_guidance.optim.problem import SubproblemPool
    from art_guidance.planning.transfer import Transfer, Transfers


@dataclass
class _Loaded:
    """The worker's model and configuration (one pair at a time, by `key`)."""

    key: tuple[str, ModelKey]
    provider: Any  # `art.provider.ArtWarmStart`
    config: GuidanceConfig
    transfers: Transfers


@dataclass
class _State:
    """What the worker keeps between jobs: the loaded pair, the last plan job's transfer and
    deadline (for SCVx* from its proposal), its own subproblems."""

    loaded: _Loaded | None = None
    plan: tuple[Transfer, Deadline | None] | None = None
    pool: SubproblemPool | None = None


def serve(conn: Any, slot: CancelSlot | None = None) -> None:
    """The worker's loop (module docstring).

    SIGINT is ignored: a Ctrl-C in a terminal (or `ros2 launch`'s) reaches the whole process
    group, and the worker is stopped by its planner (`close`) or when the pipe closes, not with
    a KeyboardInterrupt traceback in the node's output."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    state = _State()
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):  # the planner's process is gone
            return
        if job is None:
            return
        answer = _answer(job.job_id, lambda: _run(job, state))
        if not _send(conn, answer):
            return
        if not isinstance(job, PlanJob) or not job.solve_art:
            continue
        # the second answer: SCVx* from the proposal (None: not made or cancelled)
        follow = _answer(job.job_id, lambda: ScvxAnswer(job.job_id,
                                                        _solve_art(job, state, answer, slot)))
        if not _send(conn, follow):
            return


def _answer(job_id: int, make: Any) -> Any:
    """`make()`, or the `Failure` it raised (reported to the planner, which works in line)."""
    try:
        return make()
    except BaseException as exc:
        return Failure(job_id, f"{type(exc).__name__}: {exc}")


def _send(conn: Any, answer: Any) -> bool:
    try:
        conn.send(answer)
        return True
    except (EOFError, OSError):
        return False


def _run(job: WarmUpJob | PlanJob, state: _State) -> Proposal:
    """One job: a warm-up loads the model; a plan job makes the learned step."""
    from art_guidance.art.provider import ArtWarmStart
    from art_guidance.config import GuidanceConfig
    from art_guidance.planning.learned import CvxSafety, timed_learned_warm_start
    from art_guidance.planning.transfer import Transfers
    from art_guidance.planning.warm_up import seed_request, warm_up

    key = (job.config_sha256, job.model)
    if state.loaded is None or state.loaded.key != key:
        path, sha, threads, scales, runtime = job.model
        provider = ArtWarmStart.load(path, expected_sha256=sha, threads=threads,
                                     reward_scales=scales, runtime=runtime)
        config = GuidanceConfig.from_json(job.config_json)
        # the numerics, chosen once at the worker's start: loaded, or the numpy path while a
        # background process compiles them (never a compile before the first fix)
        kernels.prepare(config.planning.numerics)
        state.loaded = _Loaded(key, provider, config,
                               Transfers(config.scenario, config.uncertainty))
    loaded = state.loaded
    if isinstance(job, WarmUpJob):  # the runtime's first inference, not the first plan's
        config = loaded.config
        warm_up(loaded.provider, loaded.transfers.get(seed_request(config.scenario)).problem,
                config.planning)
        return Proposal(job.job_id)
    left_s = job.time_left_s  # the plan's deadline, on this process's clock
    deadline = None if left_s is None else Deadline.after(left_s)
    transfer = loaded.transfers.get(job.request)
    state.plan = (transfer, deadline)  # for SCVx* from the proposal (`_solve_art`)
    learned, wall_ms = timed_learned_warm_start(
        loaded.provider, transfer, job.cvx, loaded.config.planning, deadline,
        CvxSafety(job.cvx, transfer.safety, job.cvx_safe))
    return Proposal(job.job_id, learned, wall_ms, deadline is not None and deadline.hit)


def _solve_art(job: PlanJob, state: _State, answer: Any, slot: CancelSlot | None) -> Any:
    """SCVx* from the job's proposal as the planner would solve it (`planning.runs`), or None:
    no valid proposal, or the planner cancelled the run (before or during it)."""
    from art_guidance.optim.problem import SubproblemPool
    from art_guidance.planning.request import WarmStartSource

    def cancelled() -> bool:
        return slot is not None and slot.cancelled(job.job_id)

    if not isinstance(answer, Proposal) or answer.learned.dv is None or cancelled():
        return None
    learned, config = answer.learned, state.loaded.config
    transfer, deadline = state.plan
    if deadline is not None and learned.source is WarmStartSource.ART:
        # the first run of the plan: a share of what is left, the rest for the run from CVX
        deadline = deadline.share(config.planning.art_deadline_share)
    at_s = math.inf if deadline is None else deadline.at_s
    until = Deadline(at_s) if slot is None \
        else CancellableDeadline(at_s, slot=slot, job_id=job.job_id)
    if state.pool is None:
        state.pool = SubproblemPool()  # the worker's own, as a pipeline's
    scvx = transfer.scvx(config, job.subproblem, state.pool)
    result = scvx.solve(learned.scvx_start, deadline=until)
    return None if cancelled() else result
