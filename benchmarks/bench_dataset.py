"""Benchmark: chance-constrained dataset generation with 2 local worker processes.

Generates `repeats` samples (seeds 0..repeats-1 of base seed 0) into a temporary directory
with the full 3-stage pipeline and the sharded storage (fsync included), and reports the
end-to-end throughput, the per-stage median solve times and the per-stage infeasible rates.
The 1-minute load average before the run is reported too: other processes on the machine
lower the throughput.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from art_guidance.data.stages import STAGES
from art_guidance.data.generate import generate
from art_guidance.optim import FEASIBLE_STATUSES, ScpStatus
from art_guidance.data.storage import load_dataset

WORKERS = 2


def run(repeats: int = 40) -> dict:
    """Generate `repeats` chance-constrained trajectories on 2 workers; throughput and stages."""
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench_dataset_") as tmp:
        summary = generate(tmp, repeats, "chance", base_seed=0, workers=WORKERS,
                           engine="local", shard_size=2, log=lambda _: None)
        data = load_dataset(tmp)
    status, times = data["stage_status"], data["stage_time_ms"]
    feasible = [s.value for s in FEASIBLE_STATUSES]
    out = {
        "samples": repeats,
        "workers": WORKERS,
        "trajectories_per_s": summary["this_run"]["trajectories_per_s"],
        "wall_time_s": summary["this_run"]["wall_time_s"],
        "load_average_1min_before": load_before,
    }
    for k, stage in enumerate(STAGES):
        out[f"{stage}_median_ms"] = float(np.median(times[:, k]))
    for k, stage in enumerate(STAGES):
        ok = np.isin(status[:, k], (ScpStatus.CONVERGED.value,) if k == 0 else feasible)
        out[f"{stage}_infeasible_rate"] = float(1.0 - ok.mean())
    out["passive_safety_median_iterations"] = float(np.median(data["stage_iterations"][:, 2]))
    out["kept_passive_safety_fraction"] = float(np.mean(data["kept_stage"] == 3))
    out["kept_collision_avoidance_fraction"] = float(np.mean(data["kept_stage"] == 2))
    out["infeasible_sample_fraction"] = float(np.mean(~data["feasible"]))
    return out


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
