"""Closed-loop flights of a benchmark on worker processes or a Ray cluster: one progress bar,
the figures in the order of the jobs."""
from __future__ import annotations

import multiprocessing
import os
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from art_guidance.errors import ConfigError, InputError
from art_guidance.jobs import ENGINES

HERE = str(Path(__file__).resolve().parent)


FlyJob = Callable[[tuple], dict]


def fly_all(fly_job: FlyJob, jobs: list[tuple], workers: int, desc: str,
            engine: str = "local", address: str | None = None) -> list[dict]:
    """The figures of every job, in order: `fly_job(job)` (a benchmark module's top-level
    function, pickled by reference) on `workers` spawned processes (which import its module:
    benchmarks/ is on the path), in this one
    (`workers` <= 1), or, with `engine` "ray", as Ray tasks of one CPU each (a local instance
    of `workers` CPUs, or the cluster at `address`; benchmarks/ travels on the tasks'
    PYTHONPATH, so every node needs this checkout at the same path).

    Raises:
        InputError: an unknown engine.
        ConfigError: engine "ray" without Ray installed.
    """
    if engine not in ENGINES:
        raise InputError("--engine", f"must be one of {ENGINES}", engine)
    if engine == "ray":
        return _fly_ray(fly_job, jobs, workers, desc, address)
    if int(workers) > 1:
        with multiprocessing.get_context("spawn").Pool(int(workers)) as pool:
            return list(tqdm(pool.imap(fly_job, jobs, chunksize=1), total=len(jobs),
                             desc=desc, unit="flight"))
    return [fly_job(j) for j in tqdm(jobs, desc=desc, unit="flight")]


def _fly_ray(fly_job: FlyJob, jobs: list[tuple], workers: int, desc: str,
             address: str | None) -> list[dict]:
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("--engine ray needs Ray: pip install 'art_guidance[distributed]'") \
            from exc
    path = os.pathsep.join(p for p in (HERE, os.environ.get("PYTHONPATH", "")) if p)
    started = not ray.is_initialized()
    if started:
        kwargs = {"address": address} if address else {"num_cpus": max(int(workers), 1)}
        ray.init(include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}},
                 **kwargs)
    try:
        remote = ray.remote(num_cpus=1)(fly_job)  # benchmarks/ is on the tasks' PYTHONPATH
        refs = [remote.remote(job) for job in jobs]
        index = {ref: i for i, ref in enumerate(refs)}
        out: list[dict | None] = [None] * len(refs)
        pending = list(refs)
        with tqdm(total=len(refs), desc=desc, unit="flight") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                out[index[done[0]]] = ray.get(done[0])
                bar.update(1)
        return out
    finally:
        if started:
            ray.shutdown()
