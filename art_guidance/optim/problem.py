"""Sparse assembly of the SCP convex subproblem (paper eq. for the convex subproblem).

Variables, in order: scaled states x~ (N x 6), controls u (N x 3) [m/s], cost auxiliaries
(t_i >= ||u_i||_2, or s >= |u| for the 1-norm variant) and the passive-safety virtual buffers
zeta (N). States are scaled by s_x = 1/n [s] (x = s_x x~) so that every block is O(1).

    minimise  sum_i cost_i + mu' zeta + w/2 ||zeta||^2
    s.t.      x_1 = x0,  x_{k+1} = P_k z_k + r_k,  z_N = x_f
              -a_i' z_i + rhs_i <= zeta_i,  zeta >= 0
              ||x - xbar||_inf <= r,  ||u - ubar||_inf <= r

with the post-burn state linearised about the reference, ``z_k = E_k x_k + B_k u_k - j_k``
(`dynamics.DeputyLinearization`: B at the deputy's reference state, E = I + d(B u)/dx, P = Phi
plus the slope of the second-order along-track drift, r the affine remainder that makes the
model exact along the reference). Before `set_dynamics` is called the rows hold the linear model
of the convex problem (E = I, B = B(0), P = Phi, r = j = 0).

The sparsity pattern is built once per horizon; per iteration only the dynamics and safety
coefficients, the right-hand sides, the penalty multipliers and the weight change (updated in
place). A `SubproblemPool`, owned by its caller, keeps the last subproblem (and its solver) of
every shape, so that consecutive SCVx* runs over one horizon (the dataset's stages, the
pipeline's two warm starts) update it instead of assembling and factorising the pattern again:
the solutions are bit-identical to a fresh build's (`test/unit/test_problem_pool.py`).

The control rows of the trust region are implied by its state rows
(`SubproblemOptions.drop_idle_control_box`). Between any feasible point and the reference, the
dynamics rows give ``P_k B_k du_k = dx_{k+1} - P_k E_k dx_k - res_k`` (res_k: the rows'
residual at the reference, zero to rounding along an SCVx* reference) and the terminal rows
``B_N du_N = -E_N dx_N - res_N``. P_k B_k (6 x 3) has full column rank, so with its left
pseudo-inverse ``|du_k|_inf <= ||(P_k B_k)^+||_inf ((1 + ||P_k E_k||_inf) r + |res_k|_inf)``
(terminal: ``||B_N^+||_inf (||E_N||_inf r + |res_N|_inf)``) whenever ``|dx|_inf <= r`` [m].
Along SCVx* runs this is <= 3.5e-3 r [m/s] (``||(PB)^+|| ~ n/2``): the rows ``|du| <= r``
[m/s] cut off no feasible point. When the bound is below r / 2 at every node the subproblem is
solved by a second solver built on the pattern without those 6N rows, which has the same
feasible set and optimum (11 % fewer KKT rows, 1.5 fewer interior-point iterations;
`docs/results.md`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from art_guidance.dynamics import DeputyLinearization, Horizon, mean_motion
from art_guidance.errors import InputError
from art_guidance.optim.solvers import Cones, CscPattern, SolverOutput, make_solver
from art_guidance.optim.terminal_set import TerminalSet

IDLE_BOX_MARGIN = 0.5  # control rows left out where the bound they imply is <= this * r


@dataclass(frozen=True)
class SubproblemOptions:
    """How the subproblem is handed to the solver; every choice keeps its optimum (to the
    solver's tolerance).

    Attributes:
        tol: Clarabel's gap and feasibility tolerances (absolute and relative). 1e-6 is 1000
            times below SCVx*'s eps_opt and eps_feas and saves ~2 of ~25 interior-point
            iterations against 1e-8; 1e-5 lost converged runs (`docs/results.md`).
        drop_idle_control_box: solve without the control rows of the trust region where its
            state rows imply them (module docstring).
    """

    tol: float = 1e-6
    drop_idle_control_box: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.tol < 1e-2:
            raise InputError("tol", "must be in (0, 1e-2)", self.tol)


# the subproblem as it was posed before the latency work: the oracle of `SubproblemOptions`
REFERENCE_OPTIONS = SubproblemOptions(tol=1e-8, drop_idle_control_box=False)


@dataclass(frozen=True)
class SubproblemSolution:
    """Unscaled primal solution of one subproblem."""

    output: SolverOutput
    roe_m: np.ndarray       # (N, 6) [m]
    dv_rtn_mps: np.ndarray  # (N, 3) [m/s]
    zeta: np.ndarray        # (N,) virtual buffers (normalised safety units)
    cost_mps: float         # sum of the cost auxiliaries [m/s]


class _Triplets:
    """Collects (row, col, value) entries and hands out slot indices for later updates."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.count = 0

    def add(self, rows: np.ndarray, cols: np.ndarray, vals: np.ndarray) -> np.ndarray:
        rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
        vals = np.broadcast_to(np.asarray(vals, float), rows.shape)
        self.rows.append(rows.ravel())
        self.cols.append(cols.ravel())
        self.vals.append(vals.ravel().copy())
        slots = np.arange(self.count, self.count + rows.size).reshape(rows.shape)
        self.count += rows.size
        return slots

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.concatenate(self.rows), np.concatenate(self.cols),
                np.concatenate(self.vals))


