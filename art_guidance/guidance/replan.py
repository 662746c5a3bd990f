"""When to replan, over which window, and which plan is in force: the node's policy as pure code.

The guidance node (and the simulator's in-process link) hold one `ReplanPolicy` and call it
under their own lock: `check_stamp` and `accept` for every navigation fix, `decide` to choose
between replanning and staying on the plan in force, `window` for the remaining horizon of a
replan, and `on_result` when a solve finishes. A plan that is not usable never replaces the one
in force.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from art_guidance.config import ScenarioConfig, node_parameter_defaults
from art_guidance.dynamics import (
    control_matrix, orbital_period_s, propagate_mean_oe, stm_j2,
)
from art_guidance.errors import ConfigError, GuidanceError
from art_guidance.planning.carry import GRID_TOL, CarriedPlan
from art_guidance.planning.request import (
    REFERENCE_TARGETS, TERMINAL_TARGETS, NavState, PlanRequest, RolloutContext, Target,
    window_nodes_valid,
)
from art_guidance.planning.result import PlanResult

STAMP_CHECKS = ("wallclock", "order", "off")
_NODE = node_parameter_defaults()  # the defaults are the node's: config/guidance_node.yaml


class Decision(str, enum.Enum):
    """What the policy does with a navigation fix."""

    REPLANNING = "replanning"
    ON_PLAN = "on_plan"
    REJECTED = "rejected"


class Action(str, enum.Enum):
    """What a finished solve did to the plan in force."""

    ACTIVATED = "activated"
    KEPT_ACTIVE_PLAN = "kept_active_plan"
    NO_PLAN = "no_plan"


@dataclass(frozen=True)
class ReplanSettings:
    """Policy parameters (the node's ROS parameters of the same names; the defaults are read
    from config/guidance_node.yaml and scenario.yaml, declared there once).

    Attributes:
        replan_sigma_threshold: replan when any ROE axis deviates more than this [nav sigma].
        replan_period_s: also replan this often in stamp time [s]; 0 = off.
        stamp_check: "wallclock" (age/future limits and order), "order" (monotonic), "off".
        max_nav_age_s, max_nav_future_s: wall-clock stamp limits [s].
        max_stamp_jump_s: "order": largest step of a stamp ahead of the last accepted one [s].
        min_remaining_nodes: below this many nodes left the plan in force is flown out.
        replan_window_nodes: H, the nodes after the first a replan optimises (0: the whole
            remainder); a windowed plan is replanned at the latest when fewer than H / 2 of
            its window's nodes are left (`planning.window`).
        terminal_target: where a window shorter than the remainder ends: "art" (the learned
            proposal's state there; CVX's where it is rejected or missing) or "cvx".
        art_context: give the learned proposal the steps flown since the target was set as
            its context (`context_at`), T-MPC's closed loop; False: each replan's rollout
            starts afresh from the fix.
        ae_to_koz_node: node of the approach-ellipsoid -> keep-out-zone switch of a new plan.
        horizon_nodes: nodes of a fresh plan's horizon (the scenario's: a window may not be
            longer).
    """

    replan_sigma_threshold: float = _NODE["replan_sigma_threshold"]
    replan_period_s: float = _NODE["replan_period_s"]
    stamp_check: str = _NODE["stamp_check"]
    max_nav_age_s: float = _NODE["max_nav_age_s"]
    max_nav_future_s: float = _NODE["max_nav_future_s"]
    max_stamp_jump_s: float = _NODE["max_stamp_jump_s"]
    min_remaining_nodes: int = _NODE["min_remaining_nodes"]
    replan_window_nodes: int = _NODE["replan_window_nodes"]
    terminal_target: str = _NODE["terminal_target"]
    art_context: bool = _NODE["art_context"]
    ae_to_koz_node: int = ScenarioConfig().ae_to_koz_node
    horizon_nodes: int = ScenarioConfig().n_nodes

    def __post_init__(self) -> None:
        if self.stamp_check not in STAMP_CHECKS:
            raise ConfigError(f"stamp_check must be one of {STAMP_CHECKS}, "
                              f"got {self.stamp_check!r}")
        for name in ("replan_sigma_threshold", "max_nav_age_s", "max_nav_future_s",
                     "max_stamp_jump_s"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"parameter {name} must be > 0, got {getattr(self, name)}")
        if not float(self.replan_period_s) >= 0:
            raise ConfigError(f"replan_period_s must be >= 0, got {self.replan_period_s}")
        if int(self.min_remaining_nodes) < 2:
            raise ConfigError("min_remaining_nodes must be >= 2")
        check_window(self.replan_window_nodes, self.terminal_target, self.horizon_nodes)


def check_window(window_nodes: int, terminal_target: str, horizon_nodes: int) -> None:
    """Refuse a replan window outside 0 (the whole remainder) or [2, horizon_nodes - 1], or an
    unknown terminal target.

    Raises:
        ConfigError: with the reason.
    """
    if not window_nodes_valid(window_nodes, int(horizon_nodes) - 1):
        raise ConfigError(f"replan_window_nodes must be 0 (the whole remainder) or in [2, "
                          f"{int(horizon_nodes) - 1}] (the horizon's nodes after the first), "
                          f"got {window_nodes!r}")
    if terminal_target not in TERMINAL_TARGETS + REFERENCE_TARGETS:
        raise ConfigError(f"terminal_target must be one of {TERMINAL_TARGETS}, got "
                          f"{terminal_target!r}")


@dataclass(frozen=True)
class ActivePlan:
    """The plan in force, in absolute time.

    Attributes:
        plan_id: its id.
        t0_ns: stamp of the nav fix it answers (its node 0) [ns].
        result: the plan.
        end_ns: epoch of its last node [ns].
        dt_s: node spacing [s].
        switch_ns: absolute epoch of the AE -> KOZ switch [ns].
        window_end_ns: epoch of the last node of its window [ns] (None: not windowed, or its
            window reaches the waypoint).
    """

    plan_id: str
    t0_ns: int
    result: PlanResult
    end_ns: int
    dt_s: float
    switch_ns: int
    window_end_ns: int | None = None


@dataclass(frozen=True)
class ReplanWindow:
    """The horizon of a replan: None fields mean the scenario's (a fresh plan)."""

    n_nodes: int | None
    n_orbits: float | None
    koz_switch_node: int | None


