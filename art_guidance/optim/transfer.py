"""The transfer problem every solver stage solves: a passive-safety model (its horizon) and
the boundary conditions, the terminal one solved once from the RTN target (`terminal_roe`).

CVX (`TransferProblem.cvx`), SCVx* (`TransferProblem.scvx`) and the terminal warm start
(`TransferProblem.terminal_warm_start`) of the post hoc check and of the learned proposal all
take the one `TransferProblem`; the planner's `planning.transfer.Transfer` pairs it with its
request. The problem builds its solvers, and the solvers take it as it is: `scp.Scvx` reads
only what its protocol `scp.ScvxProblem` names and imports nothing from here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.config import ScpConfig
from art_guidance.dynamics import DeputyLinearization, Horizon
from art_guidance.optim.cvx import solve_cvx
from art_guidance.optim.problem import SubproblemOptions, SubproblemPool
from art_guidance.optim.results import ConvexSolution, Trajectory
from art_guidance.optim.scp import Scvx, onto_terminal_set
from art_guidance.optim.terminal_set import TerminalSet
from art_guidance.safety import PassiveSafety


def terminal_roe(horizon: Horizon, target_rtn: object) -> np.ndarray:
    """The post-burn a-scaled ROE [m] at the last node of `horizon` of an RTN target
    [m, m/s]: (6,) for a (6,) target, (B, 6) for a (B, 6) batch (Psi_N^-1 target)."""
    target = np.asarray(target_rtn, dtype=float)
    if target.ndim == 1:
        return np.linalg.solve(horizon.psi[-1], target)
    return np.linalg.solve(horizon.psi[-1], target.T).T


@dataclass(frozen=True, eq=False)
class TransferProblem:
    """One transfer: from `roe0_m` to `roe_f_m` over the horizon of `safety`.

    Attributes:
        safety: the passive-safety model (deterministic or chance-constrained); its horizon
            is the problem's.
        roe0_m: (6,) initial pre-burn a-scaled ROE [m] (a float array: converted when given
            otherwise).
        roe_f_m: (6,) terminal post-burn a-scaled ROE [m] (likewise).
        target_rtn: (6,) the RTN target [m, m/s] `roe_f_m` was solved from (the learned
            proposal's goal), or None for a problem given in ROE.
        terminal_set: where the plan may end about `roe_f_m` (`optim.terminal_set`; None:
            exactly there).
    """

    safety: PassiveSafety
    roe0_m: np.ndarray
    roe_f_m: np.ndarray
    target_rtn: np.ndarray | None = None
    terminal_set: TerminalSet | None = None

    def __post_init__(self) -> None:
        """Boundary conditions as float arrays (the same objects when they are already)."""
        object.__setattr__(self, "roe0_m", np.asarray(self.roe0_m, float))
        object.__setattr__(self, "roe_f_m", np.asarray(self.roe_f_m, float))

    @classmethod
    def to_target(cls, safety: PassiveSafety, roe0_m: np.ndarray, target_rtn: np.ndarray,
                  terminal_set: TerminalSet | None = None) -> "TransferProblem":
        """The problem from `roe0_m` to the RTN target `target_rtn` (`terminal_roe`, solved
        once here), or to within `terminal_set` of it."""
        return cls(safety, roe0_m, terminal_roe(safety.horizon, target_rtn), target_rtn,
                   terminal_set)

    @property
    def horizon(self) -> Horizon:
        """The time grid, dynamics and frames (the safety model's)."""
        return self.safety.horizon

    def cvx(self, norm: str = "l2", solver: str = "clarabel") -> ConvexSolution:
        """The convex TPBVP of this transfer (`cvx.solve_cvx`)."""
        return solve_cvx(self.horizon, self.roe0_m, self.roe_f_m, norm, solver,
                         self.terminal_set)

    def scvx(self, scp_config: ScpConfig | None = None, samples_per_node: int = 1,
             subproblem: SubproblemOptions | None = None, pool: SubproblemPool | None = None,
             norm: str = "l2", solver: str = "clarabel") -> Scvx:
        """SCVx* on this transfer (`scp.Scvx`: its parameters, drift instants linearised per
        node, subproblem options, the caller's subproblems, control norm and solver)."""
        return Scvx(self, scp_config, norm=norm, solver=solver,
                    samples_per_node=samples_per_node, subproblem=subproblem, pool=pool)

    def terminal_warm_start(self, dv_rtn_mps: np.ndarray,
                            lin: DeputyLinearization | None = None) -> Trajectory:
        """Controls (N, 3) [m/s] corrected onto the terminal condition, and their states
        (`scp.terminal_warm_start`; with a terminal set `scp.onto_terminal_set`: unchanged
        when they end in it): where SCVx* starts from them."""
        return onto_terminal_set(self.horizon, self.roe0_m, self.roe_f_m, self.terminal_set,
                                 dv_rtn_mps, lin, project_first=True)

    def propagate(self, dv_rtn_mps: np.ndarray) -> Trajectory:
        """Controls (N, 3) [m/s] as they are, and their states under the deputy-aware model."""
        dv = np.asarray(dv_rtn_mps, float)
        return Trajectory(dv, self.horizon.propagate_nonlinear(self.roe0_m, dv))
