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
from art_guidance.config import GuidanceConfig

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
