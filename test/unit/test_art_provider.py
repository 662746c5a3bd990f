"""The learned warm start in the pipeline: provider, post hoc decision, fallbacks, retries.

The model here is untrained (fixed-seed weights, `helpers.art_models`): these tests check the
decisions and the fallbacks, which must hold whatever the model proposes. The shipped trained
model is tested in `test_shipped_model.py`.
"""
from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest
import torch
from helpers.art_models import write_untrained_checkpoint

from art_guidance.art.provider import ArtWarmStart
from art_guidance.cli import main as cli_main
from art_guidance.deadline import Deadline
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import CheckpointError
from art_guidance.optim import ScpStatus, Trajectory
from art_guidance.planning import (
    GuidancePipeline, PlanRequest, PosthocThresholds, WarmStartProposal, WarmStartSource,
)

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX
PAPER = PosthocThresholds()  # -1.5 <= 100 E_R <= 3.5, 0 <= E_C <= 2


def _judging(subject: str) -> GuidanceConfig:
    """The packaged configuration with the post hoc check judging `subject`, and deciding
    alone (a rejected proposal is not also solved, as `first_plan_from_both` would for a
    plan with nothing to carry)."""
    cfg = GuidanceConfig.load()
    return cfg.replace(planning=dataclasses.replace(cfg.planning, posthoc_subject=subject,
                                                    first_plan_from_both=False))


RAW = _judging("rollout")  # the paper's check: the rollout itself


class Scaled:
    """Proposes the CVX controls times a factor: E_R = factor - 1 exactly."""

    sha256 = ""

    def __init__(self, factor: float) -> None:
        self.factor = factor

    def propose(self, problem, cvx, planning=None, deadline=None):
        return WarmStartProposal(cvx.dv_rtn_mps * self.factor)


def _request(seed: int, chance: bool = False, **kw) -> PlanRequest:
    scenario = ScenarioConfig.from_yaml()
    s = sample_scenario(scenario, seed)
    chief = np.array(scenario.chief_oe)
    return PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
                       chance_constrained=chance, **kw)


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "untrained.pt"
    write_untrained_checkpoint(path, seed=0)
    return path


@pytest.fixture(scope="module")
def provider(model_path):
    return ArtWarmStart.load(model_path)


@pytest.mark.parametrize("factor,inside", [(0.984, False), (0.986, True), (1.034, True),
                                           (1.036, False), (0.5, False)])
def test_decision_follows_the_thresholds(factor, inside):
    """E_R just inside / outside [-1.5 %, 3.5 %]; accepted iff E_R and E_C are both inside
    (the paper's check of the rollout itself)."""
    result = GuidancePipeline(RAW, provider=Scaled(factor)).plan(_request(4))
    ph = result.posthoc
    assert ph.e_r == pytest.approx(factor - 1.0, abs=1e-9)
    e_c_inside = PAPER.e_c_min <= ph.e_c <= PAPER.e_c_max
    assert ph.accepted == (inside and e_c_inside)
    # an accepted rollout's plan is also solved from CVX and the cheaper one is kept
    assert result.warm_start is (ART if ph.accepted else CVX) or (
        ph.accepted and "kept the CVX-warm-started plan" in result.warm_start_reason)
    word = "accepted" if ph.accepted else "rejected"
    assert word in result.warm_start_reason and "100 E_R" in result.warm_start_reason


def test_constraint_budget_bound_rejects():
    """With E_C's upper bound set below the rollout's C(t1), the same rollout is rejected."""
    base = GuidancePipeline(RAW, provider=Scaled(1.0)).plan(_request(4))
    e_c = base.posthoc.e_c
    assert e_c == int(e_c) and e_c >= 0
    cfg = RAW
    tight = dataclasses.replace(cfg.planning, posthoc=PosthocThresholds(e_c_max=e_c - 1.0)
                                if e_c >= 1 else PosthocThresholds(e_c_min=e_c + 1.0,
                                                                   e_c_max=e_c + 2.0))
    result = GuidancePipeline(cfg.replace(planning=tight), provider=Scaled(1.0)).plan(
        _request(4))
    assert not result.posthoc.accepted and result.warm_start is CVX


