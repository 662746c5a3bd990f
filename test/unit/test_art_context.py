"""A replan's flown steps as the learned proposal's context (`art.policies`, T-MPC's closed
loop): a rollout continued from node k with its own first k steps as the context is the
rollout it came from; the KV cache fed the history in one call equals recomputing the whole
context; the guidance builds the context from the plans in force and records it.

Models here have random weights (fixed seeds): what is tested is the machinery. Tolerances in
the model's normalised units (z-scores), as test_art_rollout.py states them.
"""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from helpers.art_models import untrained_art

from art_guidance.art.policies import fitted_context
from art_guidance.art.rollout import rollout
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import Horizon, propagate_mean_oe, roe_from_rtn_linear, time_grid_s
from art_guidance.errors import InputError
from art_guidance.planning import GuidancePipeline, NavState, PlanRequest
from art_guidance.guidance.replan import ReplanPolicy, ReplanSettings
from art_guidance.planning.request import RolloutContext
from art_guidance.safety import PassiveSafety

torch.set_num_threads(1)
TOL = 1e-5
SC = ScenarioConfig()
CHIEF = np.array(SC.chief_oe)
TARGET = np.array(SC.waypoints_rtn["plus_vbar"])


@pytest.fixture(scope="module")
def setup():
    horizon = Horizon.build(CHIEF, time_grid_s(CHIEF[0], SC.n_orbits, SC.n_nodes))
    x0 = roe_from_rtn_linear(CHIEF, np.array(SC.rtn0_nominal))
    return horizon, PassiveSafety(horizon, SC, None), x0


def _flown(res, horizon, k: int) -> types.SimpleNamespace:
    """The first k steps of rollout 0 as a history (the rollout's own R and C)."""
    roe = res.roe_m[0, :k]
    return types.SimpleNamespace(roe_m=roe, rtn=np.einsum("kij,kj->ki", horizon.psi[:k], roe),
                                 dv_rtn_mps=res.dv_rtn_mps[0, :k],
                                 reward_mps=res.reward_to_go_mps[0, :k],
                                 constraint=res.constraint_to_go[0, :k])


@pytest.mark.parametrize("size,representation", [("tiny", "roe"), ("tiny", "rtn"),
                                                 ("slim1", "rtn")])
def test_a_rollout_continued_with_its_own_history_is_the_rollout(setup, size, representation):
    horizon, safety, x0 = setup
    art = untrained_art(size, representation)
    whole = rollout(art, safety, x0, TARGET, -0.25, use_cache=False, speculate=False)
    k = 37
    again = rollout(art, safety, whole.roe_m[0, k], TARGET, whole.reward_to_go_mps[0, k],
                    whole.constraint_to_go[0, k], start_node=k, use_cache=False,
                    speculate=False, history=_flown(whole, horizon, k))
    # recomputing the whole context: the same inputs, the same numbers
    np.testing.assert_array_equal(again.dv_rtn_mps[0], whole.dv_rtn_mps[0, k:])
    # the KV cache fed the history in one call: equal to round-off
    cached = rollout(art, safety, whole.roe_m[0, k], TARGET, whole.reward_to_go_mps[0, k],
                     whole.constraint_to_go[0, k], start_node=k,
                     history=_flown(whole, horizon, k))
    std = art.normalizer.std
    assert np.max(np.abs(cached.dv_rtn_mps[0] - whole.dv_rtn_mps[0, k:])
                  / std["control"]) <= TOL


def test_a_history_changes_the_proposal_and_must_fit_the_context(setup):
    horizon, safety, x0 = setup
    art = untrained_art("tiny", "roe")
    whole = rollout(art, safety, x0, TARGET, -0.25)
    fresh = rollout(art, safety, whole.roe_m[0, 50], TARGET, -0.2, start_node=50)
    told = rollout(art, safety, whole.roe_m[0, 50], TARGET, -0.2, start_node=50,
                   history=_flown(whole, horizon, 50))
    assert not np.array_equal(fresh.dv_rtn_mps, told.dv_rtn_mps)
    with pytest.raises(InputError, match="history"):  # 51 steps before node 50: no room
        rollout(art, safety, x0, TARGET, -0.25, start_node=50,
                history=_flown(whole, horizon, 51))


def test_the_context_keeps_what_fits_and_carries_r():
    rng = np.random.default_rng(3)
    ctx = RolloutContext(rng.normal(size=(10, 6)), rng.normal(size=(10, 6)),
                         rng.normal(0, 0.01, (10, 3)), -2.0)
    norms = np.linalg.norm(ctx.dv_rtn_mps, axis=1)
    np.testing.assert_allclose(ctx.reward_mps, -2.0 + np.concatenate([[0], np.cumsum(norms)[:-1]]))
    assert fitted_context(ctx, 10) is ctx and fitted_context(ctx, 0) is None
    last = fitted_context(ctx, 4)
    assert last.n_steps == 4 and np.array_equal(last.roe_m, ctx.roe_m[6:])
    np.testing.assert_allclose(last.reward_mps, ctx.reward_mps[6:])
    again = RolloutContext.from_json(ctx.to_json())
    np.testing.assert_array_equal(again.dv_rtn_mps, ctx.dv_rtn_mps)
    with pytest.raises(InputError, match="context"):
        RolloutContext(np.full((2, 6), np.nan), np.zeros((2, 6)), np.zeros((2, 3)), 0.0)


def test_the_guidance_context_is_the_plans_in_force_flown_nodes():
    roe0 = roe_from_rtn_linear(CHIEF, np.array(SC.rtn0_nominal))
    pipeline = GuidancePipeline()
    first = pipeline.plan(PlanRequest(CHIEF, roe0, TARGET, warm_start="cvx"))
    t0 = 1_700_000_000_000_000_000
    policy = ReplanPolicy(ReplanSettings(stamp_check="order", art_context=True))
    policy.on_result("plan-1", t0, first)

    def nav(result, t_ns, k):
        return NavState(t_ns + int(round(result.epochs_s[k] * 1e9)),
                        propagate_mean_oe(CHIEF, result.epochs_s[k]), result.roe_m[k], np.eye(6))

    assert policy.context_at(nav(first, t0, 0)) is None  # nothing flown yet
    ctx = policy.context_at(nav(first, t0, 5))
    assert ctx.n_steps == 5 and ctx.reward0_mps == -first.cvx.cost_mps
    np.testing.assert_array_equal(ctx.dv_rtn_mps, first.dv_rtn_mps[:5])
    # the replan from node 5 carries it; its own flown nodes extend it
    request = PlanRequest(propagate_mean_oe(CHIEF, first.epochs_s[5]), first.roe_m[5], TARGET,
                          warm_start="cvx", n_nodes=95,
                          n_orbits=SC.n_orbits * 94 / 99, context=ctx)
    second = pipeline.plan(request)
    t5 = t0 + int(round(first.epochs_s[5] * 1e9))
    policy.on_result("plan-2", t5, second)
    longer = policy.context_at(nav(second, t5, 3))
    assert longer.n_steps == 8 and longer.reward0_mps == ctx.reward0_mps
    np.testing.assert_array_equal(longer.roe_m[5:], second.roe_m[:3])
    assert PlanRequest.from_json(request.to_json()).context.n_steps == 5
    off = ReplanPolicy(ReplanSettings(stamp_check="order", art_context=False))
    off.on_result("plan-1", t0, first)
    assert off.context_at(nav(first, t0, 5)) is None
