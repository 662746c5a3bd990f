"""Planning types: warm-start choices, requests, results, navigation states and targets.

Frozen, validated dataclasses that round-trip through JSON; no ROS, no solver calls.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.dynamics import Horizon, check_oe
from art_guidance.errors import InputError
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus


class WarmStart(str, enum.Enum):
    """Where the SCP warm start comes from.

    AUTO: the learned proposal (ART) if a model is loaded and it passes the post hoc check,
    else CVX. CVX: the convex TPBVP solution. ART: the learned proposal even if the check fails.
    """

    AUTO = "auto"
    CVX = "cvx"
    ART = "art"


WARM_STARTS = tuple(w.value for w in WarmStart)


@dataclass(frozen=True)
class PlanRequest:
    """What to plan.

    Attributes:
        chief_oe: (6,) chief mean elements at t0 (a [m], e, i, raan, argp, M [rad]).
        roe0_m: (6,) initial a-scaled ROE [m].
        target_rtn: (6,) terminal RTN state after the last burn [m, m/s].
        chance_constrained: False plans deterministic passive safety (covariance zero).
        warm_start: "auto" (ART if available and accepted, else CVX), "cvx" or "art".
        n_nodes, n_orbits: horizon; None uses the scenario's.
        koz_switch_node: node index where the approach ellipsoid switches to the keep-out zone;
            None uses the scenario's (a replan over the remaining horizon shifts it).
    """

    chief_oe: np.ndarray
    roe0_m: np.ndarray
    target_rtn: np.ndarray
    chance_constrained: bool = True
    warm_start: str = "auto"
    n_nodes: int | None = None
    n_orbits: float | None = None
    koz_switch_node: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "chief_oe", check_oe(self.chief_oe))
        object.__setattr__(self, "roe0_m", as_finite_array("roe0_m", self.roe0_m, (6,)))
        object.__setattr__(self, "target_rtn",
                           as_finite_array("target_rtn", self.target_rtn, (6,)))
        if self.warm_start not in WARM_STARTS:
            raise InputError("warm_start", f"must be one of {WARM_STARTS}", self.warm_start)
        if self.n_nodes is not None and not 3 <= int(self.n_nodes) <= 1000:
            raise InputError("n_nodes", "must be in [3, 1000]", self.n_nodes)
        if self.n_orbits is not None and not 0.01 <= float(self.n_orbits) <= 20:
            raise InputError("n_orbits", "must be in [0.01, 20] orbits", self.n_orbits)
        if self.koz_switch_node is not None and int(self.koz_switch_node) < 0:
            raise InputError("koz_switch_node", "must be >= 0", self.koz_switch_node)

    def to_json(self) -> dict:
        """Everything needed to solve this request again (see `from_json`)."""
        return {"chief_oe": self.chief_oe.tolist(), "roe0_m": self.roe0_m.tolist(),
                "target_rtn": self.target_rtn.tolist(),
                "chance_constrained": bool(self.chance_constrained),
                "warm_start": self.warm_start, "n_nodes": self.n_nodes,
                "n_orbits": self.n_orbits, "koz_switch_node": self.koz_switch_node}

    @classmethod
    def from_json(cls, data: dict) -> "PlanRequest":
        """Inverse of `to_json` (validated again)."""
        try:
            return cls(np.asarray(data["chief_oe"]), np.asarray(data["roe0_m"]),
                       np.asarray(data["target_rtn"]), bool(data["chance_constrained"]),
                       data["warm_start"], data.get("n_nodes"), data.get("n_orbits"),
                       data.get("koz_switch_node"))
        except (KeyError, TypeError) as exc:
            raise InputError("request_json", f"malformed: {exc!r}") from exc


@dataclass(frozen=True)
class PosthocDecision:
    """Post hoc check of a learned warm start (paper: E_R, E_C)."""

    e_r: float
    e_c: float
    accepted: bool


@dataclass(frozen=True)
class PlanResult:
    """A plan and everything needed to publish, record and replay it."""

    status: ScpStatus
    chief_oe: np.ndarray
    epochs_s: np.ndarray     # (N,) [s] from t0
    dv_rtn_mps: np.ndarray   # (N, 3)
    roe_m: np.ndarray        # (N, 6) pre-burn
    rtn: np.ndarray          # (N, 6) [m, m/s]
    cost_mps: float
    scp: ScpResult
    cvx: ConvexSolution
    warm_start: str          # "art" or "cvx"
    posthoc: PosthocDecision | None
    constraint_margin_m: float
    timings_ms: dict = field(default_factory=dict)
    request: PlanRequest | None = None
    art_dv_rtn_mps: np.ndarray | None = None  # (N, 3) learned warm start, if one was proposed

    def to_json(self) -> dict:
        """The plan as JSON-ready data (units in the names)."""
        ph = self.posthoc
        return {
            "chief_oe": self.chief_oe.tolist(),
            "epochs_s": self.epochs_s.tolist(),
            "dv_rtn_mps": self.dv_rtn_mps.tolist(),
            "roe_m": self.roe_m.tolist(),
            "rtn": self.rtn.tolist(),
            "cost_mps": self.cost_mps,
            "cvx_cost_mps": self.cvx.cost_mps,
            "status": self.status.name,
            "scp_iterations": self.scp.iterations,
            "warm_start": self.warm_start,
            "posthoc": None if ph is None else {"E_R": ph.e_r, "E_C": ph.e_c,
                                                "accepted": ph.accepted},
            "timings_ms": dict(self.timings_ms),
            "constraint_margin_m": self.constraint_margin_m,
        }


class WarmStartProvider(Protocol):
    """Proposes warm-start controls (N, 3) [m/s] for a request, or None (e.g. out of domain).

    The pipeline rolls them out through its own dynamics and applies the post hoc check.
    """

    def propose(self, request: PlanRequest, horizon: Horizon,
                cvx: ConvexSolution) -> np.ndarray | None:
        ...


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
