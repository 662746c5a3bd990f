"""Solver facade: Clarabel (SOCP/QP) and OSQP (QP) called directly on sparse matrices.

Each wrapper follows the solver's lifecycle: the sparsity pattern is fixed at construction,
numbers are updated in place between solves, and every solve returns a `SolverOutput`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import clarabel
import numpy as np
import osqp
import scipy.sparse as sp

from art_guidance.errors import SolverError


@dataclass(frozen=True)
class Cones:
    """Row blocks of A, in order: equalities, inequalities (A v <= b), then 2-norm cones."""

    n_zero: int
    n_nonneg: int
    soc_sizes: tuple[int, ...] = ()

    @property
    def n_rows(self) -> int:
        """Total number of constraint rows."""
        return self.n_zero + self.n_nonneg + int(sum(self.soc_sizes))


@dataclass(frozen=True)
class SolverOutput:
    """Primal solution and status of one solve."""

    ok: bool
    x: np.ndarray
    status: str
    iterations: int
    solve_time_ms: float


class CscPattern:
    """A sparse matrix assembled from (row, col, value) triplets with a fixed pattern.

    Values can be replaced later through the same triplet order (`csc_data(values)`), so a
    solver built once can be updated in place. Structural zeros are kept.
    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> None:
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        self.shape = shape
        self.order = np.lexsort((rows, cols))
        key = cols[self.order] * shape[0] + rows[self.order]
        if np.any(np.diff(key) == 0):
            raise SolverError("duplicate entries in a sparse pattern")
        self.indices = rows[self.order].astype(np.int64)
        self.indptr = np.searchsorted(cols[self.order], np.arange(shape[1] + 1)).astype(np.int64)

    def csc_data(self, values: np.ndarray) -> np.ndarray:
        """Values in triplet order -> CSC data order."""
        return np.asarray(values, dtype=float)[self.order]

    def matrix(self, values: np.ndarray) -> sp.csc_matrix:
        """The CSC matrix with these triplet values (structural zeros kept)."""
        return sp.csc_matrix((self.csc_data(values), self.indices.copy(), self.indptr.copy()),
                             shape=self.shape)


def _clarabel_cones(cones: Cones) -> list:
    out = []
    if cones.n_zero:
        out.append(clarabel.ZeroConeT(cones.n_zero))
    if cones.n_nonneg:
        out.append(clarabel.NonnegativeConeT(cones.n_nonneg))
    out.extend(clarabel.SecondOrderConeT(int(k)) for k in cones.soc_sizes)
    return out


class _UpdatableSolver:
    """In-place numeric updates shared by the wrappers (same sparsity pattern)."""

    _names = {"q": "q", "a_data": "A", "p_data": "P"}
    _solver: object

    def _b_update(self, b: np.ndarray) -> dict:
        return {"b": self._vector(b)}

    @staticmethod
    def _vector(values: object) -> object:
        """An update vector in the form the solver's binding reads fastest."""
        return np.asarray(values, float)

    def update(self, q: np.ndarray | None = None, b: np.ndarray | None = None,
               a_data: np.ndarray | None = None, p_data: np.ndarray | None = None) -> None:
        """Replace numbers: q, b, CSC data of A, CSC data of triu(P) (None = unchanged)."""
        given = {"q": q, "a_data": a_data, "p_data": p_data}
        kwargs = {self._names[k]: self._vector(v) for k, v in given.items() if v is not None}
        if b is not None:
            kwargs.update(self._b_update(np.asarray(b, float)))
        if kwargs:
            self._solver.update(**kwargs)


