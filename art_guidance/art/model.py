"""The Autonomous Rendezvous Transformer: a causal GPT over (goal, R, C, state, control) tokens.

Paper sections III and V ("ART architecture"). Every time step t_i contributes five tokens in
this order: the goal (terminal target state), the reward-to-go R(t_i), the constraint-violation
budget C(t_i), the state x(t_i) and the control u(t_i). Each modality has its own linear
embedding; a learned time-step embedding is added to the five tokens of its step (no positional
embedding); the stacked tokens go through a LayerNorm and causal pre-LN GPT-2 blocks. Two
modality-specific decoders read the final hidden states: the control u(t_i) from the output of
the state token x(t_i), and the next state x(t_{i+1}) from the output of the control token
u(t_i). With `ArtConfig.tokens_per_step` = 1 the five embeddings of a step are summed into
one token (the control slot holding the previous step's control), which both heads read.
Training minimises the paper's state + control MSE with teacher forcing
(`loss_terms`), on z-scored features (`normalization`).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from art_guidance.art.config import (
    CONTROL_DIM, GOAL_DIM, MODALITIES, STATE_DIM, TOKENS_PER_STEP, ArtConfig,
)

_IN_DIMS = {"goal": GOAL_DIM, "reward": 1, "constraint": 1, "state": STATE_DIM,
            "control": CONTROL_DIM}
STATE_TOKEN, CONTROL_TOKEN = MODALITIES.index("state"), MODALITIES.index("control")


def activation(name: str):
    """The MLP non-linearity of a config ("relu" or "gelu")."""
    return F.relu if name == "relu" else F.gelu


class Block(nn.Module):
    """Pre-LN transformer block: x + attn(ln1(x)), then x + mlp(ln2(x))."""

    def __init__(self, cfg: ArtConfig) -> None:
        super().__init__()
        d = cfg.width
        self.n_heads = cfg.n_heads
        self.attn_dropout = cfg.attn_dropout
        self.act = activation(cfg.activation)
        self.ln1 = nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.proj = nn.Linear(d, d)
        self.ln2 = nn.LayerNorm(d)
        self.fc = nn.Linear(d, cfg.mlp_ratio * d)
        self.out = nn.Linear(cfg.mlp_ratio * d, d)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """Causal self-attention and MLP over `h` (B, L, d)."""
        b, length, d = h.shape
        qkv = self.qkv(self.ln1(h)).view(b, length, 3, self.n_heads, d // self.n_heads)
        q, k, v = qkv.permute(2, 0, 3, 1, 4)  # each (B, H, L, hd)
        p = self.attn_dropout if self.training else 0.0
        a = F.scaled_dot_product_attention(q, k, v, is_causal=True, dropout_p=p)  # (B, H, L, hd)
        h = h + self.drop(self.proj(a.transpose(1, 2).reshape(b, length, d)))  # (B, L, d)
        return h + self.drop(self.out(self.act(self.fc(self.ln2(h)))))  # (B, L, d)


class ArtModel(nn.Module):
    """Causal GPT over the paper's trajectory representation (five tokens per step).

    Attributes:
        cfg: the ArtConfig the model was built from.
    """

    def __init__(self, cfg: ArtConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.width
        self.embed = nn.ModuleDict({m: nn.Linear(_IN_DIMS[m], d) for m in MODALITIES})
        self.time_embed = nn.Embedding(cfg.context, d)
        self.embed_ln = nn.LayerNorm(d)
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layers))
        self.ln_f = nn.LayerNorm(d)
        self.head_control = nn.Linear(d, CONTROL_DIM + int(cfg.burn_gate))
        self.head_state = nn.Linear(d, STATE_DIM)
        self.apply(self._init_weights)
        for block in self.blocks:  # GPT-2: scale the residual projections by 1/sqrt(2 L)
            for lin in (block.proj, block.out):
                nn.init.normal_(lin.weight, std=0.02 / math.sqrt(2 * cfg.n_layers))

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        if isinstance(module, (nn.Linear, nn.Embedding)):
            nn.init.normal_(module.weight, std=0.02)
        if isinstance(module, nn.Linear) and module.bias is not None:
            nn.init.zeros_(module.bias)

    def n_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters())

    def forward(self, goal: torch.Tensor, reward: torch.Tensor, constraint: torch.Tensor,
                state: torch.Tensor, control: torch.Tensor, timestep: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict every step's control and next state from the whole (causal) context.

        Args:
            goal: (B, T, 6) normalised goal (the same target at every step).
            reward: (B, T) normalised reward-to-go R(t_i).
            constraint: (B, T) normalised constraint-violation budget C(t_i).
            state: (B, T, 6) normalised state x(t_i).
            control: (B, T, 3) normalised control u(t_i) (teacher forcing; the last step's
                control only influences predictions after it).
            timestep: (B, T) int64 time-step indices in [0, K).

        Returns:
            control_pred (B, T, 3) (or (B, T, 4) with the burn gate's logit last): u(t_i) read
                from the state token of step i (the packed token of step i with one token a
                step);
            state_pred (B, T, 6): x(t_{i+1}) read from the control token of step i (the
                packed token of step i, which has not seen u(t_i)).
        """
        b, t = reward.shape
        emb = self.embed
        packed = self.cfg.tokens_per_step == 1
        if packed:  # one token a step: the five embeddings summed, u(t_{i-1}) in it
            prev = torch.cat([torch.zeros_like(control[:, :1]), control[:, :-1]], dim=1)
            h = (emb["goal"](goal) + emb["reward"](reward[..., None])
                 + emb["constraint"](constraint[..., None]) + emb["state"](state)
                 + emb["control"](prev) + self.time_embed(timestep))  # (B, T, d)
        else:
            tokens = torch.stack([
                emb["goal"](goal), emb["reward"](reward[..., None]),
                emb["constraint"](constraint[..., None]), emb["state"](state),
                emb["control"](control)], dim=2)  # (B, T, 5, d)
            tokens = tokens + self.time_embed(timestep)[:, :, None, :]  # (B, T, 5, d)
            h = tokens.reshape(b, t * TOKENS_PER_STEP, -1)  # (B, 5T, d)
        h = self.drop(self.embed_ln(h))  # (B, tps T, d)
        for block in self.blocks:
            h = block(h)  # (B, tps T, d)
        h = self.ln_f(h)  # (B, tps T, d)
        if packed:
            return self.head_control(h), self.head_state(h)  # (B, T, 3), (B, T, 6)
        h = h.reshape(b, t, TOKENS_PER_STEP, -1)  # (B, T, 5, d)
        control_pred = self.head_control(h[:, :, STATE_TOKEN])  # (B, T, 3)
        state_pred = self.head_state(h[:, :, CONTROL_TOKEN])  # (B, T, 6)
        return control_pred, state_pred


