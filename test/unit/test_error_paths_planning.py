"""Planning error paths that the other planning tests leave out: requests and settings that
must be refused naming the field, a learned step without a model or with a broken terminal
warm start, two failed SCVx* runs, and the proposal worker process when a job fails, when it
answers late and when it dies holding a job. Each is an error in words, never an exception out
of the planner."""
from __future__ import annotations

import multiprocessing
import os
import re
import signal
import types

import numpy as np
import pytest
from helpers.shipped import heldout_requests

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus, Trajectory
from art_guidance.optim.problem import SubproblemOptions
from art_guidance.planning import (
    GuidancePipeline, PlanRequest, WarmStartProposal, WarmStartSource,
)
from art_guidance.planning.choice import better_plan
from art_guidance.planning.learned import carried_warm_start, learned_warm_start
from art_guidance.planning.worker.process import ProposalProcess, model_key
from art_guidance.planning.worker.serve import serve
from art_guidance.planning.worker.messages import (
    Failure, PlanJob, Proposal, ScvxAnswer, WarmUpJob,
)
from art_guidance.guidance.replan import check_window
from art_guidance.planning.request import RolloutContext

SCENARIO = ScenarioConfig()
CHIEF = np.array(SCENARIO.chief_oe)
ROE0 = roe_from_rtn_linear(CHIEF, np.array(SCENARIO.rtn0_nominal))
TARGET = np.array(SCENARIO.waypoints_rtn["plus_vbar"])


@pytest.fixture(scope="module")
def pipeline() -> GuidancePipeline:
    """The CVX-only pipeline of the default configuration."""
    return GuidancePipeline(GuidanceConfig.load())


@pytest.fixture(scope="module")
def shipped():
    """The shipped chance-constrained model (as the node loads it) and its worker key."""
    provider = ArtWarmStart.load(default_model_path("chance"))
    return provider, model_key(provider)


# --------------------------------------------------------------------------- requests, settings
@pytest.mark.parametrize("field, value, message", [
    ("warm_start", "bogus", "warm_start: must be one of ('auto', 'cvx', 'art')"),
    ("n_nodes", 2, "n_nodes: must be in [3, 1000] (got 2)"),
    ("koz_switch_node", -1, "koz_switch_node: must be >= 0 (got -1)"),
    ("context", "the last steps", "context: must be a RolloutContext or None (got 'str')"),
    ("carry", [0.0, 1.0], "carry: must be a CarriedPlan or None (got 'list')"),
])
def test_a_request_field_out_of_its_domain_is_named(field, value, message):
    with pytest.raises(InputError, match=re.escape(message)) as exc:
        PlanRequest(CHIEF, ROE0, TARGET, **{field: value})
    assert exc.value.field == field


def test_a_context_with_an_undefined_reward_is_refused():
    roe = np.tile(ROE0, (2, 1))
    with pytest.raises(InputError, match="context reward0_mps: must be finite"):
        RolloutContext(roe, np.zeros((2, 6)), np.zeros((2, 3)), float("nan"))


@pytest.mark.parametrize("change", [
    lambda data: data.pop("target_rtn"),
    lambda data: data.update(roe0_m="six numbers"),
    lambda data: data.update(warm_start="bogus"),
    lambda data: data.update(context={"roe_m": [1.0]}),
])
def test_a_malformed_request_json_is_an_input_error(change):
    """`PlanRequest.from_json` (a recorded request, a replayed one): whatever is wrong with the
    JSON, an InputError on `request_json` that says what, never a KeyError or TypeError."""
    data = PlanRequest(CHIEF, ROE0, TARGET).to_json()
    change(data)
    with pytest.raises(InputError, match=r"request_json: malformed: \w+\(") as exc:
        PlanRequest.from_json(data)
    assert exc.value.field == "request_json"


def test_an_unknown_terminal_target_is_a_config_error():
    with pytest.raises(ConfigError, match=re.escape(
            "terminal_target must be one of ('art', 'cvx', 'carry'), got 'nowhere'")):
        check_window(0, "nowhere", 100)


# --------------------------------------------------------------------------- the learned step
def test_art_requested_without_a_model_plans_from_cvx(pipeline):
    request = PlanRequest(CHIEF, ROE0, TARGET, warm_start="art")
    transfer = pipeline.transfer(request)
    assert transfer.roe_f_m.shape == (6,)
    learned = learned_warm_start(None, transfer, transfer.problem.cvx(),
                                 pipeline.config.planning)
    assert learned.source is WarmStartSource.CVX and learned.dv is None
    assert learned.reason == ("art requested but no learned model is loaded: CVX warm start")
    result = pipeline.plan(request)
    assert result.warm_start is WarmStartSource.CVX and result.scp.feasible
    assert result.warm_start_reason.startswith("art requested but no learned model is loaded")


class _BrokenTerminalWarmStart:
    """A model whose proposal is CVX's controls with a terminal warm start that is not one:
    non-finite controls, or states of the wrong shape."""

    def __init__(self, shape_ok: bool) -> None:
        self.shape_ok = shape_ok

    def propose(self, problem, cvx, **kwargs) -> WarmStartProposal:
        n = problem.horizon.n_nodes
        warm = (Trajectory(np.full((n, 3), np.nan), np.zeros((n, 6))) if self.shape_ok
                else Trajectory(np.zeros((n, 3)), np.zeros((n - 1, 6))))
        return WarmStartProposal(np.array(cvx.dv_rtn_mps), warm_start=warm)


@pytest.mark.parametrize("shape_ok", [True, False])
def test_a_broken_terminal_warm_start_is_computed_again(pipeline, shape_ok):
    """The terminal warm start a proposal carries is used only once checked; one that is not
    finite or not of the horizon's shape is ignored (the post hoc check computes it), and the
    plan, forced onto ART, is a usable one."""
    provider = _BrokenTerminalWarmStart(shape_ok)
    request = PlanRequest(CHIEF, ROE0, TARGET, warm_start="art")
    transfer = pipeline.transfer(request)
    cvx = transfer.problem.cvx()
    assert carried_warm_start(transfer.problem, provider.propose(transfer.problem, cvx)) is None
    art = GuidancePipeline(pipeline.config, provider=provider)
    result = art.plan(request)
    assert result.warm_start is WarmStartSource.ART and result.scp.feasible
    assert np.all(np.isfinite(result.dv_rtn_mps)) and result.proposal is not None


def test_of_two_failed_runs_the_smaller_violation_is_better():
    def run(feasible, cost_mps, violation):
        return types.SimpleNamespace(feasible=feasible, cost_mps=cost_mps,
                                     max_violation=violation, status=ScpStatus.MAX_ITERATIONS)

    assert better_plan(run(False, 9.0, 0.1), run(False, 1.0, 0.2))
    assert not better_plan(run(False, 1.0, 0.3), run(False, 9.0, 0.2))
    assert better_plan(run(True, 9.0, 0.0), run(False, 1.0, 0.1))  # feasible first
    assert better_plan(run(True, 1.0, 0.0), run(True, 1.5, 0.0))  # then the lower cost


# --------------------------------------------------------------------------- the proposal worker
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