def test_provider_rollout_is_what_the_pipeline_checks(provider):
    """With the paper's check, the pipeline's E_C (its own propagation and safety evaluation)
    equals the rollout's own realised C(t1), and R(t_i) is the realised reward-to-go of the
    proposed controls."""
    req = _request(5, chance=True, warm_start="art")
    result = GuidancePipeline(RAW, provider=provider).plan(req)
    prop = result.proposal
    n = result.epochs_s.size
    assert prop.dv_rtn_mps.shape == (n, 3) and prop.model_sha256 == provider.sha256
    norms = np.linalg.norm(prop.dv_rtn_mps, axis=1)
    assert prop.reward_to_go_mps[0] == pytest.approx(-norms.sum(), rel=1e-9)
    assert np.all(np.diff(prop.constraint_to_go) <= 0)  # C(t_i) counts nodes j >= i
    assert result.posthoc.e_c == prop.constraint_to_go[0]
    assert result.posthoc.e_r == pytest.approx(
        (-norms.sum() + result.cvx.cost_mps) / -result.cvx.cost_mps, rel=1e-9)
    # forced (the untrained model's rollout is rejected) and flown unless SCVx* from it failed
    assert "forced" in result.warm_start_reason or result.posthoc.accepted
    assert result.warm_start is ART or "retried from CVX" in result.warm_start_reason
    assert result.timings.art >= prop.rollout_ms > 0.0
    assert result.scp.feasible


@pytest.mark.parametrize("factor", [0.5, 1.0, 1.3])
def test_default_check_judges_the_terminal_warm_start(factor):
    """By default the check judges the controls corrected onto the terminal condition, i.e.
    where SCVx* starts: CVX scaled by 0.5 or 1.3 misses the target, and E_R and E_C are those
    of the corrected controls, not those of the scaled ones."""
    req = _request(4)
    result = GuidancePipeline(provider=Scaled(factor)).plan(req)
    problem = GuidancePipeline().transfer(req).problem
    safety, h = problem.safety, problem.horizon
    dv, roe = problem.terminal_warm_start(result.cvx.dv_rtn_mps * factor)
    assert np.abs(h.final_post_burn_nonlinear(roe, dv) - problem.roe_f_m).max() < 1e-4
    cost = np.linalg.norm(dv, axis=1).sum()
    assert result.posthoc.e_r == pytest.approx(cost / result.cvx.cost_mps - 1.0, rel=1e-9)
    assert result.posthoc.e_c == safety.evaluate(roe, dv).constraint_to_go[0]
    raw = GuidancePipeline(RAW, provider=Scaled(factor)).plan(req).posthoc
    assert raw.e_r == pytest.approx(factor - 1.0, abs=1e-9)


def test_provider_ranks_candidates_as_the_check_judges_them(provider):
    """The proposal among the sweep's candidates is the best by the check's own subject: with
    the default, by the terminal warm starts' cost and C(t_1)."""
    from art_guidance.art.provider import best_candidate, judged_candidates
    from art_guidance.art.rollout import rollout

    req = _request(6, chance=True, warm_start="art")
    pipe = GuidancePipeline(provider=provider)
    result = pipe.plan(req)
    problem = pipe.transfer(req).problem
    safety = problem.safety
    j = result.cvx.cost_mps
    threads = torch.get_num_threads()
    torch.set_num_threads(provider.threads)  # as the provider rolls out (bit-identical)
    try:
        res = rollout(provider.art, safety,
                      np.tile(req.roe0_m, (len(provider.reward_scales), 1)), req.target_rtn,
                      -j * np.array(provider.reward_scales), 0.0)
    finally:
        torch.set_num_threads(threads)
    cost, c_t1 = judged_candidates(res, problem, "warm_start")
    b = best_candidate(cost, c_t1, j, PAPER)
    np.testing.assert_array_equal(result.proposal.dv_rtn_mps, res.dv_rtn_mps[b])
    assert result.posthoc.e_c == c_t1[b]
    assert result.posthoc.e_r == pytest.approx(cost[b] / j - 1.0, rel=1e-9)


