"""Benchmark: SCVx* from the CVX warm start, the subproblem as posed now against the reference.

For scenario seeds first_seed .. first_seed + repeats - 1 (the `plan --seed S` scenarios:
`sample_scenario`, the linear RTN -> ROE map of the plan command), chance-constrained, and the
first repeats // 5 of them deterministic, each problem is solved by SCVx* three times in the
same process, each path first on a third of the seeds:

- current: the subproblem as posed now (`optim.problem.SubproblemOptions()`: without the
  control rows of the trust region, which its state rows imply, Clarabel tolerances 1e-6);
- reference: as posed before (`optim.problem.REFERENCE_OPTIONS`: every row, tolerances 1e-8);
- equivalent: the reference without the implied rows, at 1e-8: the same feasible set and
  optimum, so its differences from the reference are rounding alone. SCVx* on this non-convex
  problem sometimes takes another path after a perturbation that small (a step ratio on a
  threshold); what current changes beyond that is what its tolerances change.

All paths run the same dynamics and safety code. Timed: `TransferProblem.scvx(...)` and
`solve`, as in `plan`'s `timings_ms.scp` (the subproblems, from one `SubproblemPool` as the
pipeline holds, built before the first timed run).

Reports per mode and path the medians [ms], iterations, converged and feasible shares, and per
pair (current or equivalent against reference) the paired time ratios, the problems converged by
one only, and the cost differences over the problems both converge on, against
`ScpConfig.eps_opt`.

The kernels are loaded before the first solve (`common.warm_up`; `warm_up_ms`).
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from art_guidance.config import GuidanceConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.optim import ScpStatus, TransferProblem
from art_guidance.optim.problem import REFERENCE_OPTIONS, SubproblemOptions, SubproblemPool
from art_guidance.safety import PassiveSafety
from art_guidance.scenarios import sample_scenario
from common import warm_up

PATHS = ("current", "equivalent", "reference")


def run(repeats: int = 40, first_seed: int = 20000, out: str | None = None) -> dict:
    """Solve `repeats` chance-constrained and repeats // 5 deterministic problems three ways.

    Args:
        repeats: chance-constrained scenarios (>= 500 for the committed summary).
        first_seed: first scenario seed.
        out: directory for `summary.json` and `rows.json` (per problem), or None.
    """
    return compare(SubproblemOptions(), REFERENCE_OPTIONS, int(repeats), int(first_seed), out)


def compare(current: SubproblemOptions, reference: SubproblemOptions, repeats: int,
            first_seed: int, out: str | None = None) -> dict:
    """The benchmark with any two subproblem forms (`run` uses the shipped ones); the third,
    "equivalent", is the reference without its implied control rows (same feasible set, same
    optimum, same tolerance): what rounding alone changes."""
    equivalent = dataclasses.replace(reference, drop_idle_control_box=True)
    config = GuidanceConfig.load()
    chief = np.array(config.scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], config.scenario.n_orbits,
                                               config.scenario.n_nodes))
    options = dict(zip(PATHS, (current, equivalent, reference)))
    summary: dict = {"first_seed": first_seed, "eps_opt": config.scp.eps_opt,
                     "options": {p: dataclasses.asdict(o) for p, o in options.items()},
                     "warm_up_ms": warm_up()}  # the kernels, before the first solve
    rows = []
    t0 = time.perf_counter()
    for mode, count in (("chance", repeats), ("deterministic", max(repeats // 5, 1))):
        safety = PassiveSafety(horizon, config.scenario,
                               config.uncertainty if mode == "chance" else None)
        seeds = range(first_seed, first_seed + count)
        pool = SubproblemPool()
        _solve_both(config, safety, chief, first_seed, options, mode, pool)  # builds them
        mode_rows = [_solve_both(config, safety, chief, seed, options, mode, pool)
                     for seed in tqdm(seeds, desc=f"bench scvx {mode}", unit="scenario")]
        summary[mode] = _summarise(mode_rows, config.scp.eps_opt)
        rows += mode_rows
    summary["wall_s"] = time.perf_counter() - t0
    if out is not None:
        path = Path(out)
        path.mkdir(parents=True, exist_ok=True)
        (path / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        (path / "rows.json").write_text(json.dumps(_rounded(rows)) + "\n")
    return _flat(summary)


def _solve_both(config: GuidanceConfig, safety: PassiveSafety, chief: np.ndarray, seed: int,
                options: dict, mode: str, pool: SubproblemPool) -> dict:
    """One problem solved by both paths, in an order that alternates with the seed."""
    s = sample_scenario(config.scenario, seed)
    problem = TransferProblem.to_target(safety, roe_from_rtn_linear(chief, s.rtn0),
                                        s.target_rtn)
    warm = problem.cvx().dv_rtn_mps  # (N, 3) [m/s]
    row: dict = {"seed": seed, "mode": mode}
    order = PATHS[seed % 3:] + PATHS[:seed % 3]  # each path first on a third of the seeds
    for name in order:
        t = time.perf_counter()
        res = problem.scvx(config.scp, config.planning.samples_per_node,
                           subproblem=options[name], pool=pool).solve(warm)
        ms = 1e3 * (time.perf_counter() - t)
        row[name] = {"ms": ms, "status": res.status.name, "iterations": res.iterations,
                     "cost_mps": res.cost_mps,
                     "subproblem_ms": float(np.mean([h.solve_time_ms for h in res.history]))
                     if res.history else float("nan")}
    return row


def _summarise(rows: list[dict], eps_opt: float) -> dict:
    """Medians, shares and the paired comparisons of one mode's rows."""
    out: dict = {"problems": len(rows)}
    for p in PATHS:
        col = _column(rows, p)
        out[p] = {"median_ms": float(np.median(col["ms"])),
                  "p90_ms": float(np.percentile(col["ms"], 90)),
                  "mean_ms": float(col["ms"].mean()),
                  "median_iterations": float(np.median(col["iterations"])),
                  "mean_iterations": float(col["iterations"].mean()),
                  "median_subproblem_ms": float(np.nanmedian(col["subproblem_ms"])),
                  "converged_share": float(col["converged"].mean()),
                  "feasible_share": float(col["feasible"].mean())}
    for p in PATHS[:-1]:
        out[f"{p}_vs_reference"] = _paired(_column(rows, p), _column(rows, "reference"),
                                           eps_opt)
    return out


