"""Benchmark: `also_solve_from_art` in the closed loop (SCVx* also from rejected proposals).

The same seeds flown in-process (`bench_closed_loop.fly`: simulator with navigation and
actuation errors, the node's replan policy, `warm_start auto` with the shipped chance-constrained
default) twice: with the planning configuration as shipped (the second SCVx* run only where the
post hoc check accepts the proposal) and with `also_solve_from_art: true` (also where it
rejects it; the cheaper plan kept by the same rule). Paired per seed: the executed delta-v
difference (on - off) [mm/s], the misses, how many replans flew the ART-warm-started plan, and
the median plan time of each.

Both planners are warmed up before the first flight (`common.warm_up`: the kernels, the model's
first inference); the wall time is `warm_up_ms`.

    art-guidance bench solve_both --repeats 30 --json out/solve_both.json
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch
from tqdm import tqdm

from bench_closed_loop import fly
from common import warm_up

from art_guidance.art.provider import ArtWarmStart
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline


def run(repeats: int = 10, first_seed: int = 0) -> dict:
    """Seeds first_seed.. (repeats of them), paired off / on; see the module."""
    torch.set_num_threads(1)
    config = GuidanceConfig.load()
    on = config.replace(planning=dataclasses.replace(config.planning, also_solve_from_art=True))
    off_pipeline = GuidancePipeline(config, provider=ArtWarmStart.load())
    on_pipeline = GuidancePipeline(on, provider=ArtWarmStart.load())
    warm_up_ms = warm_up(off_pipeline) + warm_up(on_pipeline)  # before the first timed plan
    rows, t0 = [], time.perf_counter()
    seeds = range(int(first_seed), int(first_seed) + max(int(repeats), 1))
    for seed in tqdm(seeds, desc="solve both", unit="seed"):
        a, b = fly(seed, True, off_pipeline, "auto"), fly(seed, True, on_pipeline, "auto")
        rows.append((seed, a["total_dv_mps"], b["total_dv_mps"], a["miss_m"], b["miss_m"],
                     a["art_kept"], b["art_kept"], float(np.median(a["plan_ms"])),
                     float(np.median(b["plan_ms"]))))
    r = np.array(rows)
    d = 1e3 * (r[:, 2] - r[:, 1])
    return {"seeds": [int(s) for s in r[:, 0]], "warm_up_ms": warm_up_ms,
            "dv_on_minus_off_mmps": d.tolist(),
            "dv_on_minus_off_mmps_mean": float(d.mean()),
            "dv_on_minus_off_mmps_sd": float(d.std()),
            "dv_on_minus_off_mmps_min": float(d.min()),
            "dv_on_minus_off_mmps_max": float(d.max()),
            "seeds_cheaper_by_1mmps": int(np.sum(d < -1.0)),
            "seeds_dearer_by_1mmps": int(np.sum(d > 1.0)),
            "miss_m_median_off": float(np.median(r[:, 3])),
            "miss_m_median_on": float(np.median(r[:, 4])),
            "art_flown_replans_off": int(r[:, 5].sum()),
            "art_flown_replans_on": int(r[:, 6].sum()),
            "plan_ms_median_off": float(np.median(r[:, 7])),
            "plan_ms_median_on": float(np.median(r[:, 8])),
            "wall_s": time.perf_counter() - t0}
