"""Model variants of the ablations: per-time-step normalisation and the burn gate.

Machinery only (random weights, fixed seeds): the statistics, the checkpoint round trip, the
gate's loss term and its effect on a rollout, and cache == recompute for both variants.
Tolerances in the model's normalised units unless said otherwise.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers.art_models import deterministic_setup, untrained_art

from art_guidance.art import ArtModel, TrainedArt, preset
from art_guidance.art.checkpoint import load, model_payload, save
from art_guidance.art.model import loss_terms
from art_guidance.art.normalization import Normalizer
from art_guidance.art.rollout import rollout
from art_guidance.errors import ConfigError

torch.set_num_threads(1)
M, N, K = 40, 100, 100


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    ctrl = rng.normal(0.0, 1e-3, (M, N, 3))
    ctrl[:, 0] += rng.normal(0.0, 1.0, (M, 3))  # a busy first node, quiet elsewhere
    return {"goal": rng.normal(size=(M, 6)), "reward": rng.normal(size=(M, N)),
            "constraint": np.zeros((M, N)), "state": rng.normal(size=(M, N, 6)) * 100.0,
            "control": ctrl}


def test_timestep_statistics_are_per_index_and_round_trip():
    raw = _arrays()
    norm = Normalizer.fit(raw, "timestep", K)
    assert norm.per_step("control") and norm.per_step("state")
    assert not norm.per_step("goal") and not norm.per_step("reward")
    assert norm.std["control"].shape == (K, 3)
    # node 0 is scaled by its own spread (~1 m/s), the quiet nodes by theirs (~1 mm/s)
    assert norm.std["control"][0].min() > 100 * norm.std["control"][1:].max()
    t = np.arange(N)
    z = norm.normalize("control", raw["control"], t)
    assert np.allclose(z.std(axis=0), 1.0, atol=1e-9)
    assert np.allclose(norm.denormalize("control", z, t), raw["control"], atol=1e-12)
    with pytest.raises(ValueError, match="time indices"):
        norm.normalize("control", raw["control"])
    back = Normalizer.from_dict(norm.to_dict())
    assert all(np.array_equal(back.std[k], norm.std[k]) for k in norm.std)
    with pytest.raises(ValueError, match="normalisation scheme"):
        Normalizer.fit(raw, "per-node")


def test_shorter_training_horizon_fills_the_leading_indices_per_feature():
    raw = {k: (v[:, :60] if v.ndim > 1 and k != "goal" else v) for k, v in _arrays().items()}
    norm = Normalizer.fit(raw, "timestep", K)
    flat = Normalizer.fit(raw, "feature")
    assert np.array_equal(norm.std["state"][:40], np.tile(flat.std["state"], (40, 1)))
    assert np.allclose(norm.std["state"][40:], raw["state"].std(axis=0))


def test_gate_adds_a_cross_entropy_term_and_a_fourth_output():
    cfg, _ = preset("tiny")
    torch.manual_seed(0)
    gated = ArtModel(cfg.__class__(**{**cfg.to_dict(), "burn_gate": True}))
    assert gated.head_control.out_features == 4
    b, t = 2, 10
    batch = {"goal": torch.zeros(b, t, 6), "reward": torch.zeros(b, t),
             "constraint": torch.zeros(b, t), "state": torch.randn(b, t, 6),
             "control": torch.randn(b, t, 3), "timestep": torch.arange(t).expand(b, t) + 90,
             "mask": torch.ones(b, t, dtype=torch.bool),
             "burn_mps": torch.tensor([[0.5] * 5 + [0.0] * 5] * b)}
    _, _, bce = loss_terms(gated, batch, 1e-3)
    assert float(bce.detach()) > 0
    _, _, none = loss_terms(ArtModel(cfg), batch, 1e-3)
    assert float(none.detach()) == 0.0
    with pytest.raises(ConfigError, match="burn_gate"):
        preset("tiny", burn_gate=1)


@pytest.fixture(scope="module")
def setup():
    return deterministic_setup(1, 2)


def _gated(bias: float) -> TrainedArt:
    art = untrained_art("small", burn_gate=True)
    with torch.no_grad():
        art.model.head_control.bias[3] = bias
    return TrainedArt(art.model, art.normalizer)


def test_closed_gate_coasts_and_open_gate_burns(setup):
    safety, x0, target = setup
    closed = rollout(_gated(-50.0), safety, x0, target, -0.25)
    assert np.all(closed.dv_rtn_mps == 0.0)
    assert np.allclose(closed.roe_m[:, -1], np.stack(
        [safety.horizon.propagate_nonlinear(x, np.zeros((N, 3)))[-1] for x in x0]))
    opened = rollout(_gated(50.0), safety, x0, target, -0.25)
    assert np.all(np.linalg.norm(opened.dv_rtn_mps, axis=-1) > 0)


@pytest.mark.parametrize("changes", [{"burn_gate": True}, {"normalization": "timestep"}])
def test_variant_cache_equals_recompute_and_survives_a_checkpoint(setup, changes, tmp_path):
    safety, x0, target = setup
    art = untrained_art("small", **changes)
    if changes.get("normalization") == "timestep":  # per-index scales of the same magnitude
        std = {k: (np.tile(v, (K, 1)) * np.linspace(0.5, 2.0, K)[:, None]
                   if k in ("state", "control") else v) for k, v in art.normalizer.std.items()}
        mean = {k: (np.tile(v, (K, 1)) if k in ("state", "control") else v)
                for k, v in art.normalizer.mean.items()}
        art = TrainedArt(art.model, Normalizer(mean, std))
    cached = rollout(art, safety, x0, target, -0.25)
    full = rollout(art, safety, x0, target, -0.25, use_cache=False)
    assert np.allclose(cached.dv_rtn_mps, full.dv_rtn_mps, rtol=0, atol=1e-7)  # [m/s]
    save(tmp_path / "m.pt", model_payload(art.model, art.normalizer, {}))
    again = load(tmp_path / "m.pt")
    assert again.config == art.config
    assert np.array_equal(rollout(again, safety, x0, target, -0.25).dv_rtn_mps,
                          cached.dv_rtn_mps)
