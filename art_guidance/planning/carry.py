"""The carried warm start: a replan starts from the plan in force (receding-horizon shift).

At a replan with a plan in force, the guidance (`guidance.replan.ReplanPolicy.carry_at`) puts
that plan's burns at the replan's nodes into the request (`CarriedPlan`; the replan's horizon is
the plan in force's remaining nodes). With `replan_warm_start: carry` (planning.yaml) the
pipeline corrects them onto the terminal condition from the new fix
(`TransferProblem.terminal_warm_start`, the learned proposal's correction) and runs SCVx* from
them first; the fresh solve (SCVx* from CVX, and from the learned proposal with warm start
`auto`) runs only:

- as the rescue, where the carried run does not converge (the better plan is kept);
- as the guard against a locked basin (`guard_reason`), where the carried plan has grown far
  above what was last verified against a fresh solve *and* stands far above J_CVX, the lower
  bound every replan has: the cheaper plan is kept;
- where there is nothing to carry (no plan in force, a new target, another mode, a changed
  configuration, a fix off the node grid, a horizon raised to its minimum, non-finite burns:
  the plan says which), and where the CVX plan is already passively safe (its SCVx* plan is the
  optimum: one iteration, no carry needed).

The growth is tracked in `CarryReport.excess_mps`: 0 for a plan chosen against a fresh solve,
else the plan in force's excess plus what this replan's plan costs above the plan in force's
remaining burns. It travels in the request (`CarriedPlan.excess_mps`), so a recorded solve
replays bit for bit from its request alone.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.errors import InputError

GRID_TOL = 0.01  # a fix within this share of a node spacing of a node is on the grid


@dataclass(frozen=True)
class CarriedPlan:
    """The plan in force, carried to a replan.

    Attributes:
        plan_id: the plan in force's id.
        dv_rtn_mps: (N, 3) its burns at the replan's N nodes [m/s].
        roe_m: (N, 6) its own predicted pre-burn a-scaled ROE there [m] (a windowed replan's
            `terminal_target: carry` ends at its post-burn state at the window's end).
        excess_mps: its growth since it was last chosen against a fresh solve [m/s]
            (`CarryReport.excess_mps`).
        chance_constrained: the mode it was planned in.
        config_sha256: the configuration it was planned with (`GuidanceConfig.sha256`).
    """

    plan_id: str
    dv_rtn_mps: np.ndarray
    roe_m: np.ndarray
    excess_mps: float
    chance_constrained: bool
    config_sha256: str

    def __post_init__(self) -> None:
        dv = np.asarray(self.dv_rtn_mps, float)
        if dv.ndim != 2 or dv.shape[1] != 3 or dv.shape[0] < 2:
            raise InputError("carry dv_rtn_mps", "must be (N, 3) with N >= 2", dv.shape)
        object.__setattr__(self, "dv_rtn_mps", dv)
        object.__setattr__(self, "roe_m", as_finite_array("carry roe_m", self.roe_m,
                                                          (dv.shape[0], 6)))
        excess = float(self.excess_mps)
        if not np.isfinite(excess):
            raise InputError("carry excess_mps", "must be finite", self.excess_mps)
        object.__setattr__(self, "excess_mps", excess)

    def first(self, n_nodes: int) -> "CarriedPlan":
        """The same plan over its first `n_nodes` nodes (a window's)."""
        return CarriedPlan(self.plan_id, self.dv_rtn_mps[:n_nodes], self.roe_m[:n_nodes],
                           self.excess_mps, self.chance_constrained, self.config_sha256)

    @property
    def remaining_mps(self) -> float:
        """What the plan in force still plans to spend from the replan's first node [m/s]."""
        return float(np.linalg.norm(self.dv_rtn_mps, axis=1).sum())

    def to_json(self) -> dict:
        """JSON-ready fields (exact: floats round-trip through JSON)."""
        return {"plan_id": self.plan_id, "dv_rtn_mps": self.dv_rtn_mps.tolist(),
                "roe_m": self.roe_m.tolist(), "excess_mps": self.excess_mps,
                "chance_constrained": self.chance_constrained,
                "config_sha256": self.config_sha256}

    @classmethod
    def from_json(cls, data: dict) -> "CarriedPlan":
        """Inverse of `to_json` (validated again)."""
        dv = as_finite_array("carry dv_rtn_mps", np.asarray(data["dv_rtn_mps"], float)
                             .reshape(-1, 3), (None, 3))
        return cls(str(data["plan_id"]), dv, np.asarray(data["roe_m"], float).reshape(-1, 6),
                   data["excess_mps"],
                   bool(data["chance_constrained"]), str(data["config_sha256"]))


@dataclass(frozen=True)
class CarryReport:
    """What a plan did with the plan in force.

    Attributes:
        policy: the `replan_warm_start` it was planned under ("carry" or "fresh").
        carried: SCVx* ran from the plan in force.
        reason: why it did or did not, in words.
        kept: the plan is the carried run's.
        guard: why the guard solved fresh too ("" = it did not fire).
        excess_mps: this plan's growth since it was last chosen against a fresh solve [m/s]
            (0: chosen against one; the next carry's `CarriedPlan.excess_mps`).
        carried_iterations: SCVx* iterations of the carried run (0: none).
        config_sha256: the configuration it was planned with.
    """

    policy: str
    carried: bool
    reason: str
    kept: bool = False
    guard: str = ""
    excess_mps: float = 0.0
    carried_iterations: int = 0
    config_sha256: str = ""

    def to_json(self) -> dict:
        """JSON-ready fields."""
        return {"policy": self.policy, "carried": self.carried, "reason": self.reason,
                "kept": self.kept, "guard": self.guard, "excess_mps": self.excess_mps,
                "carried_iterations": self.carried_iterations}


def refusal(carry: CarriedPlan | None, no_carry: str, policy: str, chance_constrained: bool,
            config_sha256: str, n_nodes: int) -> str:
    """Why a request's carried plan cannot warm-start this plan ("" = it can).

    Args:
        carry: the request's carried plan, or None.
        no_carry: the request's own reason for having none ("" = no plan in force).
        policy: `replan_warm_start`.
        chance_constrained: the request's mode.
        config_sha256: the planner's configuration.
        n_nodes: the request's horizon.
    """
    if policy != "carry":
        return "replan_warm_start fresh"
    if carry is None:
        return no_carry or "no plan in force"
    if carry.chance_constrained != chance_constrained:
        return "the plan in force was planned in the other mode"
    if carry.config_sha256 != config_sha256:
        return "the configuration changed since the plan in force was made"
    if carry.dv_rtn_mps.shape[0] != n_nodes:
        return (f"the plan in force has {carry.dv_rtn_mps.shape[0]} nodes left, the replan "
                f"{n_nodes}")
    if not np.all(np.isfinite(carry.dv_rtn_mps)):
        return "the plan in force's burns are not finite"
    return ""


def guard_reason(excess_mps: float, cost_mps: float, cvx_cost_mps: float,
                 guard_mps: float) -> str:
    """Why the carried plan must be checked against a fresh solve ("" = it need not): it has
    grown by more than `guard_mps` since it was last chosen against one, and it stands more
    than `guard_mps` above J_CVX (the lower bound: below that a fresh solve cannot gain)."""
    gap = cost_mps - cvx_cost_mps
    if excess_mps > guard_mps and gap > guard_mps:
        return (f"the carried plan grew {1e3 * excess_mps:.0f} mm/s since it was checked "
                f"against a fresh solve and stands {1e3 * gap:.0f} mm/s above J_CVX "
                f"(carry_guard_mps {1e3 * guard_mps:.0f} mm/s)")
    return ""
