"""The Autonomous Rendezvous Transformer (paper sections III and V), in plain PyTorch.

One concept per module: `config` (model and training configuration, presets), `model` (the
causal GPT over goal / R / C / state / control tokens and its loss), `normalization`
(training-split statistics), `data` (dataset directories -> batches), `train` and
`distributed` (`art-guidance train`, also under torchrun), `checkpoint` (checksummed,
weights-only files), `kv_cache` (incremental decoding), `rollout` (dynamics in the loop;
`art_guidance.art.rollout.rollout`) and `provider` (the warm start as the planner flies it:
conditioning sweep, judging, post hoc check). Scoring rollouts on held-out scenarios lives in
`art_guidance.eval` (`scoring`, `suite`), the DAgger dataset generator in
`art_guidance.data.dagger`. Importing this package imports torch, not the solvers.
"""

from art_guidance.art.checkpoint import TrainedArt, load
from art_guidance.art.config import PRESETS, ArtConfig, TrainConfig, preset
from art_guidance.art.model import ArtModel
from art_guidance.art.rollout import RolloutResult, build_safety

__all__ = ["PRESETS", "ArtConfig", "ArtModel", "RolloutResult", "TrainConfig", "TrainedArt",
           "build_safety", "load", "preset"]
