"""What to plan: warm-start choices, the request (and the flown steps it carries), navigation
states and targets.

Frozen, validated dataclasses that round-trip through JSON; no ROS, no solver calls.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.dynamics import check_chief, check_deputy_inclination, mean_motion
from art_guidance.errors import InputError
from art_guidance.optim import TerminalSet
from art_guidance.planning.carry import CarriedPlan


class WarmStart(enum.StrEnum):
    """Where the SCP warm start comes from (a request's `warm_start`; a string that equals
    its value, in texts and JSON alike).

    AUTO: the learned proposal (ART) if a model is loaded and it passes the post hoc check,
    else CVX. CVX: the convex TPBVP solution. ART: the learned proposal even if the check fails.
    """

    AUTO = "auto"
    CVX = "cvx"
    ART = "art"


WARM_STARTS = tuple(w.value for w in WarmStart)


class WarmStartSource(enum.Enum):
    """The warm start an SCVx* run started from: the convex TPBVP solution, the learned
    proposal or the plan in force (`planning.carry`). Its value is the string the plan message,
    the solve record and the JSON carry."""

    CVX = "cvx"
    ART = "art"
    CARRIED = "carried"

    @property
    def other(self) -> "WarmStartSource":
        """The other fresh warm start (CVX for ART and for the carried plan)."""
        return WarmStartSource.ART if self is WarmStartSource.CVX else WarmStartSource.CVX

    @property
    def label(self) -> str:
        """The name in texts: "CVX" or "ART"."""
        return self.value.upper()


class TerminalTarget(enum.StrEnum):
    """Where a replan window shorter than the remainder ends (`planning.window`; a request's
    `terminal_target`, a string that equals its value).

    ART: the learned proposal's state there (CVX's where it is rejected or missing). CVX: the
    convex plan's. CARRY: the plan in force's. Benchmark references (`bench mpc`), not node
    parameters: SCVX, the full-horizon SCVx* plan's state (the oracle: costs the full replan
    it saves), and ART_ANY, ART's whatever the check says.
    """

    ART = "art"
    CVX = "cvx"
    CARRY = "carry"
    SCVX = "scvx"
    ART_ANY = "art_any"


N_ORBITS_RANGE = (0.01, 20.0)  # a plan's horizon [orbits], inclusive
# a node parameter's choices, and the benchmarks' references
TERMINAL_TARGETS = tuple(t.value for t in (TerminalTarget.ART, TerminalTarget.CVX,
                                           TerminalTarget.CARRY))
REFERENCE_TARGETS = tuple(t.value for t in (TerminalTarget.SCVX, TerminalTarget.ART_ANY))


def window_nodes_valid(window_nodes: object, most: int) -> bool:
    """Whether `window_nodes` is a replan window: the integer 0 (the whole remainder) or one in
    [2, `most`] (a window needs two burns to reach its terminal state)."""
    h = window_nodes
    return not isinstance(h, bool) and isinstance(h, (int, np.integer)) \
        and (h == 0 or 2 <= h <= int(most))


@dataclass(frozen=True)
class RolloutContext:
    """The steps flown before a replan's first node, as the learned proposal's context (after
    T-MPC): the plans in force's own states and burns at the nodes flown since the target was
    set, with R decreased by each burn from the first plan's R(t_1) = -J_CVX and C = 0 (the
    constraint-to-go clipped at zero, as T-MPC's closed loop keeps it).

    Attributes:
        roe_m: (h, 6) pre-burn a-scaled ROE at each flown node [m].
        rtn: (h, 6) the same states in RTN [m, m/s].
        dv_rtn_mps: (h, 3) the burn applied there [m/s].
        reward0_mps: R at the first flown node [m/s].
    """

    roe_m: np.ndarray
    rtn: np.ndarray
    dv_rtn_mps: np.ndarray
    reward0_mps: float

    def __post_init__(self) -> None:
        roe = as_finite_array("context roe_m", self.roe_m, (None, 6))
        h = roe.shape[0]
        object.__setattr__(self, "roe_m", roe)
        object.__setattr__(self, "rtn", as_finite_array("context rtn", self.rtn, (h, 6)))
        object.__setattr__(self, "dv_rtn_mps",
                           as_finite_array("context dv_rtn_mps", self.dv_rtn_mps, (h, 3)))
        r0 = float(self.reward0_mps)
        if not np.isfinite(r0):
            raise InputError("context reward0_mps", "must be finite", self.reward0_mps)
        object.__setattr__(self, "reward0_mps", r0)

    @property
    def n_steps(self) -> int:
        """h, the flown nodes."""
        return int(self.roe_m.shape[0])

    @property
    def reward_mps(self) -> np.ndarray:
        """(h,) R(t_i) = R(t_1) + sum_{j < i} ||u_j|| [m/s]."""
        norms = np.linalg.norm(self.dv_rtn_mps, axis=1)
        return self.reward0_mps + np.concatenate([[0.0], np.cumsum(norms)[:-1]])

    @property
    def constraint(self) -> np.ndarray:
        """(h,) C(t_i) = 0."""
        return np.zeros(self.n_steps)

    def last(self, steps: int) -> "RolloutContext":
        """The last `steps` flown nodes (R carried over to the first of them)."""
        k = self.n_steps - int(steps)
        return RolloutContext(self.roe_m[k:], self.rtn[k:], self.dv_rtn_mps[k:],
                              float(self.reward_mps[k]) if k < self.n_steps else
                              self.reward0_mps)

    def extended(self, roe_m: np.ndarray, rtn: np.ndarray,
                 dv_rtn_mps: np.ndarray) -> "RolloutContext":
        """This context followed by more flown nodes."""
        return RolloutContext(np.concatenate([self.roe_m, roe_m]),
                              np.concatenate([self.rtn, rtn]),
                              np.concatenate([self.dv_rtn_mps, dv_rtn_mps]), self.reward0_mps)

    def to_json(self) -> dict:
        """JSON-ready fields."""
        return {"roe_m": self.roe_m.tolist(), "rtn": self.rtn.tolist(),
                "dv_rtn_mps": self.dv_rtn_mps.tolist(), "reward0_mps": self.reward0_mps}

    @classmethod
    def from_json(cls, data: dict) -> "RolloutContext":
        """Inverse of `to_json` (validated again)."""
        return cls(np.asarray(data["roe_m"], float).reshape(-1, 6),
                   np.asarray(data["rtn"], float).reshape(-1, 6),
                   np.asarray(data["dv_rtn_mps"], float).reshape(-1, 3),
                   data["reward0_mps"])


@dataclass(frozen=True)
class PlanRequest:
    """What to plan.

    Attributes:
        chief_oe: (6,) chief mean elements at t0 (a [m], e, i, raan, argp, M [rad]).
        roe0_m: (6,) initial a-scaled ROE [m].
        target_rtn: (6,) terminal RTN state after the last burn [m, m/s].
        chance_constrained: False plans deterministic passive safety (covariance zero).
        warm_start: `WarmStart` (a string of its values is taken: "auto", "cvx" or "art").
        n_nodes, n_orbits: horizon; None uses the scenario's.
        koz_switch_node: node index where the approach ellipsoid switches to the keep-out zone;
            None uses the scenario's (a replan over the remaining horizon shifts it).
        window_nodes: H > 0 optimises only nodes 0..H when the horizon is longer, to
            `terminal_target`'s state at node H (`planning.window`); 0 the whole horizon.
        terminal_target: `TerminalTarget` (a string of its values is taken).
        context: the steps flown before node 0, given to the learned proposal (None: none).
        carry: the plan in force's burns at the request's nodes (`planning.carry`; None: none).
        no_carry: why the guidance carried none ("" = no plan in force).
        terminal_set: where the plan may end about `target_rtn` (`optim.terminal_set`: the
            end game's last replans, `planning.endgame`); None: exactly on it. A window
            shorter than the remainder ends on its own state whatever this says.
    """

    chief_oe: np.ndarray
    roe0_m: np.ndarray
    target_rtn: np.ndarray
    chance_constrained: bool = True
    warm_start: WarmStart = WarmStart.AUTO
    n_nodes: int | None = None
    n_orbits: float | None = None
    koz_switch_node: int | None = None
    window_nodes: int = 0
    terminal_target: TerminalTarget = TerminalTarget.ART
    context: RolloutContext | None = None
    carry: CarriedPlan | None = None
    no_carry: str = ""
    terminal_set: TerminalSet | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "chief_oe", check_chief(self.chief_oe))
        object.__setattr__(self, "roe0_m", as_finite_array("roe0_m", self.roe0_m, (6,)))
        object.__setattr__(self, "target_rtn",
                           as_finite_array("target_rtn", self.target_rtn, (6,)))
        # the deputy at both ends stays inside the ROE's domain too (|dix| <= |(r_N, v_N / n)|)
        check_deputy_inclination(self.chief_oe, abs(float(self.roe0_m[4])), "roe0_m")
        n = mean_motion(float(self.chief_oe[0]))
        check_deputy_inclination(self.chief_oe, float(np.hypot(self.target_rtn[2],
                                                               self.target_rtn[5] / n)),
                                 "target_rtn")
        if self.warm_start not in WARM_STARTS:
            raise InputError("warm_start", f"must be one of {WARM_STARTS}", self.warm_start)
        object.__setattr__(self, "warm_start", WarmStart(self.warm_start))
        if self.n_nodes is not None and not 3 <= int(self.n_nodes) <= 1000:
            raise InputError("n_nodes", "must be in [3, 1000]", self.n_nodes)
        lo, hi = N_ORBITS_RANGE
        if self.n_orbits is not None and not lo <= float(self.n_orbits) <= hi:
            raise InputError("n_orbits", f"must be in [{lo:g}, {hi:g}] orbits", self.n_orbits)
        if self.koz_switch_node is not None and int(self.koz_switch_node) < 0:
            raise InputError("koz_switch_node", "must be >= 0", self.koz_switch_node)
        if not window_nodes_valid(self.window_nodes, 1000):
            raise InputError("window_nodes", "must be 0 (the whole horizon) or in [2, 1000]",
                             self.window_nodes)
        if self.context is not None and not isinstance(self.context, RolloutContext):
            raise InputError("context", "must be a RolloutContext or None",
                             type(self.context).__name__)
        if self.terminal_target not in TERMINAL_TARGETS + REFERENCE_TARGETS:
            raise InputError("terminal_target", f"must be one of {TERMINAL_TARGETS} (or a "
                             f"benchmark's reference {REFERENCE_TARGETS})", self.terminal_target)
        object.__setattr__(self, "terminal_target", TerminalTarget(self.terminal_target))
        if self.carry is not None and not isinstance(self.carry, CarriedPlan):
            raise InputError("carry", "must be a CarriedPlan or None", type(self.carry).__name__)
        if self.terminal_set is not None and not isinstance(self.terminal_set, TerminalSet):
            raise InputError("terminal_set", "must be a TerminalSet or None",
                             type(self.terminal_set).__name__)

    def to_json(self) -> dict:
        """Everything needed to solve this request again (see `from_json`; `terminal_set`
        only when there is one: a request without it reads as before)."""
        out = {"chief_oe": self.chief_oe.tolist(), "roe0_m": self.roe0_m.tolist(),
               "target_rtn": self.target_rtn.tolist(),
               "chance_constrained": bool(self.chance_constrained),
               "warm_start": self.warm_start.value, "n_nodes": self.n_nodes,
               "n_orbits": self.n_orbits, "koz_switch_node": self.koz_switch_node,
               "window_nodes": int(self.window_nodes),
               "terminal_target": self.terminal_target.value,
               "context": None if self.context is None else self.context.to_json(),
               "carry": None if self.carry is None else self.carry.to_json(),
               "no_carry": self.no_carry}
        if self.terminal_set is not None:
            out["terminal_set"] = self.terminal_set.to_json()
        return out

    @classmethod
    def from_json(cls, data: dict) -> "PlanRequest":
        """Inverse of `to_json` (validated again)."""
        try:
            return cls(np.asarray(data["chief_oe"]), np.asarray(data["roe0_m"]),
                       np.asarray(data["target_rtn"]), bool(data["chance_constrained"]),
                       data["warm_start"], data.get("n_nodes"), data.get("n_orbits"),
                       data.get("koz_switch_node"), data.get("window_nodes", 0),
                       data.get("terminal_target", "art"),
                       None if data.get("context") is None
                       else RolloutContext.from_json(data["context"]),
                       None if data.get("carry") is None
                       else CarriedPlan.from_json(data["carry"]),
                       str(data.get("no_carry", "")),
                       TerminalSet.from_json(data.get("terminal_set")))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError("request_json", f"malformed: {exc!r}") from exc


@dataclass(frozen=True)
class NavState:
    """A validated navigation estimate in a-scaled ROE.

    Attributes:
        stamp_ns: epoch of the estimate [ns].
        chief_oe: (6,) chief mean elements at the stamp.
        roe_m: (6,) mean a-scaled ROE [m].
        cov_m2: (6, 6) covariance of roe_m [m^2].
    """

    stamp_ns: int
    chief_oe: np.ndarray
    roe_m: np.ndarray
    cov_m2: np.ndarray


@dataclass(frozen=True)
class Target:
    """A validated replanning target.

    Attributes:
        waypoint: waypoint name ("custom" for an explicit state).
        target_rtn: (6,) terminal RTN state [m, m/s].
        chance_constrained: chance-constrained (True) or deterministic passive safety.
        warm_start: one of WARM_STARTS.
        n_orbits: horizon [orbits], or None for the scenario's.
    """

    waypoint: str
    target_rtn: np.ndarray
    chance_constrained: bool
    warm_start: str
    n_orbits: float | None
