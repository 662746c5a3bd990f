"""ART model and training configuration: frozen, validated, stored inside every checkpoint.

Presets (`PRESETS`): ``paper`` is the appendix table of the paper (6 layers, 6 heads, 384 wide,
K = 100, dropout 0.1 also on the attention, ReLU; 10.6 M parameters); ``medium`` 6 layers,
6 heads, 192 wide (2.7 M parameters); ``small`` is the default,
sized so that a KV-cached 100-step rollout (transformer + dynamics) stays within 40 ms on one
CPU thread of the shared 2-core development machine and trains on 2 CPU cores (3 layers,
3 heads of 32, 96 wide, K = 100, residual/embedding dropout 0.1, none on the attention
probabilities, ReLU; 0.35 M parameters). Measured there with other jobs running: 3 x 96
36 ms median, 3 x 128 46 ms, 4 x 128 69 ms. ``tiny`` exists for tests and smoke runs only.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from art_guidance.errors import ConfigError

REPRESENTATIONS = ("roe", "rtn")
NORMALIZATIONS = ("feature", "timestep")
ACTIVATIONS = ("relu", "gelu")
MODALITIES = ("goal", "reward", "constraint", "state", "control")  # token order in a step
TOKENS_PER_STEP = len(MODALITIES)  # the paper's layout: one token per modality
# `ArtConfig.tokens_per_step`: the paper's five tokens a step, or one packed token a step
TOKEN_LAYOUTS = (TOKENS_PER_STEP, 1)
STATE_DIM, CONTROL_DIM, GOAL_DIM = 6, 3, 6
# Width of a token's packed input: every modality has its own slot (goal 6, R 1, C 1, state 6,
# control 3); a token fills its slot only, so all five embeddings are one matrix product.
SLOTS = {"goal": slice(0, 6), "reward": slice(6, 7), "constraint": slice(7, 8),
         "state": slice(8, 14), "control": slice(14, 17)}
FEATURES = 17


@dataclass(frozen=True)
class ArtConfig:
    """Transformer shape and state representation (the defaults are the `small` preset).

    Attributes:
        n_layers: transformer blocks.
        n_heads: attention heads per block (divides `width`).
        width: embedding width d.
        context: K, the most time steps the model sees (5 K tokens); also the size of the
            learned time-step embedding. A horizon of n <= K nodes uses time indices K - n ..
            K - 1 (aligned to the end, so a replan over the last n nodes looks like the tail
            of a training trajectory).
        dropout: residual and embedding dropout during training.
        attn_dropout: dropout on the attention probabilities during training. GPT-2 (and the
            paper's Hugging Face model) use `dropout` here too; on CPU any value > 0 forces
            PyTorch's unfused attention (the B x H x 5K x 5K probabilities are materialised
            and masked), which made training ~2.5x slower, so the CPU presets set it to 0.
        activation: "relu" (paper) or "gelu".
        representation: state (and goal) representation: "roe" (a-scaled ROE [m]) or "rtn"
            (Psi x [m, m/s]); controls are always RTN delta-v [m/s].
        mlp_ratio: hidden width of the MLP as a multiple of `width`.
        normalization: "feature" (one mean/std per feature) or "timestep" (states and
            controls z-scored per time-step index, as the original ART); see
            `art_guidance.art.normalization`.
        burn_gate: a fourth control output, the logit of "a burn at this node" (trained with a
            binary cross-entropy against ||u|| > `TrainConfig.burn_threshold_mps`); a rollout
            fires the predicted burn only where the logit is positive and coasts elsewhere.
        tokens_per_step: 5, the paper's layout (goal, R, C, state and control tokens), or 1:
            one packed token a step that carries the goal, R(t_i), C(t_i), x(t_i) and the
            previous control u(t_{i-1}) (zero at the first step) and reads out u(t_i) (and
            the next state x(t_{i+1})). The control of step i sees exactly what it sees in
            the paper's layout, with a fifth of the tokens: a decoding step feeds one token
            and attends over one key per step.
    """

    n_layers: int = 3
    n_heads: int = 3
    width: int = 96
    context: int = 100
    dropout: float = 0.1
    attn_dropout: float = 0.0
    activation: str = "relu"
    representation: str = "roe"
    mlp_ratio: int = 4
    normalization: str = "feature"
    burn_gate: bool = False
    tokens_per_step: int = TOKENS_PER_STEP

    def __post_init__(self) -> None:
        if self.normalization not in NORMALIZATIONS:
            raise ConfigError(f"art.normalization must be one of {NORMALIZATIONS}, got "
                              f"{self.normalization!r}")
        if not isinstance(self.burn_gate, bool):
            raise ConfigError(f"art.burn_gate must be a bool, got {self.burn_gate!r}")
        if isinstance(self.tokens_per_step, bool) or self.tokens_per_step not in TOKEN_LAYOUTS:
            raise ConfigError(f"art.tokens_per_step must be one of {TOKEN_LAYOUTS}, got "
                              f"{self.tokens_per_step!r}")
        for name in ("n_layers", "n_heads", "width", "context", "mlp_ratio"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"art.{name} must be an integer >= 1, got {value!r}")
        if self.width % self.n_heads:
            raise ConfigError(f"art.width ({self.width}) must be a multiple of n_heads "
                              f"({self.n_heads})")
        for name in ("dropout", "attn_dropout"):
            if not 0.0 <= float(getattr(self, name)) < 1.0:
                raise ConfigError(f"art.{name} must be in [0, 1), got {getattr(self, name)!r}")
        if self.activation not in ACTIVATIONS:
            raise ConfigError(f"art.activation must be one of {ACTIVATIONS}, got "
                              f"{self.activation!r}")
        if self.representation not in REPRESENTATIONS:
            raise ConfigError(f"art.representation must be one of {REPRESENTATIONS}, got "
                              f"{self.representation!r}")

    @property
    def head_dim(self) -> int:
        """Width of one attention head."""
        return self.width // self.n_heads

    def to_dict(self) -> dict[str, Any]:
        """Plain data for the checkpoint."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "ArtConfig":
        """Inverse of `to_dict` (validated again; unknown keys are an error)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ConfigError(f"unknown ART config keys {sorted(unknown)}")
        return cls(**data)


# The reward-to-go labels of DAgger rows (`TrainConfig.dagger_reward`, `art.data`).
DAGGER_REWARDS = ("hindsight", "fed")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (AdamW, warm-up then cosine decay, gradient-norm clipping).

    Attributes:
        batch_size: trajectories per optimiser step (global, over all processes).
        lr: peak learning rate.
        min_lr_ratio: final learning rate as a fraction of `lr` (cosine decay over
            `max_epochs`); 1.0 keeps it constant like the paper.
        warmup_steps: linear warm-up steps.
        weight_decay: AdamW weight decay (torch default).
        grad_clip: gradient-norm clip (paper: 1.0).
        max_epochs: passes over the training trajectories at most.
        eval_every: optimiser steps between validation passes and checkpoints (0: once per
            epoch).
        patience: validation passes without improvement before early stopping.
        val_fraction: share of the training split held out for validation and early
            stopping (the dataset's test split is never read).
        suffix_fraction: share of the training sequences that start at a random node k > 0
            (teaches replanning over the remaining horizon).
        burn_threshold_mps: a node "burns" when ||u|| exceeds this [m/s] (target of the burn
            gate, models with `ArtConfig.burn_gate`).
        gate_weight: weight of the gate's binary cross-entropy in the loss.
        max_train: use at most this many training trajectories (the first of the seeded
            train rows; 0: all): learning curves over the dataset size.
        precision: "fp32", or "bf16" autocast of the forward pass on CUDA (weights, optimiser
            and loss reduction stay fp32; ignored on CPU).
        dagger_max_cost_ratio: skip DAgger rows whose expert costs more from the takeover
            node on than this many times the scenario's J_CVX (-R(t_k) / J_CVX; 0: keep all):
            the late takeovers of a rollout that drifted off need recovery burns far outside
            the plans' range, whose squared errors would dominate the loss.
        dagger_reward: reward-to-go of the DAgger rows, "hindsight" (as stored) or "fed"
            (as the rollout was fed, `art.data.fed_reward_to_go`).
    """

    batch_size: int = 32
    lr: float = 5e-4
    min_lr_ratio: float = 0.1
    warmup_steps: int = 200
    weight_decay: float = 0.01
    grad_clip: float = 1.0
    max_epochs: int = 200
    eval_every: int = 0
    patience: int = 10
    val_fraction: float = 0.05
    suffix_fraction: float = 0.5
    burn_threshold_mps: float = 1e-3
    gate_weight: float = 0.1
    max_train: int = 0
    precision: str = "fp32"
    dagger_max_cost_ratio: float = 0.0
    dagger_reward: str = "hindsight"

    def __post_init__(self) -> None:
        if self.dagger_reward not in DAGGER_REWARDS:
            raise ConfigError(f"train.dagger_reward must be hindsight or fed, got "
                              f"{self.dagger_reward!r}")
        if self.precision not in ("fp32", "bf16"):
            raise ConfigError(f"train.precision must be fp32 or bf16, got {self.precision!r}")
        ratio = self.dagger_max_cost_ratio
        if isinstance(ratio, bool) or not isinstance(ratio, (int, float)) \
                or not (ratio >= 0 and math.isfinite(ratio)):
            raise ConfigError(f"train.dagger_max_cost_ratio must be a finite number >= 0 (0: "
                              f"keep every DAgger row), got {ratio!r}")
        if not (self.burn_threshold_mps > 0 and self.gate_weight >= 0):
            raise ConfigError("train needs burn_threshold_mps > 0 and gate_weight >= 0")
        if isinstance(self.max_train, bool) or not isinstance(self.max_train, int) \
                or self.max_train < 0:
            raise ConfigError(f"train.max_train must be an integer >= 0, got {self.max_train!r}")
        for name in ("batch_size", "max_epochs", "patience"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"train.{name} must be an integer >= 1, got {value!r}")
        for name in ("warmup_steps", "eval_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"train.{name} must be an integer >= 0, got {value!r}")
        if not (self.lr > 0 and self.grad_clip > 0 and self.weight_decay >= 0):
            raise ConfigError("train needs lr > 0, grad_clip > 0 and weight_decay >= 0")
        if not 0 < self.min_lr_ratio <= 1:
            raise ConfigError(f"train.min_lr_ratio must be in (0, 1], got {self.min_lr_ratio}")
        if not 0 < self.val_fraction < 1 or not 0 <= self.suffix_fraction <= 1:
            raise ConfigError("train needs 0 < val_fraction < 1 and 0 <= suffix_fraction <= 1")

    def to_dict(self) -> dict[str, Any]:
        """Plain data for the checkpoint."""
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> "TrainConfig":
        """A copy with some fields changed (validated again); None values are ignored."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


# first scenario seed of `art-guidance distill`, apart from every benchmark and from the datasets
# the models were trained on; its scenarios are those of dataset seeds 8 (its last indices) and
# 9 (`scenarios.SEED_RULE`), so a student is never evaluated on datasets of those seeds
# (`art.data.trained_seed_bases`: `evaluate --split all` refuses them)
DISTILL_FIRST_SEED = 9_000_000


def check_steps(cfg: ArtConfig, n_steps: int, t0: int) -> None:
    """Raise ValueError unless decoding steps t0 .. t0 + n_steps - 1 fit the context K."""
    if not (0 <= t0 and n_steps >= 1 and t0 + n_steps <= cfg.context):
        raise ValueError(f"time steps {t0}..{t0 + n_steps - 1} do not fit the context "
                         f"K = {cfg.context}")


PRESETS: dict[str, tuple[ArtConfig, TrainConfig]] = {
    "paper": (ArtConfig(n_layers=6, n_heads=6, width=384, context=100, dropout=0.1,
                        attn_dropout=0.1),
              TrainConfig(batch_size=32, lr=2e-4, warmup_steps=500)),
    "medium": (ArtConfig(n_layers=6, n_heads=6, width=192, context=100, dropout=0.1),
               TrainConfig(batch_size=64, lr=3e-4, warmup_steps=300)),
    "small": (ArtConfig(), TrainConfig()),  # the dataclass defaults are the default model
    # the distilled student (`art-guidance distill`): 2 layers, 2 heads of 32, 64 wide, about a
    # third of the small preset's arithmetic per decoding step
    "slim": (ArtConfig(n_layers=2, n_heads=2, width=64, context=100, dropout=0.1),
             TrainConfig(batch_size=32, lr=1e-3, warmup_steps=100)),
    # the slim student with one packed token a step (a fifth of the tokens to decode and
    # attend over)
    "slim1": (ArtConfig(n_layers=2, n_heads=2, width=64, context=100, dropout=0.1,
                        tokens_per_step=1),
              TrainConfig(batch_size=32, lr=1e-3, warmup_steps=100)),
    "tiny": (ArtConfig(n_layers=2, n_heads=2, width=32, context=100, dropout=0.0),
             TrainConfig(batch_size=8, lr=3e-3, warmup_steps=10, eval_every=20)),
}


def preset(name: str, representation: str = "roe", **model_changes: Any
           ) -> tuple[ArtConfig, TrainConfig]:
    """The model and training configuration of a preset, in the chosen representation.

    Args:
        name: preset name.
        representation: "roe" or "rtn".
        model_changes: ArtConfig fields to change (e.g. normalization="timestep"); None
            values are ignored.

    Raises:
        ConfigError: unknown preset, representation or field value.
    """
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    model, train = PRESETS[name]
    changes = {k: v for k, v in model_changes.items() if v is not None}
    try:
        return dataclasses.replace(model, representation=representation, **changes), train
    except TypeError as exc:
        raise ConfigError(f"unknown ART config field: {exc}") from exc
