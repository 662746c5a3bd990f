"""The Autonomous Rendezvous Transformer (paper sections III and V), in plain PyTorch.

One concept per module: `config` (model and training configuration, presets), `model` (the
causal GPT over goal / R / C / state / control tokens and its loss), `normalization`
(training-split statistics), `data` (dataset directories -> batches), `train` and
`distributed` (`art-guidance train`, also under torchrun), `checkpoint` (checksummed,
weights-only files), `kv_cache` (incremental decoding), `rollout` (dynamics in the loop;
`art_guidance.art.rollout.rollout`), `evaluate` (held-out comparison with CVX) and `dagger`
(expert re-solves from the model's own rollouts, `art-guidance dagger`). Importing this
package imports torch.
"""

from art_guidance.art.checkpoint import TrainedArt, load
from art_guidance.art.config import PRESETS, ArtConfig, TrainConfig, preset
from art_guidance.art.scoring import (
    RolloutScores, score_oracle, score_rollouts, heldout_scenarios,
)
from art_guidance.art.model import ArtModel
from art_guidance.art.rollout import RolloutResult, build_safety

__all__ = ["PRESETS", "ArtConfig", "ArtModel", "RolloutScores", "RolloutResult",
           "TrainConfig", "TrainedArt", "build_safety", "score_oracle", "score_rollouts",
           "heldout_scenarios", "load", "preset"]
