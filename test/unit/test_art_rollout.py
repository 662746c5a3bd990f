"""ART model, KV-cached decoding and rollouts with the dynamics in the loop.

Models here have random weights (fixed seeds) and plausible normalisation scales: what is
tested is the machinery (cache == recompute, dynamics, R/C bookkeeping, replans), not skill.
Tolerances are stated in the model's normalised units (z-scores) unless said otherwise.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from helpers.art_models import untrained_art

from art_guidance.art import ArtModel, TrainedArt, preset
from art_guidance.art.config import FEATURES, SLOTS
from art_guidance.eval.scoring import score_rollouts, heldout_scenarios
from art_guidance.art.model import loss_terms
from art_guidance.art.rollout import rollout
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.errors import InputError
from art_guidance.safety import PassiveSafety

torch.set_num_threads(1)
TOL = 1e-5  # cached vs recomputed, batched vs single: normalised units
_art = untrained_art


@pytest.fixture(scope="module")
def setup():
    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
    rng = np.random.default_rng(0)
    rtn0 = np.array(sc.rtn0_nominal) + rng.uniform(-1, 1, (3, 6)) * np.array(sc.rtn0_half_width)
    x0 = np.array([roe_from_rtn_linear(chief, r) for r in rtn0])  # (3, 6)
    targets = np.array([sc.waypoints_rtn[w] for w in ("plus_vbar", "minus_rbar", "plus_rbar")])
    return sc, horizon, PassiveSafety(horizon, sc, None), x0, targets


def _close(a, b, art: TrainedArt, tol: float = TOL) -> None:
    std = art.normalizer.std
    assert np.max(np.abs(a.dv_rtn_mps - b.dv_rtn_mps) / std["control"]) <= tol
    assert np.max(np.abs(a.roe_m - b.roe_m) / std["state"]) <= tol
    assert np.array_equal(a.constraint_to_go, b.constraint_to_go)
    assert np.allclose(a.reward_to_go_mps, b.reward_to_go_mps, rtol=0, atol=tol * 0.2)


@pytest.mark.parametrize("representation,start", [("roe", 0), ("rtn", 0), ("roe", 37)])
def test_kv_cached_rollout_equals_recomputing_the_context(setup, representation, start):
    _, horizon, safety, x0, targets = setup
    art = _art("small", representation)
    x_start = np.array([horizon.propagate(x, np.zeros((100, 3)))[start] for x in x0])
    cached = rollout(art, safety, x_start, targets, -0.25, 0.0, start_node=start)
    full = rollout(art, safety, x_start, targets, -0.25, 0.0, start_node=start, use_cache=False)
    _close(cached, full, art)


def test_cache_equals_recompute_in_float64_to_round_off(setup):
    _, _, safety, x0, targets = setup
    art = _art("tiny", dtype=torch.float64)
    a = rollout(art, safety, x0[:1], targets[0], -0.25)
    b = rollout(art, safety, x0[:1], targets[0], -0.25, use_cache=False)
    _close(a, b, art, tol=1e-10)


def test_decoder_steps_equal_the_full_forward_pass():
    """Every step's control from the cache equals the forward pass on the whole context."""
    art = _art("small")
    g = torch.Generator().manual_seed(1)
    b, t = 2, 100
    goal, reward, constraint = torch.randn(b, 6, generator=g), torch.randn(b, t, generator=g), \
        torch.randn(b, t, generator=g)
    state, control = torch.randn(b, t, 6, generator=g), torch.randn(b, t, 3, generator=g)
    feats = torch.zeros(b, 5 * t, FEATURES)
    feats[:, 0::5, SLOTS["goal"]] = goal[:, None]
    feats[:, 1::5, 6], feats[:, 2::5, 7] = reward, constraint
    feats[:, 3::5, SLOTS["state"]], feats[:, 4::5, SLOTS["control"]] = state, control
    with torch.inference_mode():
        ref, _ = art.model(goal[:, None].expand(b, t, 6), reward, constraint, state, control,
                           torch.arange(t).expand(b, t))
        art.decoder.reset(b, t, 0)
        steps = [art.decoder.step(feats[:, max(5 * j - 1, 0):5 * j + 4], max(5 * j - 1, 0))
                 for j in range(t)]
    assert torch.max(torch.abs(torch.stack(steps, 1) - ref)) <= TOL


def test_dynamics_in_the_loop_and_the_performance_parameters(setup):
    sc, horizon, _, x0, targets = setup
    safety = PassiveSafety(horizon, sc, None)
    art = _art("tiny", seed=3)
    res = rollout(art, safety, x0, targets, -0.25, 0.0)
    for b in range(x0.shape[0]):
        dv = res.dv_rtn_mps[b]
        assert np.allclose(res.roe_m[b], horizon.propagate_nonlinear(x0[b], dv), rtol=1e-12,
                           atol=1e-9)
        norms = np.linalg.norm(dv, axis=1)
        assert np.allclose(res.reward_to_go_mps[b], -0.25 + np.concatenate([[0], np.cumsum(
            norms[:-1])]), rtol=0, atol=1e-12)
        ev = safety.evaluate(res.roe_m[b], dv)
        assert np.array_equal(res.violation[b], ev.violation)  # node i: only (x_i, u_i)
        assert np.array_equal(res.constraint_to_go[b], -np.concatenate(
            [[0], np.cumsum(ev.violation[:-1])]))
        assert res.realised_constraint_to_go[b, 0] == ev.constraint_to_go[0]
        assert res.realised_reward_to_go_mps[b, 0] == pytest.approx(-norms.sum(), rel=1e-12)