class ReplanPolicy:
    """Decisions of one guidance instance (not thread-safe: call under the caller's lock)."""

    def __init__(self, settings: ReplanSettings) -> None:
        self.settings = settings
        self.active: ActivePlan | None = None
        self.stamp_floor_ns: int | None = None
        self.last_plan_ns: int | None = None
        self.no_carry = "no plan in force"  # why `carry_at` has nothing while none is
        # the last `decide` replans only because the fix deviates from the plan in force (not
        # for want of a plan, a solve under way, a period or a window): the end game may keep
        # the plan in force instead (`planning.endgame`)
        self.deviation_only = False

    @property
    def active_id(self) -> str:
        """Id of the plan in force ("" = none)."""
        return "" if self.active is None else self.active.plan_id

    def reset(self) -> None:
        """A new target: drop the plan in force and start a new stamp sequence."""
        self.active = None
        self.stamp_floor_ns = None
        self.no_carry = "a new target"

    def check_stamp(self, stamp_ns: int, now_ns: int) -> None:
        """Refuse a stale, out-of-order or future stamp.

        Raises:
            GuidanceError: with the reason.
        """
        s = self.settings
        if s.stamp_check == "off":
            return
        floor = self.stamp_floor_ns
        if floor is not None and stamp_ns <= floor:
            raise GuidanceError(f"stale stamp: {stamp_ns} ns is not newer than {floor} ns")
        if s.stamp_check == "order" and floor is not None \
                and (stamp_ns - floor) * 1e-9 > s.max_stamp_jump_s:
            raise GuidanceError(f"stamp jumps {(stamp_ns - floor) * 1e-9:.3f} s ahead of the "
                                f"last accepted fix (max_stamp_jump_s {s.max_stamp_jump_s:g} s)")
        if s.stamp_check == "wallclock":
            age_s = (now_ns - stamp_ns) * 1e-9
            if age_s > s.max_nav_age_s:
                raise GuidanceError(f"stale stamp: {age_s:.3f} s old")
            if -age_s > s.max_nav_future_s:
                raise GuidanceError(f"stamp {-age_s:.3f} s in the future")

    def accept(self, nav: NavState) -> None:
        """Record an accepted fix's stamp as the new floor for the order check."""
        self.stamp_floor_ns = nav.stamp_ns

    def decide(self, nav: NavState, busy: bool) -> tuple[Decision, float]:
        """Replan when nothing is in force, a solve is under way, the state deviates or is due.

        Args:
            nav: the accepted fix.
            busy: a solve is running or queued (the newest state supersedes it).

        Returns:
            The decision and the largest per-axis deviation from the plan [nav sigma] (NaN if
            not computed).
        """
        active, s = self.active, self.settings
        self.deviation_only = False
        if active is None or busy:
            return Decision.REPLANNING, math.nan
        remaining = (active.end_ns - nav.stamp_ns) * 1e-9
        if remaining < (s.min_remaining_nodes - 1) * active.dt_s:
            return Decision.ON_PLAN, math.nan
        deviation = deviation_sigma(active, nav)
        due = (s.replan_period_s > 0
               and (nav.stamp_ns - (self.last_plan_ns or 0)) * 1e-9 >= s.replan_period_s)
        if active.window_end_ns is not None:  # timed by the plan's own window
            window_left = (active.window_end_ns - nav.stamp_ns) * 1e-9 / active.dt_s
            due = due or window_left < 0.5 * active.result.window.window_nodes - 1e-6
        if deviation > s.replan_sigma_threshold or due:
            self.deviation_only = not due
            return Decision.REPLANNING, deviation
        return Decision.ON_PLAN, deviation

    def window(self, nav: NavState, n_orbits: float | None) -> ReplanWindow:
        """The horizon of a replan from `nav`: the remaining nodes of the plan in force.

        Args:
            nav: the fix to plan from.
            n_orbits: the target's horizon for a fresh plan [orbits] (None = scenario's).
        """
        active = self.active
        if active is None:
            return ReplanWindow(None, n_orbits, None)
        remaining_s = (active.end_ns - nav.stamp_ns) * 1e-9
        n_nodes = int(round(remaining_s / active.dt_s)) + 1
        period = orbital_period_s(nav.chief_oe[0])
        switch = max(0, math.ceil((active.switch_ns - nav.stamp_ns) * 1e-9 / active.dt_s))
        return ReplanWindow(max(n_nodes, 3), max(remaining_s, 2 * active.dt_s) / period, switch)

    def carry_at(self, nav: NavState, window: ReplanWindow) -> tuple[CarriedPlan | None, str]:
        """The plan in force's burns at the nodes of a replan from `nav` over `window`
        (`planning.carry`), or None and why there are none."""
        active = self.active
        if active is None:
            return None, self.no_carry
        res = active.result
        offset = (nav.stamp_ns - active.t0_ns) * 1e-9 / active.dt_s
        m = int(round(offset))
        if abs(offset - m) > GRID_TOL:
            return None, (f"the fix is {abs(offset - m) * active.dt_s:.1f} s off the plan in "
                          "force's node grid")
        left = len(res.epochs_s) - m
        if window.n_nodes != left:
            return None, (f"the replan's horizon was raised to its minimum of "
                          f"{window.n_nodes} nodes ({left} left in the plan in force)")
        dv, roe = res.dv_rtn_mps[m:], res.roe_m[m:]
        if not (np.all(np.isfinite(dv)) and np.all(np.isfinite(roe))):
            return None, "the plan in force's burns or states are not finite"
        report = res.carry
        return CarriedPlan(active.plan_id, dv, roe, 0.0 if report is None else report.excess_mps,
                           bool(res.request is None or res.request.chance_constrained),
                           "" if report is None else report.config_sha256), ""

    def context_at(self, nav: NavState) -> RolloutContext | None:
        """The steps flown before `nav` since the target was set (`art_context`; None: off,
        or nothing flown): the context of the plan in force followed by its own states and
        burns at its nodes before the fix's. A plan that was not usable never entered it."""
        active = self.active
        if not self.settings.art_context or active is None:
            return None
        res = active.result
        m = int(round((nav.stamp_ns - active.t0_ns) * 1e-9 / active.dt_s))
        m = min(max(m, 0), len(res.epochs_s))
        base = None if res.request is None else res.request.context
        if m == 0:
            return base
        flown = (res.roe_m[:m], res.rtn[:m], res.dv_rtn_mps[:m])
        if base is None:
            return RolloutContext(*flown, -float(res.cvx.cost_mps))
        return base.extended(*flown)

    def on_result(self, plan_id: str, t0_ns: int, result: PlanResult) -> Action:
        """Put a usable plan in force; an unusable one leaves the plan in force as it is."""
        if not result.scp.feasible:
            return Action.KEPT_ACTIVE_PLAN if self.active is not None else Action.NO_PLAN
        dt_s = float(result.epochs_s[1] - result.epochs_s[0])
        if self.active is None:
            switch_ns = t0_ns + int(self.settings.ae_to_koz_node * dt_s * 1e9)
        else:
            switch_ns = self.active.switch_ns
        window = result.window
        window_end_ns = None
        if window is not None and window.end_node < len(result.epochs_s) - 1:
            window_end_ns = t0_ns + int(round(result.epochs_s[window.end_node] * 1e9))
        self.active = ActivePlan(plan_id, t0_ns, result,
                                 t0_ns + int(round(result.epochs_s[-1] * 1e9)), dt_s, switch_ns,
                                 window_end_ns)
        self.last_plan_ns = t0_ns
        return Action.ACTIVATED


