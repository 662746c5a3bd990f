"""Test oracles of the package's array doors (entry points no code outside the tests needs).

- `sign_only_violations`: `PassiveSafety.violated`'s oracle, the sign of the sign-only
  certified minimum (`PassiveSafety.minimum(..., sign_only=True)`);
- `final_post_burn_linear`: the linear model's post-burn state at the last node, the convex
  problem's terminal condition (`Horizon.final_post_burn_nonlinear` is the deputy-aware one).
"""
from __future__ import annotations

import numpy as np

from art_guidance.dynamics import Horizon
from art_guidance.safety import PassiveSafety


def sign_only_violations(safety: PassiveSafety, nodes: object, roe_m: object,
                         dv_rtn_mps: object) -> np.ndarray:
    """Bool of the leading shape of `roe_m` (..., 6) [m]: the sign-only minimum below zero
    (validated as `PassiveSafety.minimum` validates; `dv_rtn_mps` (..., 3) [m/s])."""
    return safety.minimum(nodes, roe_m, dv_rtn_mps, sign_only=True)[0] < 0.0


def final_post_burn_linear(horizon: Horizon, roe_m: np.ndarray,
                           dv_rtn_mps: np.ndarray) -> np.ndarray:
    """``x_N + B_N u_N`` (6,) [m] of a trajectory (N, 6) [m], (N, 3) [m/s] (B at zero
    separation)."""
    return roe_m[-1] + horizon.b[-1] @ dv_rtn_mps[-1]
