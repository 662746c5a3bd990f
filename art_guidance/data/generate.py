"""`art-guidance generate`: run the 3-stage dataset pipeline on a process pool or on Ray.

The driver opens (creates or resumes) the dataset directory and runs `dataset.generate_chunk`
over the missing sample indices with `jobs.run_missing` (chunks of `shard_size`, each committed
as one shard). Both engines run the same task function on the same inputs, so they produce the
same data.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.data.stages import KEPT_INFEASIBLE, STAGES, GenerationSpec, generate_chunk
from art_guidance.errors import InputError
from art_guidance.jobs import check_run_options, default_workers, run_missing
from art_guidance.optim import FEASIBLE_STATUSES, ScpStatus
from art_guidance.scenarios import SEED_RULE, SEED_STRIDE
from art_guidance.data.storage import SUMMARY, DatasetWriter, aggregate_stats

_FEASIBLE = [s.value for s in FEASIBLE_STATUSES]


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