def request_for(nav: NavState, target: Target, window: ReplanWindow,
                settings: ReplanSettings | None = None,
                context: RolloutContext | None = None, carry: CarriedPlan | None = None,
                no_carry: str = "") -> PlanRequest:
    """The planning request for a fix, a target and a replan window (optimised over the
    `settings`' window, if any; the learned proposal given the flown `context`, if any; the
    plan in force `carry`, or why there is none)."""
    s = settings or ReplanSettings()
    return PlanRequest(nav.chief_oe, nav.roe_m, target.target_rtn,
                       chance_constrained=target.chance_constrained,
                       warm_start=target.warm_start, n_nodes=window.n_nodes,
                       n_orbits=window.n_orbits, koz_switch_node=window.koz_switch_node,
                       window_nodes=int(s.replan_window_nodes),
                       terminal_target=s.terminal_target, context=context, carry=carry,
                       no_carry=no_carry)


def check_target(target: Target) -> None:
    """Validate a target as a fresh plan's request would (with the scenario's chief and start).

    Raises:
        InputError: naming the offending field.
    """
    sc = ScenarioConfig()
    PlanRequest(np.asarray(sc.chief_oe, float), np.zeros(6), target.target_rtn,
                chance_constrained=target.chance_constrained, warm_start=target.warm_start,
                n_orbits=target.n_orbits)


