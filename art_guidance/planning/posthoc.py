"""The paper's post hoc acceptance check of a learned warm start (E_R, E_C)."""
from __future__ import annotations

import numpy as np

from art_guidance.config import PosthocThresholds
from art_guidance.planning.types import PosthocDecision
from art_guidance.safety import PassiveSafety


def posthoc_check(dv_rtn_mps: np.ndarray, roe_m: np.ndarray, cvx_cost_mps: float,
                  safety: PassiveSafety, thresholds: PosthocThresholds) -> PosthocDecision:
    """Compare a rollout's realised performance with the desired one (paper eq. for E_P).

    The desired reward-to-go is the CVX lower bound (R_des = -J_CVX) and the desired
    constraint-violation budget is zero, so E_R = (R - R_des) / R_des and E_C = C(t1).

    Args:
        dv_rtn_mps: (N, 3) rollout controls [m/s].
        roe_m: (N, 6) rollout states [m] (dynamics in the loop).
        cvx_cost_mps: J_CVX [m/s].
        safety: the plan's passive-safety model (gives C(t1)).
        thresholds: acceptance region.
    """
    r_des = -float(cvx_cost_mps)
    r_art = -float(np.linalg.norm(dv_rtn_mps, axis=1).sum())
    e_r = (r_art - r_des) / r_des if abs(r_des) > 1e-12 else float("inf")
    e_c = float(safety.evaluate(roe_m, dv_rtn_mps).constraint_to_go[0])
    accepted = bool(thresholds.contains(100.0 * e_r, e_c))
    return PosthocDecision(float(e_r), e_c, accepted)
