"""Closed-loop flights of a benchmark on worker processes: one pool, one progress bar."""
from __future__ import annotations

import importlib
import multiprocessing

from tqdm import tqdm


def fly_all(module: str, jobs: list[tuple], workers: int, desc: str) -> list[dict]:
    """The figures of every job, in order: `module`'s `_fly_job(job)` on `workers` spawned
    processes (the module as they import it: benchmarks/ is on the path), or in this one."""
    fly_job = importlib.import_module(module)._fly_job
    if int(workers) > 1:
        with multiprocessing.get_context("spawn").Pool(int(workers)) as pool:
            return list(tqdm(pool.imap(fly_job, jobs, chunksize=1), total=len(jobs),
                             desc=desc, unit="flight"))
    return [fly_job(j) for j in tqdm(jobs, desc=desc, unit="flight")]
