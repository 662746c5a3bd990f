"""A worker process that makes the learned proposal while the planner solves SCVx* from CVX.

In `warm_start auto`, SCVx* from CVX is solved whenever ART may be run (it is the fallback, the
retry and the plan ART must beat), so the proposal and that solve need not wait for each
other. In one process they cannot overlap: both hold Python's lock for most of their time
(measured with a second thread: CPU time = wall time, no gain). This worker is a second
process, started once (spawned: it imports torch and loads the model itself) and fed one job
per plan through a pipe: the plan's configuration, the model's file and checksum, the request,
the CVX solution and the time left. It rebuilds the same transfer problem
(`planning.transfer.Transfers`) and runs the same learned step
(`planning.learned.learned_warm_start`) as the planner would in line, so the decision is the
same bit for bit (tested), only made on another core.

A plan job may also ask for SCVx* from the proposal (`solve_art`): right after answering with
the decision, the worker solves SCVx* from a valid proposal with the planner's own options
(from where the planner would: the proposal's terminal warm start) and answers again with the
result. The planner needs that run where the check accepted the proposal, where SCVx* from CVX
did not converge (the retry) or with `also_solve_from_art`; made in the worker it overlaps
SCVx* from CVX instead of following it. Where the planner does not need it, it cancels the run
(`dismiss`: the run stops at its next iteration) and the answer is drained before the next
job. The run is the planner's run, so its result is the in-line one, bit for bit (tested).

Only a model loaded from a file (`ArtWarmStart` with a path) can be sent this way; any other
provider, a worker that cannot start, fails or answers too late is reported through
`ProposalProcess.error` and the planner proposes in line instead.
"""
from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import sys
import threading
import time
from typing import Any, Iterator

from art_guidance.deadline import Deadline
from art_guidance.optim.results import ScpStatus
from art_guidance.planning.worker.serve import serve
from art_guidance.planning.worker.messages import (
    CancelSlot, Failure, ModelKey, PlanJob, Proposal, ScvxAnswer, WarmUpJob,
)

STARTUP_TIMEOUT_S = 120.0  # importing torch and loading the model in the spawned process
NO_DEADLINE_TIMEOUT_S = 120.0  # the longest wait for a job without a deadline
# A worker that failed to start is started again after RESTART_AFTER_S, doubled after every
# further failed start up to RESTART_MAX_S (reset by a start that succeeds) [s].
RESTART_AFTER_S = 5.0
RESTART_MAX_S = 300.0
LOCK_WAIT_S = 1.0  # a job waits this long for the one before it to be collected [s]
CLOSE_WAIT_S = 5.0  # `close` waits this long for a job in flight, then stops the worker [s]
# A cancelled SCVx* run in the worker stops at its next iteration (tens of ms); the next job
# awaits its answer at most DRAIN_SHARE of that job's time left (DRAIN_WAIT_S without a
# deadline), else the worker is taken for stalled: stopped, and started anew on a later job.
DRAIN_WAIT_S = 5.0
DRAIN_SHARE = 0.05


def restart_delay_s(failed_starts: int) -> float:
    """How long after its `failed_starts`-th failed start in a row (>= 1) the worker is
    started again [s]: exponential backoff, RESTART_AFTER_S doubled up to RESTART_MAX_S."""
    return min(RESTART_AFTER_S * 2.0 ** max(failed_starts - 1, 0), RESTART_MAX_S)


def model_key(provider: object) -> ModelKey | None:
    """What the worker needs to load the same model, or None when the provider is not a model
    loaded from a checked file."""
    path = getattr(provider, "path", "")
    sha = getattr(provider, "sha256", "")
    if not path or not sha or not hasattr(provider, "reward_scales"):
        return None
    return ModelKey(str(path), str(sha), int(getattr(provider, "threads", 1)),
                    tuple(float(s) for s in provider.reward_scales),
                    str(getattr(provider, "runtime", "torch")))