def test_batched_rollout_equals_single_rollouts(setup):
    _, _, safety, x0, targets = setup
    art = _art("small", seed=2)
    batch = rollout(art, safety, x0, targets, [-0.2, -0.3, -0.4], [0, 1, 2])
    for b in range(3):
        one = rollout(art, safety, x0[b], targets[b], [-0.2, -0.3, -0.4][b], b)
        _close(dataclasses.replace(batch, **{f.name: getattr(batch, f.name)[b:b + 1] for f in
                                             dataclasses.fields(batch) if f.name != "nodes"}),
               one, art)


def test_a_shorter_horizon_uses_the_last_time_steps(setup):
    """Planning the last 40 nodes as their own horizon == replanning from node 60."""
    sc, horizon, _, x0, targets = setup
    art = _art("small", seed=4)
    k = 60
    tail = Horizon.build(horizon.chief_oe[0], horizon.epochs_s[k:])  # same nodes, own horizon
    x_k = horizon.propagate(x0[0], np.zeros((100, 3)))[k]
    replan = rollout(art, PassiveSafety(horizon, sc, None), x_k, targets[0], -0.1, 0.0, k)
    short = rollout(art, PassiveSafety(tail, sc.replace(ae_to_koz_node=0), None), x_k,
                    targets[0], -0.1, 0.0)
    assert replan.nodes.tolist() == list(range(k, 100)) and short.nodes.tolist() == list(
        range(40))
    _close(replan, short, art, tol=0.0)


def test_horizon_longer_than_the_context_is_refused(setup):
    sc, horizon, safety, x0, targets = setup
    art = _art("tiny", context=50)
    with pytest.raises(InputError, match="start_node"):
        rollout(art, safety, x0[0], targets[0], -0.2)
    assert rollout(art, safety, horizon.propagate(x0[0], np.zeros((100, 3)))[50], targets[0],
                   -0.2, start_node=50).dv_rtn_mps.shape == (1, 50, 3)
    with pytest.raises(InputError):
        rollout(art, safety, x0[0], targets[0], np.nan)


def test_loss_ignores_the_padding_of_suffix_sequences():
    """A suffix is padded at the end; causality and the mask keep the padding out."""
    art = _art("tiny", dropout=0.0)
    g = torch.Generator().manual_seed(5)
    t, valid = 100, 30
    shapes = {"goal": (1, t, 6), "reward": (1, t), "constraint": (1, t), "state": (1, t, 6),
              "control": (1, t, 3)}
    batch = {k: torch.randn(*shape, generator=g) for k, shape in shapes.items()}
    batch["timestep"] = torch.arange(70, 170).clamp(max=99)[None]  # a suffix from node 70
    batch["mask"] = (torch.arange(t) < valid)[None]
    changed = {k: v.clone() for k, v in batch.items()}
    for key in ("reward", "constraint", "state", "control"):
        changed[key][:, valid:] = 123.0
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(loss_terms(art.model, batch),
                                                     loss_terms(art.model, changed)))


def test_preset_sizes():
    assert ArtModel(preset("paper")[0]).n_parameters() == pytest.approx(10.6e6, rel=0.01)
    assert ArtModel(preset("small")[0]).n_parameters() == pytest.approx(0.35e6, rel=0.02)


def test_evaluate_rollouts_against_cvx(setup):
    """C(t_1), E_R and the post hoc region computed as the paper defines them."""
    sc, horizon, safety, x0, targets = setup
    art = _art("tiny", seed=6)
    j_cvx = np.array([0.05, 0.5, 50.0])  # R_des = -J_CVX: tiny, plausible, huge
    ev = score_rollouts(art, safety, x0, targets, j_cvx, [0, 3, 1], batch_size=2)
    res = rollout(art, safety, x0, targets, -j_cvx, 0.0)
    cost = np.linalg.norm(res.dv_rtn_mps, axis=2).sum(1)
    assert np.allclose(ev.cost_mps, cost, rtol=1e-6)
    assert np.allclose(ev.e_r, (-cost + j_cvx) / -j_cvx, rtol=1e-6)
    for b in range(3):
        c1 = safety.evaluate(res.roe_m[b], res.dv_rtn_mps[b]).constraint_to_go[0]
        assert ev.c_art[b] == c1
    inside = (-1.5 <= 100 * ev.e_r) & (100 * ev.e_r <= 3.5) & (ev.c_art <= 2)
    assert np.array_equal(ev.accepted, inside) and not ev.accepted[2]  # E_R ~ -1 at 50 m/s
    summary = ev.summary()
    assert summary["n"] == 3 and summary["mean_c_cvx"] == pytest.approx(4 / 3)
    assert summary["frac_c_art_zero"] == np.mean(ev.c_art == 0)
    with pytest.raises(InputError):
        score_rollouts(art, safety, x0, targets, [0.1, 0.0, 0.1], [0, 0, 0])
    data = {"is_test": np.array([True, False, True]), "cvx_constraint_to_go0": np.array(
        [0, 0, -1]), "roe0_m": x0, "target_rtn": targets, "cvx_cost_mps": j_cvx,
        "index": np.arange(3)}
    assert heldout_scenarios(data)["index"].tolist() == [0]  # test split, CVX succeeded
