"""The proposal worker (`planning.worker`): a worker that cannot start is reported and started
again with exponential backoff (the plans meanwhile propose in line); a plan that fails while
its proposal is out frees the worker; `close` is bounded whatever a job does; a job that fails,
that the worker finds past its deadline, or that it dies or stalls holding is answered in
words, never with an exception out of the planner."""
from __future__ import annotations

import dataclasses
import multiprocessing
import os
import re
import signal
import time

import pytest

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig
from art_guidance.optim import Scvx
from art_guidance.optim.problem import SubproblemOptions
from art_guidance.planning import GuidancePipeline
from art_guidance.planning.worker import process as proposal_process
from art_guidance.planning.worker.process import ProposalProcess, model_key, restart_delay_s
from art_guidance.planning.worker.serve import serve
from art_guidance.planning.worker.messages import (
    Failure, PlanJob, Proposal, ScvxAnswer, WarmUpJob,
)
from helpers.shipped import heldout_requests


def test_restart_delay_doubles_up_to_its_cap():
    delays = [restart_delay_s(n) for n in range(1, 10)]
    assert delays[:4] == [5.0, 10.0, 20.0, 40.0]
    assert delays[-1] == proposal_process.RESTART_MAX_S
    assert all(b >= a for a, b in zip(delays, delays[1:]))


def test_a_failed_worker_is_started_again_with_backoff(tmp_path, monkeypatch):
    config = GuidanceConfig.load()
    model = (str(tmp_path / "missing.pt"), "0" * 64, 1, (1.0,), "torch")
    worker = ProposalProcess()
    try:
        assert worker.start(config.to_json(), config.sha256(), model) is False
        assert "missing.pt" in worker.error and not worker.alive
        assert "1 failed start(s)" in worker.state and "started again in 5 s" in worker.state
        job = PlanJob(0, config.to_json(), config.sha256(), model, None, None, None, None,
                      SubproblemOptions())
        assert worker.submit(job) is None and not worker.alive  # declined, nothing spawned
        assert "missing.pt" in worker.error  # the reason stays
        monkeypatch.setattr(proposal_process, "RESTART_AFTER_S", 0.0)
        assert worker.submit(job) is None and worker.alive  # started again, in the background
        assert worker.error == "the worker process is starting"
        assert worker.state == "loading the model"
        deadline = time.monotonic() + 60.0
        while worker.alive and time.monotonic() < deadline:  # it fails again
            assert worker.submit(job) is None
            time.sleep(0.2)
        monkeypatch.setattr(proposal_process, "RESTART_AFTER_S", 5.0)
        assert worker.submit(job) is None and not worker.alive  # noticed, not restarted
        assert "missing.pt" in worker.error or "died loading" in worker.error
        assert "2 failed start(s)" in worker.state, worker.state
        assert re.search(r"started again in (8|9|10) s", worker.state), worker.state  # 2 x 5 s
        assert worker.deaths == 0  # failed starts are not deaths
    finally:
        worker.close()


@pytest.fixture(scope="module")
def concurrent() -> GuidancePipeline:
    config = GuidanceConfig.load()
    config = config.replace(planning=dataclasses.replace(config.planning,
                                                         propose_concurrently=True))
    pipeline = GuidancePipeline(config, provider=ArtWarmStart.load(default_model_path("chance")),
                                deadline_s=4.0)
    assert pipeline.start_proposal_worker(), pipeline.proposal_worker_error
    yield pipeline
    pipeline.close()


def test_a_plan_that_fails_while_the_proposal_is_out_frees_the_worker(concurrent, monkeypatch):
    """SCVx* from CVX raises while the worker makes the proposal: the exception reaches the
    caller, the worker is given up (and stopped), and the next plan completes within its
    deadline (4 s; slack 2 s, for the overrun of one SCVx* iteration on a slow machine)
    instead of waiting for the worker forever."""
    requests = heldout_requests(12, DEFAULT_MODELS["chance"])
    request = next(r for r in requests if concurrent.plan(r).proposal is not None)
    assert concurrent.proposal_worker_error == ""  # the worker made that proposal

    def fail(*args, **kwargs):
        raise RuntimeError("injected solver failure")

    with monkeypatch.context() as patch:
        patch.setattr(Scvx, "solve", fail)
        with pytest.raises(RuntimeError, match="injected"):
            concurrent.plan(request)
    assert "job abandoned" in concurrent.proposal_worker_error
    t0 = time.perf_counter()
    result = concurrent.plan(request)
    assert time.perf_counter() - t0 <= 4.0 + 2.0
    assert result.scp.feasible and result.proposal is not None, result.warm_start_reason


