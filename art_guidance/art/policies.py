"""How a rollout asks the model for each step's control: the KV-cached decoder (torch's
`CachedDecoder` or ONNX Runtime's `OnnxDecoder`) or the module's whole forward pass, optionally
after the steps already flown (`History`: the context of a replan, as T-MPC feeds it).

The flown steps take the time-step indices just before the first planned node's, so a replan
from node k sees nodes 0 .. k - 1 as they were flown, then plans k .. N - 1: the model's own
training sequence with its past filled in. With the cache, the history's tokens are fed in
the first step's call together with that step's own (one multi-token call); the recompute
policy feeds them with every step (its oracle).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from art_guidance.art.config import FEATURES, SLOTS, TOKENS_PER_STEP

_R_COL, _C_COL = SLOTS["reward"].start, SLOTS["constraint"].start


class History(NamedTuple):
    """The h flown steps before a rollout's first planned node, normalised and tiled over the
    batch B (each step at its own time index).

    Attributes:
        reward: (B, h) R(t_i) of each flown step.
        constraint: (B, h) C(t_i).
        state: (B, h, 6) the state in the model's representation.
        control: (B, h, 3) the burn applied.
    """

    reward: np.ndarray
    constraint: np.ndarray
    state: np.ndarray
    control: np.ndarray

    @property
    def steps(self) -> int:
        """h."""
        return int(self.reward.shape[1])


def fitted_context(context: object, room: int) -> object:
    """The last `room` flown steps of a replan's context (`planning.request.RolloutContext`;
    all of them where they fit), or None where there are none or no room is left before the
    horizon."""
    if context is None or room <= 0 or context.n_steps == 0:
        return None
    return context if context.n_steps <= room else context.last(room)


class CachedPolicy:
    """Feeds each step's new tokens through the KV-cached decoder: the control of the step
    before and the goal, R, C and state tokens of this one, or the one packed token of this
    step (a model with `tokens_per_step` = 1); the history's tokens go with the first step."""

    def __init__(self, art, goal_n: np.ndarray, t0: int, n_steps: int,
                 history: History | None = None) -> None:
        self.dec = art.decoder
        b = goal_n.shape[0]
        h = 0 if history is None else history.steps
        self.h, self.history = h, history
        self.dec.reset(b, h + n_steps, t0 - h)
        tps = self.tps = art.config.tokens_per_step
        self.packed = tps == 1
        # (B, tps (h + T), 17)
        self.feats = np.zeros((b, (h + n_steps) * tps, FEATURES), self.dec.np_dtype)
        self.feats[:, 0::tps, SLOTS["goal"]] = goal_n[:, None]
        for i in range(h):
            prev = history.control[:, i - 1] if i else None
            self._fill(i, history.reward[:, i], history.constraint[:, i],
                       history.state[:, i], prev)

    def _fill(self, jj: int, reward_n: np.ndarray, constraint_n: np.ndarray,
              state_n: np.ndarray, prev_control_n: np.ndarray | None) -> None:
        """Write step jj's tokens (and the control of step jj - 1)."""
        f = self.feats
        if self.packed:
            f[:, jj, _R_COL] = reward_n
            f[:, jj, _C_COL] = constraint_n
            f[:, jj, SLOTS["state"]] = state_n
            if prev_control_n is not None:
                f[:, jj, SLOTS["control"]] = prev_control_n
            return
        base = TOKENS_PER_STEP * jj
        f[:, base + 1, _R_COL] = reward_n
        f[:, base + 2, _C_COL] = constraint_n
        f[:, base + 3, SLOTS["state"]] = state_n
        if prev_control_n is not None:
            f[:, base - 1, SLOTS["control"]] = prev_control_n

    def control(self, j: int, reward_n: np.ndarray, constraint_n: np.ndarray,
                state_n: np.ndarray, prev_control_n: np.ndarray | None) -> np.ndarray:
        """The normalised control of planned step j (B, 3), or (B, 4) with a burn gate."""
        jj = j + self.h
        if prev_control_n is None and jj:  # the first planned step after the history
            prev_control_n = self.history.control[:, self.h - 1]
        self._fill(jj, reward_n, constraint_n, state_n, prev_control_n)
        first = self.h and j == 0  # the history's tokens go with it
        if self.packed:
            p0 = 0 if first else jj
            return self.dec.step_numpy(self.feats[:, p0:jj + 1], p0)
        base = TOKENS_PER_STEP * jj
        p0 = 0 if first else (base - 1 if jj else base)
        return self.dec.step_numpy(self.feats[:, p0:base + 4], p0)


class RecomputePolicy:
    """Feeds the whole context (the history's steps included) again at every step through the
    module's forward pass (torch only)."""

    def __init__(self, art, goal_n: np.ndarray, t0: int, n_steps: int,
                 history: History | None = None) -> None:
        import torch

        self._inference_mode = torch.inference_mode
        self.model = art.model
        p = next(self.model.parameters())
        b = goal_n.shape[0]
        h = 0 if history is None else history.steps
        self.h, n = h, h + n_steps
        kw = {"dtype": p.dtype, "device": p.device}
        self.goal = torch.as_tensor(goal_n, **kw)[:, None].expand(b, n, 6)  # (B, n, 6)
        self.reward = torch.zeros(b, n, **kw)  # (B, n)
        self.constraint = torch.zeros(b, n, **kw)  # (B, n)
        self.state = torch.zeros(b, n, 6, **kw)  # (B, n, 6)
        self.ctrl = torch.zeros(b, n, 3, **kw)  # (B, n, 3)
        self.time = (t0 - h + torch.arange(n, device=p.device)).expand(b, n)  # (B, n)
        if h:
            self.reward[:, :h] = torch.as_tensor(history.reward, **kw)
            self.constraint[:, :h] = torch.as_tensor(history.constraint, **kw)
            self.state[:, :h] = torch.as_tensor(history.state, **kw)
            self.ctrl[:, :h] = torch.as_tensor(history.control, **kw)

    def control(self, j: int, reward_n: np.ndarray, constraint_n: np.ndarray,
                state_n: np.ndarray, prev_control_n: np.ndarray | None) -> np.ndarray:
        """The normalised control of planned step j (B, 3), or (B, 4) with a burn gate."""
        jj = j + self.h
        as_t = self.reward.new_tensor
        self.reward[:, jj] = as_t(reward_n)
        self.constraint[:, jj] = as_t(constraint_n)
        self.state[:, jj] = as_t(state_n)
        if j:
            self.ctrl[:, jj - 1] = as_t(prev_control_n)
        s = slice(0, jj + 1)
        with self._inference_mode():
            u_pred, _ = self.model(self.goal[:, s], self.reward[:, s], self.constraint[:, s],
                                   self.state[:, s], self.ctrl[:, s], self.time[:, s])
        return u_pred[:, jj].cpu().numpy()  # (B, 3), (B, 4) with a burn gate
