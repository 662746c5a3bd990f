"""The windowed replan (receding horizon with a learned terminal target, after T-MPC).

A request with `window_nodes` H > 0 whose remainder has more than H + 1 nodes is planned over
the window [0, H] only: SCVx* (with everything a plan has: the deputy-aware dynamics, the
passive-safety chance constraint after every burn, the deadline, the fallbacks) from the
request's state to a terminal state at node H taken from a reference trajectory over the whole
remainder:

- `terminal_target` "art": the learned proposal over the remainder (the terminal warm start the
  post hoc check accepted: the rollout's controls corrected onto the waypoint condition, so that
  its state at node H lies on a trajectory that reaches the waypoint);
- "cvx", or "art" where the proposal is rejected, missing or not run: the convex solution of the
  remainder (CVX, solved for every plan anyway as the post hoc reference);
- "carry": the plan in force (`planning.carry`), its own predicted state at node H: a tracking
  MPC. The window's SCVx* starts from the plan in force's burns there. With nothing to carry
  (the first plan of a target, or a carry refused) the whole remainder is planned.

The terminal condition is hard: the window's post-burn state at node H equals the reference's
(within SCVx*'s terminal tolerance), so the plan published is the window's plan followed by
the reference's burns from node H + 1 to the waypoint: it always ends at the waypoint, and the
guidance replans before the window runs out (`planning.replan`: at the latest when fewer than
H / 2 of its nodes are left). A remainder that fits in the window is planned whole, to the
waypoint, as without a window. `PlanResult.window` says which, with the target's source and why.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from art_guidance.deadline import Deadline
from art_guidance.optim import ConvexSolution
from art_guidance.planning.learned import learned_warm_start
from art_guidance.planning.transfer import Transfer
from art_guidance.planning.types import (  # noqa: F401  (targets re-exported)
    N_ORBITS_RANGE, REFERENCE_TARGETS, TERMINAL_TARGETS, PlanRequest, PlanResult, WarmStart,
    WarmStartSource,
)

if TYPE_CHECKING:
    from art_guidance.planning.pipeline import GuidancePipeline


@dataclass(frozen=True)
class PlanWindow:
    """How a plan used its window.

    Attributes:
        window_nodes: H, the window asked for (nodes after the first).
        end_node: index of the window's last node in the plan (the last node when the
            waypoint is inside the window).
        target_source: "waypoint" (the remainder fits in the window), "art" or "cvx" (or a
            benchmark's reference: "scvx", or "art" for "art_any").
        reason: why this target, in words.
        context_nodes: nodes of flown history the learned proposal was given (0: none).
    """

    window_nodes: int
    end_node: int
    target_source: str
    reason: str
    context_nodes: int = 0

    def to_json(self) -> dict:
        """JSON-ready fields."""
        return dataclasses.asdict(self)


def needs_window(request: PlanRequest, n_nodes: int) -> bool:
    """Whether a request over `n_nodes` nodes is planned over a window shorter than it."""
    return 0 < int(request.window_nodes) < n_nodes - 1


def window_orbits(request: PlanRequest, n_nodes: int, default_orbits: float) -> float:
    """The span of a request's window [orbits]: its H of the remainder's `n_nodes` - 1
    intervals (`default_orbits`: the scenario's horizon, for a request that names none)."""
    return float(request.n_orbits or default_orbits) * int(request.window_nodes) / (n_nodes - 1)


def short_window(request: PlanRequest, n_nodes: int, default_orbits: float) -> str:
    """Why a request's window is too short for the planner to take ("" = it is not): such a
    request plans the whole remainder."""
    span, lowest = window_orbits(request, n_nodes, default_orbits), N_ORBITS_RANGE[0]
    if span >= lowest:
        return ""
    return (f"a window of {int(request.window_nodes)} of {n_nodes - 1} nodes would span "
            f"{span:.3g} orbits, below the planner's {lowest:g}: the whole remainder is "
            "planned")


def waypoint_window(request: PlanRequest, n_nodes: int, why: str = "") -> PlanWindow:
    """The window of a request whose remainder of `n_nodes` fits in it, or that has no target
    (`why`): planned whole."""
    return PlanWindow(int(request.window_nodes), n_nodes - 1, "waypoint",
                      why or "the waypoint is inside the window: the whole remainder is "
                      "planned", context_steps(request))


def context_steps(request: PlanRequest) -> int:
    """The flown steps a request gives the learned proposal (0: none)."""
    return 0 if request.context is None else request.context.n_steps


def plan_window(pipeline: "GuidancePipeline", transfer: Transfer,
                deadline: Deadline | None) -> PlanResult:
    """Plan `transfer` (the whole remainder) over its request's window (module docstring);
    never raises for solver or model trouble (the plan's status and reason say what
    happened)."""
    t0 = time.perf_counter()
    request = transfer.request
    horizon, n, h = transfer.horizon, transfer.horizon.n_nodes, int(request.window_nodes)
    cvx = transfer.problem.cvx()
    t_cvx = time.perf_counter()
    ref_dv, ref_roe, source, reason, learned = _reference(pipeline, transfer, cvx, deadline)
    t_art = time.perf_counter()
    result, source, reason = _solve_window(pipeline, request, transfer, ref_dv, ref_roe, h,
                                           source, reason, cvx, deadline)
    dv = np.concatenate([result.dv_rtn_mps, ref_dv[h + 1:]])
    roe = np.concatenate([result.roe_m, ref_roe[h + 1:]])
    t_end = time.perf_counter()
    timings = {"setup": 0.0, "cvx": 1e3 * (t_cvx - t0), "art": 1e3 * (t_art - t_cvx),
               "scp": 1e3 * (t_end - t_art), "total": 1e3 * (t_end - t0),
               "window": float(result.timings_ms.get("total", 0.0))}
    window = PlanWindow(h, h, source, reason, context_steps(request))
    text = (f"window of {h} of {n - 1} nodes to a {source.upper()} target ({reason}); "
            f"{result.warm_start_reason}")
    return dataclasses.replace(
        result, epochs_s=horizon.epochs_s, dv_rtn_mps=dv, roe_m=roe, rtn=horizon.to_rtn(roe),
        cost_mps=float(np.linalg.norm(dv, axis=1).sum()), cvx=cvx,
        posthoc=None if learned is None else learned.posthoc, timings_ms=timings,
        request=request, proposal=None if learned is None else learned.proposal,
        warm_start_reason=text, window=window)


def _reference(pipeline: "GuidancePipeline", transfer: Transfer, cvx: ConvexSolution,
               deadline: Deadline | None) -> tuple:
    """The trajectory the window's target is taken from: (dv (N, 3), roe (N, 6), source,
    reason, the learned step or None)."""
    request = transfer.request
    cvx_ref = (cvx.dv_rtn_mps, cvx.roe_m)
    if request.terminal_target == "carry":  # usable: `GuidancePipeline.plan` checked it
        carry = request.carry
        return carry.dv_rtn_mps, carry.roe_m, "carry", f"the plan in force {carry.plan_id}", \
            None
    if request.terminal_target == "cvx":
        return (*cvx_ref, "cvx", "terminal_target cvx", None)
    if not cvx.status.feasible:
        return (*cvx_ref, "cvx", f"CVX ended {cvx.status.name}", None)
    if request.terminal_target == "scvx":  # the oracle: the full-horizon plan
        full = pipeline.plan(dataclasses.replace(request, window_nodes=0,
                                                 warm_start=WarmStart.CVX.value), deadline)
        if full.scp.feasible:
            return full.dv_rtn_mps, full.roe_m, "scvx", "the full-horizon SCVx* plan", None
        return (*cvx_ref, "cvx", f"the full-horizon plan ended {full.status.name}", None)
    if request.terminal_target == "art_any":  # ART whatever the check says
        transfer = dataclasses.replace(transfer, request=dataclasses.replace(
            request, warm_start=WarmStart.ART.value))
    learned = learned_warm_start(pipeline.provider, transfer, cvx, pipeline.config.planning,
                                 deadline)
    if learned.source is WarmStartSource.ART and learned.warm_start is not None:
        dv, roe = learned.warm_start
        return dv, roe, "art", learned.reason, learned
    return (*cvx_ref, "cvx", f"no ART target: {learned.reason}", learned)


def _solve_window(pipeline: "GuidancePipeline", request: PlanRequest, transfer: Transfer,
                  ref_dv: np.ndarray, ref_roe: np.ndarray, h: int, source: str, reason: str,
                  cvx: ConvexSolution, deadline: Deadline | None) -> tuple[PlanResult, str, str]:
    """SCVx* over nodes 0..h to the reference's post-burn state at node h; an infeasible
    window to an ART (or carried) target is solved again to the CVX target in the time
    left."""
    result = pipeline.plan(window_request(pipeline, request, transfer, ref_dv, ref_roe, h,
                                          tracking=source == "carry"), deadline)
    if result.scp.feasible or source == "cvx" or not cvx.status.feasible \
            or (deadline is not None and deadline.passed()):
        return result, source, reason
    retry = pipeline.plan(window_request(pipeline, request, transfer, cvx.dv_rtn_mps,
                                         cvx.roe_m, h), deadline)
    return retry, "cvx", (f"the window to the {source.upper()} target ended "
                          f"{result.status.name}")


def window_request(pipeline: "GuidancePipeline", request: PlanRequest, transfer: Transfer,
                   ref_dv: np.ndarray, ref_roe: np.ndarray, h: int,
                   tracking: bool = False) -> PlanRequest:
    """The request of the window [0, h] of `transfer` ending at the post-burn state of the
    reference (`ref_dv`, `ref_roe`) at node h (warm-started from CVX, no window of its own;
    with `tracking`, the reference is the request's carried plan, whose first h + 1 nodes it
    carries)."""
    horizon = transfer.horizon
    n = horizon.n_nodes
    n_orbits = window_orbits(request, n, pipeline.scenario.n_orbits)
    switch = request.koz_switch_node
    if switch is None:
        switch = pipeline.scenario.ae_to_koz_node
    z_h = horizon.post_burn_at(h, ref_roe[h], ref_dv[h])
    carry = request.carry.first(h + 1) if tracking else None
    shape = dataclasses.replace(request, n_nodes=h + 1, n_orbits=n_orbits,
                                koz_switch_node=int(switch), warm_start=WarmStart.CVX.value,
                                window_nodes=0, carry=carry,
                                no_carry="" if tracking else "a window to a fresh target")
    psi_h = pipeline.transfer(shape).horizon.psi[-1]
    return dataclasses.replace(shape, target_rtn=psi_h @ z_h)