def test_out_of_domain_horizons_fall_back_to_cvx(provider):
    # the provider's domain check is under test: ART runs even where CVX is already safe
    cfg = GuidanceConfig.load()
    cfg = cfg.replace(planning=dataclasses.replace(cfg.planning, skip_art_when_cvx_safe=False))
    too_long = _request(5, n_nodes=120, n_orbits=1.29 * 119 / 99)
    result = GuidancePipeline(cfg, provider=provider).plan(too_long)
    assert result.warm_start is CVX and result.posthoc is None
    assert "longer than the model's context" in result.warm_start_reason
    wrong_spacing = _request(5, n_nodes=50, n_orbits=1.29)
    result = GuidancePipeline(cfg, provider=provider).plan(wrong_spacing)
    assert result.warm_start is CVX and "node spacing" in result.warm_start_reason
    replan = _request(5, n_nodes=40, n_orbits=1.29 * 39 / 99, koz_switch_node=10)
    result = GuidancePipeline(cfg, provider=provider).plan(replan)  # a training tail
    assert result.proposal is not None and result.proposal.dv_rtn_mps.shape == (40, 3)


def test_failing_provider_never_takes_the_plan_down():
    class Raises:
        sha256 = ""

        def propose(self, problem, cvx, planning=None, deadline=None):
            raise RuntimeError("boom")

    class WrongShape(Raises):
        def propose(self, problem, cvx, planning=None, deadline=None):
            return np.zeros((3, 3))

    result = GuidancePipeline(provider=Raises()).plan(_request(4, warm_start="art"))
    assert result.warm_start is CVX and "RuntimeError: boom" in result.warm_start_reason
    assert result.posthoc is None and result.scp.feasible
    result = GuidancePipeline(provider=WrongShape()).plan(_request(4))
    assert result.warm_start is CVX and "output rejected" in result.warm_start_reason
    assert not result.posthoc.accepted and np.isnan(result.posthoc.e_r)


def test_no_model_says_not_run():
    result = GuidancePipeline().plan(_request(4, warm_start="art"))
    assert result.warm_start is CVX and result.posthoc is None
    assert "no learned model" in result.warm_start_reason
    assert "requested" in GuidancePipeline().plan(_request(4, warm_start="cvx")
                                                  ).warm_start_reason


def test_unconverged_art_scp_is_retried_from_cvx():
    """SCVx* from ART stopped after 2 iterations (MAX_ITERATIONS) -> retried from CVX; the
    better feasible plan is kept and the other is reported."""
    cfg = GuidanceConfig.load()
    cfg = cfg.replace(scp=dataclasses.replace(cfg.scp, max_iterations=2))
    result = GuidancePipeline(cfg, provider=Scaled(1.5)).plan(_request(4, warm_start="art"))
    lost = result.discarded
    assert lost is not None and "retried from CVX" in result.warm_start_reason
    assert {result.warm_start, lost.warm_start} == {ART, CVX}
    if result.scp.feasible and lost.status in (ScpStatus.CONVERGED, ScpStatus.MAX_ITERATIONS):
        assert result.cost_mps <= lost.cost_mps + 1e-12


def test_deadline_is_honoured_with_art(provider):
    """The deadline bounds the whole plan: CVX, the proposal and both SCVx* runs (one SCVx*
    iteration, one rollout step and the final evaluation may run past it: allowance 400 ms on a
    loaded 2-core machine)."""
    for deadline_s in (0.15, 0.4):
        pipeline = GuidancePipeline(provider=provider, deadline_s=deadline_s)
        for seed in (3, 11):
            result = pipeline.plan(_request(seed, chance=True, warm_start="art"))
            assert result.timings.total <= 1e3 * deadline_s + 400.0, result.timings
            assert result.status in set(ScpStatus)


