"""`art-guidance generate`: run the 3-stage dataset pipeline on a process pool or on Ray.

The driver opens (creates or resumes) the dataset directory, splits the missing sample indices
into chunks of `shard_size`, hands each chunk to an engine as one task
(`dataset.generate_chunk`), and commits every finished chunk as one shard. Both engines run the
same task function on the same inputs, so they produce the same data. The engines take any
picklable task `task(spec, chunk) -> dict` (`run_chunks`, `commit_results`): the evaluation
driver (`art_guidance.eval.runner`) runs its scenarios on them too.

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
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
from tqdm import tqdm

from art_guidance.config import GuidanceConfig
from art_guidance.data.stages import (
    KEPT_INFEASIBLE, SEED_RULE, SEED_STRIDE, STAGES, GenerationSpec, generate_chunk,
)
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import FEASIBLE_STATUSES, ScpStatus
from art_guidance.data.storage import SUMMARY, DatasetWriter, aggregate_stats

Task = Callable[[Any, list[int]], dict]
Engine = Callable[[Task, Any, list[list[int]], int, str | None], Iterator[dict]]
ENGINES = ("local", "ray")
_PR_SET_PDEATHSIG = 1
_FEASIBLE = [s.value for s in FEASIBLE_STATUSES]


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


def run_missing(writer: DatasetWriter, n: int, task: Task, spec: Any,
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


# --------------------------------------------------------------------------- statistics
def shard_stats(arrays: dict[str, np.ndarray]) -> dict[str, float]:
    """Per-shard counts and time sums stored in the manifest (summed into the summary)."""
    status, kept = arrays["stage_status"], arrays["kept_stage"]
    out: dict[str, float] = {"n": int(kept.size)}
    for k, stage in enumerate(STAGES):
        ok = (status[:, k] == ScpStatus.CONVERGED.value) if k == 0 else \
            np.isin(status[:, k], _FEASIBLE)
        out[f"failed_{stage}"] = int((~ok).sum())
        out[f"time_ms_{stage}"] = float(arrays["stage_time_ms"][:, k].sum())
        out[f"iterations_{stage}"] = int(arrays["stage_iterations"][:, k].sum())
    for value, name in ((3, "passive_safety"), (2, "collision_avoidance"),
                        (KEPT_INFEASIBLE, "infeasible")):
        out[f"kept_{name}"] = int((kept == value).sum())
    return out


def _summary(writer: DatasetWriter, run: list[dict], wall_s: float, engine: str,
             workers: int) -> dict:
    agg = aggregate_stats(writer.shards)
    total = max(int(agg.get("n", 0)), 1)
    head = writer.header
    out = {
        "dir": str(writer.root), "mode": head["mode"], "base_seed": head["base_seed"],
        "n": head["n"], "samples": int(agg.get("n", 0)),
        "complete": int(agg.get("n", 0)) == head["n"],
        "kept": {k: int(agg.get(f"kept_{k}", 0))
                 for k in ("passive_safety", "collision_avoidance", "infeasible")},
        "infeasible_rate": {s: agg.get(f"failed_{s}", 0) / total for s in STAGES},
        "mean_time_ms": {s: agg.get(f"time_ms_{s}", 0.0) / total for s in STAGES},
        "mean_iterations": {s: agg.get(f"iterations_{s}", 0) / total for s in STAGES},
    }
    done = sum(int(r["kept_stage"].size) for r in run)
    this = {"samples": done, "wall_time_s": wall_s, "engine": engine, "workers": workers,
            "trajectories_per_s": done / wall_s if wall_s > 0 else 0.0}
    if run:
        times = np.concatenate([r["stage_time_ms"] for r in run])
        this["median_time_ms"] = {s: float(np.median(times[:, k])) for k, s in enumerate(STAGES)}
    out["this_run"] = this
    return out


def _report(summary: dict, log: Callable[[str], None]) -> None:
    this, kept, rate = summary["this_run"], summary["kept"], summary["infeasible_rate"]
    log(f"generated {this['samples']} trajectories in {this['wall_time_s']:.1f} s "
        f"({this['trajectories_per_s']:.2f} traj/s, {this['engine']} engine, "
        f"{this['workers']} workers)")
    log(f"{summary['dir']}: {summary['samples']} of {summary['n']} samples ({summary['mode']}, "
        f"seed {summary['base_seed']}); kept passive safety {kept['passive_safety']}, "
        f"collision avoidance {kept['collision_avoidance']}, infeasible {kept['infeasible']}")
    log("infeasible rate per stage: " + ", ".join(f"{s} {100 * r:.1f} %"
                                                  for s, r in rate.items()))


# --------------------------------------------------------------------------- driver
def generate(out_dir: str | Path, n: int, mode: str, *, base_seed: int = 0,
             workers: int | None = None, engine: str = "local", shard_size: int = 32,
             config: GuidanceConfig | None = None, ray_address: str | None = None,
             progress: bool = True, log: Callable[[str], None] = print) -> dict:
    """Generate (or resume) a dataset of `n` samples in `out_dir`.

    Args:
        out_dir: dataset directory (created if missing; resumed if it holds this dataset).
        n: number of samples, 1 <= n <= SEED_STRIDE.
        mode: "deterministic" or "chance" (stage-3 passive-safety model).
        base_seed: dataset seed S >= 0; sample i uses scenario seed S * 1_000_003 + i.
        workers: parallel processes / Ray CPUs (default: the CPUs available).
        engine: "local" (process pool) or "ray".
        shard_size: samples per task and per shard.
        config: the configuration bundle (default: the packaged YAML files).
        ray_address: Ray cluster address (engine "ray"); None starts a local instance.
        progress: show a tqdm progress bar (rate, ETA) on stderr.
        log: where the one-line messages go.

    Returns:
        The summary (also written to `out_dir/summary.json` unless nothing was to do), with
        "status": "complete", "already_complete" or "interrupted".

    Raises:
        InputError: bad options, an unwritable or foreign directory, or a directory holding
            a dataset of another mode, seed or size.
        ConfigError: changed configuration on resume, or Ray missing for engine "ray".
        DatasetError: corrupt existing shards or manifest.
    """
    workers = default_workers() if workers is None else workers
    _check_options(n, workers, engine, shard_size)
    spec = GenerationSpec.build(mode, base_seed, config)
    with DatasetWriter(out_dir, spec.header(n)) as writer:
        run: list[dict] = []

        def commit(arrays: dict) -> None:
            writer.write_shard(arrays, shard_stats(arrays))
            run.append({k: arrays[k] for k in ("kept_stage", "stage_time_ms")})

        status, wall, _ = run_missing(
            writer, n, generate_chunk, spec, commit, shard_size=shard_size, workers=workers,
            engine=engine, ray_address=ray_address, unit="traj", desc=f"generate {mode}",
            progress=progress, log=log, where=out_dir)
        if status == "already_complete":
            log(f"{out_dir}: already complete ({n} of {n} samples, {mode}, seed {base_seed});"
                " nothing to do")
            return dict(_summary(writer, [], 0.0, engine, workers), status=status)
        summary = dict(_summary(writer, run, wall, engine, workers), status=status)
        writer.write_json(SUMMARY, summary)
    _report(summary, log)
    if status == "interrupted":
        log("interrupted: re-run the same command to resume")
    return summary


def _check_options(n: int, workers: int, engine: str, shard_size: int) -> None:
    check_run_options({"--n": n, "--workers": workers, "--shard-size": shard_size}, engine)
    if n > SEED_STRIDE:
        raise InputError("--n", f"must be <= {SEED_STRIDE} (seed rule: {SEED_RULE})", n)
