"""SCP from the CVX warm start against SCP from the ART warm start, scenario by scenario.

For each scenario (paper section V, chance-constrained or deterministic by the safety model):
CVX is solved (J_CVX, C_CVX(t_1)); ART rolls out conditioned on R(t_1) = -J_CVX, C(t_1) = 0
and is checked post hoc (E_R, E_C; by default those of the terminal warm start SCVx* starts
from, `planning.learned.check_proposal`, with the paper's check of the rollout itself beside
them); SCVx* then runs once from CVX ("PS-CVX") and once from the ART rollout ("PS-ART"),
both with the same configuration and no deadline. The `auto` plan is what the pipeline flies:
PS-ART if the post hoc check accepts the rollout, else PS-CVX; when
that run does not converge, the better of the two (`planning.choice.keep_first_plan`, with
`art_min_gain_mps`), as the pipeline's retry from the other warm start gives (without a
deadline); with `also_solve_from_cvx`, an accepted rollout's plan is always compared with
PS-CVX.

`summarize` turns rows into the paper's numbers: per cumulative bin of C_CVX(t_1) (">= value",
BINS) the absolute suboptimality J_SCP - J_CVX, the improvement ratio
(J_SCP,CVX - J_SCP,ART) / (J_SCP,CVX - J_CVX), SCP iterations, runtimes and the infeasibility
rate (infeasible or not converged: any status but CONVERGED); the histogram of
J_SCP,CVX - J_SCP,ART without and with the post hoc check (a rejected rollout flies PS-CVX, so
its difference is 0); and the post hoc maps over the (100 E_R, E_C) grid.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Mapping, Sequence

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.errors import GuidanceError
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus, Scvx, TransferProblem
from art_guidance.optim.problem import SubproblemPool
from art_guidance.planning.choice import keep_first_plan, second_run
from art_guidance.planning.learned import check_proposal, posthoc_check
from art_guidance.planning.request import WarmStartSource
from art_guidance.planning.result import PosthocDecision, WarmStartProposal

BINS = (0, 10, 20, 30, 40)  # the paper's cumulative C_CVX(t_1) >= value bins
GAP_TOL_MPS = 1e-6  # J_SCP,CVX - J_CVX below this: no improvement ratio for the scenario [m/s]
HIST_BINS = 40      # bins of the J_SCP,CVX - J_SCP,ART histograms
WORSE_MMPS = 10.0   # a flown ART plan dearer than PS-CVX by more than this counts as worse
# Post hoc map cells: 100 E_R [%] (paper's acceptance region -1.5 .. 3.5 is inside one row of
# cells) and E_C = C_ART(t_1) [nodes], integer-valued, cells 0, 1, 2-4, 5-10, 11-20, > 20.
ER_PCT_EDGES = (-math.inf, -50.0, -25.0, -12.5, -7.5, -2.5, 2.5, 7.5, 12.5, 25.0, 50.0, math.inf)
EC_EDGES = (-0.5, 0.5, 1.5, 4.5, 10.5, 20.5, math.inf)
_CONVERGED = ScpStatus.CONVERGED.value


@dataclass(frozen=True)
class WarmStartRow:
    """One scenario's numbers (costs [m/s], times [ms], statuses `ScpStatus` values).

    `ms_art` is the rollout plus the post hoc check; `ok_*` means feasible (`ScpStatus.feasible`),
    `st_* == ScpStatus.CONVERGED.value` converged. `e_r`, `e_c`, `accepted` are the post hoc
    check the pipeline applies (`planning.learned.check_proposal`), `*_rollout` the paper's
    check of the rollout itself (the same when the check's subject is "rollout").
    """

    j_cvx: float
    c_cvx: int
    art_cost: float
    c_art: int
    e_r: float
    e_c: float
    accepted: bool
    j_scp_cvx: float
    j_scp_art: float
    it_scp_cvx: int
    it_scp_art: int
    ms_cvx: float
    ms_art: float
    ms_scp_cvx: float
    ms_scp_art: float
    ok_scp_cvx: bool
    ok_scp_art: bool
    j_auto: float
    ok_auto: bool
    it_auto: int
    st_scp_cvx: int
    st_scp_art: int
    e_r_rollout: float = math.nan
    e_c_rollout: float = math.nan
    accepted_rollout: bool = False


ROW_FIELDS = tuple(f.name for f in fields(WarmStartRow))
# fields added later, read from these when an older evaluation directory is read
_SAME_BEFORE = {"e_r_rollout": "e_r", "e_c_rollout": "e_c", "accepted_rollout": "accepted"}


@dataclass(frozen=True)
class WarmStartRun:
    """Everything one comparison produced (the trajectories, for plots and checks).

    Attributes:
        cvx: the convex TPBVP solution (the warm start "CVX").
        proposal: the ART rollout (the warm start "ART").
        art_roe_m: (N, 6) the rollout's states [m], propagated from its controls.
        posthoc: its post hoc decision.
        from_cvx: SCVx* warm-started by CVX (PS-CVX).
        from_art: SCVx* warm-started by ART (PS-ART).
        auto: the plan the pipeline flies (one of the two).
        c_cvx: C_CVX(t_1) under `safety`.
        ms_cvx: CVX solve time [ms].
        ms_art: rollout plus post hoc check [ms].
        posthoc_rollout: the paper's check of the rollout itself (= `posthoc` when the
            configuration's `posthoc_subject` is "rollout").
    """

    cvx: ConvexSolution
    proposal: WarmStartProposal
    art_roe_m: np.ndarray
    posthoc: PosthocDecision
    from_cvx: ScpResult
    from_art: ScpResult
    auto: ScpResult
    c_cvx: int
    ms_cvx: float
    ms_art: float
    posthoc_rollout: PosthocDecision | None = None

    def row(self) -> WarmStartRow:
        """The scenario's numbers."""
        a, b, p = self.from_cvx, self.from_art, self.posthoc
        q = self.posthoc_rollout or p
        return WarmStartRow(
            j_cvx=float(self.cvx.cost_mps), c_cvx=self.c_cvx,
            art_cost=float(np.linalg.norm(self.proposal.dv_rtn_mps, axis=1).sum()),
            c_art=int(self.proposal.constraint_to_go[0]), e_r=float(p.e_r), e_c=float(p.e_c),
            accepted=bool(p.accepted), j_scp_cvx=float(a.cost_mps), j_scp_art=float(b.cost_mps),
            it_scp_cvx=a.iterations, it_scp_art=b.iterations, ms_cvx=self.ms_cvx,
            ms_art=self.ms_art, ms_scp_cvx=a.solve_time_ms, ms_scp_art=b.solve_time_ms,
            ok_scp_cvx=a.feasible, ok_scp_art=b.feasible, j_auto=float(self.auto.cost_mps),
            ok_auto=self.auto.feasible, it_auto=self.auto.iterations,
            st_scp_cvx=a.status.value, st_scp_art=b.status.value,
            e_r_rollout=float(q.e_r), e_c_rollout=float(q.e_c), accepted_rollout=q.accepted)


def solve_both(problem: TransferProblem, provider: object, config: GuidanceConfig,
               pool: SubproblemPool | None = None) -> WarmStartRun:
    """Both warm starts and both SCVx* runs for one transfer problem.

    Args:
        problem: initial state, RTN target and passive-safety model (deterministic or
            chance-constrained), e.g. `eval.inputs.problem_of`.
        provider: a `WarmStartProvider` (e.g. `art.provider.ArtWarmStart`).
        config: SCP, post hoc and planning settings.
        pool: the caller's SCVx* subproblems, reused over requests on one horizon (None: set
            up for this request).

    Raises:
        GuidanceError: CVX or the rollout failed (a SCVx* failure is a SOLVER_ERROR result).
    """
    safety = problem.safety
    t0 = time.perf_counter()
    cvx = problem.cvx()
    t1 = time.perf_counter()
    prop = provider.propose(problem, cvx, planning=config.planning)  # ranked as flown
    art_dv, art_roe = problem.propagate(prop.dv_rtn_mps)
    ph = check_proposal(problem, art_dv, cvx.cost_mps, config.planning)
    t2 = time.perf_counter()
    raw = ph if config.planning.posthoc_subject == "rollout" else \
        posthoc_check(art_dv, art_roe, cvx.cost_mps, safety, config.planning.posthoc)
    c_cvx = int(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0])
    scvx = problem.scvx(config.scp, config.planning.samples_per_node, pool=pool)
    from_cvx = _solve(scvx, cvx.dv_rtn_mps)
    from_art = _solve(scvx, art_dv)
    source = WarmStartSource.ART if ph.accepted else WarmStartSource.CVX
    first, second = (from_art, from_cvx) if ph.accepted else (from_cvx, from_art)
    again = second_run(first, source, True, config.planning.also_solve_from_cvx)
    auto = second if again is not None and not keep_first_plan(
        first, second, source, config.planning.art_min_gain_mps) else first
    if config.planning.skip_art_when_cvx_safe and c_cvx == 0:
        auto = from_cvx  # the pipeline does not run ART then (`skip_art_when_cvx_safe`)
    return WarmStartRun(cvx, prop, art_roe, ph, from_cvx, from_art, auto, c_cvx,
                        1e3 * (t1 - t0), 1e3 * (t2 - t1), raw)


