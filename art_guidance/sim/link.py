"""The simulator's link to a guidance instance: over DDS (`ros.sim_node.SimNode`) or in-process.

`ClosedLoop` talks to the guidance only through this protocol, so the same loop runs against the
guidance node over ROS 2 and, without DDS, against `InProcessGuidance` (Monte Carlo runs, the
offline demo). Plans cross it as `LinkPlan`: plain arrays, no message types.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

from art_guidance.optim import ScpStatus


@dataclass(frozen=True)
class LinkPlan:
    """A plan (or a status without maneuvers) as the guidance published it.

    Attributes:
        stamp_ns: the nav stamp it answers [ns] (its node 0).
        plan_id: the guidance's id.
        status: the solve's status, or None for a rejection notice (the nav fix was refused).
        status_text: what happened, in words.
        active_plan_id: the plan the guidance follows after this message ("" = none).
        epochs_s: (N,) node epochs from `stamp_ns` [s] (empty for a rejection).
        dv_rtn_mps: (N * 3,) delta-v in RTN, row-major [m/s].
        rtn: (N * 6,) predicted RTN states, row-major [m, m/s] (may be empty).
    """

    stamp_ns: int
    plan_id: str
    status: ScpStatus | None
    status_text: str
    active_plan_id: str
    epochs_s: np.ndarray
    dv_rtn_mps: np.ndarray
    rtn: np.ndarray

    @property
    def rejection(self) -> bool:
        """True for the answer to a refused nav fix (not a replan)."""
        return self.status is None


class GuidanceLink(Protocol):
    """What the closed loop needs from a guidance instance.

    Protocol: every processed nav fix gets a decision (key-values with `decision` in
    {replanning, on_plan, rejected}); after "replanning" a plan stamped with that fix follows.
    """

    epoch0_ns: int

    def wait_matched(self, timeout_s: float) -> bool:
        """True once the guidance is reachable in both directions."""

    def publish_request(self, waypoint: str, chance_constrained: bool, warm_start: str) -> None:
        """Send the replanning request (target and mode)."""

    def publish_nav(self, stamp_ns: int, chief_oe: np.ndarray, roe_m: np.ndarray,
                    cov_m2: np.ndarray) -> None:
        """Send a navigation fix in ROE."""

    def wait_decision(self, stamp_ns: int, timeout_s: float) -> dict[str, str] | None:
        """The decision key-values answering the fix `stamp_ns`, or None on timeout."""

    def wait_plan(self, stamp_ns: int, timeout_s: float) -> bool:
        """True once a plan (not a rejection notice) stamped `stamp_ns` has arrived."""

    def take_plans(self, start: int) -> list[LinkPlan]:
        """Plans received from index `start` on, in arrival order."""

    def publish_truth(self, t_s: Sequence[float], rtn: Sequence[np.ndarray]) -> None:
        """Show the truth trajectory so far: K sim times [s] and K RTN states (6,) [m, m/s]
        (the simulator's record, passed as is; a link without a visualisation ignores it)."""
