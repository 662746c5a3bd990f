"""The paper's qualitative example: one scenario recomputed with its trajectories.

The evaluation stores numbers, not trajectories; for the scenario where ART helped most
(largest J_SCP,CVX - J_SCP,ART) the comparison is solved again (`warmstart.solve_both`, the
same inputs and settings, so the same result) and the four trajectories (CVX, ART, PS-CVX,
PS-ART) are stored with what the paper's sample-trajectory and constraint-history figures
show: RTN states, the passive-safety margins of every node with and without the uncertainty
margin, and PS-ART's free-drift arcs with their position covariances.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.data.storage import encode_shard
from art_guidance.eval.warmstart import ROW_FIELDS, WarmStartRun, solve_both
from art_guidance.files import write_atomic
from art_guidance.optim import TransferProblem
from art_guidance.safety import PassiveSafety

TRAJECTORIES = ("cvx", "art", "ps_cvx", "ps_art")
N_ARC = 41  # samples per drift arc
TIMING = ("ms_cvx", "ms_art", "ms_scp_cvx", "ms_scp_art")


def _plans(run: WarmStartRun) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(roe_m (N, 6), dv_rtn_mps (N, 3)) of the four trajectories."""
    return {"cvx": (run.cvx.roe_m, run.cvx.dv_rtn_mps),
            "art": (run.art_roe_m, np.asarray(run.proposal.dv_rtn_mps, float)),
            "ps_cvx": (run.from_cvx.roe_m, run.from_cvx.dv_rtn_mps),
            "ps_art": (run.from_art.roe_m, run.from_art.dv_rtn_mps)}


def drift_arcs(safety: PassiveSafety, roe_m: np.ndarray,
               dv_rtn_mps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Free-drift arcs from every post-burn state, with their position covariances.

    Returns:
        (N, K, 3) RTN positions [m] at K = N_ARC offsets over the safety drift, and (N, K, 3, 3)
        their covariances [m^2] (zeros when deterministic).
    """
    z = safety.post_burn(roe_m, dv_rtn_mps)  # (N, 6)
    cov = safety.covariance(roe_m, dv_rtn_mps)  # (N, 6, 6)
    tau = np.linspace(0.0, float(safety.tau_s[-1]), N_ARC)
    pos = np.empty((safety.n_nodes, N_ARC, 3))
    pos_cov = np.empty((safety.n_nodes, N_ARC, 3, 3))
    for i in range(safety.n_nodes):
        maps = safety.drift_maps(i, tau)[1]  # (K, 3, 6)
        pos[i] = maps @ z[i]
        pos_cov[i] = maps @ cov[i] @ maps.transpose(0, 2, 1)
    return pos, pos_cov


def recompute(problem: TransferProblem, provider: object, config: GuidanceConfig,
              stored: dict | None = None) -> dict[str, np.ndarray]:
    """Solve one scenario again and collect what the example figures plot.

    Args:
        problem: the scenario's transfer problem (`eval.inputs.problem_of`; its
            passive-safety model of the model's mode).
        provider: the ART warm-start provider.
        config: the evaluation's settings.
        stored: the stored row ({field: value}) to check the recomputation against.

    Returns:
        {"<traj>_rtn": (N, 6), "<traj>_dv_rtn_mps": (N, 3), "<traj>_margin_m": (N,) with the
        uncertainty margin, "<traj>_margin_mean_m": (N,) without it, "<traj>_cost_mps": ()
        for traj in TRAJECTORIES; "arc_rtn_m": (N, K, 3), "arc_cov_m2": (N, K, 3, 3) of
        PS-ART; "semi_axes_m": (N, 3); "target_rtn", "q_sigma", "chance", "e_r", "e_c",
        "accepted", "reproduced" (the row equals `stored` up to timings)}.
    """
    from art_guidance.art.rollout import build_safety

    safety = problem.safety
    run = solve_both(problem, provider, config)
    mean = safety if safety.uncertainty is None else build_safety(provider.art, False)
    out: dict[str, np.ndarray] = {}
    for name, (roe, dv) in _plans(run).items():
        ok = np.all(np.isfinite(roe)) and np.all(np.isfinite(dv))
        nan = np.full(safety.n_nodes, np.nan)
        out[f"{name}_rtn"] = safety.horizon.to_rtn(roe)
        out[f"{name}_dv_rtn_mps"] = np.asarray(dv)
        out[f"{name}_margin_m"] = safety.evaluate(roe, dv).margin_m if ok else nan
        out[f"{name}_margin_mean_m"] = mean.evaluate(roe, dv).margin_m if ok else nan
        out[f"{name}_cost_mps"] = np.float64(np.linalg.norm(dv, axis=1).sum())
    if np.all(np.isfinite(run.from_art.roe_m)):
        out["arc_rtn_m"], out["arc_cov_m2"] = drift_arcs(safety, run.from_art.roe_m,
                                                         run.from_art.dv_rtn_mps)
    row = run.row()
    same = stored is None or all(
        np.isclose(getattr(row, f), stored[f], rtol=1e-9, atol=1e-12, equal_nan=True)
        for f in ROW_FIELDS if f not in TIMING)
    out.update(semi_axes_m=safety.semi_axes_m, target_rtn=np.asarray(problem.target_rtn),
               q_sigma=np.float64(safety.q_sigma), chance=np.bool_(safety.uncertainty is not None),
               e_r=np.float64(row.e_r), e_c=np.float64(row.e_c),
               accepted=np.bool_(row.accepted), j_cvx=np.float64(row.j_cvx),
               j_scp_cvx=np.float64(row.j_scp_cvx), j_scp_art=np.float64(row.j_scp_art),
               reproduced=np.bool_(same))
    return out


def save(path: str | Path, example: dict[str, np.ndarray], index: int) -> None:
    """Atomically store an example (as .npz, with its pair index)."""
    write_atomic(path, encode_shard({"index": np.int64(index), **example}))


def load(path: str | Path) -> dict[str, np.ndarray] | None:
    """A stored example, or None if there is none."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError):
        return None
