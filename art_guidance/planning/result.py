"""What a plan is: the result, its post hoc decision and discarded run, the learned proposal and
the provider protocol that makes it.

Frozen dataclasses; no ROS, no solver calls.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from art_guidance.config import PlanningConfig
from art_guidance.deadline import Deadline
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus, Trajectory, TransferProblem
from art_guidance.planning.carry import CarryReport
from art_guidance.planning.request import PlanRequest, WarmStartSource


@dataclass(frozen=True)
class Timings:
    """A plan's wall times per stage [ms]: its transfer's set-up, CVX, the learned step, every
    SCVx* run, the whole plan, and for a windowed replan its window's own plan (None: not
    one). With the concurrent proposal "art" (its own wall time) overlaps "scp": their sum then
    exceeds the total."""

    setup: float = 0.0
    cvx: float = 0.0
    art: float = 0.0
    scp: float = 0.0
    total: float = 0.0
    window: float | None = None

    def to_json(self) -> dict:
        """{"setup", "cvx", "art", "scp", "total"[, "window"]} [ms], as recorded since the
        first plans."""
        out = {"setup": self.setup, "cvx": self.cvx, "art": self.art, "scp": self.scp,
               "total": self.total}
        if self.window is not None:
            out["window"] = self.window
        return out


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


@dataclass(frozen=True)
class PosthocDecision:
    """Post hoc check of a learned warm start (paper: E_R, E_C).

    NaN values mean the proposal could not be checked (non-finite or wrong-shape output); it
    is then rejected.
    """

    e_r: float
    e_c: float
    accepted: bool

    def text(self) -> str:
        """E_R and E_C in the units of the acceptance region (100 E_R [%], E_C [nodes])."""
        return f"100 E_R = {100.0 * self.e_r:+.2f} %, E_C = {self.e_c:g}"


@dataclass(frozen=True)
class WarmStartProposal:
    """A learned warm start as proposed (before the post hoc check).

    Attributes:
        dv_rtn_mps: (N, 3) proposed controls [m/s] (any shape or value: the pipeline validates).
        reward_to_go_mps: (N,) realised R(t_i) = -sum_{j >= i} ||u_j|| of the rollout [m/s].
        constraint_to_go: (N,) realised C(t_i) = number of violating nodes j >= i.
        model_sha256: checksum of the model that produced it ("" if unknown).
        rollout_ms: wall time of the rollout [ms].
        warm_start: the controls corrected onto the terminal condition and their states
            (`optim.TransferProblem.terminal_warm_start`), when the provider computed them
            judging its candidates (None: it did not). The pipeline uses them for the post hoc
            check and as SCVx*'s first reference once it has checked that they are finite,
            that the states are those of the controls and that they meet the terminal
            condition; otherwise it computes them.
    """

    dv_rtn_mps: np.ndarray
    reward_to_go_mps: np.ndarray | None = None
    constraint_to_go: np.ndarray | None = None
    model_sha256: str = ""
    rollout_ms: float = 0.0
    warm_start: Trajectory | None = None


@dataclass(frozen=True)
class ScpAttempt:
    """An SCP run of the plan that was not kept (e.g. from ART before the retry from CVX)."""

    warm_start: WarmStartSource
    status: ScpStatus
    cost_mps: float
    iterations: int
    solve_time_ms: float


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
    warm_start: WarmStartSource  # the warm start of the SCP run kept
    posthoc: PosthocDecision | None  # None: no learned warm start was tried
    constraint_margin_m: float
    timings: Timings = field(default_factory=Timings)  # wall times per stage [ms]
    request: PlanRequest | None = None
    proposal: WarmStartProposal | None = None  # the learned warm start, if one was proposed
    warm_start_reason: str = ""  # why this warm start, in words
    discarded: ScpAttempt | None = None  # an SCP run replaced by a better retry
    window: PlanWindow | None = None  # how a windowed replan used its window (None: not one)
    carry: CarryReport | None = None  # what the plan did with the plan in force
    scp_iterations_all: int = 0  # iterations of every SCVx* run of this plan, kept or not
    # the path its numerics ran on: "compiled", "numpy", or "mixed" (the kernels became ready
    # during the plan); "" = not said (a result not made by `GuidancePipeline.plan`)
    numerics: str = ""
    deadline_hit: bool = False  # a stage found the plan's deadline passed (`deadline`)

    @property
    def art_dv_rtn_mps(self) -> np.ndarray | None:
        """(N, 3) learned warm-start controls as proposed, or None."""
        return None if self.proposal is None else np.asarray(self.proposal.dv_rtn_mps)

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
            "scp_iterations_all": self.scp_iterations_all,
            "warm_start": self.warm_start.value,
            "warm_start_reason": self.warm_start_reason,
            "posthoc": None if ph is None else {"E_R": ph.e_r, "E_C": ph.e_c,
                                                "accepted": ph.accepted},
            "art_cost_mps": (None if self.art_dv_rtn_mps is None or not np.all(
                np.isfinite(self.art_dv_rtn_mps)) else float(
                np.linalg.norm(self.art_dv_rtn_mps.reshape(-1, 3), axis=1).sum())),
            "discarded_attempt": None if (d := self.discarded) is None else {
                "warm_start": d.warm_start.value, "status": d.status.name,
                "cost_mps": d.cost_mps, "iterations": d.iterations},
            "timings_ms": self.timings.to_json(),
            "constraint_margin_m": self.constraint_margin_m,
            "window": None if self.window is None else self.window.to_json(),
            "carry": None if self.carry is None else self.carry.to_json(),
            "numerics_path": self.numerics,
            "deadline_hit": self.deadline_hit,
        }


class WarmStartProvider(Protocol):
    """Proposes a learned warm start for a transfer problem (its RTN target the goal).

    `propose` returns a `WarmStartProposal` (or bare (N, 3) controls [m/s]); it raises a
    `GuidanceError` saying why when the problem is outside what it can propose for (e.g. a
    horizon longer than the model's context, or a problem without an RTN target). `planning`
    says how the pipeline will check the proposal (a provider with several candidates ranks
    them by it; None: the packaged defaults); `deadline` is the plan's (None: none), after
    which a provider should stop (raising `DeadlineError`). The pipeline never trusts the
    output: it validates it, rolls it out through its own dynamics and applies the post hoc
    check; any exception is caught and the plan falls back to CVX.

    Attributes:
        sha256: checksum of the model ("" if none), recorded with every run.
    """

    sha256: str

    def propose(self, problem: TransferProblem, cvx: ConvexSolution,
                planning: PlanningConfig | None = None,
                deadline: Deadline | None = None) -> "WarmStartProposal | np.ndarray":
        ...