@pytest.mark.parametrize("when", ["after a plan", "mid-job"])
def test_a_stalled_worker_never_holds_a_plan_past_its_deadline(concurrent, monkeypatch, when):
    """The worker stopped (SIGSTOP: a swapped-out or starved process behaves alike) after a
    plan, or while it makes the plan's proposal: the plan is published by its deadline (4 s;
    slack 1 s for one SCVx* iteration's overrun and the kill) with a usable plan (SCVx* from
    CVX, solved meanwhile), the stall is counted as a death with its reason, and a later plan
    has a worker again."""
    import os
    import signal

    # ready (an earlier test may have left it loading: a loading worker declines jobs)
    assert concurrent.start_proposal_worker(), concurrent.proposal_worker_error
    worker = concurrent.producers.worker()
    requests = heldout_requests(12, DEFAULT_MODELS["chance"])
    request = next(r for r in requests if concurrent.plan(r).proposal is not None
                   and concurrent.proposal_worker_error == "")  # the worker proposed
    pid, deaths, stalls = worker._proc.pid, worker.deaths, worker.stalls
    try:
        if when == "after a plan":
            os.kill(pid, signal.SIGSTOP)
        else:
            solve = Scvx.solve

            def stop_then_solve(self, *args, **kwargs):
                os.kill(pid, signal.SIGSTOP)
                return solve(self, *args, **kwargs)

            monkeypatch.setattr(Scvx, "solve", stop_then_solve)
        t0 = time.perf_counter()
        result = concurrent.plan(request)
        took_s = time.perf_counter() - t0
        monkeypatch.undo()
    finally:
        try:
            os.kill(pid, signal.SIGCONT)  # a worker not given up is let go on
        except ProcessLookupError:
            pass
    assert took_s <= 4.0 + 1.0, took_s
    assert result.scp.feasible, result.scp.status
    assert worker.deaths == deaths + 1 and worker.stalls == stalls + 1
    assert "stalled" in concurrent.proposal_worker_error
    assert worker._proc is None or worker._proc.pid != pid  # the stopped one is gone
    assert concurrent.start_proposal_worker(), concurrent.proposal_worker_error
    assert any(concurrent.plan(r).proposal is not None for r in requests)
    assert concurrent.proposal_worker_error == ""


def test_close_is_bounded_while_a_job_is_out(concurrent, monkeypatch):
    """A job never collected (a caller stuck elsewhere) does not hold the shutdown: `close`
    kills the worker after CLOSE_WAIT_S."""
    monkeypatch.setattr(proposal_process, "CLOSE_WAIT_S", 0.5)
    worker = ProposalProcess()
    config = concurrent.config
    from art_guidance.planning.worker.process import model_key

    assert worker.start(config.to_json(), config.sha256(), model_key(concurrent.provider))
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    cvx = concurrent.transfer(request).problem.cvx()
    assert worker.submit(PlanJob(0, config.to_json(), config.sha256(),
                                 model_key(concurrent.provider), request, cvx, None, None,
                                 SubproblemOptions()))
    t0 = time.perf_counter()
    worker.close()  # this thread holds the job: close waits 0.5 s, then kills
    assert time.perf_counter() - t0 < 5.0 and not worker.alive


def test_the_worker_ignores_sigint(concurrent):
    """Ctrl-C reaches the node's whole process group: the worker keeps serving (its planner
    stops it), so no KeyboardInterrupt traceback reaches the node's output."""
    import os
    import signal

    worker = concurrent.producers.worker()
    assert worker.alive or concurrent.start_proposal_worker(), concurrent.proposal_worker_error
    os.kill(worker._proc.pid, signal.SIGINT)
    time.sleep(1.0)
    assert worker.alive
    request = heldout_requests(12, DEFAULT_MODELS["chance"])
    assert any(concurrent.plan(r).proposal is not None for r in request)
    assert concurrent.proposal_worker_error == ""


def test_a_cancel_stops_its_own_job_only():
    """The cancel is per job: the slot names one job id, and only that job's deadline has
    passed (a later job's run is not touched by an earlier dismiss)."""
    import math
    import multiprocessing

    from art_guidance.planning.worker.messages import CancellableDeadline, CancelSlot

    slot = CancelSlot(multiprocessing.get_context("spawn"))
    first, second = (CancellableDeadline(math.inf, slot=slot, job_id=j) for j in (1, 2))
    assert not first.passed() and not second.passed()
    slot.cancel(1)
    assert first.passed() and not second.passed()
    slot.cancel(2)
    assert second.passed()


@pytest.fixture(scope="module")
def pipeline() -> GuidancePipeline:
    """The CVX-only pipeline of the default configuration."""
    return GuidancePipeline(GuidanceConfig.load())


