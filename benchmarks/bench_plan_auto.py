"""Benchmark: the learned warm start in flight (`plan --warm-start auto`) against CVX only.

For scenario seeds 0..repeats-1 (the `plan --seed S` scenarios; the shipped chance-constrained
models were trained on dataset seed 1, whose scenario seeds start at 1,000,003, so these are
held out), the chance-constrained pipeline plans each transfer twice in the same run: with the
shipped default model (`auto`: ART rollout, post hoc check, SCVx* from the accepted warm start,
also solved from CVX when ART is accepted) and CVX only. Reports how often the post hoc check
accepted ART, how often the plan kept came from ART, the paired cost difference (auto - CVX
only) [mm/s], and the median total planning time of both (one process, one torch thread) with
the median of the paired ratios, over all seeds and over those where ART ran (`auto` skips it
where CVX is already passively safe); `auto` also once more with the proposal and SCVx* from
CVX run concurrently, the proposal in a worker process (`propose_concurrently: true`; the
default is one after the other), which also solves SCVx* from its proposal meanwhile (taken
where the plan needs that run: the check accepted ART, or SCVx* from CVX did not converge),
and once more with that worker making the proposal only (`producers.solve_art_in_worker`
False: every SCVx* run in the planner's process, the reference of the overlap).

Before the first timed plan every pipeline is warmed up (`common.warm_up`: the kernels, the
model's first inference) and plans one throwaway transfer whose CVX plan is unsafe (the
proposal workers' first job); the wall time of it all is `warm_up_ms`, apart from the timings.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

from art_guidance.art.provider import ArtWarmStart
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest, WarmStartSource
from common import unsafe_cases, warm_up


def run(repeats: int = 40, first_seed: int = 0, model: str | None = None) -> dict:
    """Seeds first_seed.. (repeats of them), `auto` with the shipped default (or `model`)
    against CVX only, paired; the ratios also over the plans where `auto` ran SCVx* once."""
    torch.set_num_threads(1)
    warm_up_ms = warm_up()  # the kernels, in the cache before the proposal workers start
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    provider = ArtWarmStart.load(model or None)
    auto = GuidancePipeline(provider=provider)
    config = GuidanceConfig.load()
    concurrent = GuidancePipeline(config.replace(planning=dataclasses.replace(
        config.planning, propose_concurrently=True)), provider=ArtWarmStart.load(model or None))
    concurrent.start_proposal_worker()
    propose_only = GuidancePipeline(concurrent.config, provider=ArtWarmStart.load(model or None))
    propose_only.producers.solve_art_in_worker = False
    propose_only.start_proposal_worker()
    cvx_only = GuidancePipeline()
    rows, t_con, t_pro = [], [], []
    try:
        warm_up_ms += _warm_up(auto, concurrent, propose_only, cvx_only)
        t0 = time.perf_counter()
        for seed in range(int(first_seed), int(first_seed) + max(int(repeats), 1)):
            s = sample_scenario(scenario, seed)
            request = PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
                                  chance_constrained=True, warm_start="auto")
            a = auto.plan(request)
            t_con.append(concurrent.plan(request).timings.total)
            t_pro.append(propose_only.plan(request).timings.total)
            c = cvx_only.plan(PlanRequest(chief, request.roe0_m, s.target_rtn,
                                          chance_constrained=True, warm_start="cvx"))
            rows.append((a.posthoc is not None and a.posthoc.accepted,
                         a.warm_start is WarmStartSource.ART,
                         a.status.feasible, c.status.feasible, a.cost_mps, c.cost_mps,
                         a.timings.total, c.timings.total,
                         a.posthoc.e_r if a.posthoc is not None else np.nan,
                         a.proposal is not None, a.timings.art, a.discarded is None))
        runs_made, runs_taken = concurrent.proposal_worker_scvx_runs
    finally:
        concurrent.close()
        propose_only.close()
    acc, art, ok_a, ok_c, j_a, j_c, t_a, t_c, e_r, ran, t_art, once = (np.array(x)
                                                                       for x in zip(*rows))
    t_con, t_pro = np.array(t_con), np.array(t_pro)
    both = ok_a & ok_c
    gap_mmps = 1e3 * (j_a - j_c)[both]
    return {"seeds": int(len(rows)), "warm_up_ms": warm_up_ms,
            "art_accepted_share": float(acc.mean()),
            "art_kept_share": float(art.mean()),
            "feasible_auto": int(ok_a.sum()), "feasible_cvx_only": int(ok_c.sum()),
            "cost_auto_minus_cvx_only_mmps_min": float(gap_mmps.min()),
            "cost_auto_minus_cvx_only_mmps_median": float(np.median(gap_mmps)),
            "cost_auto_minus_cvx_only_mmps_max": float(gap_mmps.max()),
            "cost_auto_minus_cvx_only_mmps_mean": float(gap_mmps.mean()),
            "better_by_1mmps": int((gap_mmps < -1).sum()),
            "worse_by_1mmps": int((gap_mmps > 1).sum()),
            "e_r_pct_median": float(np.nanmedian(100 * e_r)),
            "total_ms_median_auto": float(np.median(t_a)),
            "total_ms_median_cvx_only": float(np.median(t_c)),
            "total_auto_over_cvx_only_paired_median": float(np.median(t_a / t_c)),
            "total_ms_median_auto_concurrent": float(np.median(t_con)),
            "total_auto_concurrent_over_cvx_only_paired_median": float(np.median(t_con / t_c)),
            "total_auto_concurrent_over_cvx_only_paired_p90": float(np.percentile(t_con / t_c,
                                                                                  90)),
            # the same worker making the proposal only (every SCVx* run in the planner)
            "total_ms_median_auto_propose_only": float(np.median(t_pro)),
            "total_auto_propose_only_over_cvx_only_paired_median": float(np.median(t_pro / t_c)),
            "total_auto_propose_only_over_cvx_only_paired_p90": float(np.percentile(t_pro / t_c,
                                                                                    90)),
            "concurrent_over_propose_only_paired_median": float(np.median(t_con / t_pro)),
            "worker_scvx_runs_made": int(runs_made), "worker_scvx_runs_taken": int(runs_taken),
            # `auto` solves SCVx* twice where the first run did not converge (the retry from
            # the other warm start) or ART was accepted (also solved from CVX): its ratio on
            # the plans with one run is what the proposal itself costs
            "auto_scvx_once": int(once.sum()),
            "total_auto_over_cvx_only_paired_median_scvx_once":
                float(np.median((t_a / t_c)[once])) if once.any() else 0.0,
            "total_auto_concurrent_over_cvx_only_paired_median_scvx_once":
                float(np.median((t_con / t_c)[once])) if once.any() else 0.0,
            "total_auto_concurrent_over_cvx_only_paired_median_scvx_twice":
                float(np.median((t_con / t_c)[~once])) if (~once).any() else 0.0,
            "total_auto_propose_only_over_cvx_only_paired_median_scvx_twice":
                float(np.median((t_pro / t_c)[~once])) if (~once).any() else 0.0,
            "art_run": int(ran.sum()),
            "art_ms_median_where_run": float(np.median(t_art[ran])) if ran.any() else 0.0,
            "total_auto_over_cvx_only_paired_median_where_art_run":
                float(np.median((t_a / t_c)[ran])) if ran.any() else 0.0,
            "wall_s": time.perf_counter() - t0}


def _warm_up(*pipelines: GuidancePipeline) -> float:
    """Each pipeline's warm-up (`common.warm_up`: the kernels, its provider's first inference)
    and one throwaway plan of a transfer whose CVX plan is unsafe (the first from seed
    10,000), so that every timed plan finds the same warm process: the plan gives the proposal
    worker of the concurrent pipelines its first job (its runtime's first inference there) and
    sets SCVx* up for the horizon in each pipeline. The wall time [ms]."""
    transfer = unsafe_cases(pipelines[0], True, 10_000, 1)[0][0]
    total = 0.0
    for pipeline in pipelines:
        request = transfer.request if pipeline.provider is not None else dataclasses.replace(
            transfer.request, warm_start="cvx")
        total += warm_up(pipeline, lambda: pipeline.plan(request))
    return total


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(int(sys.argv[1]) if len(sys.argv) > 1 else 40), indent=1))