@dataclass(frozen=True)
class _Form:
    """One way of handing the subproblem to a solver: its pattern, the triplet values in CSC
    data order (`a_take`), the rows of b it keeps and its cones."""

    pattern: CscPattern
    a_take: np.ndarray
    rows: np.ndarray
    cones: Cones


class ScpSubproblem:
    """The convex subproblem with a fixed pattern; numbers are updated between solves."""

    def __init__(self, horizon: Horizon, roe0_m: np.ndarray, roe_f_m: np.ndarray,
                 norm: str = "l2", solver: str = "clarabel", samples_per_node: int = 1,
                 options: SubproblemOptions | None = None,
                 terminal_set: TerminalSet | None = None) -> None:
        """`terminal_set`: the problem's shape ends in a terminal set's two cones instead of
        the six terminal equality rows (its sizes: `set_boundary`; module docstring)."""
        if norm not in ("l2", "l1"):
            raise InputError("norm", "must be 'l2' or 'l1'", norm)
        if norm == "l2" and solver == "osqp":
            raise InputError("solver", "OSQP cannot solve the 2-norm problem; use clarabel")
        if terminal_set is not None and solver == "osqp":
            raise InputError("solver", "OSQP cannot solve a terminal set (a cone); use clarabel")
        self.has_terminal_set = terminal_set is not None
        self._k_term = np.eye(6)  # terminal rows' map (the set's scaled rows with a set)
        self.horizon, self.norm, self.solver_name = horizon, norm, solver
        self.k = int(samples_per_node)
        n = self.n = horizon.n_nodes
        self.sx = 1.0 / mean_motion(float(horizon.chief_oe[0, 0]))
        self.ix = np.arange(6 * n).reshape(n, 6)
        self.iu = 6 * n + np.arange(3 * n).reshape(n, 3)
        n_aux = n if norm == "l2" else 3 * n
        self.ic = 9 * n + np.arange(n_aux)
        self.iz = 9 * n + n_aux + np.arange(n)
        self.n_var = 10 * n + n_aux
        self.options = options or SubproblemOptions()
        self._assemble(np.asarray(roe0_m, float), np.asarray(roe_f_m, float), terminal_set)
        self._solvers: dict = {}  # one per form: False = every row, True = no control box
        self._ref_x = np.zeros(6 * n)  # (6N,) reference scaled states
        self._ref_u = np.zeros((n, 3))  # (N, 3) reference controls [m/s]
        self._radius = 0.0

    # ------------------------------------------------------------------ assembly
    def _assemble(self, roe0_m: np.ndarray, roe_f_m: np.ndarray,
                  terminal_set: TerminalSet | None) -> None:
        h, n, sx, trip = self.horizon, self.n, self.sx, _Triplets()
        eye6 = np.eye(6)
        trip.add(np.arange(6)[:, None], self.ix[0][None, :], eye6)
        # x_{k+1} - Phi_k x_k - Phi_k B_k u_k = 0 for k = 0 .. n-2, one block of 6 rows each
        r = (6 + 6 * np.arange(n - 1)[:, None] + np.arange(6))[:, :, None]  # (n-1, 6, 1)
        trip.add(r, self.ix[1:][:, None, :], eye6)
        self._slot_dx = trip.add(r, self.ix[:-1][:, None, :], -h.stm)
        self._slot_du = trip.add(r, self.iu[:-1][:, None, :], -(h.stm @ h.b[:-1]) / sx)
        row = 6 * n
        if not self.has_terminal_set:
            self._add_terminal_rows(trip, row + np.arange(6))
            row += 6
        n_zero = row
        # post-burn model z = e x + bu u - jx used by the safety rows (`set_dynamics`)
        self._e = np.broadcast_to(eye6, (n, 6, 6))
        self._bu = h.b
        self._u_gain, self._x_gain = _control_box_gains(h.stm, self._e, h.b)
        self._jx = np.zeros((n, 6))
        # safety rows (k per node): -a_im' (sx x~_i + B_i u_i) - zeta_i <= -rhs_im
        r_safe = row + np.arange(n * self.k).reshape(n, self.k)
        self._slot_ax = trip.add(r_safe[:, :, None], self.ix[:, None, :], 0.0)
        self._slot_au = trip.add(r_safe[:, :, None], self.iu[:, None, :], 0.0)
        trip.add(r_safe, self.iz[:, None], -1.0)
        self._row_safe = r_safe
        row += n * self.k
        trip.add(row + np.arange(n), self.iz, -1.0)  # zeta >= 0
        row += n
        self._row_trust = row
        for idx in (self.ix.ravel(), self.iu.ravel()):
            m = idx.size
            trip.add(row + np.arange(m), idx, 1.0)
            trip.add(row + m + np.arange(m), idx, -1.0)
            row += 2 * m
        if self.norm == "l1":
            m = 3 * n
            trip.add(row + np.arange(m), self.iu.ravel(), 1.0)
            trip.add(row + np.arange(m), self.ic, -1.0)
            trip.add(row + m + np.arange(m), self.iu.ravel(), -1.0)
            trip.add(row + m + np.arange(m), self.ic, -1.0)
            row += 2 * m
            soc = ()
        else:  # cone i: rows (t_i, u_i) <- (-t_i, -u_i)
            r_cone = row + 4 * np.arange(n)
            trip.add(r_cone, self.ic, -1.0)
            trip.add(r_cone[:, None] + 1 + np.arange(3), self.iu, -1.0)
            row += 4 * n
            soc = (4,) * n
        n_nonneg = row - n_zero - 4 * len(soc)
        if self.has_terminal_set:  # cones (1, R[:3] ...), (1, R[3:] ...): head rows 0, 4
            self._add_terminal_rows(trip, row + np.r_[1:4, 5:8])
            self._row_head = row + np.array([0, 4])
            row += 8
            soc = (*soc, 4, 4)
        self.cones = Cones(n_zero, n_nonneg, soc)
        rows, cols, vals = trip.arrays()
        self._pattern = CscPattern(rows, cols, (row, self.n_var))
        self._a_vals = vals
        self._trip_rows, self._trip_cols = rows, cols  # (n_triplets,) each
        self._forms = {False: _Form(self._pattern, self._pattern.order, np.arange(row),
                                    self.cones),
                       True: self._without_control_box(rows, cols, row)}
        self._b = np.zeros(row)
        self.set_boundary(roe0_m, roe_f_m, terminal_set)
        self._q = np.zeros(self.n_var)
        self._q[self.ic] = 1.0
        self._p_diag = np.zeros(self.n_var)

    def _add_terminal_rows(self, trip: _Triplets, rows: np.ndarray) -> None:
        """The terminal rows ``K (E_N x~_N + B_N u_N / s_x) = K (x_f + j_N) / s_x`` at `rows`
        (K: the identity, or the terminal set's cone rows, `TerminalSet.cone`)."""
        n = self.n
        self._row_term = rows
        r = rows[:, None]
        self._slot_fx = trip.add(r, self.ix[n - 1][None, :], np.eye(6))
        self._slot_fu = trip.add(r, self.iu[n - 1][None, :], self.horizon.b[n - 1] / self.sx)

    def _without_control_box(self, rows: np.ndarray, cols: np.ndarray, n_rows: int
                             ) -> "_Form":
        """The problem without the 6N control rows of the trust region
        (`SubproblemOptions.drop_idle_control_box`)."""
        lo = self._row_trust + 12 * self.n
        hi = lo + 6 * self.n
        kept = (rows < lo) | (rows >= hi)  # (n_triplets,)
        new_rows = np.where(rows >= hi, rows - (hi - lo), rows)[kept]
        pattern = CscPattern(new_rows, cols[kept], (n_rows - (hi - lo), self.n_var))
        cones = Cones(self.cones.n_zero, self.cones.n_nonneg - (hi - lo), self.cones.soc_sizes)
        return _Form(pattern, np.flatnonzero(kept)[pattern.order], np.r_[0:lo, hi:n_rows],
                     cones)

    # ------------------------------------------------------------------ updates
    def set_boundary(self, roe0_m: np.ndarray, roe_f_m: np.ndarray,
                     terminal_set: TerminalSet | None = None) -> None:
        """Initial state and terminal post-burn state [m], and the terminal set about the
        latter of a subproblem shaped for one (the terminal rows take them at the next
        `set_dynamics`)."""
        if (terminal_set is not None) != self.has_terminal_set:
            raise InputError("terminal_set", "does not match the subproblem's shape",
                             terminal_set)
        self._b[:6] = np.asarray(roe0_m, float) / self.sx
        self._roe_f_m = np.asarray(roe_f_m, float)
        if terminal_set is not None:
            self._k_term, self._b[self._row_head] = terminal_set.cone(self.horizon.psi[-1],
                                                                      self.sx)
        self._b[self._row_term] = self._k_term @ self._roe_f_m / self.sx

    def set_reference(self, roe_m: np.ndarray, dv_rtn_mps: np.ndarray, radius: float) -> None:
        """Trust region ||x - xbar||_inf <= r [m], ||u - ubar||_inf <= r [m/s]."""
        xs = roe_m.ravel() / self.sx
        rs = radius / self.sx
        u = dv_rtn_mps.ravel()
        self._ref_x[:] = xs
        self._ref_u[:] = dv_rtn_mps
        self._radius = float(radius)
        row = self._row_trust
        for ref, rad in ((xs, rs), (u, radius)):
            m = ref.size
            self._b[row:row + m] = ref + rad
            self._b[row + m:row + 2 * m] = rad - ref
            row += 2 * m

    def set_dynamics(self, lin: DeputyLinearization) -> None:
        """Dynamics, terminal and post-burn rows linearised about a reference (see module doc).

        Rows ``x_{k+1} - P_k E_k x_k - P_k B_k u_k = r_k`` with ``r_k = xbar_{k+1} - P_k (zbar_k
        + j_k)`` and the terminal ``E_N x_N + B_N u_N = x_f + j_N``, all exact at the reference.
        Call `set_safety` afterwards: its rows use this post-burn model.
        """
        sx = self.sx
        pe = lin.p @ lin.e[:-1]  # (N-1, 6, 6)
        pb = lin.p @ lin.b[:-1]  # (N-1, 6, 3)
        self._a_vals[self._slot_dx] = -pe
        self._a_vals[self._slot_du] = -pb / sx
        self._a_vals[self._slot_fx] = self._k_term @ lin.e[-1]
        self._a_vals[self._slot_fu] = self._k_term @ lin.b[-1] / sx
        zj = lin.z[:-1] + lin.jx[:-1]
        rem = lin.roe_m[1:] - (lin.p @ zj[:, :, None])[:, :, 0]  # (N-1, 6) [m]
        self._b[6:6 * self.n] = rem.ravel() / sx
        self._b[self._row_term] = self._k_term @ (self._roe_f_m + lin.jx[-1]) / sx
        self._e, self._bu, self._jx = lin.e, lin.b, lin.jx
        self._u_gain, self._x_gain = _control_box_gains(lin.p, lin.e, lin.b)

    def set_safety(self, a: np.ndarray, rhs: np.ndarray) -> None:
        """Linearised rows a_im' z_i >= rhs_im, a (N, k, 6), rhs (N, k), z_i the post-burn ROE.

        ``z_i = E_i x_i + B_i u_i - j_i`` with the current post-burn model (`set_dynamics`;
        ``x_i + B_i u_i`` before it is called).
        """
        a = np.asarray(a, float).reshape(self.n, self.k, 6)
        self._a_vals[self._slot_ax] = -np.einsum("kmi,kij->kmj", a, self._e) * self.sx
        self._a_vals[self._slot_au] = -np.einsum("kmi,kij->kmj", a, self._bu)
        rhs = np.asarray(rhs, float).reshape(self.n, self.k)
        self._b[self._row_safe] = -(rhs + np.einsum("kmi,ki->km", a, self._jx))

    def set_penalty(self, mu: np.ndarray, weight: float) -> None:
        """Penalty mu' zeta + w/2 ||zeta||^2 on the virtual buffers."""
        self._q[self.iz] = mu
        self._p_diag[self.iz] = weight

    # ------------------------------------------------------------------ solve
    def control_box_idle(self) -> bool:
        """True when the state rows of the trust region and the dynamics rows imply the control
        rows with margin at the current numbers (module docstring); never with a terminal
        set (its cones do not fix the last burn)."""
        if self.has_terminal_set:
            return False
        v = np.zeros(self.n_var)  # the reference point (zeta, cost auxiliaries: 0)
        v[self.ix.ravel()] = self._ref_x
        v[self.iu.ravel()] = self._ref_u.ravel()
        av = np.bincount(self._trip_rows, self._a_vals * v[self._trip_cols],
                         minlength=self._b.size)  # (rows,) A v
        res = (av - self._b)[6:self.cones.n_zero].reshape(self.n, 6)  # (N, 6) dynamics rows
        res_m = np.abs(res).max(axis=1) * self.sx  # (N,) [m], the last: terminal rows
        bound = self._u_gain * (self._x_gain * self._radius + res_m)  # (N,) [m/s]
        return bool(bound.max() <= IDLE_BOX_MARGIN * self._radius)

    def solve(self, keep_control_box: bool = False) -> SubproblemSolution:
        """Solve with the current numbers (solver built on the first call of each form,
        updated after).

        Args:
            keep_control_box: solve with every row even where the options would leave the idle
                control box out (the oracle of the reduced form).
        """
        idle = (not keep_control_box and self.options.drop_idle_control_box
                and self.control_box_idle())
        form = self._forms[idle]
        a_data = self._a_vals[form.a_take]  # CSC data order
        b = self._b[form.rows]
        pattern, cones = form.pattern, form.cones
        p_data = self._p_diag[self.iz]
        solver = self._solvers.get(idle)
        if solver is None:
            p = sp.csc_matrix((p_data, (self.iz, self.iz)), shape=(self.n_var, self.n_var))
            a = sp.csc_matrix((a_data, pattern.indices, pattern.indptr), shape=pattern.shape)
            # every block is O(1) by construction (states scaled by s_x, safety rows
            # normalised): Clarabel's own equilibration only adds interior-point iterations
            solver = self._solvers[idle] = make_solver(self.solver_name, p, self._q, a, b,
                                                       cones, scaled=True,
                                                       tol=self.options.tol)
        else:
            solver.update(q=self._q, b=b, a_data=a_data, p_data=p_data)
        out = solver.solve()
        if not out.ok or out.x.size != self.n_var:
            nan = np.full(self.n, np.nan)
            return SubproblemSolution(out, np.full((self.n, 6), np.nan),
                                      np.full((self.n, 3), np.nan), nan, float("nan"))
        x = out.x
        return SubproblemSolution(out, x[self.ix] * self.sx, x[self.iu].copy(),
                                  np.maximum(x[self.iz], 0.0), float(x[self.ic].sum()))