def deviation_sigma(active: ActivePlan, nav: NavState) -> float:
    """Largest per-axis |nav - predicted| in navigation sigmas (prediction at the fix's epoch)."""
    res = active.result
    tau = (nav.stamp_ns - active.t0_ns) * 1e-9
    k = int(np.searchsorted(res.epochs_s, tau + 0.5, side="right")) - 1
    k = min(max(k, 0), len(res.epochs_s) - 1)
    dt = tau - res.epochs_s[k]
    if abs(dt) < 0.5:
        predicted = res.roe_m[k]
    else:
        oe_k = propagate_mean_oe(res.chief_oe, res.epochs_s[k])
        post = res.roe_m[k] + control_matrix(oe_k) @ res.dv_rtn_mps[k]
        predicted = stm_j2(oe_k, dt) @ post
    sigma = np.sqrt(np.maximum(np.diag(nav.cov_m2), 1e-12))
    return float(np.max(np.abs(nav.roe_m - predicted) / sigma))


def unusable_text(result: PlanResult, active_id: str) -> str:
    """Status text of a replan that did not replace the plan in force."""
    kept = f"plan {active_id} stays in force" if active_id else "no plan is in force"
    return (f"{result.status.name}: replan not usable (margin "
            f"{result.constraint_margin_m:.2f} m after {result.scp.iterations} iterations); "
            f"{kept}")
