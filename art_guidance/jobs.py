"""Run a picklable task over chunks of indices on a local process pool or Ray, resumably.

The general job runner of every long command: `generate` (dataset samples), `evaluate` (the
warm-start analysis), `dagger` (expert re-solves) and `bench contingency` (closed-loop flights).
A task is a module-level function `task(spec, chunk) -> dict` of arrays with an "index" entry;
`run_missing` hands the indices a `DatasetWriter` does not hold yet to an engine and commits
every finished chunk as one shard, so an interrupted run resumes where it stopped.

- local: a process pool of `workers` processes (forked where available; each worker dies with
  the driver) or, with one worker, the driver process itself;
- ray: Ray tasks (`pip install .[distributed]`), on a local Ray instance of `workers` CPUs, on
  the instance the caller already initialised, or on the cluster at `ray_address`.
"""
from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np
from tqdm import tqdm

from art_guidance.errors import ConfigError, InputError

if TYPE_CHECKING:  # the writer's type only; storage does not need the runner
    from art_guidance.data.storage import DatasetWriter

Task = Callable[[Any, list[int]], dict]
Engine = Callable[[Task, Any, list[list[int]], int, str | None], Iterator[dict]]
ENGINES = ("local", "ray")
_PR_SET_PDEATHSIG = 1


def default_workers() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


# --------------------------------------------------------------------------- local engine
def _worker_init(parent_pid: int) -> None:
    """Pool worker set-up: die with the driver (even on SIGKILL), leave Ctrl-C to it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the driver died before prctl took effect
        os._exit(1)


def _local_engine(task: Task, spec: Any, chunks: list[list[int]], workers: int,
                  address: str | None = None) -> Iterator[dict]:
    """Run the chunks on `workers` processes (in this process when workers == 1)."""
    if workers == 1 or len(chunks) == 1:
        return (task(spec, c) for c in chunks)
    methods = mp.get_all_start_methods()
    ctx = mp.get_context("fork" if "fork" in methods else "spawn")
    pool = ProcessPoolExecutor(min(workers, len(chunks)), mp_context=ctx,
                               initializer=_worker_init, initargs=(os.getpid(),))
    futures = [pool.submit(task, spec, c) for c in chunks]  # workers start here
    return _drain_pool(pool, futures)


def _drain_pool(pool: ProcessPoolExecutor, futures: list[Future]) -> Iterator[dict]:
    finished = False
    try:
        for fut in as_completed(futures):
            yield fut.result()
        finished = True
    finally:
        if not finished:  # interrupted or failed: stop the workers now
            for fut in futures:
                fut.cancel()
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
        pool.shutdown(wait=True, cancel_futures=True)


# --------------------------------------------------------------------------- ray engine
def _ray_engine(task: Task, spec: Any, chunks: list[list[int]], workers: int,
                address: str | None = None) -> Iterator[dict]:
    """Run the chunks as Ray tasks of one CPU each."""
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("--engine ray needs Ray: pip install 'art_guidance[distributed]' "
                          "(or use --engine local)") from exc
    started = not ray.is_initialized()
    if started:
        kwargs = {"address": address} if address else {"num_cpus": workers}
        ray.init(include_dashboard=False, log_to_driver=False, **kwargs)
    remote = ray.remote(num_cpus=1)(task)
    spec_ref = ray.put(spec)
    pending = [remote.remote(spec_ref, c) for c in chunks]
    return _drain_ray(ray, pending, started)


def _drain_ray(ray, pending: list, started: bool) -> Iterator[dict]:
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


_ENGINES: dict[str, Engine] = {"local": _local_engine, "ray": _ray_engine}


def run_chunks(task: Task, spec: Any, chunks: list[list[int]], workers: int,
               engine: str = "local", address: str | None = None) -> Iterator[dict]:
    """Run `task(spec, chunk)` for every chunk on an engine; results in completion order.

    Args:
        task: a picklable module-level function (it runs in worker processes or Ray tasks).
        spec: its first argument, identical for every chunk (sent once per worker).
        chunks: the second arguments.
        workers: processes (local; 1 runs in this process) or CPUs of a local Ray instance.
        engine: "local" or "ray".
        address: Ray cluster address (engine "ray"); None starts a local instance.

    Returns:
        An iterator of the task results; closing it stops the workers.

    Raises:
        ConfigError: engine "ray" without Ray installed.
    """
    return _ENGINES[engine](task, spec, chunks, workers, address)


def progress_bar(total: int, initial: int, unit: str, desc: str, enabled: bool) -> tqdm:
    """The drivers' tqdm bar on stderr (rate, ETA)."""
    return tqdm(total=total, initial=initial, unit=unit, desc=desc, disable=not enabled,
                smoothing=0.05, dynamic_ncols=True)


def commit_results(results: Iterator[dict], commit: Callable[[dict], None],
                   bar: tqdm | None = None) -> str:
    """Pass every finished result to `commit` as it arrives (and advance `bar` by its
    "index" size).

    Returns:
        "complete", or "interrupted" on Ctrl-C (the engine is closed, so the workers stop;
        what was committed stays committed).
    """
    try:
        for result in results:
            commit(result)
            if bar is not None:
                bar.update(int(result["index"].size))
    except KeyboardInterrupt:
        results.close()
        return "interrupted"
    return "complete"


def run_missing(writer: "DatasetWriter", n: int, task: Task, spec: Any,
                commit: Callable[[dict], None], *, shard_size: int, workers: int, engine: str,
                ray_address: str | None, unit: str, desc: str, progress: bool,
                log: Callable[[str], None], where: object, noun: str = "samples"
                ) -> tuple[str, float, int]:
    """Run `task` over the indices 0..n-1 that `writer` does not hold yet and `commit` each
    finished chunk (the resumable core of `generate`, the evaluation and DAgger drivers).

    Chunks of `shard_size` indices run on the engine; a progress bar counts `unit`s; a resumed
    run says how many `noun` were present in `where` (the output as the caller names it).

    Returns:
        (status, wall time [s], indices present before): status "complete", "interrupted"
        (Ctrl-C; what was committed stays), or "already_complete" when nothing was missing
        (then nothing ran).
    """
    done = int(writer.done_indices.size)
    todo = np.setdiff1d(np.arange(n), writer.done_indices)
    if todo.size == 0:
        return "already_complete", 0.0, done
    if done:
        log(f"resuming {where}: {done} of {n} {noun} present, {todo.size} to go")
    chunks = [todo[i:i + shard_size].tolist() for i in range(0, todo.size, shard_size)]
    t0 = time.perf_counter()
    results = run_chunks(task, spec, chunks, workers, engine, ray_address)
    with progress_bar(n, done, unit, desc, progress) as bar:
        status = commit_results(results, commit, bar)
    return status, time.perf_counter() - t0, done


def check_run_options(counts: dict[str, object], engine: str) -> None:
    """Raise InputError unless every count ({option: value}) is an integer >= 1 and the
    engine is one of ENGINES."""
    for name, value in counts.items():
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(name, "must be an integer >= 1", value)
    if engine not in ENGINES:
        raise InputError("--engine", f"must be one of {ENGINES}", engine)
