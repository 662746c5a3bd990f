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
guidance replans before the window runs out (`guidance.replan`: at the latest when fewer than
H / 2 of its nodes are left). A remainder that fits in the window is planned whole, to the
waypoint, as without a window. `PlanResult.window` says which, with the target's source and why.

This module is pure functions of the request and of what the pipeline solved
(`GuidancePipeline` drives the window): whether a request takes its window (`window_size`, the
one place it is checked), the reference (`reference`), the window's request and transfer
problem, built in ROE from the reference's post-burn state at node H (`window_request`,
`target_roe`), and the splice of the window's plan onto the reference (`splice`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from art_guidance.config import ScenarioConfig
from art_guidance.optim import ConvexSolution, Trajectory
from art_guidance.planning.learned import Learned
from art_guidance.planning.request import (  # noqa: F401  (targets re-exported)
    N_ORBITS_RANGE, REFERENCE_TARGETS, TERMINAL_TARGETS, PlanRequest, TerminalTarget,
    WarmStart, WarmStartSource,
)
from art_guidance.planning.result import PlanResult, PlanWindow, Timings
from art_guidance.planning.transfer import Transfer


@dataclass(frozen=True)
class Reference:
    """The trajectory over the whole remainder a window's target is taken from.

    Attributes:
        trajectory: its burns (N, 3) [m/s] and pre-burn states (N, 6) [m].
        source: "carry", "cvx", "art" or "scvx".
        reason: why this one, in words.
        learned: the learned step, where it was run (None: not run).
    """

    trajectory: Trajectory
    source: str
    reason: str
    learned: Learned | None = None


def window_orbits(request: PlanRequest, n_nodes: int, default_orbits: float) -> float:
    """The span of a request's window [orbits]: its H of the remainder's `n_nodes` - 1
    intervals (`default_orbits`: the scenario's horizon, for a request that names none)."""
    return float(request.n_orbits or default_orbits) * int(request.window_nodes) / (n_nodes - 1)


def window_size(request: PlanRequest, n_nodes: int, default_orbits: float,
                no_target: str = "") -> tuple[int, str]:
    """The one check of a request's window against its remainder of `n_nodes` nodes: (H, "")
    where the window [0, H] is planned; (0, why) where the whole remainder is planned (the
    waypoint is inside the window, the window would span less than the planner takes, or it
    has no target: `no_target`, "" = it has one). A request without a window gives (0, "")."""
    h = int(request.window_nodes)
    if h == 0:
        return 0, ""
    if no_target:
        return 0, no_target
    span, lowest = window_orbits(request, n_nodes, default_orbits), N_ORBITS_RANGE[0]
    if span < lowest:
        return 0, (f"a window of {h} of {n_nodes - 1} nodes would span {span:.3g} orbits, "
                   f"below the planner's {lowest:g}: the whole remainder is planned")
    if h >= n_nodes - 1:
        return 0, "the waypoint is inside the window: the whole remainder is planned"
    return h, ""


def waypoint_window(request: PlanRequest, n_nodes: int, why: str) -> PlanWindow:
    """The window of a request planned whole over its remainder of `n_nodes`, and why."""
    return PlanWindow(int(request.window_nodes), n_nodes - 1, "waypoint", why,
                      context_steps(request))


def context_steps(request: PlanRequest) -> int:
    """The flown steps a request gives the learned proposal (0: none)."""
    return 0 if request.context is None else request.context.n_steps


def wants_learned(request: PlanRequest, cvx: ConvexSolution) -> bool:
    """Whether the reference of a windowed request asks the learned step."""
    return request.terminal_target in (TerminalTarget.ART, TerminalTarget.ART_ANY) \
        and cvx.status.feasible


def learned_request(request: PlanRequest) -> PlanRequest:
    """The request the learned step is asked with (`art_any`: ART whatever the check says)."""
    if request.terminal_target is TerminalTarget.ART_ANY:
        return dataclasses.replace(request, warm_start=WarmStart.ART)
    return request


