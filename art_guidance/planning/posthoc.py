"""The paper's post hoc acceptance check of a learned warm start (E_R, E_C).

`check_proposal` is what the pipeline, the provider's candidate ranking and the warm-start
evaluation apply: `posthoc_check` on the trajectory `judged_trajectory` selects by the
planning configuration's `posthoc_subject`:

- "warm_start" (default): the rollout's controls corrected onto the terminal condition with
  the smallest burn-weighted change (`optim.TransferProblem.terminal_warm_start`), which is
  exactly where SCVx* starts from. The rollouts miss the target (by a median 1.7 km for the
  shipped model), so the rollout's own cost and C(t_1) say little about the warm start SCVx*
  receives: the correction adds cost and moves drift arcs into the keep-out region.
- "rollout": the rollout as the model produced it (the paper's check).
"""
from __future__ import annotations

import numpy as np

from art_guidance.config import PlanningConfig, PosthocThresholds
from art_guidance.optim import Trajectory, TransferProblem
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


def judged_trajectory(problem: TransferProblem, dv_rtn_mps: np.ndarray,
                      subject: str) -> Trajectory:
    """The trajectory the check judges for a rollout's controls `dv_rtn_mps` (N, 3) [m/s]:
    the terminal warm start ("warm_start") or the rollout ("rollout"), both propagated with
    the deputy-aware model."""
    if subject == "rollout":
        return problem.propagate(dv_rtn_mps)
    return problem.terminal_warm_start(dv_rtn_mps)


def check_proposal(problem: TransferProblem, dv_rtn_mps: np.ndarray, cvx_cost_mps: float,
                   planning: PlanningConfig, warm_start: Trajectory | None = None
                   ) -> PosthocDecision:
    """The post hoc decision on a rollout's controls for `problem` under `planning` (its
    region and its `posthoc_subject`).

    `warm_start`: the controls' terminal warm start when the caller has it; judged under
    "warm_start" instead of computing it again (`judged_trajectory`)."""
    if warm_start is not None and planning.posthoc_subject == "warm_start":
        dv, roe = warm_start
    else:
        dv, roe = judged_trajectory(problem, dv_rtn_mps, planning.posthoc_subject)
    return posthoc_check(dv, roe, cvx_cost_mps, problem.safety, planning.posthoc)