class ProposalProcess:
    """The worker process of one `GuidancePipeline`.

    A plan never waits for the worker to start: `submit` on a worker that is not running
    starts it (the model loads in the background) and declines the job, and so does every
    `submit` until the worker is ready; `start` starts it and waits (a node's configure step).
    A worker that failed to start (its model did not load, it died loading) is started again
    with exponential backoff (`restart_delay_s`): meanwhile jobs are declined with the reason.

    Every `submit` that returns True must be followed by `collect` or `abandon` (the job holds
    the worker until then); `close` stops the worker within `CLOSE_WAIT_S` whatever a plan does.
    A job submitted with `solve_art` has a second answer, SCVx* from the proposal:
    `scvx_result` waits for it, `dismiss` cancels the run (its answer is drained before the
    next job is sent).

    Attributes:
        error: why the last job was declined or failed ("" = it was not): the planner then
            proposes in line; a failed worker is stopped and started anew on the next job.
        deaths: how many times a running worker was found dead, broken or stalled (no answer
            by the plan's deadline: a stopped, swapped-out or starved process; it is stopped
            and started again on the next job).
        stalls: how many of those were stalls.
        scvx_runs: (made, taken): SCVx* runs from the proposal the worker answered with, and
            those of them a plan took (`scvx_result`).
    """

    def __init__(self) -> None:
        self._proc: Any = None
        self._conn: Any = None
        self._lock = threading.Lock()  # one job at a time
        self._warming = False  # a warm-up job was sent and not yet answered
        self._start_failed_at: float | None = None  # time.monotonic() of a failed start
        self._slot: CancelSlot | None = None  # the running worker's: cancel a job's run
        self._follow: int | None = None  # the job whose second answer is still in the pipe
        self._job_ids = itertools.count(1)
        self._failed_starts = 0  # failed starts in a row
        self.error = ""
        self.deaths = 0
        self.stalls = 0
        self.scvx_runs = (0, 0)

    @property
    def alive(self) -> bool:
        """Whether the worker process runs."""
        return self._proc is not None and self._proc.is_alive()

    def start(self, config_json: dict, config_sha256: str, model: ModelKey,
              timeout_s: float = STARTUP_TIMEOUT_S) -> bool:
        """Start the worker (if needed), load the model in it and wait until it is ready;
        False (see `error`) if it could not."""
        with self._lock:
            if not self.alive:
                self._launch(WarmUpJob(config_json, config_sha256, model))
            return self._ready(timeout_s)

    @property
    def state(self) -> str:
        """The worker in words, for the diagnostics: running, loading, or stopped and when it
        is started again."""
        if self.alive:
            return "loading the model" if self._warming else "running"
        if self._start_failed_at is not None:
            left = self._restart_in_s()
            return (f"stopped after {self._failed_starts} failed start(s) in a row ("
                    f"{self.error}); started again " +
                    (f"in {left:.0f} s" if left > 0 else "on the next job"))
        return "stopped" + (f" ({self.error})" if self.error else "") + \
            "; started on the next job"

    def _restart_in_s(self) -> float:
        if self._start_failed_at is None:
            return 0.0
        due = self._start_failed_at + restart_delay_s(self._failed_starts)
        return max(due - time.monotonic(), 0.0)

    def submit(self, job: PlanJob, solve_art: bool = False) -> int | None:
        """Send a plan job if the worker is ready: its id, or None if not (see `error`): the
        caller proposes in line. After an id the caller must `collect` the answer (or
        `abandon` the job): the worker serves one job at a time. With `solve_art` the worker
        also solves SCVx* from a valid proposal after answering (`scvx_result`, `dismiss`)."""
        if not self._lock.acquire(timeout=LOCK_WAIT_S):
            self.error = "the worker is still held by an earlier job"
            return None
        sent = None
        try:
            sent = self._send(job.numbered(next(self._job_ids), solve_art))
        except Exception as exc:
            self._fail(f"could not send the job: {type(exc).__name__}: {exc}")
        finally:
            if sent is None:
                self._lock.release()
        return sent

    def _send(self, job: PlanJob) -> int | None:
        """`submit` with the lock held: the job's id once it is sent."""
        if self._follow is not None and self.alive:  # a dismissed run's answer: drain it
            self._follow = None
            wait = DRAIN_WAIT_S if job.time_left_s is None \
                else min(DRAIN_WAIT_S, DRAIN_SHARE * max(job.time_left_s, 0.0))
            answer = self._receive(wait)
            if answer is None:
                self.error = f"a cancelled SCVx* run did not stop: {self.error}"
            elif isinstance(answer, ScvxAnswer) and answer.result is not None:  # ended first
                self.scvx_runs = (self.scvx_runs[0] + 1, self.scvx_runs[1])
        if not self.alive:
            if self._proc is not None:  # it stopped by itself since the last job
                if self._warming:
                    self._fail("the worker process died loading the model")
                    self._start_failed()
                else:
                    self._died("the worker process died")
            if self._restart_in_s() <= 0.0:
                self._launch(job.warm_up())
                self.error = "the worker process is starting"
            return None
        if not self._ready(0.0):
            return None
        self._conn.send(job)
        self._follow = job.job_id if job.solve_art else None
        return job.job_id

    def collect(self, timeout_s: float) -> Proposal | None:
        """The answer to the submitted job, or None (see `error`)."""
        try:
            answer = self._receive(timeout_s)
            if not isinstance(answer, Proposal):
                self._follow = None
                return None
            return answer
        finally:
            self._lock.release()

    def scvx_result(self, job_id: int, timeout_s: float) -> Any:
        """SCVx* from the proposal of job `job_id` (its second answer, an `ScpResult`), or
        None: not made (no valid proposal, the worker failed: see `error`), or the answer was
        drained meanwhile by a later job. The caller then solves it in line."""
        if not self._lock.acquire(timeout=LOCK_WAIT_S):
            return None
        try:
            if self._follow != job_id or not self.alive:
                return None
            self._follow = None
            answer = self._receive(timeout_s)
            if not isinstance(answer, ScvxAnswer) or answer.job_id != job_id \
                    or answer.result is None:
                return None
            self.scvx_runs = (self.scvx_runs[0] + 1, self.scvx_runs[1] + 1)
            return answer.result
        finally:
            self._lock.release()

    def dismiss(self, job_id: int) -> None:
        """The planner does not need SCVx* from the proposal of job `job_id`: cancel the run
        (it stops at its next iteration; the next job drains its answer)."""
        slot = self._slot
        if self._follow == job_id and slot is not None:
            slot.cancel(job_id)

    def abandon(self, why: str) -> None:
        """Give up the submitted job (the caller failed before collecting it): the worker,
        busy with it, is stopped and started anew on the next job."""
        try:
            self._fail(f"job abandoned: {why}")
        finally:
            self._lock.release()

    def close(self) -> None:
        """Stop the worker (it also stops by itself when this process ends). A job still in
        flight after `CLOSE_WAIT_S` does not hold the shutdown: the worker is killed."""
        held = self._lock.acquire(timeout=CLOSE_WAIT_S)
        try:
            if self._slot is not None and self._follow is not None:
                self._slot.cancel(self._follow)  # a run still going stops at its next iteration
            self._stop(graceful=held)
        finally:
            if held:
                self._lock.release()

    # ------------------------------------------------------------------ internals
    def _ready(self, timeout_s: float) -> bool:
        """Whether the warm-up has been answered (waiting up to `timeout_s` for it)."""
        if not self._warming:
            return True
        if timeout_s <= 0.0 and not self._conn.poll(0.0):
            self.error = "the worker process is loading the model"
            return False
        if self._receive(timeout_s, dying=False) is None:
            self._start_failed()
            return False
        self._warming = False
        self._start_failed_at, self._failed_starts = None, 0
        return True

    def _start_failed(self) -> None:
        """Count a failed start: the worker is not started again before `restart_delay_s`."""
        self._start_failed_at = time.monotonic()
        self._failed_starts += 1

    def _receive(self, timeout_s: float, dying: bool = True) -> Proposal | ScvxAnswer | None:
        """The worker's answer within `timeout_s`, or None (see `error`); a worker found dead
        counts in `deaths` when `dying` (not while it loads: that is a failed start)."""
        try:
            if not self._conn.poll(max(timeout_s, 0.0)):
                why = f"no answer within {max(timeout_s, 0.0):.2f} s"
                if dying:  # a running worker that does not answer in time: a stall
                    self.stalls += 1
                    self._died(f"the worker stalled ({why}): stopped, started anew on a "
                               "later job")
                else:
                    self._fail(why)
                return None
            answer = self._conn.recv()
        except Exception as exc:  # the worker died (EOF) or the pipe broke
            why = f"the worker stopped: {type(exc).__name__}: {exc}"
            if dying:
                self._died(why)
            else:
                self._fail(why)
            return None
        if isinstance(answer, Failure):
            self._fail(f"the worker failed: {answer.text}")
            return None
        self.error = ""
        return answer

    def _launch(self, warm_up: WarmUpJob) -> None:
        """Spawn the worker and send it its warm-up job (not waited for)."""
        self._stop(graceful=False)
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with threads
        parent, child = ctx.Pipe()
        self._slot = CancelSlot(ctx)
        proc = ctx.Process(target=serve, args=(child, self._slot), name="art_proposal",
                           daemon=True)
        with _main_left_out():
            proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        parent.send(warm_up)
        self._warming = True

    def _fail(self, why: str) -> None:
        self.error = why
        self._stop(graceful=False)  # a late or broken worker is not waited for

    def _died(self, why: str) -> None:
        self.deaths += 1
        self._fail(why)

    def _stop(self, graceful: bool = False) -> None:
        proc, conn, self._proc, self._conn = self._proc, self._conn, None, None
        self._warming, self._follow = False, None
        if conn is not None:
            if graceful:
                try:
                    conn.send(None)
                except Exception:  # already gone
                    pass
            conn.close()
        if proc is not None:
            if graceful:
                proc.join(timeout=2.0)
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=2.0)


