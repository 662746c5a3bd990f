"""The learned step (`planning.learned`): the warm-start seam, the post hoc check and the CVX
fallback; a request for ART without a model, and a proposal whose terminal warm start is not
one, plan from a usable warm start and say why."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import ConfigError
from art_guidance.optim import ScpStatus, Trajectory
from art_guidance.planning import (
    GuidancePipeline, PlanRequest, PosthocThresholds, WarmStartProposal, WarmStartSource,
    posthoc_check,
)
from art_guidance.planning.learned import carried_warm_start, learned_warm_start

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX
SCENARIO = ScenarioConfig()
CHIEF = np.array(SCENARIO.chief_oe)
ROE0 = roe_from_rtn_linear(CHIEF, np.array(SCENARIO.rtn0_nominal))
TARGET = np.array(SCENARIO.waypoints_rtn["plus_vbar"])


class ScaledCvx:
    """A stand-in learned model: the CVX controls times a factor (cost changes by it)."""

    def __init__(self, factor: float) -> None:
        self.factor = factor
        self.calls = 0

    def propose(self, problem, cvx, planning=None, deadline=None):
        self.calls += 1
        return cvx.dv_rtn_mps * self.factor


def _config(scenario: ScenarioConfig, posthoc: PosthocThresholds | None = None,
            subject: str = "rollout") -> GuidanceConfig:
    """The packaged configuration on `scenario`; the post hoc check judges the rollout itself
    (the paper's definitions) unless `subject` says otherwise, and decides alone (a rejected
    proposal is not also solved: `first_plan_from_both` off)."""
    cfg = GuidanceConfig.load().replace(scenario=scenario)
    planning = dataclasses.replace(cfg.planning, posthoc_subject=subject,
                                   first_plan_from_both=False)
    if posthoc is not None:
        planning = dataclasses.replace(planning, posthoc=posthoc)
    return cfg.replace(planning=planning)


@pytest.fixture(scope="module")
def pipeline() -> GuidancePipeline:
    """The CVX-only pipeline of the default configuration."""
    return GuidancePipeline(GuidanceConfig.load())


@pytest.fixture(scope="module")
def request_0():
    scenario = ScenarioConfig.from_yaml()
    s = sample_scenario(scenario, 4)
    chief = np.array(scenario.chief_oe)
    return scenario, PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
                                 chance_constrained=False)


def test_posthoc_metrics_follow_the_paper_definitions(request_0):
    scenario, req = request_0
    pipeline = GuidancePipeline(_config(scenario), provider=ScaledCvx(1.02))
    result = pipeline.plan(req)
    ph = result.posthoc
    # R_art = 1.02 R_des  =>  E_R = (R_art - R_des) / R_des = +0.02
    assert ph.e_r == pytest.approx(0.02, abs=1e-9)
    assert ph.e_c == int(ph.e_c) and ph.e_c >= 0  # C(t1) of the rollout, an integer count
    assert ph.accepted == (ph.e_c <= 2)
    assert result.art_dv_rtn_mps is not None


def test_rejected_rollout_falls_back_to_cvx(request_0):
    scenario, req = request_0
    provider = ScaledCvx(0.5)  # half the lower bound: 100 E_R = -50, outside [-1.5, 3.5]
    result = GuidancePipeline(_config(scenario), provider=provider).plan(req)
    assert provider.calls == 1
    assert result.posthoc is not None and not result.posthoc.accepted
    assert result.posthoc.e_r == pytest.approx(-0.5)
    assert result.warm_start is CVX
    assert result.status in (ScpStatus.CONVERGED, ScpStatus.MAX_ITERATIONS)


def test_accepted_rollout_warm_starts_scp(request_0):
    scenario, req = request_0
    wide = PosthocThresholds(e_r_pct_min=-100.0, e_r_pct_max=100.0, e_c_max=1000.0)
    result = GuidancePipeline(_config(scenario, wide), provider=ScaledCvx(1.01)).plan(req)
    assert result.posthoc.accepted and result.warm_start is ART
    assert result.scp.feasible
    assert np.abs(result.rtn[-1, :3] - req.target_rtn[:3]).max() < 100.0  # pre-burn, near it


def test_forced_art_uses_the_rollout_even_if_rejected(request_0):
    scenario, req = request_0
    forced = PlanRequest(req.chief_oe, req.roe0_m, req.target_rtn, False, warm_start="art")
    result = GuidancePipeline(_config(scenario), provider=ScaledCvx(0.5)).plan(forced)
    assert not result.posthoc.accepted and result.warm_start is ART
    cvx_only = PlanRequest(req.chief_oe, req.roe0_m, req.target_rtn, False, warm_start="cvx")
    provider = ScaledCvx(1.0)
    pipeline = GuidancePipeline(_config(scenario), provider=provider)
    assert pipeline.plan(cvx_only).warm_start is CVX
    assert provider.calls == 0


def test_broken_provider_output_falls_back_to_cvx(request_0):
    scenario, req = request_0

    class Broken:
        def propose(self, problem, cvx, planning=None, deadline=None):
            return np.full((problem.safety.n_nodes, 3), np.nan)

    for warm_start in ("auto", "art"):
        forced = PlanRequest(req.chief_oe, req.roe0_m, req.target_rtn, False, warm_start)
        result = GuidancePipeline(_config(scenario), provider=Broken()).plan(forced)
        assert result.warm_start is CVX and not result.posthoc.accepted
        assert result.scp.feasible


def test_posthoc_check_on_an_unsafe_rollout(request_0):
    scenario, req = request_0
    pipeline = GuidancePipeline(_config(scenario))
    transfer = pipeline.transfer(req)
    horizon, safety = transfer.horizon, transfer.safety
    dv = np.zeros((horizon.n_nodes, 3))
    roe = horizon.propagate(req.roe0_m, dv)
    decision = posthoc_check(dv, roe, 1.0, safety, PosthocThresholds())
    assert decision.e_r == pytest.approx(-1.0) and not decision.accepted
    with pytest.raises(ConfigError, match="min <= max"):
        PosthocThresholds(e_r_pct_min=5.0, e_r_pct_max=1.0)


@pytest.mark.parametrize("skip", [True, False])
def test_art_is_not_run_when_cvx_is_already_passively_safe(request_0, skip):
    """`skip_art_when_cvx_safe`: with zones too small to matter (1 m) the CVX plan is passively
    safe, SCVx* from it is the plan, and `auto` does not roll ART out (the decision says why);
    `art` still does, and switched off `auto` runs it as before."""
    scenario, req = request_0
    tiny = dataclasses.replace(scenario, ae_semi_axes_m=(1.0, 1.0, 1.0),
                               koz_semi_axes_m=(1.0, 1.0, 1.0))
    cfg = _config(tiny)
    cfg = cfg.replace(planning=dataclasses.replace(cfg.planning, skip_art_when_cvx_safe=skip))
    provider = ScaledCvx(1.0)
    result = GuidancePipeline(cfg, provider=provider).plan(req)
    assert result.scp.feasible and result.warm_start is CVX
    if skip:
        assert provider.calls == 0 and result.posthoc is None
        assert "CVX is passively safe" in result.warm_start_reason, result.warm_start_reason
    else:
        assert provider.calls == 1 and result.posthoc is not None
    forced = PlanRequest(req.chief_oe, req.roe0_m, req.target_rtn, False, warm_start="art")
    assert GuidancePipeline(cfg, provider=provider).plan(forced).warm_start is ART
    assert provider.calls == (1 if skip else 2)


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
