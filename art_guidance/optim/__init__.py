"""Optimisation: sparse conic assembly, solver facade, convex TPBVP and SCVx*."""
from art_guidance.optim.cvx import control_cost, solve_cvx
from art_guidance.optim.results import (
    FEASIBLE_STATUSES, ConvexSolution, ScpIteration, ScpResult, ScpStatus,
)
from art_guidance.optim.scp import Scvx, project_to_boundary_conditions, terminal_warm_start

__all__ = ["FEASIBLE_STATUSES", "ConvexSolution", "ScpIteration", "ScpResult", "ScpStatus",
           "Scvx", "control_cost", "project_to_boundary_conditions", "solve_cvx",
           "terminal_warm_start"]