class WorkerScvx:
    """SCVx* from the proposal of one plan, solved in the proposal worker: taken where the plan
    needs it (`result`), cancelled otherwise (`dismiss`, or leaving the `with` block)."""

    def __init__(self, worker: ProposalProcess, job_id: int) -> None:
        self._worker, self._job_id = worker, job_id
        self._taken = False

    def result(self, deadline: Deadline | None) -> Any:
        """The worker's run (an `ScpResult`, waited for until the plan's deadline, not past
        it), or None: the plan solves it in line. A run the deadline stopped (TIMEOUT, as the
        planner's own runs) is a hit of the plan's deadline."""
        self._taken = True
        wait = NO_DEADLINE_TIMEOUT_S if deadline is None else max(deadline.left_s(), 0.0)
        result = self._worker.scvx_result(self._job_id, wait)
        if result is not None and result.status is ScpStatus.TIMEOUT and deadline is not None:
            deadline.mark_hit()
        return result

    def dismiss(self) -> None:
        """Cancel the run if the plan did not take it."""
        if not self._taken:
            self._worker.dismiss(self._job_id)

    def __enter__(self) -> "WorkerScvx":
        return self

    def __exit__(self, *exc: object) -> None:
        self.dismiss()


@contextlib.contextmanager
def _main_left_out() -> Iterator[None]:
    """The worker started without this process's main module: spawn imports the parent's
    `__main__` again in the child (the node's: rclpy and the whole ROS side, ~0.3 s of CPU a
    start) unless it has neither a spec nor a file, and the worker needs `serve` alone."""
    main = sys.modules.get("__main__")
    saved = {name: getattr(main, name) for name in ("__spec__", "__file__")
             if hasattr(main, name)}
    try:
        if main is not None:
            main.__spec__ = None
            if "__file__" in saved:
                del main.__file__
        yield
    finally:
        for name, value in saved.items():
            setattr(main, name, value)
