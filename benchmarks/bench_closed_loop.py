"""Benchmark: closed-loop terminal accuracy over many seeds, without DDS.

The simulator (two-body + J2 truth, mean-element navigation) drives the in-process guidance
(`sim.inprocess.InProcessGuidance`: the node's replan policy and `GuidancePipeline`, CVX warm
start, chance-constrained) from the randomised initial states of seeds 0..repeats-1 to the
`plus_vbar` waypoint, once with navigation (ARTMS) and actuation (Gates) errors and once
without them (the reference, same seeds, same run). Reports per seed and as distributions the
terminal miss [m] and the total delta-v [m/s]; the miss with errors is dominated by the errors
of the last correction burns (a few metres), the miss without them by the models.

Run it on two checkouts to compare planner versions seed by seed (the numbers do not depend on
the machine's speed: the solve deadline is far above the solve times).
"""
from __future__ import annotations

import logging
import tempfile
import time

import numpy as np

from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance

_LOG = logging.getLogger("bench_closed_loop")


def fly(seed: int, errors: bool, pipeline: GuidancePipeline) -> dict:
    """One closed-loop run; its summary (miss_m, total_dv_mps, n_replans, ...)."""
    with tempfile.TemporaryDirectory(prefix="bench_closed_loop_") as tmp:
        params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=f"{tmp}/s.json",
                      seed=seed, warm_start="cvx", errors=errors)
        loop = ClosedLoop(InProcessGuidance(pipeline, SIM_EPOCH0_NS), params, _LOG,
                          settle_s=0.0)
        summary, _ = loop.finish(loop.run(), 0.0)
    return summary


def _dist(x: np.ndarray) -> dict:
    return {"mean": float(x.mean()), "median": float(np.median(x)),
            "p90": float(np.percentile(x, 90)), "max": float(x.max())}


def run(repeats: int = 30) -> dict:
    """Seeds 0..repeats-1 with and without errors; miss and delta-v distributions."""
    pipeline = GuidancePipeline()
    seeds = list(range(max(int(repeats), 1)))
    out: dict = {"seeds": seeds}
    t0 = time.perf_counter()
    for label, errors in (("errors", True), ("no_errors", False)):
        runs = [fly(s, errors, pipeline) for s in seeds]
        miss = np.array([r["miss_m"] for r in runs])
        dv = np.array([r["total_dv_mps"] for r in runs])
        out[label] = {"miss_m": _dist(miss), "total_dv_mps": _dist(dv),
                      "per_seed_miss_m": [round(float(m), 3) for m in miss],
                      "outcomes": sorted({r["outcome"] for r in runs})}
    out["wall_s"] = time.perf_counter() - t0
    return out


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(int(sys.argv[1]) if len(sys.argv) > 1 else 30), indent=1))