def _column(rows: list[dict], path: str) -> dict:
    """One path's results as arrays (ms, iterations, cost, converged, feasible)."""
    col = {key: np.array([r[path][key] for r in rows])
           for key in ("ms", "iterations", "cost_mps", "subproblem_ms", "status")}
    col["converged"] = col["status"] == ScpStatus.CONVERGED.name
    col["feasible"] = np.isin(col["status"], [s.name for s in ScpStatus if s.feasible])
    return col


def _paired(new: dict, ref: dict, eps_opt: float) -> dict:
    """Paired time ratios and cost differences (new - reference) [m/s]."""
    ratio = new["ms"] / ref["ms"]
    both = new["converged"] & ref["converged"]
    diff = (new["cost_mps"] - ref["cost_mps"])[both]
    return {
        "median_ratio": float(np.median(ratio)),
        "ratio_of_medians": float(np.median(new["ms"]) / np.median(ref["ms"])),
        "ratio_of_totals": float(new["ms"].sum() / ref["ms"].sum()),
        "both_converged": int(both.sum()),
        "converged_only_new": int((new["converged"] & ~ref["converged"]).sum()),
        "converged_only_reference": int((ref["converged"] & ~new["converged"]).sum()),
        "max_abs_cost_diff_mps": float(np.abs(diff).max()) if diff.size else float("nan"),
        "median_abs_cost_diff_mps": float(np.median(np.abs(diff))) if diff.size
        else float("nan"),
        "mean_cost_diff_mps": float(diff.mean()) if diff.size else float("nan"),
        "cheaper_by_more_than_eps_opt": int((diff < -eps_opt).sum()),
        "dearer_by_more_than_eps_opt": int((diff > eps_opt).sum()),
        "same_iterations_share": float(np.mean(new["iterations"] == ref["iterations"]))}


def _rounded(value: object) -> object:
    """Rows as written: times to 10 us, costs to 1 nm/s (the file stays small)."""
    if isinstance(value, dict):
        return {k: (round(v, 9) if k == "cost_mps" else _rounded(v)) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return round(value, 2) if isinstance(value, float) else value


def _flat(summary: dict) -> dict:
    """The summary as one level of keys (what `art-guidance bench` prints)."""
    flat = {}
    for key, value in summary.items():
        if isinstance(value, dict):
            for sub, inner in _flat(value).items():
                flat[f"{key}.{sub}"] = inner
        else:
            flat[key] = value
    return flat


if __name__ == "__main__":
    import sys

    print(json.dumps(run(int(sys.argv[1]) if len(sys.argv) > 1 else 40), indent=1))
