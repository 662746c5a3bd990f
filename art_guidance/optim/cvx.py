"""The convex two-point boundary value problem (paper: "CVX", the lower bound of the OCP).

minimise sum_i ||u_i||   (+ reg/2 ||u||^2 for the 1-norm variant)
s.t.     x_{k+1} = Phi_k (x_k + B_k u_k),  x_1 = x0,  x_N + B_N u_N = x_f.

Model: the linear one of `Horizon.propagate` (B at zero separation, first-order relative drift),
so that this stays a single convex program solved in milliseconds. It is the warm start of
SCVx* and the post hoc reference (the cost lower bound of this model's problem; plans of the
deputy-aware model can cost ~1e-4 less when safety is inactive), not a plan to fly: SCVx*
re-projects its controls onto the deputy-aware model (`Horizon.propagate_nonlinear`, B at the
deputy's state and the second-order along-track drift), and flown open loop in a two-body + J2
truth the CVX controls of a 6-8 m/s transfer miss the waypoint by ~200 m.

The states are eliminated (condensed form): the only equality is the 6-row terminal condition
sum_k M_k B_k u_k = x_f - M_0 x0 with M_k = Phi_{N-1} ... Phi_k, so the problem has 3N + N
variables (2-norm) and is solved by Clarabel in a few milliseconds. The 1-norm variant (fuel
for axis-aligned thrusters) is a QP solved by Clarabel or OSQP: the pure LP is degenerate (many
optimal control sequences) and first-order OSQP stalls on it, so a small quadratic term
L1_REG_S_PER_M/2 ||u||^2 (about 0.1 % of the cost) makes the optimum unique for both solvers.
"""
from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from art_guidance.checks import as_finite_array
from art_guidance.dynamics import Horizon
from art_guidance.errors import InputError
from art_guidance.optim.results import ConvexSolution, ScpStatus
from art_guidance.optim.solvers import Cones, make_solver
from art_guidance.optim.terminal_set import TerminalSet

NORMS = ("l2", "l1")
L1_REG_S_PER_M = 1e-3


def terminal_maps(horizon: Horizon) -> np.ndarray:
    """M_k = Phi_{N-1} ... Phi_k, (N, 6, 6): the post-burn final state is sum_k M_k (.)_k."""
    n = horizon.n_nodes
    maps = np.empty((n, 6, 6))
    maps[-1] = np.eye(6)
    for k in range(n - 2, -1, -1):
        maps[k] = maps[k + 1] @ horizon.stm[k]
    return maps


def control_cost(dv_rtn_mps: np.ndarray, norm: str = "l2") -> float:
    """Sum over nodes of ||dv||_2 (or ||dv||_1) [m/s]."""
    if norm == "l1":
        return float(np.abs(dv_rtn_mps).sum())
    return float(np.linalg.norm(dv_rtn_mps, axis=1).sum())


ConicData = tuple[sp.csc_matrix, np.ndarray, sp.csc_matrix, np.ndarray, Cones]


def condensed_tpbvp(horizon: Horizon, roe0_m: np.ndarray, roe_f_m: np.ndarray,
                    norm: str = "l2", terminal_set: TerminalSet | None = None) -> ConicData:
    """Conic data (P, q, A, b, cones) of the condensed TPBVP; variables [u (3N), cost aux].

    With a `terminal_set` the six terminal equality rows become its two 4-row cones (head
    row h, then ``R (x_f - M_0 x_0) - R G u`` with (R, h) = `TerminalSet.cone`), after every
    other row."""
    n = horizon.n_nodes
    maps = terminal_maps(horizon)
    g = np.einsum("kij,kjl->ikl", maps, horizon.b).reshape(6, 3 * n)  # (6, 3N) [s]
    offset = roe_f_m - maps[0] @ roe0_m  # what the burns must add to the final state [m]
    span_s = horizon.epochs_s[-1] - horizon.epochs_s[0]
    # Terminal rows scaled by the mean motion: B ~ 1/n [s], so n*G is O(1) and n*rhs is in m/s.
    scale = 2.0 * np.pi / span_s if n > 1 else 1.0
    p, q, a, b, cones = _condensed_equality(n, scale * g, scale * offset, norm)
    if terminal_set is None:
        return p, q, a, b, cones
    # the cones on ROE in units of 1/n [s]: O(1) entries on controls in m/s (`cone`)
    scale_s = span_s / (2.0 * np.pi) if n > 1 else 1.0
    rows, heads = terminal_set.cone(horizon.psi[-1], scale_s)
    rows = rows / scale_s
    term_a = np.zeros((8, a.shape[1]))
    term_b = np.zeros(8)
    for i, part in enumerate((slice(0, 3), slice(3, 6))):
        term_a[4 * i + 1:4 * i + 4, :g.shape[1]] = rows[part] @ g
        term_b[4 * i + 1:4 * i + 4] = rows[part] @ offset
        term_b[4 * i] = heads[i]
    a = sp.vstack([a[6:], sp.csr_matrix(term_a)], format="csc")
    b = np.concatenate([b[6:], term_b])
    return p, q, a, b, Cones(0, cones.n_nonneg, (*cones.soc_sizes, 4, 4))