def _control_box_gains(p: np.ndarray, e: np.ndarray, b: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Per node, ``||M_k^+||_inf`` [1/s] and the state factor [-] of the implied control bound
    (module docstring): ``M_k = P_k B_k`` with ``1 + ||P_k E_k||_inf`` for k < N-1, ``M = B_N``
    with ``||E_N||_inf`` at the last node.

    Args:
        p: (N-1, 6, 6) dx_{k+1}/dz_k [-]; e: (N, 6, 6) dz/dx [-]; b: (N, 6, 3) dz/du [s].

    Returns:
        (N,) [1/s] and (N,) [-].
    """
    m = np.concatenate([p @ b[:-1], b[-1:]])  # (N, 6, 3) [s]
    mt = np.swapaxes(m, 1, 2)
    pinv = np.linalg.solve(mt @ m, mt)  # (N, 3, 6) left pseudo-inverses [1/s]
    x_gain = np.empty(m.shape[0])
    x_gain[:-1] = 1.0 + np.abs(p @ e[:-1]).sum(axis=2).max(axis=1)
    x_gain[-1] = np.abs(e[-1]).sum(axis=1).max()
    return np.abs(pinv).sum(axis=2).max(axis=1), x_gain


class SubproblemPool:
    """The subproblems of one caller, set up once per horizon and shape and updated between
    solves (the solver's lifecycle: set up, update, solve).

    It keeps one subproblem per (norm, solver, rows per node, options), for the last horizon
    object it was built on (`roe0_m`, `roe_f_m` only serve a new build). A reused one holds the
    numbers of its last problem: its user sets all of them before each run (`Scvx.solve`:
    `set_boundary`, `set_dynamics`, then per iteration `set_reference`, `set_safety`,
    `set_penalty`), so consecutive runs of several problems share it. The caller owns the pool
    and uses it from one thread at a time (the pipeline holds one; its proposal worker, a
    process, holds its own); an `Scvx` built without one sets up a subproblem of its own.
    """

    def __init__(self) -> None:
        self._subproblems: dict[tuple, ScpSubproblem] = {}

    def get(self, horizon: Horizon, roe0_m: np.ndarray, roe_f_m: np.ndarray,
            norm: str = "l2", solver: str = "clarabel", samples_per_node: int = 1,
            options: SubproblemOptions | None = None,
            terminal_set: TerminalSet | None = None) -> ScpSubproblem:
        """The subproblem of this shape over `horizon` (a terminal set or the equality):
        the last one built, or a new one."""
        options = options or SubproblemOptions()
        key = (norm, solver, int(samples_per_node), options, terminal_set is not None)
        sub = self._subproblems.get(key)
        if sub is None or sub.horizon is not horizon:
            sub = self._subproblems[key] = ScpSubproblem(horizon, roe0_m, roe_f_m, norm, solver,
                                                         samples_per_node, options,
                                                         terminal_set)
        return sub

    def __len__(self) -> int:
        return len(self._subproblems)