class ClarabelSolver(_UpdatableSolver):
    """Clarabel interior-point solver: min 1/2 v'Pv + q'v s.t. b - A v in cones."""

    name = "clarabel"

    @staticmethod
    def _vector(values: object) -> list[float]:
        # Clarabel's binding reads a numpy array element by element and a list of floats in
        # one pass; the values are the same.
        return np.asarray(values, float).tolist()

    def __init__(self, p: sp.csc_matrix, q: np.ndarray, a: sp.csc_matrix, b: np.ndarray,
                 cones: Cones, tol: float = 1e-8, max_iter: int = 100,
                 refine: bool = False, equilibrate: bool = True) -> None:
        if a.shape[0] != cones.n_rows:
            raise SolverError(f"A has {a.shape[0]} rows, cones describe {cones.n_rows}")
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False
        settings.input_sparse_dropzeros = False
        settings.tol_gap_abs = settings.tol_gap_rel = tol
        settings.tol_feas = tol
        settings.max_iter = max_iter
        # Iterative refinement of each KKT solve roughly doubles the time here and changed the
        # subproblem objectives by < 1e-8 relative (measured); off unless asked for.
        settings.iterative_refinement_enable = refine
        # Ruiz equilibration: off for problems assembled already scaled (the SCP subproblem:
        # 22 instead of 30 interior-point iterations, objectives equal to 3e-8 relative)
        settings.equilibrate_enable = equilibrate
        self._solver = clarabel.DefaultSolver(sp.triu(p, format="csc"), np.asarray(q, float),
                                              a, np.asarray(b, float),
                                              _clarabel_cones(cones), settings)

    def solve(self) -> SolverOutput:
        """Solve; `ok` is True for Solved and AlmostSolved."""
        t0 = time.perf_counter()
        sol = self._solver.solve()
        status = str(sol.status)
        ok = status in ("Solved", "AlmostSolved")
        return SolverOutput(ok, np.asarray(sol.x), status, int(sol.iterations),
                            1e3 * (time.perf_counter() - t0))


class OsqpSolver(_UpdatableSolver):
    """OSQP operator-splitting solver for QPs/LPs: the same rows, SOC blocks not allowed."""

    name = "osqp"
    _names = {"q": "q", "a_data": "Ax", "p_data": "Px"}

    def __init__(self, p: sp.csc_matrix, q: np.ndarray, a: sp.csc_matrix, b: np.ndarray,
                 cones: Cones, eps: float = 1e-6, max_iter: int = 50000) -> None:
        if cones.soc_sizes:
            raise SolverError("OSQP cannot handle second-order cones; use Clarabel")
        self._n_zero = cones.n_zero
        lower = np.full(cones.n_rows, -np.inf)
        self._solver = osqp.OSQP()
        self._solver.setup(P=sp.triu(p, format="csc"), q=np.asarray(q, float), A=a,
                           l=self._lower(lower, b), u=np.asarray(b, float), verbose=False,
                           eps_abs=eps, eps_rel=eps, max_iter=max_iter, polishing=True,
                           polish_refine_iter=10, adaptive_rho=True)

    def _lower(self, lower: np.ndarray, b: np.ndarray) -> np.ndarray:
        lower = lower.copy()
        lower[: self._n_zero] = np.asarray(b, float)[: self._n_zero]
        return lower

    def _b_update(self, b: np.ndarray) -> dict:
        return {"u": b, "l": self._lower(np.full(b.size, -np.inf), b)}

    def solve(self) -> SolverOutput:
        """Solve; `ok` is True for a solved (possibly inaccurate) status."""
        t0 = time.perf_counter()
        res = self._solver.solve(raise_error=False)
        status = str(res.info.status)
        ok = status.lower().startswith("solved")
        x = np.asarray(res.x) if res.x is not None else np.full(0, np.nan)
        return SolverOutput(ok, x, status, int(res.info.iter), 1e3 * (time.perf_counter() - t0))


SOLVERS = {"clarabel": ClarabelSolver, "osqp": OsqpSolver}


def make_solver(name: str, p: sp.csc_matrix, q: np.ndarray, a: sp.csc_matrix, b: np.ndarray,
                cones: Cones, scaled: bool = False,
                tol: float | None = None) -> ClarabelSolver | OsqpSolver:
    """Construct a solver by name ('clarabel' or 'osqp').

    Args:
        name: 'clarabel' or 'osqp'.
        p, q, a, b, cones: the problem (see the solver classes).
        scaled: the data is already well scaled (Clarabel then skips its equilibration).
        tol: Clarabel's gap and feasibility tolerances (None: its class default).
    """
    try:
        cls = SOLVERS[name]
    except KeyError:
        raise SolverError(f"unknown solver {name!r}; choose from {sorted(SOLVERS)}") from None
    if cls is ClarabelSolver:
        extra = {} if tol is None else {"tol": tol}
        return cls(p, q, a, b, cones, equilibrate=not scaled, **extra)
    return cls(p, q, a, b, cones)