@pytest.fixture(scope="module")
def shipped():
    """The shipped chance-constrained model (as the node loads it) and its worker key."""
    provider = ArtWarmStart.load(default_model_path("chance"))
    return provider, model_key(provider)


def _serve_here(jobs: list) -> list:
    """Run the worker's loop in this process over a real pipe: `jobs` are queued, then the
    end of input; returns the answers in order. SIGINT, which the loop ignores, is restored."""
    parent, child = multiprocessing.Pipe()
    for job in jobs + [None]:
        parent.send(job)
    before = signal.getsignal(signal.SIGINT)
    try:
        serve(child)
    finally:
        signal.signal(signal.SIGINT, before)
    answers = []
    while parent.poll(0.0):
        answers.append(parent.recv())
    return answers


def test_a_deadline_the_worker_finds_passed_is_said_in_its_answer(pipeline, shipped):
    """The worker's learned step finds the plan's deadline passed (no time left): its answer
    says so in data (`Proposal.deadline_hit`), not only in the reason's words, and the planner
    marks its own deadline from it; a job with time left says no hit."""
    from art_guidance.deadline import Deadline

    _, key = shipped
    config = pipeline.config
    base = (config.to_json(), config.sha256())
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    cvx = pipeline.transfer(request).problem.cvx()
    answers = _serve_here([
        WarmUpJob(*base, key),
        PlanJob(5, *base, key, request, cvx, 0.0, False, SubproblemOptions()),
        PlanJob(6, *base, key, request, cvx, 600.0, False, SubproblemOptions()),
    ])
    assert [type(a) for a in answers] == [Proposal] * 3, answers
    assert answers[1].deadline_hit and "passed before ART" in answers[1].learned.reason
    assert not answers[2].deadline_hit
    planner = Deadline.after(600.0)
    assert not planner.hit
    planner.mark_hit()
    assert planner.hit


def test_a_failing_job_is_answered_with_its_error(tmp_path, pipeline, shipped):
    """The worker's loop answers a job it cannot do (its model file missing; a plan job whose
    SCVx* options are not options) with the error in words and goes on with the next job: the
    planner then proposes, or solves, in line."""
    provider, key = shipped
    config = pipeline.config
    base = (config.to_json(), config.sha256())
    missing = (str(tmp_path / "missing.onnx"), *key[1:])
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    cvx = pipeline.transfer(request).problem.cvx()
    answers = _serve_here([
        WarmUpJob(*base, missing),
        WarmUpJob(*base, key),
        PlanJob(7, *base, key, request, cvx, None, False, "no_such_options", solve_art=True),
    ])
    assert len(answers) == 4, answers
    assert isinstance(answers[0], Failure) and "missing.onnx" in answers[0].text
    assert answers[1] == Proposal(0)
    assert isinstance(answers[2], Proposal) and answers[2].job_id == 7
    assert answers[2].learned.dv is not None, answers[2].learned.reason
    assert isinstance(answers[3], Failure) and answers[3].job_id == 7
    assert answers[3].text.startswith("AttributeError: "), answers[3].text
    assert not any(isinstance(a, ScvxAnswer) for a in answers)


def test_a_worker_that_stalls_or_dies_holding_a_job(pipeline, shipped):
    """A worker that does not answer within the wait is stopped as stalled ("no answer
    within", a death and a stall, counted); one that dies holding a job is found dead when its
    answer is collected (a death, counted).
    Either way the caller gets None and the reason, and the next job starts a new worker.
    The worker is held with SIGSTOP, so the job cannot be answered before it is stopped."""
    _, key = shipped
    config = pipeline.config
    job = PlanJob(0, config.to_json(), config.sha256(), key, None, None, None, None,
                  SubproblemOptions())
    worker = ProposalProcess()
    try:
        for ending in ("late", "dead"):
            assert worker.start(config.to_json(), config.sha256(), key), worker.error
            pid = worker._proc.pid
            os.kill(pid, signal.SIGSTOP)
            assert worker.submit(job) is not None
            if ending == "late":
                assert worker.collect(0.5) is None  # a stall: counted with the deaths
                assert worker.error == ("the worker stalled (no answer within 0.50 s): "
                                        "stopped, started anew on a later job")
                assert worker.deaths == 1 and worker.stalls == 1
            else:
                os.kill(pid, signal.SIGKILL)  # its end of the pipe closes as it dies
                assert worker.collect(30.0) is None
                # EOF, or a reset where the job was still unread in the dead worker's socket
                assert re.match(r"the worker stopped: (EOFError|ConnectionResetError)",
                                worker.error), worker.error
                assert worker.deaths == 2 and worker.stalls == 1
            assert not worker.alive
        assert worker.submit(job) is None and worker.alive  # started again
        assert worker.error == "the worker process is starting"
    finally:
        worker.close()
    assert not worker.alive