def reference(request: PlanRequest, cvx: ConvexSolution, learned: Learned | None = None,
              full: PlanResult | None = None) -> Reference:
    """The trajectory the window's target is taken from (module docstring), given the learned
    step where `wants_learned` (`learned`) and the full-horizon plan for the "scvx" oracle
    (`full`)."""
    target = request.terminal_target
    cvx_ref = Trajectory(cvx.dv_rtn_mps, cvx.roe_m)
    if target is TerminalTarget.CARRY:  # usable: `window_size` was given its refusal
        carry = request.carry
        return Reference(Trajectory(carry.dv_rtn_mps, carry.roe_m), "carry",
                         f"the plan in force {carry.plan_id}")
    if target is TerminalTarget.CVX:
        return Reference(cvx_ref, "cvx", "terminal_target cvx")
    if not cvx.status.feasible:
        return Reference(cvx_ref, "cvx", f"CVX ended {cvx.status.name}")
    if target is TerminalTarget.SCVX:  # the oracle: the full-horizon plan
        if full.scp.feasible:
            return Reference(Trajectory(full.dv_rtn_mps, full.roe_m), "scvx",
                             "the full-horizon SCVx* plan")
        return Reference(cvx_ref, "cvx", f"the full-horizon plan ended {full.status.name}")
    if learned.source is WarmStartSource.ART and learned.warm_start is not None:
        return Reference(learned.warm_start, "art", learned.reason, learned)
    return Reference(cvx_ref, "cvx", f"no ART target: {learned.reason}", learned)


def cvx_reference(cvx: ConvexSolution, failed: Reference, status: str) -> Reference:
    """The CVX reference a window is solved to again after the window to `failed` ended with
    `status` (the learned step kept)."""
    return Reference(Trajectory(cvx.dv_rtn_mps, cvx.roe_m), "cvx",
                     f"the window to the {failed.source.upper()} target ended {status}",
                     failed.learned)


def window_request(request: PlanRequest, n_nodes: int, scenario: ScenarioConfig,
                   tracking: bool = False) -> PlanRequest:
    """The request of the window [0, H] of `request` (its remainder of `n_nodes` nodes): the
    same grid and switch, warm-started from CVX, no window of its own; with `tracking`, the
    request's carried plan over the window's nodes. Its target is the window transfer's
    (`target_roe`, given by `planning.transfer.Transfers.in_roe`)."""
    h = int(request.window_nodes)
    switch = request.koz_switch_node
    if switch is None:
        switch = scenario.ae_to_koz_node
    return dataclasses.replace(
        request, n_nodes=h + 1, n_orbits=window_orbits(request, n_nodes, scenario.n_orbits),
        koz_switch_node=int(switch), warm_start=WarmStart.CVX, window_nodes=0,
        carry=request.carry.first(h + 1) if tracking else None,
        no_carry="" if tracking else "a window to a fresh target")


def target_roe(transfer: Transfer, ref: Reference, h: int) -> np.ndarray:
    """The window's terminal condition: the reference's post-burn state at node `h` [m]."""
    traj = ref.trajectory
    return transfer.horizon.post_burn_at(h, traj.roe_m[h], traj.dv_rtn_mps[h])


def splice(transfer: Transfer, window: PlanResult, ref: Reference, cvx: ConvexSolution,
           timings: Timings) -> PlanResult:
    """The plan over the whole remainder: the window's plan, then the reference's burns from
    node H + 1 to the waypoint."""
    request, horizon = transfer.request, transfer.horizon
    h, learned = int(request.window_nodes), ref.learned
    dv = np.concatenate([window.dv_rtn_mps, ref.trajectory.dv_rtn_mps[h + 1:]])
    roe = np.concatenate([window.roe_m, ref.trajectory.roe_m[h + 1:]])
    text = (f"window of {h} of {horizon.n_nodes - 1} nodes to a {ref.source.upper()} target "
            f"({ref.reason}); {window.warm_start_reason}")
    return dataclasses.replace(
        window, epochs_s=horizon.epochs_s, dv_rtn_mps=dv, roe_m=roe, rtn=horizon.to_rtn(roe),
        cost_mps=float(np.linalg.norm(dv, axis=1).sum()), cvx=cvx,
        posthoc=None if learned is None else learned.posthoc,
        timings=dataclasses.replace(timings, window=float(window.timings.total)),
        request=request, proposal=None if learned is None else learned.proposal,
        warm_start_reason=text,
        window=PlanWindow(h, h, ref.source, ref.reason, context_steps(request)))
