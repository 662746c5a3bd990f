"""The speculative rollout (several steps decoded before their violations are searched) gives
the step-by-step rollout's result bit for bit: same controls, states, R, C and violations, on
held-out scenarios of both shipped modes, on both runtimes, with replans from a later node;
and the batched violation search decides each arc as the one-node search does."""
from __future__ import annotations

import time

import numpy as np
import pytest
from helpers.shipped import heldout_requests

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.art.rollout import build_safety, rollout
from art_guidance.errors import DeadlineError

N_SCENARIOS = 6  # per mode and runtime (8 candidates each: ~50 rollouts with misses)
FIELDS = ("nodes", "dv_rtn_mps", "roe_m", "reward_to_go_mps", "constraint_to_go", "violation")


def _pair(provider: ArtWarmStart, safety, request, start_node: int = 0):
    k = len(provider.reward_scales)
    x0 = np.tile(request.roe0_m, (k, 1))
    if start_node:  # a replan from a later node: the first rollout's state there
        x0 = rollout(provider.art, safety, x0, request.target_rtn, -6.0).roe_m[:, start_node]
    args = (provider.art, safety, x0, request.target_rtn,
            -6.0 * np.asarray(provider.reward_scales), 0.0, start_node)
    return rollout(*args, speculate=False), rollout(*args, speculate=True)


@pytest.mark.parametrize("runtime", ["torch", "onnx"])
@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_speculation_gives_the_step_by_step_rollout_bit_for_bit(mode, runtime):
    provider = ArtWarmStart.load(default_model_path(mode), runtime=runtime)
    safety = build_safety(provider.art)
    violations = 0
    for i, request in enumerate(heldout_requests(N_SCENARIOS, DEFAULT_MODELS[mode])):
        plain, spec = _pair(provider, safety, request, start_node=40 if i % 3 == 2 else 0)
        for field in FIELDS:
            assert np.array_equal(getattr(plain, field), getattr(spec, field)), field
        violations += int(plain.violation.sum())
    assert violations > 0  # the predictions missed somewhere: the rollback path ran


def test_the_batched_search_decides_each_arc_as_one_node_at_a_time():
    provider = ArtWarmStart.load(default_model_path("chance"))
    safety = build_safety(provider.art)
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    res = rollout(provider.art, safety, np.tile(request.roe0_m, (8, 1)), request.target_rtn,
                  -6.0 * np.asarray(provider.reward_scales))
    h = safety.horizon
    z = np.stack([h.post_burn_at(i, res.roe_m[:, i], res.dv_rtn_mps[:, i])
                  for i in range(h.n_nodes)], axis=1)  # (8, N, 6)
    rng = np.random.default_rng(3)
    pick = rng.permutation(8 * h.n_nodes)[:300]  # a mix of nodes and candidates, shuffled
    b, i = np.divmod(pick, h.n_nodes)
    batched = safety.violated(i, res.roe_m[b, i], res.dv_rtn_mps[b, i], z[b, i])
    one = [safety.violated(int(n), res.roe_m[[c], n], res.dv_rtn_mps[[c], n], z[[c], n])[0]
           for c, n in zip(b, i)]
    assert np.array_equal(batched, np.array(one)) and batched.any() and not batched.all()


def test_a_speculative_rollout_stops_at_its_deadline():
    provider = ArtWarmStart.load(default_model_path("chance"))
    safety = build_safety(provider.art)
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    with pytest.raises(DeadlineError, match="deadline"):
        rollout(provider.art, safety, request.roe0_m, request.target_rtn, -6.0,
                deadline=time.perf_counter())
