"""Held-out evaluation of ART rollouts against CVX (paper section V, post hoc check).

For every held-out scenario the model is rolled out from the initial state, conditioned on
R(t_1) = -J_CVX and C(t_1) = 0 with the target as goal, and compared with the CVX solution of
the same scenario: its realised constraint-violation budget C(t_1) against CVX's, the share of
rollouts with C(t_1) = 0, the cost error E_R = (R_ART - R_des) / R_des with R_des = -J_CVX, and
the share inside the paper's post hoc acceptance region (-1.5 <= 100 E_R <= 3.5,
0 <= E_C <= 2, with E_C = C_ART(t_1) - 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.art.checkpoint import TrainedArt
from art_guidance.art.provider import best_candidate, judged_controls
from art_guidance.art.rollout import replay, rollout
from art_guidance.checks import as_finite_array
from art_guidance.config import PosthocThresholds
from art_guidance.errors import InputError
from art_guidance.optim import TransferProblem
from art_guidance.safety import PassiveSafety


@dataclass(frozen=True)
class RolloutScores:
    """Per-scenario results and their summary.

    Attributes:
        c_art: (M,) C(t_1) realised by the rollouts.
        c_cvx: (M,) C(t_1) of the CVX solutions.
        e_r: (M,) E_R = (R_ART - R_des) / R_des, R_des = -J_CVX [-].
        accepted: (M,) inside the post hoc acceptance region.
        cost_mps: (M,) rollout cost sum ||dv|| [m/s].
    """

    c_art: np.ndarray
    c_cvx: np.ndarray
    e_r: np.ndarray
    accepted: np.ndarray
    cost_mps: np.ndarray

    def summary(self) -> dict[str, float]:
        """Means and shares over the scenarios (JSON-ready)."""
        return {"n": int(self.c_art.size),
                "mean_c_art": float(self.c_art.mean()), "mean_c_cvx": float(self.c_cvx.mean()),
                "frac_c_art_zero": float(np.mean(self.c_art == 0)),
                "frac_c_cvx_zero": float(np.mean(self.c_cvx == 0)),
                "frac_c_art_le_cvx": float(np.mean(self.c_art <= self.c_cvx)),
                "mean_e_r": float(self.e_r.mean()), "median_e_r": float(np.median(self.e_r)),
                "frac_posthoc_accepted": float(self.accepted.mean())}


def heldout_scenarios(data: dict[str, np.ndarray], extra: tuple[str, ...] = (),
                      split: str = "test") -> dict[str, np.ndarray]:
    """The held-out scenarios of a loaded dataset whose CVX solve succeeded.

    Args:
        data: `art_guidance.data.storage.load_dataset` output.
        extra: further dataset fields to select for the same scenarios (e.g. "cvx_roe_m").
        split: "test" (the dataset's test split) or "all" (every scenario: for a dataset
            generated with a seed no model was trained on).

    Returns:
        {"roe0_m": (M, 6), "target_rtn": (M, 6), "cvx_cost_mps": (M,),
        "cvx_constraint_to_go0": (M,), "index": (M,)} and the `extra` fields.
    """
    if split not in ("test", "all"):
        raise InputError("split", "must be 'test' or 'all'", split)
    keep = (data["is_test"] | (split == "all")) & (data["cvx_constraint_to_go0"] >= 0)
    return {k: data[k][keep] for k in ("roe0_m", "target_rtn", "cvx_cost_mps",
                                       "cvx_constraint_to_go0", "index", *extra)}


def score_rollouts(art: TrainedArt, safety: PassiveSafety, roe0_m: object,
                   target_rtn: object, cvx_cost_mps: object, cvx_constraint_to_go0: object,
                   thresholds: PosthocThresholds | None = None,
                   batch_size: int = 64,
                   reward_scales: tuple[float, ...] = (1.0,),
                   subject: str = "warm_start") -> RolloutScores:
    """Roll the model out on held-out scenarios and compare with CVX.

    Args:
        art: the trained model.
        safety: passive-safety model of the dataset's horizon and mode (`build_safety`).
        roe0_m: (M, 6) initial a-scaled ROE [m].
        target_rtn: (M, 6) terminal RTN states [m, m/s].
        cvx_cost_mps: (M,) J_CVX [m/s], > 0.
        cvx_constraint_to_go0: (M,) C(t_1) of the CVX solutions.
        thresholds: post hoc acceptance region (default: the paper's).
        batch_size: scenarios per batched rollout.
        reward_scales: the conditioning sweep of the in-flight provider (R(t_1) = -s J_CVX per
            s; the candidate per scenario the provider proposes: `art.provider.best_candidate`
            on the numbers of `subject`); (1.0,): the model's single rollout. The scores are
            those of the proposed candidate's rollout itself (the paper's criteria).
        subject: what the provider ranks the candidates by, as the check judges them
            ("warm_start": each candidate's terminal warm start, the packaged default;
            "rollout": the rollout itself).

    Returns:
        RolloutScores (call `.summary()` for the aggregate numbers).

    Raises:
        InputError: mismatched shapes, non-finite values or a non-positive J_CVX.
    """
    x0 = as_finite_array("roe0_m", roe0_m, (None, 6))
    m = x0.shape[0]
    target = as_finite_array("target_rtn", target_rtn, (m, 6))
    j_cvx = as_finite_array("cvx_cost_mps", cvx_cost_mps, (m,))
    c_cvx = as_finite_array("cvx_constraint_to_go0", cvx_constraint_to_go0, (m,))
    if m == 0 or np.any(j_cvx <= 0):
        raise InputError("cvx_cost_mps", "need at least one scenario and J_CVX > 0", j_cvx)
    region = thresholds or PosthocThresholds()
    scales = np.asarray(reward_scales, dtype=float)
    k = scales.size
    c_art, cost = np.empty(m, dtype=int), np.empty(m)
    for s in range(0, m, batch_size):
        sl = slice(s, min(s + batch_size, m))
        b = sl.stop - sl.start
        res = rollout(art, safety, np.repeat(x0[sl], k, axis=0), np.repeat(target[sl], k, axis=0),
                      -np.repeat(j_cvx[sl], k) * np.tile(scales, b), 0.0)
        c_all = res.realised_constraint_to_go[:, 0].reshape(b, k)
        cost_all = res.cost_mps.reshape(b, k)
        if k == 1:
            pick = [0] * b
        else:  # as the provider ranks them (`ArtWarmStart.propose`)
            judged = [(cost_all[i], c_all[i]) if subject == "rollout" else judged_controls(
                TransferProblem.to_target(safety, x0[sl][i], target[sl][i]),
                res.dv_rtn_mps[i * k:(i + 1) * k], subject) for i in range(b)]
            pick = [best_candidate(*judged[i], j_cvx[sl][i], region) for i in range(b)]
        c_art[sl] = c_all[np.arange(b), pick]
        cost[sl] = cost_all[np.arange(b), pick]
    return _judge(c_art, c_cvx, cost, j_cvx, region)


def score_oracle(safety: PassiveSafety, roe0_m: object, dv_rtn_mps: object,
                 cvx_cost_mps: object, cvx_constraint_to_go0: object,
                 thresholds: PosthocThresholds | None = None) -> RolloutScores:
    """The metrics of `score_rollouts` for a perfect model: the plans' own controls driven
    through the rollout machinery (`replay`: same propagation, R and C updates).

    Args:
        safety: passive-safety model of the dataset's horizon and mode.
        roe0_m: (M, 6) initial a-scaled ROE [m].
        dv_rtn_mps: (M, N, 3) the plans' controls [m/s].
        cvx_cost_mps: (M,) J_CVX [m/s], > 0.
        cvx_constraint_to_go0: (M,) C(t_1) of the CVX solutions.
        thresholds: post hoc acceptance region (default: the paper's).
    """
    x0 = as_finite_array("roe0_m", roe0_m, (None, 6))
    m = x0.shape[0]
    j_cvx = as_finite_array("cvx_cost_mps", cvx_cost_mps, (m,))
    c_cvx = as_finite_array("cvx_constraint_to_go0", cvx_constraint_to_go0, (m,))
    res = replay(safety, x0, dv_rtn_mps, -j_cvx, 0.0)
    return _judge(res.realised_constraint_to_go[:, 0], c_cvx, res.cost_mps, j_cvx, thresholds)


def _judge(c_art: np.ndarray, c_cvx: np.ndarray, cost: np.ndarray, j_cvx: np.ndarray,
           thresholds: PosthocThresholds | None) -> RolloutScores:
    """E_R, E_C and the post hoc decision of realised rollouts against CVX."""
    t = thresholds or PosthocThresholds()
    r_des = -j_cvx
    e_r = (-cost - r_des) / r_des
    accepted = t.contains(100.0 * e_r, c_art - 0)
    return RolloutScores(c_art.astype(int), c_cvx.astype(int), e_r, accepted, cost)