def _condensed_equality(n: int, g: np.ndarray, rhs: np.ndarray, norm: str) -> ConicData:
    """`condensed_tpbvp` with the terminal equality ``g u = rhs`` (its first six rows; `g`
    (6, 3N) and `rhs` (6,) scaled by the mean motion) over `n` nodes."""
    if norm == "l2":
        n_var = 4 * n
        idx = np.arange(n)
        # cone rows (t_i, u_i): row 4i <- -t_i, rows 4i+1..4i+3 <- -u_i
        soc_r = np.concatenate([4 * idx, (4 * idx[:, None] + np.arange(1, 4)).ravel()])
        soc_c = np.concatenate([3 * n + idx, np.arange(3 * n)])
        soc = sp.csr_matrix((-np.ones(4 * n), (soc_r, soc_c)), shape=(4 * n, n_var))
        a = sp.vstack([sp.hstack([sp.csr_matrix(g), sp.csr_matrix((6, n))]), soc])
        b = np.concatenate([rhs, np.zeros(4 * n)])
        cones = Cones(6, 0, (4,) * n)
        q = np.concatenate([np.zeros(3 * n), np.ones(n)])
    else:
        n_var = 6 * n
        eye = sp.identity(3 * n, format="csr")
        a = sp.vstack([sp.hstack([sp.csr_matrix(g), sp.csr_matrix((6, 3 * n))]),
                       sp.hstack([eye, -eye]), sp.hstack([-eye, -eye])])
        b = np.concatenate([rhs, np.zeros(6 * n)])
        cones = Cones(6, 6 * n)
        q = np.concatenate([np.zeros(3 * n), np.ones(3 * n)])
        reg = np.concatenate([np.full(3 * n, L1_REG_S_PER_M), np.zeros(3 * n)])
        return sp.diags(reg, format="csc"), q, sp.csc_matrix(a), b, cones
    return sp.csc_matrix((n_var, n_var)), q, sp.csc_matrix(a), b, cones


def solve_cvx(horizon: Horizon, roe0_m: object, roe_f_m: object, norm: str = "l2",
              solver: str = "clarabel", terminal_set: TerminalSet | None = None
              ) -> ConvexSolution:
    """Solve the convex TPBVP from `roe0_m` to the post-burn terminal ROE `roe_f_m` [m] (or,
    with a `terminal_set`, to within it: `optim.terminal_set`).

    Args:
        horizon: dynamics over the N nodes.
        roe0_m: (6,) initial a-scaled ROE [m] (pre-burn at node 1).
        roe_f_m: (6,) terminal a-scaled ROE [m] after the last burn.
        norm: "l2" (sum of 2-norms, the paper's fuel) or "l1" (axis-aligned thrusters).
        solver: "clarabel" (both norms) or "osqp" (l1 only, no terminal set).
        terminal_set: where the plan may end about `roe_f_m` (None: exactly there).

    Returns:
        ConvexSolution with the controls, the propagated states and the cost.
    """
    t0 = time.perf_counter()
    x0 = as_finite_array("roe0_m", roe0_m, (6,))
    xf = as_finite_array("roe_f_m", roe_f_m, (6,))
    if norm not in NORMS:
        raise InputError("norm", f"must be one of {NORMS}", norm)
    if terminal_set is not None and solver == "osqp":
        raise InputError("solver", "OSQP cannot solve a terminal set (a cone); use clarabel")
    p, q, a, b, cones = condensed_tpbvp(horizon, x0, xf, norm, terminal_set)
    out = make_solver(solver, p, q, a, b, cones).solve()
    n = horizon.n_nodes
    if not out.ok:
        status = ScpStatus.INFEASIBLE if "Infeasible" in out.status else ScpStatus.SOLVER_ERROR
        nan = np.full((n, 3), np.nan)
        return ConvexSolution(status, np.full((n, 6), np.nan), nan, float("nan"),
                              1e3 * (time.perf_counter() - t0), solver, out.status)
    dv = out.x[: 3 * n].reshape(n, 3)
    roe = horizon.propagate(x0, dv)
    return ConvexSolution(ScpStatus.CONVERGED, roe, dv, control_cost(dv, norm),
                          1e3 * (time.perf_counter() - t0), solver, out.status)