class Slow(Scaled):
    """Scaled, after a pause longer than the test's deadline (a provider that ignores the
    deadline: the pipeline cannot stop it, only what comes after)."""

    def propose(self, problem, cvx, planning=None, deadline=None):
        import time

        time.sleep(0.3)
        return super().propose(problem, cvx, planning)


@dataclasses.dataclass(frozen=True)
class Expiring(Deadline):
    """A deadline far off that passes when the test says so (an injected clock)."""

    expired: list = dataclasses.field(default_factory=list)

    def passed(self) -> bool:
        return bool(self.expired) or super().passed()

    def left_s(self) -> float:
        return 0.0 if self.expired else super().left_s()


class PassesInRollout:
    """The model of `inner`, during whose rollout the plan's deadline passes: the rollout is
    handed a deadline already passed, and the plan's own expires (no machine has to be slow
    or fast for it)."""

    def __init__(self, inner, plan_deadline: Expiring) -> None:
        self.inner, self.plan_deadline = inner, plan_deadline

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def propose(self, problem, cvx, planning=None, deadline=None, **kw):
        self.plan_deadline.expired.append(True)
        return self.inner.propose(problem, cvx, planning=planning, deadline=Deadline(0.0), **kw)


def test_a_deadline_that_passes_in_the_proposal_ends_the_plan(provider):
    """A rollout that would run past the deadline stops (CVX warm start, said in the
    reason), and SCVx* then gets no time: the plan is the best feasible iterate at hand
    (status TIMEOUT), and the plan says its deadline was hit; a provider that ignores the
    deadline is waited for, nothing after it runs. The pipeline's `deadline_s` is the
    deadline of a plan given none."""
    request = _request(3, chance=True, warm_start="art")
    deadline = Expiring(time.perf_counter() + 3600.0)
    pipeline = GuidancePipeline(provider=PassesInRollout(provider, deadline))
    result = pipeline.plan(request, deadline)
    assert "DeadlineError" in result.warm_start_reason and result.warm_start is CVX
    assert result.status is ScpStatus.TIMEOUT and result.scp.iterations == 0
    assert result.deadline_hit
    assert not GuidancePipeline(provider=provider).plan(request).deadline_hit
    slow = GuidancePipeline(provider=Slow(1.0), deadline_s=0.05).plan(request)
    assert slow.status is ScpStatus.TIMEOUT and slow.scp.iterations == 0
    assert slow.timings.scp <= 300.0, slow.timings
    no_time = GuidancePipeline(provider=provider, deadline_s=1e-9).plan(request)
    assert "deadline (solve_deadline_s) passed before ART" in no_time.warm_start_reason


