"""SCP from the CVX warm start against SCP from the ART warm start, scenario by scenario.

For each scenario (paper section V, chance-constrained or deterministic by the safety model):
CVX is solved (J_CVX, C_CVX(t_1)); ART rolls out conditioned on R(t_1) = -J_CVX, C(t_1) = 0
and is checked post hoc (E_R, E_C); SCVx* then runs once from CVX ("PS-CVX") and once from the
ART rollout ("PS-ART"), both with the same configuration and no deadline. The `auto` plan is
what the pipeline flies: PS-ART if the post hoc check accepts the rollout, else PS-CVX; when
that run does not converge, the better of the two (`planning.pipeline.better_plan`), as the
pipeline's retry from the other warm start gives (without a deadline); with
`also_solve_from_cvx`, an accepted rollout's plan is always compared with PS-CVX.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.optim import ScpStatus, Scvx, solve_cvx
from art_guidance.planning.pipeline import better_plan
from art_guidance.planning.posthoc import posthoc_check
from art_guidance.planning.types import PlanRequest
from art_guidance.safety import PassiveSafety

BINS = (0, 10, 20, 30, 40)  # the paper's cumulative C_CVX(t_1) >= value bins


@dataclass(frozen=True)
class WarmStartRow:
    """One scenario's numbers (costs [m/s], times [ms])."""

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


def compare(request: PlanRequest, safety: PassiveSafety, provider: object,
            config: GuidanceConfig) -> WarmStartRow:
    """Both warm starts for one request on `safety.horizon` (see the module docstring)."""
    horizon = safety.horizon
    roe_f = np.linalg.solve(horizon.psi[-1], request.target_rtn)
    t0 = time.perf_counter()
    cvx = solve_cvx(horizon, request.roe0_m, roe_f)
    t1 = time.perf_counter()
    prop = provider.propose(request, safety, cvx)
    art_dv = np.asarray(prop.dv_rtn_mps, float)
    ph = posthoc_check(art_dv, horizon.propagate(request.roe0_m, art_dv), cvx.cost_mps, safety,
                       config.planning.posthoc)
    t2 = time.perf_counter()
    c_cvx = int(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0])
    scvx = Scvx(safety, request.roe0_m, roe_f, config.scp,
                samples_per_node=config.planning.samples_per_node)
    from_cvx = scvx.solve(cvx.dv_rtn_mps)
    from_art = scvx.solve(art_dv)
    first, second = (from_art, from_cvx) if ph.accepted else (from_cvx, from_art)
    if ph.accepted and config.planning.also_solve_from_cvx:
        auto = first if better_plan(first, second) else second
    else:
        auto = first if first.status is ScpStatus.CONVERGED or better_plan(first, second) \
            else second
    return WarmStartRow(
        float(cvx.cost_mps), c_cvx, float(np.linalg.norm(art_dv, axis=1).sum()),
        int(prop.constraint_to_go[0]), float(ph.e_r), float(ph.e_c), bool(ph.accepted),
        float(from_cvx.cost_mps), float(from_art.cost_mps), from_cvx.iterations,
        from_art.iterations, 1e3 * (t1 - t0), 1e3 * (t2 - t1), from_cvx.solve_time_ms,
        from_art.solve_time_ms, from_cvx.feasible, from_art.feasible, float(auto.cost_mps),
        auto.feasible, auto.iterations)


def summarize(rows: list[WarmStartRow]) -> dict:
    """Per cumulative C_CVX(t_1) bin: suboptimality, improvement ratio, iterations, runtimes,
    infeasibility, and the `auto` - PS-CVX cost distribution (JSON-ready)."""
    data = {k: np.array([getattr(r, k) for r in rows]) for k in asdict(rows[0])}
    out: dict = {"n": len(rows), "bins": {}}
    for low in BINS:
        m = data["c_cvx"] >= low
        both = m & data["ok_scp_cvx"] & data["ok_scp_art"]
        if not m.any():
            continue
        gap = data["j_scp_cvx"][both] - data["j_cvx"][both]
        gain = data["j_scp_cvx"][both] - data["j_scp_art"][both]
        ratio = np.where(gap > 1e-9, gain / np.maximum(gap, 1e-12), 0.0)
        out["bins"][f">={low}"] = {
            "n": int(m.sum()),
            "subopt_scp_cvx_mps_median": float(np.median(gap)) if both.any() else None,
            "subopt_scp_art_mps_median": (float(np.median(data["j_scp_art"][both]
                                                          - data["j_cvx"][both]))
                                          if both.any() else None),
            "improvement_ratio_mean": float(np.mean(ratio)) if both.any() else None,
            "iterations_cvx_mean": float(np.mean(data["it_scp_cvx"][m])),
            "iterations_art_mean": float(np.mean(data["it_scp_art"][m])),
            "runtime_cvx_ms_median": float(np.median((data["ms_cvx"] + data["ms_scp_cvx"])[m])),
            "runtime_art_ms_median": float(np.median((data["ms_cvx"] + data["ms_art"]
                                                      + data["ms_scp_art"])[m])),
            "infeasible_cvx": float(np.mean(~data["ok_scp_cvx"][m])),
            "infeasible_art": float(np.mean(~data["ok_scp_art"][m])),
        }
    both = data["ok_auto"] & data["ok_scp_cvx"]
    d = data["j_auto"][both] - data["j_scp_cvx"][both]
    out["auto_minus_scp_cvx_mps"] = {
        "min": float(d.min()), "median": float(np.median(d)), "max": float(d.max()),
        "n_better_by_1mm": int(np.sum(d < -1e-3)), "n_worse_by_1mm": int(np.sum(d > 1e-3))}
    out["accepted"] = int(data["accepted"].sum())
    out["c_art_zero"] = float(np.mean(data["c_art"] == 0))
    out["e_r_pct_median"] = float(np.median(100 * data["e_r"]))
    out["iterations_auto_mean"] = float(np.mean(data["it_auto"]))
    out["iterations_cvx_mean"] = float(np.mean(data["it_scp_cvx"]))
    return out