def compare(problem: TransferProblem, provider: object, config: GuidanceConfig,
            pool: SubproblemPool | None = None) -> WarmStartRow:
    """Both warm starts for one transfer problem (see `solve_both`)."""
    return solve_both(problem, provider, config, pool).row()


def _solve(scvx: Scvx, warm_dv: np.ndarray) -> ScpResult:
    """SCVx* from a warm start; a solver failure becomes a SOLVER_ERROR result."""
    t0 = time.perf_counter()
    try:
        return scvx.solve(warm_dv)
    except GuidanceError:
        n = warm_dv.shape[0]
        return ScpResult(ScpStatus.SOLVER_ERROR, np.full((n, 6), np.nan), np.array(warm_dv),
                         math.nan, 0, math.inf,
                         solve_time_ms=1e3 * (time.perf_counter() - t0))


# =========================================================================== metrics
def columns(rows: Sequence[WarmStartRow] | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{field: (M,) array} of rows (a mapping of arrays is passed through, fields only)."""
    if isinstance(rows, Mapping):
        # an evaluation from before `posthoc_subject` checked the rollout itself
        return {k: np.asarray(rows[k] if k in rows else rows[_SAME_BEFORE[k]])
                for k in ROW_FIELDS}
    return {k: np.array([getattr(r, k) for r in rows]) for k in ROW_FIELDS}


def _stat(values: np.ndarray, how: str) -> float | None:
    return float(getattr(np, how)(values)) if values.size else None


def standard_error(values: np.ndarray) -> float | None:
    """The standard error of the mean of `values` (sample standard deviation / sqrt(n); None
    for fewer than two)."""
    v = np.asarray(values, dtype=float)
    return float(np.std(v, ddof=1) / np.sqrt(v.size)) if v.size > 1 else None


def gains(data: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-scenario differences (M,), NaN where undefined.

    Returns:
        {"gain_mps": J_SCP,CVX - J_SCP,ART (both converged), "gap_mps": J_SCP,CVX - J_CVX (both
        converged), "ratio": gain / gap (gap > GAP_TOL_MPS), "gain_posthoc_mps": the gain of
        the plan flown with the post hoc check (accepted: gain; rejected: 0 if PS-CVX
        converged), "gain_posthoc_rollout_mps": the same with the paper's check of the rollout
        itself, "iterations_saved": it_SCP,CVX - it_SCP,ART (both converged)}.
    """
    conv_cvx = data["st_scp_cvx"] == _CONVERGED
    both = conv_cvx & (data["st_scp_art"] == _CONVERGED)
    gain = np.where(both, data["j_scp_cvx"] - data["j_scp_art"], np.nan)
    gap = np.where(both, data["j_scp_cvx"] - data["j_cvx"], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(gap > GAP_TOL_MPS, gain / gap, np.nan)
    rejected = np.where(conv_cvx, 0.0, np.nan)
    posthoc = np.where(data["accepted"].astype(bool), gain, rejected)
    posthoc_rollout = np.where(data["accepted_rollout"].astype(bool), gain, rejected)
    saved = np.where(both, data["it_scp_cvx"] - data["it_scp_art"], np.nan)
    return {"gain_mps": gain, "gap_mps": gap, "ratio": ratio, "gain_posthoc_mps": posthoc,
            "gain_posthoc_rollout_mps": posthoc_rollout, "iterations_saved": saved}


def _bin(data: Mapping[str, np.ndarray], g: Mapping[str, np.ndarray], m: np.ndarray) -> dict:
    """The paper's metrics over the scenarios `m` (a bool mask)."""
    both = m & np.isfinite(g["gain_mps"])
    ratio = g["ratio"][both & np.isfinite(g["ratio"])]
    gap, gain = g["gap_mps"][both], g["gain_mps"][both]
    total_cvx = data["ms_cvx"] + data["ms_scp_cvx"]
    total_art = data["ms_cvx"] + data["ms_art"] + data["ms_scp_art"]
    out: dict = {"n": int(m.sum()), "n_both_converged": int(both.sum())}
    for name, j in (("cvx", data["j_scp_cvx"]), ("art", data["j_scp_art"])):
        sub = (j - data["j_cvx"])[both]
        out[f"subopt_{name}_mps"] = {"mean": _stat(sub, "mean"), "median": _stat(sub, "median")}
    out["improvement_ratio"] = {
        "mean": _stat(ratio, "mean"), "median": _stat(ratio, "median"), "n": int(ratio.size),
        "of_means": float(gain.sum() / gap.sum()) if gap.size and gap.sum() > GAP_TOL_MPS
        else None}
    for name in ("cvx", "art"):
        it = data[f"it_scp_{name}"][m]
        out[f"iterations_{name}"] = {"mean": _stat(it, "mean"), "median": _stat(it, "median")}
        out[f"infeasible_rate_{name}"] = _stat(data[f"st_scp_{name}"][m] != _CONVERGED, "mean")
        out[f"not_feasible_rate_{name}"] = _stat(~data[f"ok_scp_{name}"][m].astype(bool),
                                                 "mean")
    times = {"ws_cvx": data["ms_cvx"], "ws_art": data["ms_art"], "scp_cvx": data["ms_scp_cvx"],
             "scp_art": data["ms_scp_art"], "total_cvx": total_cvx, "total_art": total_art}
    out["runtime_ms_median"] = {k: _stat(v[m], "median") for k, v in times.items()}
    return out


def histogram(values: np.ndarray, bins: int = HIST_BINS) -> dict | None:
    """Counts of the finite `values` [m/s] with min, max and median (None if there are none)."""
    v = values[np.isfinite(values)]
    if not v.size:
        return None
    counts, edges = np.histogram(v, bins=bins)
    return {"n": int(v.size), "min_mps": float(v.min()), "max_mps": float(v.max()),
            "median_mps": float(np.median(v)), "mean_mps": float(v.mean()),
            "n_art_better_1mm": int(np.sum(v > 1e-3)), "n_art_worse_1mm": int(np.sum(v < -1e-3)),
            "edges_mps": edges.tolist(), "counts": counts.tolist()}


def posthoc_maps(data: Mapping[str, np.ndarray], g: Mapping[str, np.ndarray]) -> dict:
    """The paper's post hoc figure over (100 E_R, E_C) cells (rows: E_C, columns: 100 E_R).

    Returns:
        edges, "population" (counts), "improvement_ratio_mean" and "iterations_saved_mean"
        (means over the converged pairs of each cell; None where a cell has none), and
        "improvement_ratio_of_sums" (sum of J_SCP,CVX - J_SCP,ART over sum of J_SCP,CVX - J_CVX
        in the cell: not dominated by a pair whose PS-CVX is within millimetres of CVX).
    """
    er = 100.0 * data["e_r"].astype(float)
    ec = data["e_c"].astype(float)
    ok = np.isfinite(er) & np.isfinite(ec)
    col = np.digitize(er, ER_PCT_EDGES[1:-1], right=True)  # (lo, hi] cells
    row = np.digitize(ec, EC_EDGES[1:-1])
    shape = (len(EC_EDGES) - 1, len(ER_PCT_EDGES) - 1)
    pop = np.zeros(shape, dtype=int)
    np.add.at(pop, (row[ok], col[ok]), 1)

    def cell_sum(values: np.ndarray, sel: np.ndarray) -> np.ndarray:
        total = np.zeros(shape)
        np.add.at(total, (row[sel], col[sel]), values[sel])
        return total

    def cell_ratio(num: np.ndarray, den: np.ndarray, floor: float) -> list:
        """num / den per cell, None where den <= floor."""
        return [[float(num[i, j] / den[i, j]) if den[i, j] > floor else None
                 for j in range(shape[1])] for i in range(shape[0])]

    def cell_mean(values: np.ndarray) -> list:
        sel = ok & np.isfinite(values)
        return cell_ratio(cell_sum(values, sel), cell_sum(np.ones_like(values), sel), 0.0)

    both = ok & np.isfinite(g["gain_mps"])
    return {"e_r_pct_edges": list(ER_PCT_EDGES), "e_c_edges": list(EC_EDGES),
            "population": pop.tolist(), "improvement_ratio_mean": cell_mean(g["ratio"]),
            "improvement_ratio_of_sums": cell_ratio(cell_sum(g["gain_mps"], both),
                                                    cell_sum(g["gap_mps"], both), GAP_TOL_MPS),
            "iterations_saved_mean": cell_mean(g["iterations_saved"])}


def summarize(rows: Sequence[WarmStartRow] | Mapping[str, np.ndarray]) -> dict:
    """The paper's warm-start analysis of some scenarios (JSON-ready; see the module docstring).

    Args:
        rows: the scenarios' rows, or their `columns`.

    Returns:
        {"n", "bins": {">=b": per-bin metrics for b in BINS}, "gain_histogram",
        "gain_histogram_posthoc", "gain_histogram_posthoc_rollout", "posthoc_maps",
        "auto_minus_scp_cvx_mps", and shares of the post hoc decisions}.
    """
    data = columns(rows)
    n = int(data["j_cvx"].size)
    if n == 0:
        return {"n": 0, "bins": {}}
    g = gains(data)
    out: dict = {"n": n, "bins": {f">={low}": _bin(data, g, data["c_cvx"] >= low)
                                  for low in BINS}}
    out["gain_histogram"] = histogram(g["gain_mps"])
    out["gain_histogram_posthoc"] = histogram(g["gain_posthoc_mps"])
    out["gain_histogram_posthoc_rollout"] = histogram(g["gain_posthoc_rollout_mps"])
    out["posthoc_maps"] = posthoc_maps(data, g)
    both = data["ok_auto"].astype(bool) & data["ok_scp_cvx"].astype(bool)
    d = data["j_auto"][both] - data["j_scp_cvx"][both]
    out["auto_minus_scp_cvx_mps"] = {
        "min": _stat(d, "min"), "median": _stat(d, "median"), "max": _stat(d, "max"),
        "mean": _stat(d, "mean"), "sem": standard_error(d), "n": int(d.size),
        "n_better_by_1mm": int(np.sum(d < -1e-3)), "n_worse_by_1mm": int(np.sum(d > 1e-3))}
    out["accepted"] = int(data["accepted"].sum())
    out["frac_accepted"] = float(np.mean(data["accepted"]))
    out["accepted_rollout"] = int(data["accepted_rollout"].sum())
    out["frac_accepted_rollout"] = float(np.mean(data["accepted_rollout"]))
    for check in ("posthoc", "posthoc_rollout"):
        out[f"{check}_worse_by_10mm"] = int(np.sum(g[f"gain_{check}_mps"] < -WORSE_MMPS * 1e-3))
    out["c_art_zero"] = float(np.mean(data["c_art"] == 0))
    out["e_r_pct_median"] = float(np.median(100 * data["e_r"]))
    out["iterations_auto_mean"] = float(np.mean(data["it_auto"]))
    out["iterations_cvx_mean"] = float(np.mean(data["it_scp_cvx"]))
    return out