def test_corrupt_model_is_refused_and_plan_falls_back(model_path, tmp_path, capsys):
    blob = bytearray(model_path.read_bytes())
    blob[-100] ^= 0xFF
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(bytes(blob))
    with pytest.raises(CheckpointError, match="corrupt"):
        ArtWarmStart.load(corrupt)
    out = tmp_path / "p.json"
    assert cli_main(["plan", "--seed", "4", "--model", str(corrupt), "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert "planning from CVX only" in err and "corrupt" in err
    data = json.loads(out.read_text())
    assert data["warm_start"] == "cvx" and data["posthoc"] is None
    assert cli_main(["plan", "--seed", "4", "--model", str(corrupt), "--warm-start", "art",
                     "--json", str(tmp_path / "q.json")]) == 2


def test_plan_cli_shows_both_warm_starts(model_path, tmp_path, capsys):
    out = tmp_path / "p.json"
    assert cli_main(["plan", "--seed", "4", "--model", str(model_path), "--json",
                     str(out)]) in (0, 1)
    text = capsys.readouterr().out
    assert "CVX" in text and "ART" in text and "post hoc" in text
    data = json.loads(out.read_text())
    assert data["art_cost_mps"] > 0 and data["posthoc"] is not None
    assert data["model_sha256"] == ArtWarmStart.load(model_path).sha256


def test_unconverged_cvx_scp_is_retried_from_a_rejected_rollout():
    """A rollout the post hoc check rejects is still a second chance: when SCVx* from CVX does
    not converge, it is retried from the rollout and the better feasible plan is kept."""
    cfg = GuidanceConfig.load()
    cfg = cfg.replace(scp=dataclasses.replace(cfg.scp, max_iterations=2))
    result = GuidancePipeline(cfg, provider=Scaled(0.5)).plan(_request(4))
    assert not result.posthoc.accepted
    assert "retried from ART" in result.warm_start_reason and result.discarded is not None
    assert {result.warm_start, result.discarded.warm_start} == {ART, CVX}


def test_best_candidate_ranks_by_the_posthoc_criteria():
    """Inside the region first, then the smallest E_C, then the smallest |E_R|; with none
    inside, the cheapest passively safe one, else the cheapest."""
    from art_guidance.art.provider import best_candidate
    from art_guidance.config import PosthocThresholds

    t = PosthocThresholds()
    j = 2.0
    # costs: +10 % (E_C 0), +1 % (E_C 2: inside), -0.5 % (E_C 1: inside, smaller E_C)
    assert best_candidate(np.array([2.2, 2.02, 1.99]), np.array([0, 2, 1]), j, t) == 2
    # none inside and none safe: the cheapest, whatever its E_C
    assert best_candidate(np.array([2.4, 2.3, 2.6]), np.array([5, 3, 3]), j, t) == 1
    assert best_candidate(np.array([2.1, 2.6]), np.array([5, 3]), j, t) == 0
    # none inside: a safe one first, the cheapest of those
    assert best_candidate(np.array([1.5, 1.9, 2.2, 2.4]), np.array([4, 0, 3, 0]), j, t) == 1
    # a tie keeps the first
    assert best_candidate(np.array([2.0, 2.0]), np.array([0, 0]), j, t) == 0


def test_sweep_proposes_the_best_of_its_candidates(model_path):
    """The conditioning sweep rolls out one candidate per reward scale in one batch and proposes
    the one `best_candidate` picks; with a single scale of 1 it is the paper's rollout."""
    from art_guidance.art.provider import best_candidate
    from art_guidance.art.rollout import rollout
    from art_guidance.config import PosthocThresholds

    scales = (0.8, 1.0, 1.2)
    sweep = ArtWarmStart.load(model_path, reward_scales=scales)
    single = ArtWarmStart.load(model_path, reward_scales=(1.0,))
    req = _request(5, chance=True)
    pipeline = GuidancePipeline(provider=sweep)
    problem = pipeline.transfer(req).problem
    safety = problem.safety
    cvx = problem.cvx()
    res = rollout(sweep.art, safety, np.tile(req.roe0_m, (3, 1)), req.target_rtn,
                  -cvx.cost_mps * np.array(scales), 0.0)
    b = best_candidate(res.cost_mps, res.realised_constraint_to_go[:, 0], cvx.cost_mps,
                       PosthocThresholds())
    prop = sweep.propose(problem, cvx)
    # float32 decoding on other thread counts: equal to 1e-6 m/s
    assert np.allclose(prop.dv_rtn_mps, res.dv_rtn_mps[b], rtol=0, atol=1e-6)
    one = single.propose(problem, cvx)
    alone = rollout(single.art, safety, req.roe0_m, req.target_rtn, -cvx.cost_mps, 0.0)
    assert np.allclose(one.dv_rtn_mps, alone.dv_rtn_mps[0], rtol=0, atol=1e-6)
    with pytest.raises(Exception, match="reward_scales"):
        ArtWarmStart.load(model_path, reward_scales=(0.0,))


def test_the_rollouts_suite_scores_what_the_sweep_proposes(model_path):
    """`evaluate --suite rollouts --sweep` scores the candidate the provider proposes (ranked
    by the check's subject, the terminal warm start by default), by its rollout's own cost."""
    from art_guidance.eval.scoring import score_rollouts

    scales = (0.8, 1.0, 1.2)
    sweep = ArtWarmStart.load(model_path, reward_scales=scales)
    for seed in (5, 6, 7):
        req = _request(seed, chance=True)
        problem = GuidancePipeline(provider=sweep).transfer(req).problem
        safety = problem.safety
        cvx = problem.cvx()
        prop = sweep.propose(problem, cvx)
        scores = score_rollouts(sweep.art, safety, req.roe0_m[None], req.target_rtn[None],
                                [cvx.cost_mps], [0], reward_scales=scales,
                                subject=GuidanceConfig().planning.posthoc_subject)
        assert scores.cost_mps[0] == pytest.approx(
            np.linalg.norm(prop.dv_rtn_mps, axis=1).sum(), abs=1e-5)
        assert scores.c_art[0] == prop.constraint_to_go[0]


class Carrying:
    """The provider with what it carries replaced: `warm` None strips the terminal warm start
    (the pipeline computes it), a `Trajectory` replaces it; counts the projections of the
    proposed controls made outside `propose`."""

    def __init__(self, inner, warm="keep") -> None:
        self.inner, self.sha256, self.warm = inner, inner.sha256, warm
        self.proposed, self.inside = None, False

    def propose(self, problem, cvx, planning=None, deadline=None):
        self.inside = True
        try:
            prop = self.inner.propose(problem, cvx, planning, deadline)
        finally:
            self.inside = False
        if self.warm != "keep":
            prop = dataclasses.replace(prop, warm_start=self.warm)
        self.proposed = prop.dv_rtn_mps
        return prop


def test_the_proposals_terminal_warm_start_is_made_once(provider, monkeypatch):
    """The provider's terminal warm start of the candidate it proposes is what the post hoc
    check judges and where SCVx* from ART starts: neither projects the proposed controls
    again, and the plans are bit for bit those made when the pipeline computes it itself
    (stripped) or when the carried one is not one (zeros: refused, computed)."""
    import art_guidance.optim.scp as scp_module

    wrapped = [Carrying(provider)]
    outside = []

    def counting(original):
        def project(horizon, roe0_m, roe_f_m, dv_rtn_mps, *args, **kwargs):
            w = wrapped[0]
            if not w.inside and w.proposed is not None \
                    and np.array_equal(np.asarray(dv_rtn_mps, float).reshape(-1, 3),
                                       np.asarray(w.proposed, float)):
                outside.append(1)
            return original(horizon, roe0_m, roe_f_m, dv_rtn_mps, *args, **kwargs)
        return project

    # every projection goes through scp's (`TransferProblem.terminal_warm_start` and SCVx*
    # alike, by `scp.onto_terminal_set`)
    monkeypatch.setattr(scp_module, "terminal_warm_start",
                        counting(scp_module.terminal_warm_start))
    for seed in (3, 11):
        request = _request(seed, chance=True, warm_start="art")
        plans = {}
        for name, warm in (("carried", "keep"), ("stripped", None),
                           ("zeros", Trajectory(np.zeros((100, 3)), np.zeros((100, 6))))):
            wrapped[0] = Carrying(provider, warm)
            outside.clear()
            plans[name] = GuidancePipeline(provider=wrapped[0]).plan(request)
            assert plans[name].proposal is not None, plans[name].warm_start_reason
            assert len(outside) == (0 if name == "carried" else 1), name
        for name in ("stripped", "zeros"):
            a, b = plans["carried"], plans[name]
            assert np.array_equal(a.dv_rtn_mps, b.dv_rtn_mps) and a.cost_mps == b.cost_mps
            assert a.posthoc == b.posthoc and a.warm_start_reason == b.warm_start_reason
            assert a.scp.iterations == b.scp.iterations


def test_each_candidate_is_projected_once_per_plan(provider, monkeypatch):
    """The terminal correction of the sweep's candidates, made to judge them, is also the
    proposed candidate's warm start: one projection per candidate and plan, no more."""
    import art_guidance.art.provider as provider_module

    calls = []
    original = provider_module.judged_trajectory

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(provider_module, "judged_trajectory", counted)
    result = GuidancePipeline(provider=provider).plan(_request(3, chance=True, warm_start="art"))
    assert result.proposal is not None and result.proposal.warm_start is not None
    assert len(calls) == len(provider.reward_scales)
