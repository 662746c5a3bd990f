"""What a flown run achieved: the AE -> KOZ switch in sim time, the passive-safety model of the
executed nodes and the outcome (miss, delta-v, margins) as JSON-ready numbers.
"""
from __future__ import annotations


import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.errors import InputError
from art_guidance.safety import PassiveSafety

from art_guidance.sim.simulator import EPOCH_MATCH_S, RendezvousSim


def koz_switch_time_s(scenario: ScenarioConfig, chief_a_m: float, t0_s: float = 0.0) -> float:
    """Sim time [s] where the approach ellipsoid switches to the keep-out zone.

    Node `scenario.ae_to_koz_node` of the nominal grid (`n_orbits`, `n_nodes` over periods of
    `chief_a_m`) started at `t0_s` (the first plan's epoch), the planner's rule by node index;
    inf if the switch node is beyond the grid.
    """
    if scenario.ae_to_koz_node >= scenario.n_nodes:
        return float("inf")
    grid = time_grid_s(float(chief_a_m), scenario.n_orbits, scenario.n_nodes)
    return float(t0_s + grid[int(scenario.ae_to_koz_node)])


def run_safety_model(sim: RendezvousSim, uncertainty: UncertaintyConfig | None = None,
                     koz_switch_t_s: float | None = None) -> PassiveSafety | None:
    """PassiveSafety on a horizon at the run's executed node epochs (None if < 2 nodes).

    The horizon uses the planner's chief model (`chief_mean_oe0` at t = 0), so the drift
    maps are the ones the planner uses. The keep-out zone applies from the first node at or
    after `koz_switch_t_s` (within EPOCH_MATCH_S; default `koz_switch_time_s` from t = 0);
    before it, the approach ellipsoid.

    Args:
        sim: a simulator with executed nodes (strictly increasing epochs).
        uncertainty: None for the deterministic margin of the realised states (default); a
            model adds the q-sigma term of the chance constraint.
        koz_switch_t_s: sim time of the AE -> KOZ switch [s].
    """
    t = sim.node_arrays()[0]
    if t.size < 2 or np.any(np.diff(t) <= 0):
        return None
    if koz_switch_t_s is None:
        koz_switch_t_s = koz_switch_time_s(sim.scenario, sim.chief_mean_oe0[0])
    n_nodes = max(t.size, 3)
    switch = int(np.searchsorted(t, float(koz_switch_t_s) - EPOCH_MATCH_S, side="left"))
    return PassiveSafety(Horizon.build(sim.chief_mean_oe0, t), sim.scenario, uncertainty,
                         koz_switch_node=min(switch, n_nodes))


def run_outcome(sim: RendezvousSim, target_rtn: object,
                safety_model: PassiveSafety | None = None, n_replans: int = 0) -> dict:
    """Outcome of a run, as JSON-ready numbers.

    Passive safety of the *realised* trajectory: at every executed node the post-burn state
    (the simulator's model ROE of the truth) drifts freely for `t_safety` with the linear
    model, and the smallest margin ``min_tau (d - 1 - q sigma) * min semi-axis`` [m] over nodes
    and the whole drift arc (the continuous minimum of `PassiveSafety.evaluate`) is reported
    (AE before the switch, KOZ after; >= 0 is safe).

    Args:
        sim: the simulator after the run.
        target_rtn: (6,) the waypoint [m, m/s].
        safety_model: evaluator built on the run's node epochs (`run_safety_model`), or None
            to build the deterministic one (q sigma = 0: the truth is known).
        n_replans: number of plans the guidance sent.

    Returns:
        dict: miss_m (position error to the waypoint at the end [m]), velocity_error_mps,
        total_dv_mps (executed), commanded_dv_mps, min_safety_margin_m (None if < 2 nodes),
        min_range_m (over the recorded truth), n_burns, n_replans, final_t_s, final_rtn,
        target_rtn.

    Raises:
        InputError: on a bad target or a safety model whose node count does not match.
    """
    target = as_finite_array("target_rtn", target_rtn, (6,))
    rtn = sim.true_rtn()
    t, _, dv, roe_post = sim.node_arrays()
    model = run_safety_model(sim) if safety_model is None else safety_model
    margin = None
    if model is not None:
        if model.n_nodes != t.size:
            raise InputError("safety_model", f"has {model.n_nodes} nodes, the run {t.size}")
        margin = float(model.evaluate(roe_post, np.zeros((t.size, 3))).margin_m.min())
    cmd = np.array([h.dv_cmd_mps for h in sim.history]).reshape(-1, 3)
    traj = np.array(sim.trajectory_rtn)
    return {
        "miss_m": float(np.linalg.norm(rtn[:3] - target[:3])),
        "velocity_error_mps": float(np.linalg.norm(rtn[3:] - target[3:])),
        "total_dv_mps": float(np.linalg.norm(dv, axis=1).sum()),
        "commanded_dv_mps": float(np.linalg.norm(cmd, axis=1).sum()),
        "min_safety_margin_m": margin,
        "min_range_m": float(np.linalg.norm(traj[:, :3], axis=1).min()),
        "n_burns": int(t.size),
        "n_replans": int(n_replans),
        "final_t_s": float(sim.t_s),
        "final_rtn": rtn.tolist(),
        "target_rtn": target.tolist(),
    }
