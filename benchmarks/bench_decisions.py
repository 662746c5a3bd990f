"""Benchmark: the compiled numerics change no decision of a plan.

Per passive-safety mode, on `repeats` fresh scenarios whose CVX plan is unsafe (where `auto`
runs the model; `bench proposal`'s screen, seeds from `first_seed`), the whole plan (`auto`:
CVX, the learned proposal and its post hoc check, SCVx* and its retries) is made once on the
numpy path and once compiled (`art_guidance.kernels`), with the teacher models on torch
(`art_small_chance_rtn.pt`, `art_small_det_roe.pt`; `model` replaces both). Counted: plans
whose post hoc decision (E_R, E_C, accepted), warm start, status or SCVx* iterations differ,
and the largest difference of their burns [m/s] and costs; where SCVx* took another path, how
often and by how much.

Each pipeline is warmed up first (`common.warm_up`, `warm_up_ms`): on a cold cache the compiled
path would otherwise be the numpy one while the kernels compile.
"""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from art_guidance import kernels
from art_guidance.art.provider import ArtWarmStart, models_dir
from art_guidance.planning import GuidancePipeline
from common import unsafe_cases, warm_up

TEACHERS = {True: "art_small_chance_rtn.pt", False: "art_small_det_roe.pt"}
DV_TOL_MPS = 1e-9


def _decision(result) -> tuple:
    ph = result.posthoc
    posthoc = None if ph is None else (ph.e_r, ph.e_c, ph.accepted)
    return posthoc, result.warm_start.value, result.status.name, result.scp.iterations


def run(repeats: int = 100, first_seed: int = 80000, model: str | None = None) -> dict:
    """Both paths on `repeats` fresh unsafe scenarios per mode; the differences."""
    out: dict = {"tolerance_dv_mps": DV_TOL_MPS, "warm_up_ms": 0.0}
    for chance in (True, False):
        path = model or str(models_dir() / TEACHERS[chance])
        pipeline = GuidancePipeline(provider=ArtWarmStart.load(path, runtime="torch"))
        # the kernels loaded (on a cold cache the compiled path would be the numpy one while
        # they compile) and the model run once
        out["warm_up_ms"] += warm_up(pipeline)
        cases = unsafe_cases(pipeline, chance, int(first_seed), int(repeats))
        rows = []
        for transfer, _ in tqdm(cases, desc="chance" if chance else "deterministic",
                                leave=False):
            plans = {}
            for mode in ("numpy", "compiled"):
                kernels.choose(mode)
                plans[mode] = pipeline.plan(transfer.request)
            a, b = plans["numpy"], plans["compiled"]
            d_dv = float(np.max(np.abs(a.dv_rtn_mps - b.dv_rtn_mps)))
            rows.append({"same_decision": _decision(a) == _decision(b), "dv_max_abs_mps": d_dv,
                         "cost_diff_mps": abs(a.cost_mps - b.cost_mps),
                         "same_warm_start": a.warm_start is b.warm_start,
                         "same_posthoc": _decision(a)[0] == _decision(b)[0],
                         "art_accepted": bool(a.posthoc is not None and a.posthoc.accepted)})
        kernels.choose("compiled")
        other = [r for r in rows if not r["same_decision"] or r["dv_max_abs_mps"] > DV_TOL_MPS]
        out["chance" if chance else "deterministic"] = {
            "model": path.rsplit("/", 1)[-1], "scenarios": len(rows),
            "first_seed": int(first_seed),
            "art_accepted": sum(r["art_accepted"] for r in rows),
            "same_decision": sum(r["same_decision"] for r in rows),
            "same_posthoc": sum(r["same_posthoc"] for r in rows),
            "same_warm_start": sum(r["same_warm_start"] for r in rows),
            "within_tolerance": sum(r["dv_max_abs_mps"] <= DV_TOL_MPS for r in rows),
            "dv_max_abs_mps": max(r["dv_max_abs_mps"] for r in rows),
            "other_path": len(other),
            "status_or_iterations_differ": sum(
                not r["same_decision"] and r["same_posthoc"] and r["same_warm_start"]
                for r in rows),
            "cost_diff_over_1mm_s": sum(r["cost_diff_mps"] > 1e-3 for r in rows),
            "cost_diff_mps_median": float(np.median([r["cost_diff_mps"] for r in rows])),
            "other_path_cost_diff_mps_max": max((r["cost_diff_mps"] for r in other),
                                                default=0.0)}
    return out
