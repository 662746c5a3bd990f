"""Does the error matter? The end-game policy's check of the plan in force from a new fix.

A navigation fix off the plan is mostly navigation noise; re-solving for it pays to null an
error that may change neither safety nor where the flight ends, and in the last nodes that
costs up to ~1 m/s a replan (docs/results.md, "The final approach"). So, with `endgame: keep`
(planning.yaml, the node's parameter of the same name), a replan the deviation triggers is made
only when the error matters: the plan in force's remaining burns, flown from the fix (the
deputy-aware model SCVx* plans with), must be

- passively safe: the planner's own check (`PassiveSafety.evaluate`: the continuous-time
  minimum over every drift arc, chance-constrained in that mode with the covariance the plan
  is made with), margin >= 0 at every remaining node; and
- on target: the predicted post-burn state after the last burn within `terminal_tolerance_m`
  (position) and `terminal_tolerance_mps` (velocity) of the waypoint.

Otherwise the replan is made as before. With `endgame: keep_cap` a replan that is made is also
capped: a plan costing more above the plan in force's remaining burns than the error it removes
is worth (`endgame_cost_cap_mps` plus `endgame_cost_per_m` per metre of predicted terminal
error) is not put in force while the plan in force is still passively safe from the fix. A cap
that ignored the error would keep a plan in force that misses by kilometres after a missed
burn (measured: seed 3, its largest burn missed, 19 km off).

With `terminal_set_nodes` > 0 a replan the end game makes with that many nodes left or fewer
ends anywhere within `terminal_set_share` of the terminal tolerances (at the waypoint's, not
widened) instead of on the waypoint: a terminal set (`optim.terminal_set`), two second-order
cones in CVX and SCVx*. It restores safety or removes what is beyond the tolerances without
paying to null what they accept.

`none` is the behaviour before the end game existed, bit for bit.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from art_guidance.config import PlanningConfig
from art_guidance.dynamics import Horizon
from art_guidance.optim import TerminalSet
from art_guidance.planning.carry import CarriedPlan
from art_guidance.planning.transfer import Transfer


class Endgame(str, enum.Enum):
    """The end-game policy (`planning.yaml` `endgame`)."""

    NONE = "none"
    KEEP = "keep"
    KEEP_CAP = "keep_cap"

    @property
    def keeps(self) -> bool:
        """A replan the deviation triggers is skipped when the error does not matter."""
        return self is not Endgame.NONE

    @property
    def caps(self) -> bool:
        """A replan far dearer than the plan in force is not put in force while it is safe."""
        return self is Endgame.KEEP_CAP


@dataclass(frozen=True)
class InForceCheck:
    """The plan in force flown from a fix.

    Attributes:
        margin_m: its smallest passive-safety margin over the remaining nodes and drift arcs
            [m] (>= 0: safe; chance-constrained in that mode).
        terminal_error_m: predicted position error at the waypoint after its last burn [m].
        terminal_error_mps: predicted velocity error there [m/s].
        remaining_mps: what it still spends [m/s].
        terminal_sigma: the predicted terminal error (position and velocity) in standard
            deviations of the fix's own navigation error mapped there (the Mahalanobis
            distance under the fix's covariance carried through the plan's fixed burns; inf:
            no covariance given): what the fix alone cannot tell from noise.
        terminal_rtn: (6,) the predicted RTN state after its last burn [m, m/s].
    """

    margin_m: float
    terminal_error_m: float
    terminal_error_mps: float
    remaining_mps: float
    terminal_sigma: float = np.inf
    terminal_rtn: np.ndarray | None = None

    @property
    def safe(self) -> bool:
        """Passively safe from the fix."""
        return bool(self.margin_m >= 0.0)

    def on_target(self, tolerance_m: float, tolerance_mps: float,
                  tolerance_sigma: float = 0.0) -> bool:
        """Its predicted terminal error is within `tolerance_m` (position) and `tolerance_mps`
        (velocity), or within `tolerance_sigma` standard deviations of what the fix's
        navigation error alone makes of it (indistinguishable from noise)."""
        return bool((self.terminal_error_m <= tolerance_m
                     and self.terminal_error_mps <= tolerance_mps)
                    or self.terminal_sigma <= tolerance_sigma)

    def kept_under(self, planning: PlanningConfig, n_nodes: int) -> bool:
        """Whether the plan in force stays in force under the end game's settings with
        `n_nodes` nodes left: safe, and on target within the terminal tolerances (scaled by
        `tolerance_scale`)."""
        return self.safe and self.on_target_under(planning, n_nodes)

    def on_target_under(self, planning: PlanningConfig, n_nodes: int) -> bool:
        """`on_target` under the end game's settings with `n_nodes` nodes left."""
        scale = tolerance_scale(planning.tolerance_growth_nodes, n_nodes)
        return self.on_target(scale * planning.terminal_tolerance_m,
                              scale * planning.terminal_tolerance_mps,
                              planning.terminal_tolerance_sigma)

    def worth_mps(self, planning: PlanningConfig) -> float:
        """What removing its predicted terminal error is worth [m/s]: `endgame_cost_cap_mps`
        plus `endgame_cost_per_m` per metre of it. A replan dearer than that above this plan's
        remaining burns is not put in force while this plan is safe (`keep_cap`); a large
        error (a missed burn's kilometres) is worth any replan."""
        return planning.endgame_cost_cap_mps + planning.endgame_cost_per_m * self.terminal_error_m

    def text(self) -> str:
        """The check in words (diagnostics, plan status)."""
        return (f"plan in force from the fix: margin {self.margin_m:.2f} m, terminal error "
                f"{self.terminal_error_m:.2f} m / {1e3 * self.terminal_error_mps:.1f} mm/s "
                f"({self.terminal_sigma:.1f} sigma of the fix's navigation error)")


