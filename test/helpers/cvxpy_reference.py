"""cvxpy formulations used only as slower references in tests (and by `bench solvers`, as its
reference).

They state the problems the way a modelling language user would (states and controls as
variables, dynamics as constraints), independently of the condensed/sparse assemblies.
"""
from __future__ import annotations

import numpy as np

from art_guidance.dynamics import Horizon, mean_motion
from art_guidance.optim.cvx import L1_REG_S_PER_M


def cvxpy_tpbvp(horizon: Horizon, roe0_m: np.ndarray, roe_f_m: np.ndarray,
                norm: str = "l2", solver: str = "CLARABEL",
                terminal_set: tuple[float, float] | None = None) -> tuple[float, np.ndarray]:
    """Solve the convex TPBVP with cvxpy; returns (cost [m/s], dv_rtn_mps (N, 3)).

    `terminal_set` (position [m], velocity [m/s]): the post-burn RTN state at the last node
    within those distances of the target's instead of on it."""
    import cvxpy as cp

    n = horizon.n_nodes
    # states in units of 1/n [m / (rad/s)]-scaled metres so the problem is well conditioned
    sx = 1.0 / mean_motion(float(horizon.chief_oe[0, 0]))
    x = cp.Variable((n, 6))
    u = cp.Variable((n, 3))
    b = horizon.b / sx
    z_f = x[n - 1] + b[n - 1] @ u[n - 1]
    cons = [x[0] == roe0_m / sx]
    if terminal_set is None:
        cons.append(z_f == roe_f_m / sx)
    else:
        err = horizon.psi[-1] @ (sx * z_f - roe_f_m)  # RTN [m, m/s]
        cons += [cp.norm(err[:3], 2) <= terminal_set[0], cp.norm(err[3:], 2) <= terminal_set[1]]
    cons += [x[k + 1] == horizon.stm[k] @ (x[k] + b[k] @ u[k]) for k in range(n - 1)]
    if norm == "l2":
        cost = cp.sum(cp.norm(u, 2, axis=1))
    else:
        cost = cp.sum(cp.abs(u)) + 0.5 * L1_REG_S_PER_M * cp.sum_squares(u)
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver=solver)
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise RuntimeError(f"cvxpy reference failed: {prob.status}")
    return float(prob.value), np.asarray(u.value)
