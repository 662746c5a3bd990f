"""Optimisation: sparse conic assembly, solver facade, convex TPBVP and SCVx*."""
from art_guidance.optim.cvx import control_cost, solve_cvx
from art_guidance.optim.results import (
    FEASIBLE_STATUSES, ConvexSolution, Multipliers, ScpIteration, ScpResult, ScpStatus,
    Trajectory,
)
from art_guidance.optim.scp import (
    ScpWarmStart, Scvx, project_to_boundary_conditions, terminal_warm_start,
)
from art_guidance.optim.terminal_set import TerminalSet
from art_guidance.optim.transfer import TransferProblem, terminal_roe

__all__ = ["FEASIBLE_STATUSES", "ConvexSolution", "Multipliers", "ScpIteration", "ScpResult",
           "ScpStatus", "ScpWarmStart", "Scvx", "TerminalSet", "Trajectory", "TransferProblem",
           "control_cost", "project_to_boundary_conditions", "solve_cvx", "terminal_roe",
           "terminal_warm_start"]
