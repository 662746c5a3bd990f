"""Untrained ART models (fixed seeds, plausible normalisation scales) for machinery tests.

What such tests check is the plumbing (cache == recompute, dynamics, R/C bookkeeping,
checkpoints, the pipeline's decisions), not skill; the shipped trained model is tested on its
own.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from art_guidance.art import ArtModel, TrainedArt, preset
from art_guidance.art.checkpoint import model_payload, save
from art_guidance.art.normalization import Normalizer
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.safety import PassiveSafety

SCALES = {"goal": [500.0, 1000.0, 100.0, 100.0, 50.0, 50.0], "reward": [0.2], "constraint": [2.0],
          "state": [1000.0, 8000.0, 300.0, 300.0, 50.0, 50.0], "control": [0.01, 0.01, 0.005]}


def untrained_art(preset_name: str = "small", representation: str = "roe", seed: int = 0,
                  dtype: torch.dtype = torch.float32, **changes) -> TrainedArt:
    """A randomly initialised model with fixed-seed weights and plausible scales."""
    torch.manual_seed(seed)
    cfg, _ = preset(preset_name, representation)
    model = ArtModel(dataclasses.replace(cfg, **changes)).to(dtype)
    mean = {k: np.zeros(len(v)) for k, v in SCALES.items()}
    mean.update(reward=np.array([-0.3]), constraint=np.array([1.0]))
    return TrainedArt(model, Normalizer(mean, {k: np.array(v) for k, v in SCALES.items()}))


def write_untrained_checkpoint(path: str | Path, seed: int = 0,
                               preset_name: str = "small") -> str:
    """Save an untrained model as a checkpoint whose provenance names the packaged scenario
    (so the provider knows the training horizon); returns its sha256."""
    art = untrained_art(preset_name, seed=seed)
    meta = {"dataset": {"mode": "chance", "guidance_config": GuidanceConfig.load().to_json()}}
    return save(path, model_payload(art.model, art.normalizer, meta))


def deterministic_setup(seed: int, n: int) -> tuple[PassiveSafety, np.ndarray, np.ndarray]:
    """The packaged scenario's deterministic safety model, `n` initial ROE drawn from its
    initial-state box (seeded) and the plus_vbar target: (safety, x0 (n, 6) [m], target (6,))."""
    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
    rng = np.random.default_rng(seed)
    rtn0 = np.array(sc.rtn0_nominal) + rng.uniform(-1, 1, (n, 6)) * np.array(sc.rtn0_half_width)
    x0 = np.array([roe_from_rtn_linear(chief, r) for r in rtn0])
    return PassiveSafety(horizon, sc, None), x0, np.array(sc.waypoints_rtn["plus_vbar"])
