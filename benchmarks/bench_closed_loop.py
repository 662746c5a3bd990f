"""Benchmark: closed-loop terminal accuracy over many seeds, without DDS.

The simulator (two-body + J2 truth, mean-element navigation) drives the in-process guidance
(`sim.inprocess.InProcessGuidance`: the node's replan policy and `GuidancePipeline`, CVX warm
start, chance-constrained) from the randomised initial states of seeds 0..repeats-1 to the
`plus_vbar` waypoint, once with navigation (ARTMS) and actuation (Gates) errors and once
without them (the reference, same seeds, same run). Reports per seed and as distributions the
terminal miss [m] and the total delta-v [m/s]; the miss with errors is dominated by the errors
of the last correction burns (a few metres), the miss without them by the models.

`warm_starts`: the same seeds with errors flown with the learned warm start in the loop
(`auto`: the shipped default model, the post hoc check, SCVx* from ART when it is accepted)
against CVX only, paired per seed: executed delta-v and miss, their paired differences, and
how often the node accepted ART.

`min_c_cvx` (`--min-c-cvx N`): the hard family instead of seeds first_seed..: the first
`repeats` seeds from first_seed whose first plan's CVX warm start violates passive safety at
N or more nodes (C_CVX >= N: the initial transfer, from the seed's true initial state to the
waypoint, as the first replan sees it without navigation error), flown with errors only, with
the learned warm start against CVX only. `model`: the model `auto` flies (default: the
shipped default).

`configs` (`--configs cvx_fresh,auto_fresh,auto_carry_keep_cap,default`): instead of the
above, every seed flown once per configuration, errors on, on `workers` processes (or as Ray
tasks: `--engine ray`, `--ray-address`). A name is `default` (the shipped planning.yaml and node
defaults) or `WARMSTART_REPLAN[_ENDGAME]`: the warm start (`cvx`: CVX only; `auto`: the learned
proposal, the shipped default model or `model`), the replan's (`fresh`: every replan solved from
scratch; `carry`: from the plan in force, `planning.carry`) and the end game (`none`, the
default: every usable replan put in force; `keep` / `keep_cap`: `planning.endgame`, optionally
with its tolerances `<m>m<mm/s>v<sigma>s`, their growth `g<nodes>` and `a` for
aim_within_tolerance, `f` for first_plan_from_both, e.g. `keep_cap10m20vg10a`; or a crude node
rule: `late6`
(min_remaining_nodes 6), `late6s5` / `late6s8` (and replan_sigma_threshold 5 / 8)).
Per configuration: reached, delta-v, the worst miss, replans, the paired delta-v against
`cvx_fresh` (flown too if not named: mean, sem, worst seed) and, where `auto_fresh` (the default
before the end game) is flown, against it; SCVx* iterations of every run of a replan (mean,
p95), replan time median and p95, the share of replans whose plan ended at the iteration cap,
the share that kept the carried plan; where the delta-v goes (`closed_loop_configs.growth`: the
first plan's cost, flown minus first, the growth of the plans put in force with <= 5 and > 5
nodes left, the largest single growth), the miss and velocity error in truth (mean, max), the
smallest realised passive-safety margin, the share of replans not converged by nodes left, and
the end game's counts (replans kept out, capped, aimed, planned into a terminal set). The
first plan of a flight (a fresh target) is left out of the per-replan figures.

Run it on two checkouts to compare planner versions seed by seed (the numbers do not depend on
the machine's speed: the solve deadline is far above the solve times).

Every planner is warmed up before its first flight (`common.warm_up`: the kernels, the model's
first inference), with `configs` in every worker process; the wall time is `warm_up_ms` (with
`configs`: per configuration, one figure per process that flew it).
"""
from __future__ import annotations

import logging
import tempfile
import time

import numpy as np

from art_guidance.planning import GuidancePipeline, WarmStartSource
from art_guidance.planning.learned import CVX_SAFE_REASON
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance
from common import hard_seeds, warm_up