def loss_terms(model: ArtModel, batch: dict[str, torch.Tensor], burn_threshold_mps: float = 1e-3
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sums of the paper's loss terms with teacher forcing (normalised units).

    The control of step i is compared with the data wherever step i is valid; the next-state
    prediction of step i with the data's state at step i + 1 wherever that step is valid. A
    model with a burn gate also gets the binary cross-entropy of its gate logit against
    ``||u_i|| > burn_threshold_mps`` (from the batch's "burn_mps", physical units).

    Args:
        model: the transformer.
        batch: "goal" (B, T, 6), "reward" (B, T), "constraint" (B, T), "state" (B, T, 6),
            "control" (B, T, 3), "timestep" (B, T) int64, "mask" (B, T) bool (valid steps;
            padding only at the end of a sequence, so causality keeps it out of the valid
            predictions), "burn_mps" (B, T) ||u_i|| [m/s] (burn-gate models).
        burn_threshold_mps: what counts as a burn for the gate [m/s].

    Returns:
        (sum of squared control errors, sum of squared next-state errors, sum of the gate's
        cross-entropy over valid steps (0 without a gate)), fp32 scalars. Divide by the counts
        of `loss_counts` over the whole (global) batch to get the means.
    """
    control_pred, state_pred = model(batch["goal"], batch["reward"], batch["constraint"],
                                     batch["state"], batch["control"], batch["timestep"])
    control_pred, state_pred = control_pred.float(), state_pred.float()
    mask = batch["mask"].to(control_pred.dtype)  # (B, T)
    sse_u = (((control_pred[..., :CONTROL_DIM] - batch["control"]) ** 2).sum(-1) * mask).sum()
    err_x = ((state_pred[:, :-1] - batch["state"][:, 1:]) ** 2).sum(-1)  # (B, T-1)
    sse_x = (err_x * mask[:, 1:]).sum()
    bce = sse_u.new_zeros(())
    if model.cfg.burn_gate:
        target = (batch["burn_mps"] > burn_threshold_mps).to(control_pred.dtype)  # (B, T)
        bce = (F.binary_cross_entropy_with_logits(control_pred[..., CONTROL_DIM], target,
                                                  reduction="none") * mask).sum()
    return sse_u, sse_x, bce


def combined_loss(sse_u: torch.Tensor | float, sse_x: torch.Tensor | float,
                  bce: torch.Tensor | float, counts: tuple[int, int],
                  gate_weight: float) -> torch.Tensor | float:
    """The training loss from the sums of `loss_terms` and the `loss_counts` of the same
    (global) batch: mean control MSE + mean next-state MSE + `gate_weight` x the gate's mean
    cross-entropy (its sum runs over the valid steps, n_u / CONTROL_DIM of them)."""
    n_u, n_x = counts
    return sse_u / n_u + sse_x / n_x + gate_weight * CONTROL_DIM * bce / n_u


def loss_counts(mask: torch.Tensor) -> tuple[int, int]:
    """Entries the control and state sums of `loss_terms` run over: (3 * valid steps,
    6 * valid next steps); the gate's sum runs over the valid steps (first count / 3).

    Args:
        mask: (B, T) bool valid steps.
    """
    return CONTROL_DIM * int(mask.sum()), STATE_DIM * int(mask[:, 1:].sum())
