"""Benchmark: the learned proposal with the compiled numerics against the numpy path, and SCVx*
from CVX, on the same fresh scenarios, one thread.

On each of `repeats` chance-constrained scenarios whose CVX plan is unsafe (where `auto` runs
the model; seeds from `first_seed`, `bench proposal`'s screen) the default model (or `model`)
proposes once on the numpy path and once compiled (`art_guidance.kernels`), in alternating
order, and SCVx* is solved from CVX on both paths: CPU time of each, paired medians, whether
the two proposals are the same bit for bit, whether SCVx* ends the same (status, iterations;
its cost to rounding), and the kernels' start-up: compiled from nothing in a fresh interpreter
with an empty cache, and loaded from the cache.

Before the first timed proposal the process is warmed up (`common.warm_up`: the kernels loaded,
the pipeline's throwaway plan of a canned transfer from the model); its wall time is
`warm_up_ms`.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile

import numpy as np
from tqdm import tqdm

from art_guidance import kernels
from art_guidance.art.provider import ArtWarmStart
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from common import alternate, cpu_ms, unsafe_cases, warm_up

_START = ("import time; t = time.perf_counter(); from art_guidance import kernels; "
          "kernels.warm_up(); print(time.perf_counter() - t)")


def _start_s(cache_dir: str) -> float:
    """Seconds to import the kernels and have them ready, in a fresh interpreter."""
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    out = subprocess.run([sys.executable, "-c", _START], env=env, capture_output=True,
                         text=True, timeout=600, check=True)
    return float(out.stdout.split()[-1])


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in (
        "dv_rtn_mps", "constraint_to_go")) and all(
        np.array_equal(x, y) for x, y in zip(a.warm_start, b.warm_start))


def run(repeats: int = 20, first_seed: int = 60000, model: str | None = None) -> dict:
    """Paired medians over `repeats` scenarios [ms CPU], and the kernels' start-up [s]."""
    with tempfile.TemporaryDirectory() as cache:
        cold_s, warm_s = _start_s(cache), _start_s(cache)
    provider = ArtWarmStart.load(model or None)
    planning = GuidanceConfig.load().planning
    pipeline = GuidancePipeline(provider=provider)
    warm_up_ms = warm_up(pipeline)  # the kernels, the runtime's first inference
    cases = unsafe_cases(pipeline, True, int(first_seed), max(int(repeats), 1))
    rows, same, same_path, cost_diff = [], 0, 0, 0.0
    for k, (transfer, cvx) in enumerate(tqdm(cases, desc="bench numerics", unit="scenario")):
        out, times = alternate(k, ("numpy", "compiled"), lambda mode: provider.propose(
            transfer.problem, cvx, planning), before=kernels.choose)
        scvx = {}
        for mode in ("numpy", "compiled"):
            kernels.choose(mode)
            scvx[mode], times[f"scvx_{mode}"] = cpu_ms(lambda: transfer.scvx(
                pipeline.config, pipeline.subproblem).solve(cvx.dv_rtn_mps))
        same += _same(out["numpy"], out["compiled"])
        a, b = scvx["numpy"], scvx["compiled"]
        same_path += (a.status, a.iterations) == (b.status, b.iterations)
        cost_diff = max(cost_diff, abs(a.cost_mps - b.cost_mps))
        rows.append(times)
    col = {key: np.array([r[key] for r in rows]) for key in rows[0]}
    return {"scenarios": len(rows), "model": os.path.basename(provider.path),
            "warm_up_ms": warm_up_ms,
            "proposal_numpy_ms_median": float(np.median(col["numpy"])),
            "proposal_compiled_ms_median": float(np.median(col["compiled"])),
            "compiled_over_numpy_paired_median": float(np.median(col["compiled"]
                                                                 / col["numpy"])),
            "scvx_numpy_ms_median": float(np.median(col["scvx_numpy"])),
            "scvx_compiled_ms_median": float(np.median(col["scvx_compiled"])),
            "scvx_compiled_over_numpy_paired_median": float(np.median(col["scvx_compiled"]
                                                                      / col["scvx_numpy"])),
            "proposal_compiled_over_scvx_compiled_paired_median": float(np.median(
                col["compiled"] / col["scvx_compiled"])),
            "proposal_numpy_over_scvx_numpy_paired_median": float(np.median(
                col["numpy"] / col["scvx_numpy"])),
            "same_proposal": f"{same}/{len(rows)}",
            "scvx_same_status_and_iterations": f"{same_path}/{len(rows)}",
            "scvx_cost_difference_mps_max": cost_diff,
            "kernels_ready_cold_s": cold_s, "kernels_ready_cached_s": warm_s}


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
