"""DAgger-style data aggregation for ART (`art-guidance dagger`), as in transformer-MPC DAgger.

A trained model is rolled out on the scenarios of a source dataset SRC; at a random node k of
each rollout the expert (the 3-stage pipeline of `art_guidance.data.stages`) is asked what to
do from the state the model actually reached, and the answer becomes a training row. Training
on SRC plus these rows teaches the model to recover from its own mistakes.

Sample i of a DAgger dataset of n samples:

1. scenario: the (i mod P)-th of the P feasible train-split scenarios of SRC whose CVX solve
   succeeded, by sample index (SRC's test split is never read);
2. rollout: the model from the scenario's initial state, conditioned on R(t_1) = -J_CVX and
   C(t_1) = 0 with the target as goal (as `art_guidance.eval.scoring`), on the horizon and
   passive-safety model of its training data (`rollout.build_safety`); the rollouts of the
   samples g B .. g B + B - 1 (B = `batch`) run as one batch, whatever the chunking;
3. node k = 1 + default_rng(SeedSequence([seed, DAGGER_STREAM, i])).integers(N - 3), in
   1 .. N - 3;
4. expert: the three stages (`stages.solve_stages`: CVX, collision avoidance with T_safety = 0,
   the mode's passive safety) from the rollout's pre-burn state x_k to the same target over the
   remaining horizon: `Horizon.build(chief_oe[k], epochs_s[k:] - epochs_s[k])`, whose keep-out
   zone starts at node max(0, ae_to_koz_node - k);
5. row: nodes 0 .. k - 1 hold the rollout's states and controls (what the model visited),
   nodes k .. N - 1 the expert's re-solved trajectory; R(t_i) = -sum_{j >= i} ||dv_j||, C and
   the margins come from the full-horizon safety model's `evaluate` of the stitched row, and
   `train_from` = k is the first node whose control is an expert label (training keeps the
   nodes before it out of the loss: `art.data.valid_mask`). A row whose sub-solve keeps no
   stage is stored infeasible (NaN trajectory, kept_stage 0), which training skips.

The output directory is a dataset directory (`data.storage`) of SRC's mode and configuration
fingerprint, with no test split, so `art-guidance train --data SRC --data DAGGER` trains on
both; its header records the model's and SRC's manifest sha256, the seed and B. Every row
depends on (model, SRC, seed, B, n, i) alone, so the engines, the worker count and the chunking
give identical data (timings aside), and a killed run resumes like `art-guidance generate`.
The rollouts run inside the worker tasks (each worker loads the model once, one torch thread);
the expert re-solves dominate the cost.
The worker side (rollouts, expert re-solves, rows) is `data.dagger_worker`, the directory's
fields, inputs and identity `data.dagger_format`; this module drives a run.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from art_guidance.data.dagger_format import (  # noqa: F401 (FIELDS, SEED_RULE ... imported here)
    FIELDS, FORMAT, SCENARIO_FIELDS, SEED_RULE, check_model as _check_model, check_resume,
    manifest_header, scenario_pool, source_generation,
)
from art_guidance.data.dagger_worker import (  # noqa: F401 (DAGGER_STREAM ... imported here)
    DAGGER_STREAM, ROW_FIELDS, DaggerSpec, dagger_chunk, dagger_node, expert_from,
)
from art_guidance.data.generate import shard_stats
from art_guidance.data.stages import STAGES
from art_guidance.data.storage import SUMMARY, DatasetWriter, aggregate_stats, read_manifest
from art_guidance.errors import InputError
from art_guidance.jobs import check_run_options, default_workers, run_missing

_ROLLOUT_FIELDS = ("roe0_m", "target_rtn", "roe_f_m", "cvx_cost_mps")


def dagger(out_dir: str | Path, model: str | Path, src: str | Path, n: int, *, seed: int = 0,
           workers: int | None = None, engine: str = "local", shard_size: int = 32,
           batch: int = 32, ray_address: str | None = None, progress: bool = True,
           log: Callable[[str], None] = print) -> dict:
    """Generate (or resume) `n` DAgger samples of `model` on SRC's scenarios in `out_dir`.

    Args:
        out_dir: output dataset directory (created if missing; resumed if it holds this run).
        model: checkpoint to roll out (trained on data of SRC's mode and configuration).
        src: source dataset directory (complete); its train split gives the scenarios.
        n: number of DAgger samples, >= 1 (the scenarios are cycled through if n > P).
        seed: seeds the node draws (>= 0).
        workers: parallel processes / Ray CPUs (default: the CPUs available).
        engine: "local" (process pool) or "ray".
        shard_size: samples per task and per shard (best a multiple of `batch`).
        batch: rollouts per batch (part of the data's identity: a resume must keep it).
        ray_address: Ray cluster address (engine "ray"); None starts a local instance.
        progress: show a tqdm progress bar (rate, ETA) on stderr.
        log: where the one-line messages go.

    Returns:
        The summary (also written to `out_dir/summary.json` unless nothing was to do), with
        "status": "complete", "already_complete" or "interrupted".

    Raises:
        InputError: bad options, a model of another mode or configuration, an SRC without
            usable scenarios, or an --out holding other data.
        ConfigError: SRC made by another pipeline version; Ray missing for engine "ray".
        DatasetError: a corrupt or incomplete SRC, corrupt existing shards.
        CheckpointError: an unreadable or corrupt model.
    """
    from art_guidance.art.checkpoint import load
    from art_guidance.art.data import manifest_digest

    workers = default_workers() if workers is None else workers
    check_run_options({"--n": n, "--workers": workers, "--shard-size": shard_size,
                       "--batch": batch}, engine)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) \
            or not 0 <= seed < 2**63:
        raise InputError("--seed", "must be an integer in [0, 2^63)", seed)
    if Path(out_dir).resolve() == Path(src).resolve():
        raise InputError("--out", "must not be the source dataset --data", str(out_dir))
    src_header, _, _ = read_manifest(src)
    generation = source_generation(src, src_header)
    art = load(model)
    _check_model(art, generation, str(model))
    pool = scenario_pool(src, n)
    spec = DaggerSpec(generation, str(model), str(art.sha256), int(seed), int(n), int(batch),
                      {k: pool[k] for k in _ROLLOUT_FIELDS})
    del art
    header = manifest_header(spec, src, src_header, manifest_digest(str(src)),
                             int(pool["pool_size"]))
    with DatasetWriter(out_dir, header) as writer:
        check_resume(writer.root, writer.header, header)
        run: list[dict] = []

        def commit(rows: dict) -> None:
            arrays = _complete(rows, pool, spec.n_scenarios)
            writer.write_shard(arrays, dict(shard_stats(arrays), train_from_sum=int(
                arrays["train_from"].sum())))
            run.append({k: arrays[k] for k in ("kept_stage", "stage_time_ms")})

        status, wall, _ = run_missing(
            writer, n, dagger_chunk, spec, commit, shard_size=shard_size, workers=workers,
            engine=engine, ray_address=ray_address, unit="traj", desc="dagger",
            progress=progress, log=log, where=out_dir)
        if status == "already_complete":
            log(f"{out_dir}: already complete ({n} of {n} DAgger samples); nothing to do")
            return dict(_summary(writer, [], 0.0, engine, workers), status=status)
        summary = dict(_summary(writer, run, wall, engine, workers), status=status)
        writer.write_json(SUMMARY, summary)
    _report(summary, log)
    if status == "interrupted":
        log("interrupted: re-run the same command to resume")
    return summary


def _complete(rows: dict[str, np.ndarray], pool: dict[str, np.ndarray],
              n_scenarios: int) -> dict[str, np.ndarray]:
    """A worker's rows with the scenario fields of SRC added, in FIELDS order."""
    pos = rows["index"] % n_scenarios
    scenario = {k: pool[k][pos] for k in (*SCENARIO_FIELDS, "src_index")}
    return {k: rows[k] if k in rows else scenario[k] for k in FIELDS}


def _summary(writer: DatasetWriter, run: list[dict], wall_s: float, engine: str,
             workers: int) -> dict:
    agg = aggregate_stats(writer.shards)
    count = int(agg.get("n", 0))
    total = max(count, 1)
    head = writer.header
    out = {
        "dir": str(writer.root), "mode": head["mode"], "n": head["n"], "samples": count,
        "complete": count == head["n"], "dagger": head["dagger"],
        "kept": {k: int(agg.get(f"kept_{k}", 0))
                 for k in ("passive_safety", "collision_avoidance", "infeasible")},
        "infeasible_rate": {s: agg.get(f"failed_{s}", 0) / total for s in STAGES},
        "mean_time_ms": {s: agg.get(f"time_ms_{s}", 0.0) / total for s in STAGES},
        "mean_train_from": agg.get("train_from_sum", 0) / total,
    }
    done = sum(int(r["kept_stage"].size) for r in run)
    out["this_run"] = {"samples": done, "wall_time_s": wall_s, "engine": engine,
                       "workers": workers,
                       "samples_per_s": done / wall_s if wall_s > 0 else 0.0}
    return out


def _report(summary: dict, log: Callable[[str], None]) -> None:
    this, kept = summary["this_run"], summary["kept"]
    log(f"made {this['samples']} DAgger samples in {this['wall_time_s']:.1f} s "
        f"({this['samples_per_s']:.2f} samples/s, {this['engine']} engine, "
        f"{this['workers']} workers)")
    log(f"{summary['dir']}: {summary['samples']} of {summary['n']} samples ({summary['mode']});"
        f" expert kept passive safety {kept['passive_safety']}, collision avoidance "
        f"{kept['collision_avoidance']}, infeasible {kept['infeasible']}; mean takeover node "
        f"{summary['mean_train_from']:.1f}")
