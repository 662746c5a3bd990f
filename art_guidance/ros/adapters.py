"""Conversions between art_guidance_msgs messages and numpy, with validation.

Only this module and `node`/`sim_node` import ROS message types. Every check raises an
`InputError` naming the offending field, which the node turns into a published status.
"""
from __future__ import annotations

import json
import math
import numpy as np
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest, SolveRecord
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from art_guidance.checks import as_finite_array, check_psd
from art_guidance.dynamics import check_chief, psi_matrix
from art_guidance.errors import InputError
from art_guidance.optim import ScpStatus
from art_guidance.planning import WARM_STARTS, NavState, PlanResult, Target
from art_guidance.planning.request import N_ORBITS_RANGE
from art_guidance.sim.link import LinkPlan

FRAMES = {RelativeNavState.REPRESENTATION_ROE: ("chief_roe",),
          RelativeNavState.REPRESENTATION_RTN: ("chief_rtn",)}
MAX_RANGE_M = 500e3     # beyond this the linear relative models are meaningless
MAX_SPEED_MPS = 500.0   # relative speed bound for an RTN state
REQUEST_WARM_STARTS = ("",) + WARM_STARTS  # "" = auto
# The one mapping between solve statuses and ManeuverPlan.status (tested to be one-to-one);
# STATUS_REJECTED_INPUT has no solve behind it.
MSG_STATUS = {
    ScpStatus.CONVERGED: ManeuverPlan.STATUS_CONVERGED,
    ScpStatus.MAX_ITERATIONS: ManeuverPlan.STATUS_MAX_ITERATIONS,
    ScpStatus.INFEASIBLE: ManeuverPlan.STATUS_INFEASIBLE,
    ScpStatus.SOLVER_ERROR: ManeuverPlan.STATUS_SOLVER_ERROR,
    ScpStatus.TIMEOUT: ManeuverPlan.STATUS_TIMEOUT,
}
STATUS_FROM_MSG = {v: k for k, v in MSG_STATUS.items()}


def stamp_to_ns(stamp: object) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(stamp: object, ns: int) -> None:
    """Write integer nanoseconds into a builtin_interfaces/Time."""
    stamp.sec, stamp.nanosec = divmod(int(ns), 1_000_000_000)


def nav_from_msg(msg: RelativeNavState) -> NavState:
    """Validate a RelativeNavState and convert it to ROE (RTN goes through Psi^-1)."""
    if msg.representation not in FRAMES:
        raise InputError("representation", "unknown representation", int(msg.representation))
    if msg.header.frame_id not in FRAMES[msg.representation]:
        raise InputError("header.frame_id", f"unknown frame for this representation; expected "
                         f"{FRAMES[msg.representation][0]!r}", msg.header.frame_id)
    if not 0 <= int(msg.header.stamp.nanosec) < 1_000_000_000:
        raise InputError("header.stamp.nanosec", "must be in [0, 1e9)",
                         int(msg.header.stamp.nanosec))
    chief = check_chief(np.asarray(msg.chief_oe, float), "chief_oe")
    mean = as_finite_array("mean", np.asarray(msg.mean, float), (6,))
    cov = check_psd("covariance", as_finite_array(
        "covariance", np.asarray(msg.covariance, float), (36,)).reshape(6, 6))
    if not np.max(np.abs(cov)) <= MAX_RANGE_M**2:  # a zero covariance is a perfect estimate
        raise InputError("covariance", f"a standard deviation above {MAX_RANGE_M:.0f} m "
                         "(m/s)", float(np.sqrt(np.max(np.abs(cov)))))
    psi = psi_matrix(chief)
    # every bound is written "not (x <= limit)" and checked before any product: a finite
    # but huge input (1e308) overflows to inf/NaN there, and NaN compares False
    if msg.representation == RelativeNavState.REPRESENTATION_RTN:
        if not np.max(np.abs(mean[:3])) <= MAX_RANGE_M:
            raise InputError("mean", f"relative range above {MAX_RANGE_M:.0f} m", mean.tolist())
        if not np.max(np.abs(mean[3:])) <= MAX_SPEED_MPS:
            raise InputError("mean", f"relative speed above {MAX_SPEED_MPS} m/s", mean.tolist())
        psi_inv = np.linalg.inv(psi)
        roe, cov = psi_inv @ mean, psi_inv @ cov @ psi_inv.T
    else:
        if not np.max(np.abs(mean)) <= 10.0 * MAX_RANGE_M:
            raise InputError("mean", f"relative range above {MAX_RANGE_M:.0f} m", mean.tolist())
        roe = mean
    with np.errstate(over="ignore", invalid="ignore"):
        rtn_m = (psi @ roe)[:3]
        range_m = float(np.linalg.norm(rtn_m)) if np.all(np.isfinite(rtn_m)) else math.inf
    if not range_m <= MAX_RANGE_M:
        raise InputError("mean", f"relative range above {MAX_RANGE_M:.0f} m", mean.tolist())
    if not (np.all(np.isfinite(roe)) and np.all(np.isfinite(cov))):
        raise InputError("covariance", "not finite once converted to ROE (values too large)")
    return NavState(stamp_to_ns(msg.header.stamp), chief, roe, 0.5 * (cov + cov.T))