_LOG = logging.getLogger("bench_closed_loop")


def fly(seed: int, errors: bool, pipeline: GuidancePipeline, warm_start: str = "cvx") -> dict:
    """One closed-loop run; its summary (miss_m, total_dv_mps, n_replans, ...)."""
    with tempfile.TemporaryDirectory(prefix="bench_closed_loop_") as tmp:
        params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=f"{tmp}/s.json",
                      seed=seed, warm_start=warm_start, errors=errors)
        guidance = InProcessGuidance(pipeline, SIM_EPOCH0_NS)
        loop = ClosedLoop(guidance, params, _LOG, settle_s=0.0)
        summary, _ = loop.finish(loop.run(), 0.0)
    posthoc = [r.posthoc for _, r in guidance.results if r.posthoc is not None]
    summary["art_checked"] = len(posthoc)
    summary["art_accepted"] = sum(bool(p.accepted) for p in posthoc)
    summary["art_kept"] = sum(r.warm_start is WarmStartSource.ART for _, r in guidance.results)
    summary["plan_ms"] = [float(r.timings.total) for _, r in guidance.results]
    summary["art_skipped_cvx_safe"] = sum(r.warm_start_reason == CVX_SAFE_REASON
                                          for _, r in guidance.results)
    # both plans solved: the CVX-warm-started plan's cost minus the ART-warm-started one's
    both = [r for _, r in guidance.results
            if r.discarded is not None and r.discarded.status.feasible and r.scp.feasible]
    summary["art_gain_mps"] = [_art_gain(r) for r in both]
    summary["art_kept_gain_mps"] = [_art_gain(r) for r in both
                                    if r.warm_start is WarmStartSource.ART]
    summary["plans"] = len(guidance.results)
    return summary


def _art_gain(result) -> float:
    """CVX-warm-started plan cost minus ART-warm-started plan cost [m/s] of a replan where
    SCVx* ran from both (positive: ART's plan is cheaper)."""
    kept, lost = float(result.cost_mps), float(result.discarded.cost_mps)
    return lost - kept if result.warm_start is WarmStartSource.ART else kept - lost


def _dist(x: np.ndarray) -> dict:
    return {"mean": float(x.mean()), "median": float(np.median(x)),
            "p90": float(np.percentile(x, 90)), "max": float(x.max())}


def run(repeats: int = 30, warm_starts: bool = True, first_seed: int = 0,
        min_c_cvx: int | None = None, model: str | None = None, configs: str | None = None,
        workers: int = 1, engine: str = "local", ray_address: str | None = None) -> dict:
    """Seeds first_seed..first_seed+repeats-1 with and without errors; miss and delta-v
    distributions; with `warm_starts`, ART in the loop against CVX only (errors on, paired per
    seed). With `min_c_cvx`, the hard family (module docstring), errors on only. With
    `configs`, the named configurations on the same seeds (module docstring)."""
    if configs is not None:
        from closed_loop_configs import compare_configs

        return compare_configs(configs, repeats, first_seed, min_c_cvx, model, workers, engine,
                               ray_address)
    pipeline = GuidancePipeline()
    warm_up_ms = warm_up(pipeline)  # the kernels, before the first timed plan
    t0 = time.perf_counter()
    n = max(int(repeats), 1)
    if min_c_cvx is None:
        seeds = list(range(int(first_seed), int(first_seed) + n))
        out: dict = {"seeds": seeds}
    else:
        seeds, c_cvx, screened = hard_seeds(pipeline, int(first_seed), n, int(min_c_cvx))
        out = {"seeds": seeds, "min_c_cvx": int(min_c_cvx), "c_cvx": c_cvx,
               "screened_seeds": screened}
    runs_cvx = []
    configurations = (("errors", True), ("no_errors", False))
    for label, errors in configurations[:1 if min_c_cvx is not None else 2]:
        runs = [fly(s, errors, pipeline) for s in seeds]
        runs_cvx = runs_cvx or runs
        miss = np.array([r["miss_m"] for r in runs])
        dv = np.array([r["total_dv_mps"] for r in runs])
        out[label] = {"miss_m": _dist(miss), "total_dv_mps": _dist(dv),
                      "per_seed_miss_m": [round(float(m), 3) for m in miss],
                      "outcomes": sorted({r["outcome"] for r in runs})}
    if warm_starts or min_c_cvx is not None:
        out["warm_starts"] = compare_warm_starts(seeds, runs_cvx, model)
        warm_up_ms += out["warm_starts"]["warm_up_ms"]
    out["warm_up_ms"] = warm_up_ms
    out["wall_s"] = time.perf_counter() - t0
    return out


