"""Benchmark: what the flown steps as the learned proposal's context cost (`art_context`).

On `repeats` fresh chance-constrained scenarios whose CVX plan is unsafe (seeds from
`first_seed`, `bench proposal`'s screen), the plan of the whole transfer is made (CVX warm
start) and flown on paper to node k (`nodes`, default 50): the replan from its state there
over the remaining nodes is proposed by the default model (or `model`) with no context and
with the k flown steps as its context (`planning.request.RolloutContext`: the plan's states and
burns, R from -J_CVX). CPU time of each proposal (paired medians, alternating order), and how
often the proposal changed. With the KV cache the context costs one multi-token call at the
first step; keeping the cache from one replan to the next would save at most that call.

Before the first timed proposal the process is warmed up (`common.warm_up`: the kernels loaded,
the model run once on the first scenario); its wall time is `warm_up_ms`.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from tqdm import tqdm

from art_guidance.art.provider import ArtWarmStart
from art_guidance.dynamics import propagate_mean_oe
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.planning.request import RolloutContext
from common import alternate, unsafe_cases, warm_up


def run(repeats: int = 20, first_seed: int = 95000, model: str | None = None) -> dict:
    """Proposals with and without the flown context; paired CPU medians."""
    provider = ArtWarmStart.load(model or None)
    pipeline = GuidancePipeline()
    warm_up_ms = warm_up(pipeline)  # the kernels
    cases = unsafe_cases(pipeline, True, int(first_seed), int(repeats))
    if cases:  # the runtime's first inference, on the first case
        warm_up_ms += warm_up(None, lambda: provider.propose(cases[0][0].problem, cases[0][1]))
    k = 50
    rows = []
    for transfer, _ in tqdm(cases, desc="bench context", leave=False):
        request = dataclasses.replace(transfer.request, warm_start="cvx")
        plan = pipeline.plan(request)
        n = plan.epochs_s.size
        scenario = pipeline.scenario
        later = PlanRequest(propagate_mean_oe(request.chief_oe, plan.epochs_s[k]),
                            plan.roe_m[k], request.target_rtn, n_nodes=n - k,
                            n_orbits=scenario.n_orbits * (n - 1 - k) / (n - 1))
        ctx = RolloutContext(plan.roe_m[:k], plan.rtn[:k], plan.dv_rtn_mps[:k],
                             -plan.cvx.cost_mps)
        replan = pipeline.transfer(later)
        cvx = replan.problem.cvx()
        kwargs = {"none": {}, "context": {"context": ctx}}
        props, times = alternate(len(rows), ("none", "context"), lambda name: provider.propose(
            replan.problem, cvx, **kwargs[name]))
        rows.append({"none_ms": times["none"], "context_ms": times["context"],
                     "changed": not np.array_equal(props["none"].dv_rtn_mps,
                                                   props["context"].dv_rtn_mps)})
    none = np.array([r["none_ms"] for r in rows])
    ctx_ms = np.array([r["context_ms"] for r in rows])
    return {"scenarios": len(rows), "context_steps": k, "warm_up_ms": warm_up_ms,
            "proposal_ms_median_no_context": float(np.median(none)),
            "proposal_ms_median_context": float(np.median(ctx_ms)),
            "context_over_none_paired_median": float(np.median(ctx_ms / none)),
            "proposals_changed": int(sum(r["changed"] for r in rows))}