def target_from_msg(msg: ReplanRequest, waypoints: dict) -> Target:
    """Validate a ReplanRequest against the configured waypoints."""
    if msg.waypoint == "custom":
        target = as_finite_array("target_rtn", np.asarray(msg.target_rtn, float), (6,))
        if not np.max(np.abs(target[:3])) <= MAX_RANGE_M:
            raise InputError("target_rtn", f"target further than {MAX_RANGE_M:.0f} m",
                             target.tolist())
        if not np.max(np.abs(target[3:])) <= MAX_SPEED_MPS:
            raise InputError("target_rtn", f"target speed above {MAX_SPEED_MPS} m/s",
                             target.tolist())
    elif msg.waypoint in waypoints:
        target = np.asarray(waypoints[msg.waypoint], float)
    else:
        raise InputError("waypoint", f"unknown; choose from {sorted(waypoints) + ['custom']}",
                         msg.waypoint)
    if msg.warm_start not in REQUEST_WARM_STARTS:
        raise InputError("warm_start", f"must be one of {REQUEST_WARM_STARTS}",
                         msg.warm_start)
    horizon = float(msg.horizon_orbits)
    lo, hi = N_ORBITS_RANGE
    if not (horizon <= 0 or lo <= horizon <= hi):  # NaN fails both
        raise InputError("horizon_orbits", f"must be in [{lo:g}, {hi:g}] orbits, or <= 0 "
                         "for the scenario's", horizon)
    return Target(msg.waypoint, target, bool(msg.chance_constrained),
                  msg.warm_start or "auto", horizon if horizon > 0 else None)


def plan_to_msg(result: PlanResult, stamp_ns: int, plan_id: str) -> ManeuverPlan:
    """PlanResult -> ManeuverPlan (arrays flattened row-major)."""
    msg = ManeuverPlan()
    ns_to_stamp(msg.header.stamp, stamp_ns)
    msg.header.frame_id = "chief_rtn"
    msg.plan_id = plan_id
    msg.status = MSG_STATUS[result.status]
    msg.status_text = (f"{result.status.name}: {result.cost_mps:.4f} m/s after "
                       f"{result.scp.iterations} SCP iterations from the "
                       f"{result.warm_start.label} warm start, passive-safety margin "
                       f"{result.constraint_margin_m:.2f} m")
    msg.epochs_s = result.epochs_s.astype(float).tolist()
    msg.dv_rtn_mps = result.dv_rtn_mps.reshape(-1).tolist()
    msg.roe_m = result.roe_m.reshape(-1).tolist()
    msg.rtn = result.rtn.reshape(-1).tolist()
    msg.cost_mps = float(result.cost_mps)
    msg.warm_start = result.warm_start.value
    msg.warm_start_reason = result.warm_start_reason[:500]
    msg.posthoc, msg.posthoc_e_r, msg.posthoc_e_c = posthoc_fields(result)
    msg.scp_iterations = int(result.scp.iterations)
    msg.solve_time_ms = float(result.timings.total)
    msg.constraint_margin_m = float(result.constraint_margin_m)
    return msg


def posthoc_fields(result: PlanResult) -> tuple[int, float, float]:
    """(POSTHOC_*, E_R, E_C) of a plan; NOT_RUN with NaNs when no learned warm start was tried
    (which must not look like a failed check)."""
    ph = result.posthoc
    if ph is None:
        return ManeuverPlan.POSTHOC_NOT_RUN, math.nan, math.nan
    return ((ManeuverPlan.POSTHOC_ACCEPTED if ph.accepted else ManeuverPlan.POSTHOC_REJECTED),
            float(ph.e_r), float(ph.e_c))