def tolerance_scale(growth_nodes: int, n_nodes: int) -> float:
    """How much wider than at the waypoint the terminal tolerances are with `n_nodes` nodes
    left: ``max(1, n_nodes / growth_nodes)`` (1 everywhere with `growth_nodes` 0). Far out, an
    error can still be removed cheaply later, and most of what a fix predicts there is the
    model's drift that later fixes re-measure; near the waypoint the tolerance is the one
    the flight is flown to."""
    return max(1.0, n_nodes / growth_nodes) if growth_nodes > 0 else 1.0


def in_set_under(planning: PlanningConfig, n_nodes: int) -> TerminalSet | None:
    """The terminal set a replan the end game makes with `n_nodes` nodes left ends in:
    `terminal_set_share` of the terminal tolerances at the waypoint when `n_nodes` <=
    `terminal_set_nodes`; else None (the waypoint exactly). Not widened, and a share of them:
    a plan ending on the boundary of the keep check's own tolerances fails the next fix's
    check at the first drift and is replanned at every fix."""
    if not (Endgame(planning.endgame).keeps and 0 < n_nodes <= planning.terminal_set_nodes):
        return None
    if planning.terminal_tolerance_m <= 0.0 or planning.terminal_tolerance_mps <= 0.0:
        return None  # no tolerance, no set (`terminal_set_share` is > 0 by validation)
    share = planning.terminal_set_share
    return TerminalSet(share * planning.terminal_tolerance_m,
                       share * planning.terminal_tolerance_mps)


def check_in_force(transfer: Transfer, carry: CarriedPlan,
                   cov_m2: np.ndarray | None = None) -> InForceCheck:
    """Fly the carried plan's burns from the transfer's initial state (the fix) and judge them
    with the transfer's own passive-safety model and terminal condition.

    Args:
        transfer: the replan's transfer (the fix, the remaining horizon, the waypoint).
        carry: the plan in force's burns at the transfer's nodes.
        cov_m2: (6, 6) the fix's covariance [m^2] (a-scaled ROE), or None.
    """
    problem = transfer.problem
    dv = carry.dv_rtn_mps
    traj = problem.propagate(dv)
    evaluation = transfer.safety.evaluate(traj.roe_m, dv)
    horizon = transfer.horizon
    z_f = horizon.final_post_burn_nonlinear(traj.roe_m, dv)
    err = horizon.psi[-1] @ (z_f - problem.roe_f_m)  # (6,) RTN [m, m/s]
    margin = float(np.min(evaluation.margin_m))
    return InForceCheck(margin if np.isfinite(margin) else -np.inf,
                        float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:])),
                        carry.remaining_mps, _in_sigmas(horizon, err, cov_m2),
                        horizon.psi[-1] @ z_f)


def _in_sigmas(horizon: Horizon, err: np.ndarray, cov_m2: np.ndarray | None) -> float:
    """The Mahalanobis distance of a terminal RTN error (6,) [m, m/s] under the fix's
    covariance (6, 6) [m^2] mapped to the waypoint through the plan's fixed burns (the last
    Psi times the STMs' product); inf without a covariance or where it maps to a singular
    one."""
    if cov_m2 is None:
        return float("inf")
    phi = np.eye(6)
    for stm in horizon.stm:
        phi = stm @ phi
    m = horizon.psi[-1] @ phi  # (6, 6): ROE at the fix -> RTN after the last burn
    s = m @ np.asarray(cov_m2, float) @ m.T
    try:
        d2 = float(err @ np.linalg.solve(s, err))
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(d2)) if np.isfinite(d2) and d2 >= 0.0 else float("inf")
