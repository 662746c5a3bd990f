"""Typed results of the convex and sequential convex solves."""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


class ScpStatus(enum.Enum):
    """Outcome of a solve (mapped to `ManeuverPlan.STATUS_*` in `ros.adapters.MSG_STATUS`)."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    INFEASIBLE = 2
    SOLVER_ERROR = 3
    TIMEOUT = 4

    @property
    def feasible(self) -> bool:
        """True if a plan with this status satisfies the constraints (to eps_feas) and may be
        flown or stored: the one definition of "feasible" (`FEASIBLE_STATUSES`)."""
        return self in FEASIBLE_STATUSES


FEASIBLE_STATUSES = frozenset({ScpStatus.CONVERGED, ScpStatus.MAX_ITERATIONS})


class Trajectory(NamedTuple):
    """Controls and their states over the N nodes of a horizon: the terminal warm start a
    proposal carries to the post hoc check and to SCVx* (`scp.terminal_warm_start`).

    Attributes:
        dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        roe_m: (N, 6) pre-burn a-scaled ROE [m] (propagated from the controls).
    """

    dv_rtn_mps: np.ndarray
    roe_m: np.ndarray


@dataclass(frozen=True)
class Multipliers:
    """SCVx*'s augmented-Lagrangian state where a run stopped: a re-solve from that run
    (`Scvx.solve` given its `ScpResult`) starts from it.

    Attributes:
        mu: (N,) multipliers of the passive-safety constraints.
        w: the penalty weight.
        trust_radius: the trust region's radius.
    """

    mu: np.ndarray
    w: float
    trust_radius: float


@dataclass(frozen=True)
class ConvexSolution:
    """One convex solve.

    Attributes:
        status: CONVERGED on success, INFEASIBLE or SOLVER_ERROR otherwise.
        roe_m: (N, 6) pre-burn a-scaled ROE [m] (propagated from the controls).
        dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        cost_mps: sum over nodes of the delta-v norm used by the problem [m/s].
        solve_time_ms: wall time of assembly plus solve [ms].
        solver: name of the solver that produced it.
        solver_status: the solver's own status text.
    """

    status: ScpStatus
    roe_m: np.ndarray
    dv_rtn_mps: np.ndarray
    cost_mps: float
    solve_time_ms: float
    solver: str
    solver_status: str

    @property
    def warm_start(self) -> np.ndarray:
        """SCVx*'s warm start from CVX (controls, `Scvx.solve` puts them on the terminal
        condition): CVX's burns, or no burns where CVX has none (not finite: it failed)."""
        dv = self.dv_rtn_mps
        return dv if np.all(np.isfinite(dv)) else np.zeros(dv.shape)


@dataclass(frozen=True)
class ScpIteration:
    """Bookkeeping of one SCVx* iteration (for logs and replay)."""

    iteration: int
    cost_mps: float
    predicted_decrease: float
    actual_decrease: float
    ratio: float
    trust_radius: float
    penalty_weight: float
    max_violation: float
    accepted: bool
    solve_time_ms: float


@dataclass(frozen=True)
class ScpResult:
    """Outcome of a sequential convex programming run.

    Attributes:
        status: see `ScpStatus`.
        roe_m: (N, 6) pre-burn a-scaled ROE [m] of the returned iterate.
        dv_rtn_mps: (N, 3) delta-v in RTN [m/s].
        cost_mps: sum of delta-v 2-norms (or 1-norms for the l1 variant) [m/s].
        iterations: number of convex subproblems solved.
        max_violation: largest nonlinear constraint violation of the returned iterate
            (normalised passive-safety units, and metres for the terminal state).
        history: per-iteration records.
        multipliers: SCVx*'s multipliers, weight and trust radius at the end (a re-solve
            from this result starts from them; None: not a run of SCVx*).
        solve_time_ms: wall time [ms].
    """

    status: ScpStatus
    roe_m: np.ndarray
    dv_rtn_mps: np.ndarray
    cost_mps: float
    iterations: int
    max_violation: float
    history: tuple[ScpIteration, ...] = ()
    multipliers: Multipliers | None = None
    solve_time_ms: float = 0.0

    @property
    def feasible(self) -> bool:
        """True when the returned iterate satisfies the constraints (to eps_feas)."""
        return self.status.feasible