def solve_record_msg(result: PlanResult, stamp_ns: int, plan_id: str, trigger: str,
                     request_stamp_ns: int = 0, model_load_ms: float = 0.0) -> SolveRecord:
    """Everything needed to replay one solve: request, warm starts, SCP history, timings, and
    the header stamp of the ReplanRequest in force (0 = none)."""
    msg = SolveRecord()
    ns_to_stamp(msg.header.stamp, stamp_ns)
    ns_to_stamp(msg.request_stamp, request_stamp_ns)
    msg.plan_id, msg.trigger = plan_id, trigger
    proposal = result.proposal
    if proposal is not None:
        msg.warm_start_art_dv_rtn_mps = _floats(proposal.dv_rtn_mps)
        msg.art_reward_to_go_mps = _floats(proposal.reward_to_go_mps)
        msg.art_constraint_to_go = _floats(proposal.constraint_to_go)
        msg.model_sha256 = proposal.model_sha256
    msg.warm_start, msg.warm_start_reason = result.warm_start.value, result.warm_start_reason
    msg.posthoc, msg.posthoc_e_r, msg.posthoc_e_c = posthoc_fields(result)
    if np.all(np.isfinite(result.cvx.dv_rtn_mps)):
        msg.warm_start_cvx_dv_rtn_mps = result.cvx.dv_rtn_mps.reshape(-1).tolist()
    hist = result.scp.history
    msg.scp_cost_history_mps = [float(h.cost_mps) for h in hist]
    msg.scp_trust_radius_history = [float(h.trust_radius) for h in hist]
    msg.scp_max_violation_history = [float(h.max_violation) for h in hist]
    t = result.timings
    msg.timing_model_load_ms = float(model_load_ms)
    msg.timing_art_ms, msg.timing_cvx_ms = float(t.art), float(t.cvx)
    msg.timing_scp_ms, msg.timing_total_ms = float(t.scp), float(t.total)
    msg.request_json = json.dumps(result.request.to_json() if result.request else {})
    msg.window_json = "" if result.window is None else json.dumps(result.window.to_json())
    msg.numerics, msg.deadline_hit = result.numerics, bool(result.deadline_hit)
    return msg


def _floats(values: object) -> list[float]:
    """Any array-like as a flat float list (empty for None or values that are not numbers)."""
    if values is None:
        return []
    try:
        return np.asarray(values, dtype=float).reshape(-1).tolist()
    except (TypeError, ValueError):
        return []


def status_plan_msg(stamp_ns: int, plan_id: str, status: int, text: str,
                    active_plan_id: str = "") -> ManeuverPlan:
    """A ManeuverPlan carrying only a status (no maneuvers), e.g. for rejected input."""
    msg = ManeuverPlan()
    ns_to_stamp(msg.header.stamp, stamp_ns)
    msg.header.frame_id = "chief_rtn"
    msg.plan_id, msg.status, msg.status_text = plan_id, int(status), text[:500]
    msg.posthoc_e_r = msg.posthoc_e_c = math.nan  # no solve, no post hoc check
    msg.active_plan_id = active_plan_id
    return msg


def diagnostics_msg(now_ns: int, name: str, level: int, message: str,
                    values: dict) -> DiagnosticArray:
    """One DiagnosticStatus (hardware_id art_guidance) with string key-values."""
    arr = DiagnosticArray()
    ns_to_stamp(arr.header.stamp, now_ns)
    status = DiagnosticStatus()
    status.level = bytes([level])
    status.name, status.hardware_id, status.message = name, "art_guidance", message[:500]
    status.values = [KeyValue(key=str(k), value=v if isinstance(v, str) else json.dumps(v))
                     for k, v in values.items()]
    arr.status = [status]
    return arr


def link_plan_from_msg(msg: ManeuverPlan) -> LinkPlan:
    """ManeuverPlan -> the simulator's plain `LinkPlan` (status None for a rejection notice).

    An unknown status is read as a solver error: never flown.
    """
    status = (None if msg.status == ManeuverPlan.STATUS_REJECTED_INPUT
              else STATUS_FROM_MSG.get(msg.status, ScpStatus.SOLVER_ERROR))
    return LinkPlan(stamp_to_ns(msg.header.stamp), msg.plan_id, status, msg.status_text,
                    msg.active_plan_id, np.asarray(msg.epochs_s, float),
                    np.asarray(msg.dv_rtn_mps, float), np.asarray(msg.rtn, float))