def compare_warm_starts(seeds: list[int], runs_cvx: list[dict], model: str | None = None
                        ) -> dict:
    """ART in the loop (`auto`, the shipped default model or `model`) against the CVX-only
    runs, paired."""
    from art_guidance.art.provider import ArtWarmStart

    pipeline = GuidancePipeline(provider=ArtWarmStart.load(model or None))
    warm_up_ms = warm_up(pipeline)  # its runtime's first inference, before the first plan
    runs_art = [fly(s, True, pipeline, "auto") for s in seeds]
    dv_c = np.array([r["total_dv_mps"] for r in runs_cvx])
    dv_a = np.array([r["total_dv_mps"] for r in runs_art])
    miss_c = np.array([r["miss_m"] for r in runs_cvx])
    miss_a = np.array([r["miss_m"] for r in runs_art])
    d_dv, d_miss = dv_a - dv_c, miss_a - miss_c
    sem = float(d_dv.std(ddof=1) / np.sqrt(d_dv.size)) if d_dv.size > 1 else float("nan")
    return {"warm_up_ms": warm_up_ms,
            "cvx": {"total_dv_mps": _dist(dv_c), "miss_m": _dist(miss_c),
                    "plan_ms": _latency(runs_cvx)},
            "auto": {"total_dv_mps": _dist(dv_a), "miss_m": _dist(miss_a),
                     "art": _accepted_share(runs_art), "plan_ms": _latency(runs_art)},
            "paired_dv_mps": {**_dist(d_dv), "sem": sem},
            "paired_miss_m": _dist(d_miss),
            "per_seed_dv_mps": [[round(float(c), 4), round(float(a), 4)]
                                for c, a in zip(dv_c, dv_a)]}


def _latency(runs: list[dict]) -> dict:
    """Per-replan planning time [ms] (`PlanResult.timings.total`: CVX, ART, SCVx*)."""
    return _dist(np.array([t for r in runs for t in r["plan_ms"]]))


def _accepted_share(runs: list[dict]) -> dict:
    """How often the post hoc check accepted ART, and how often the plan kept came from it."""
    checked = sum(r["art_checked"] for r in runs)
    plans = sum(r["plans"] for r in runs)
    gain = np.array([g for r in runs for g in r["art_gain_mps"]])
    kept = np.array([g for r in runs for g in r["art_kept_gain_mps"]])
    return {"checked": checked, "accepted": sum(r["art_accepted"] for r in runs),
            "plans": plans, "kept_from_art": sum(r["art_kept"] for r in runs),
            "not_run_cvx_safe": sum(r["art_skipped_cvx_safe"] for r in runs),
            "solved_from_both": int(gain.size),
            "art_cheaper_by_over_1mm_s": int((gain > 1e-3).sum()),
            "gap_mps": _dist(gain) if gain.size else None,
            "gap_abs_median_mps": float(np.median(np.abs(gain))) if gain.size else None,
            "kept_from_art_gap_mps": _dist(kept) if kept.size else None}


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(int(sys.argv[1]) if len(sys.argv) > 1 else 30), indent=1))
