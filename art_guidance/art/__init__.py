"""The Autonomous Rendezvous Transformer (paper sections III and V), in plain PyTorch.

One concept per module: `config` (model and training configuration, presets), `model` (the
causal GPT over goal / R / C / state / control tokens and its loss), `normalization`
(training-split statistics), `data` (dataset directories -> batches), `train` and
`distributed` (`art-guidance train`, also under torchrun), `checkpoint` (checksummed,
weights-only files), `kv_cache` (incremental decoding), `onnx_export` and `onnx_art` (the
exported model and its torch-free runtime on ONNX Runtime; `onnx_wire` reads the file without
the onnx package), `rollout` (dynamics in the loop;
`art_guidance.art.rollout.rollout`) and `provider` (the warm start as the planner flies it:
conditioning sweep, judging, post hoc check). Scoring rollouts on held-out scenarios lives in
`art_guidance.eval` (`scoring`, `suite`), the DAgger dataset generator in
`art_guidance.data.dagger`. Importing this package imports nothing heavy: the names below are
loaded on first use, so the flight path (`provider`, `rollout`, `onnx_art`) runs without torch
and onnx (the flight install: `art_guidance.extras`).
"""
from __future__ import annotations

import importlib

_LAZY = {"TrainedArt": "checkpoint", "load": "checkpoint", "PRESETS": "config",
         "ArtConfig": "config", "TrainConfig": "config", "preset": "config",
         "ArtModel": "model", "RolloutResult": "rollout", "build_safety": "rollout"}

__all__ = ["PRESETS", "ArtConfig", "ArtModel", "RolloutResult", "TrainConfig", "TrainedArt",
           "build_safety", "load", "preset"]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
