"""The `auto` warm start with the shipped default models against the CVX warm start, on
held-out scenarios of each mode (end-to-end: CVX, rollout, post hoc check, SCVx* from both)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline, WarmStartSource
from helpers.shipped import heldout_requests

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX

FLOOR_MPS = 0.010  # the paper's post hoc floor: auto never worse than CVX by more than this
# measured on these 50 scenarios, with the post hoc check on the terminal warm start: chance 2
# plans flown from ART, total gain 2.100 m/s (one scenario where SCVx* from CVX does not
# converge and the retry from ART does); deterministic (the model trained at GPU scale, on the
# test split of its own 25,000-trajectory dataset) 16 accepted, 0.168 m/s. Now counted as
# proposals the check accepts (with `art_min_gain_mps` an accepted plan within 1 mm/s of
# CVX's is not flown): chance 4 accepted, 2.100 m/s; deterministic 15, 0.185 m/s. Earlier
# deterministic models were measured on the test split of their own (other) dataset: the
# CPU-trained gated one 8, 0.496 m/s, the ungated one 3, 0.323. On the same 1,000 fresh
# scenarios (docs/results.md) the current model's `auto` is cheaper on 109 against 48.
# The RTN teacher, the chance-constrained default before, was flown from ART on 1 of these 50
# (2 accepted), 9.7 mm/s cheaper; the ROE model's 2.1 m/s here came from the one scenario
# where only its retry converged.
# The chance-constrained default is now the one-token student of the RTN teacher. Its
# thresholds come from its evaluation on 2,000 held-out scenarios (dataset seeds 11, 12;
# benchmarks/results/slim/eval_slim1e40_s11s12_summary.json): the check accepts 5.85 % of its
# proposals (2.9 expected in 50; none in 50 has probability 0.94^50 = 5 %, so at least 1), and
# the plan flown is cheaper than CVX alone's by > 1 mm/s on 132 of 2,000 (6.6 %: 3.3 expected
# in 50, none has probability 3 %), by 14.6 mm/s on average but carried by few scenarios (the
# median saving is 0), so the total guards the sign: at least one clearly cheaper plan, 5 mm/s.
# Measured on these 50: 2 accepted, 15 mm/s in total (one scenario, 14.6 mm/s). The
# deterministic default is now the one-token student of the ROE teacher; from its evaluation
# on 1,000 fresh scenarios (dataset seed 97; benchmarks/results/slim/
# eval_slim1e40_det_1000_summary.json) the check accepts 26 % of its proposals (13 expected in
# 50; fewer than 8 has probability ~4 %) and the flown plan saves 3.64 mm/s a scenario on
# average (0.18 m/s expected over 50), so the thresholds of the ROE teacher stand: at least 8
# accepted, 80 mm/s in total. Measured on these 50: 13 accepted, 0.305 m/s.
MIN_ACCEPTED = {"chance": 1, "deterministic": 8}
MIN_TOTAL_GAIN_MPS = {"chance": 0.005, "deterministic": 0.08}
N_HELDOUT = 50


class AutoPlans:
    """The plans of the default configuration with each mode's default model (warm start
    `auto`) on the first held-out scenarios, made once for the module: every test here compares
    another way of planning against these (one pipeline per mode, planning in the order of the
    scenarios)."""

    def __init__(self) -> None:
        config = GuidanceConfig.load()  # the check alone decides (no second run from ART)
        self.config = config.replace(planning=dataclasses.replace(
            config.planning, first_plan_from_both=False))
        self._pipelines: dict = {}
        self._plans: dict = {}

    def requests(self, mode: str, n: int) -> list:
        return heldout_requests(n, DEFAULT_MODELS[mode])

    def plans(self, mode: str, n: int) -> list:
        if mode not in self._pipelines:
            self._pipelines[mode] = GuidancePipeline(
                self.config, provider=ArtWarmStart.load(default_model_path(mode)))
            self._plans[mode] = []
        done = self._plans[mode]
        for req in self.requests(mode, n)[len(done):]:
            done.append(self._pipelines[mode].plan(req))
        return done[:n]


@pytest.fixture(scope="module")
def auto_plans() -> AutoPlans:
    return AutoPlans()


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_auto_is_never_worse_than_cvx_warm_start_on_heldout_scenarios(mode, auto_plans):
    """50 held-out scenarios per mode, with the mode's default model.

    What it guards: the learned warm start pays in flight. The post hoc check accepts ART on
    some scenarios (MIN_ACCEPTED) and the plans flown with `auto` cost less than the
    CVX-warm-started ones in total (MIN_TOTAL_GAIN_MPS). That `auto` is never worse than CVX by
    more than 10 mm/s and feasible whenever CVX is holds by construction
    (`also_solve_from_cvx`); it is checked here end to end, so a change that breaks that guard
    fails too."""
    cvx_only = GuidancePipeline(auto_plans.config)
    rows = []
    for req, a in zip(auto_plans.requests(mode, N_HELDOUT), auto_plans.plans(mode, N_HELDOUT)):
        c = cvx_only.plan(req)
        rows.append((a.cost_mps - c.cost_mps, a.scp.feasible, c.scp.feasible,
                     a.posthoc is not None and bool(a.posthoc.accepted), a.scp.iterations,
                     c.scp.iterations))
        if c.scp.feasible:
            assert a.scp.feasible, a.warm_start_reason
            assert a.cost_mps <= c.cost_mps + FLOOR_MPS, a.warm_start_reason
    d = np.array([r[0] for r in rows if r[1] and r[2]])
    accepted = np.array([r[3] for r in rows])
    print(f"\nauto - cvx cost [mm/s] over {d.size} feasible pairs: min {1e3 * d.min():.2f} "
          f"p5 {1e3 * np.percentile(d, 5):.2f} median {1e3 * np.median(d):.2f} "
          f"p95 {1e3 * np.percentile(d, 95):.2f} max {1e3 * d.max():.2f}; total gain "
          f"{-d.sum():.3f} m/s; ART accepted "
          f"{accepted.sum()}/{accepted.size}; iterations auto {np.mean([r[4] for r in rows]):.1f}"
          f" cvx {np.mean([r[5] for r in rows]):.1f}")
    assert accepted.sum() >= MIN_ACCEPTED[mode]
    assert -d.sum() >= MIN_TOTAL_GAIN_MPS[mode]


@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_the_concurrent_proposal_plans_as_the_sequence(mode, auto_plans):
    """`propose_concurrently` (the proposal made in a worker process while SCVx* from CVX is
    solved; off by default) changes the time only: on 12 held-out scenarios per mode every
    plan, its warm start, the decision's reason, the post hoc numbers and the discarded attempt
    equal those of the sequence, bit for bit (including scenarios whose proposal the check
    accepts). A worker killed between plans is noticed: the plans are proposed in line (the
    same plans) while a new worker starts in the background. The worker also solves SCVx*
    from its proposal meanwhile: the plans that need that run (the check accepted ART, or
    SCVx* from CVX did not converge) take it from the worker, and the runs the plans do not
    need are cancelled without holding the next plan."""
    import dataclasses

    config = auto_plans.config
    con_config = config.replace(planning=dataclasses.replace(config.planning,
                                                             propose_concurrently=True))
    concurrent = GuidancePipeline(con_config, provider=ArtWarmStart.load(default_model_path(mode)))
    assert concurrent.start_proposal_worker(), concurrent.proposal_worker_error
    accepted = ran = needed = 0
    try:
        for i, (req, b) in enumerate(zip(auto_plans.requests(mode, 12),
                                         auto_plans.plans(mode, 12))):
            if i == 6:  # the worker dies: proposals in line until its successor is ready
                concurrent.producers.worker()._proc.kill()
                concurrent.producers.worker()._proc.join()
            taken = concurrent.proposal_worker_scvx_runs[1]
            a = concurrent.plan(req)
            if i < 6 and a.proposal is not None:  # the worker's plans (before the kill):
                # where the sequence solved SCVx* from ART, the plan took the worker's run
                need = b.warm_start is ART or (b.discarded is not None
                                               and b.discarded.warm_start is ART)
                assert concurrent.proposal_worker_scvx_runs[1] - taken == int(need), i
                assert concurrent.proposal_worker_error == ""  # cancelled runs drained
                needed += need
            assert a.status == b.status and a.warm_start == b.warm_start, b.warm_start_reason
            assert np.array_equal(a.dv_rtn_mps, b.dv_rtn_mps) and a.cost_mps == b.cost_mps
            assert a.warm_start_reason == b.warm_start_reason and a.posthoc == b.posthoc
            assert (a.discarded is None) == (b.discarded is None)
            if a.discarded is not None:  # the same attempt, timed apart
                assert dataclasses.replace(a.discarded, solve_time_ms=0.0) == \
                    dataclasses.replace(b.discarded, solve_time_ms=0.0)
            if a.proposal is not None:
                ran += 1
                assert a.proposal.rollout_ms > 0
            accepted += a.posthoc is not None and bool(a.posthoc.accepted)
        assert concurrent.producers.worker().alive  # the successor
    finally:
        concurrent.close()
    assert ran >= 6, ran
    print(f"{mode}: SCVx* from ART taken from the worker in {needed} of the first 6 plans")
    if mode == "deterministic":
        assert accepted >= 1, accepted
        assert needed >= 1, needed


@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_also_solving_rejected_proposals_is_never_worse(mode, auto_plans):
    """`also_solve_from_art` (off by default): where the check rejects the proposal, SCVx* is
    also run from it and the better plan kept by the same rule. On 12 held-out scenarios per
    mode the flown plan is never dearer than with the check alone deciding, the second run is
    made wherever a proposal was rejected after SCVx* from CVX converged, and its reason says
    so."""
    import dataclasses

    config = auto_plans.config
    both = config.replace(planning=dataclasses.replace(config.planning,
                                                       also_solve_from_art=True))
    always = GuidancePipeline(both, provider=ArtWarmStart.load(default_model_path(mode)))
    second = 0
    for req, b in zip(auto_plans.requests(mode, 12), auto_plans.plans(mode, 12)):
        a = always.plan(req)
        if a.status.feasible and b.status.feasible:
            assert a.cost_mps <= b.cost_mps + 1e-12, (a.warm_start_reason, b.warm_start_reason)
        rejected = b.posthoc is not None and not b.posthoc.accepted and b.warm_start is CVX
        if rejected and b.discarded is None and b.scp.status.name == "CONVERGED":
            assert "also solved from ART" in a.warm_start_reason, a.warm_start_reason
            second += 1
    assert second >= 3, second
