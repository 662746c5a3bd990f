"""The warm-start evaluation driver: held-out scenarios x models, resumable and parallel.

Every model is evaluated on the held-out (test) split of each dataset of its own mode (the
mode of the dataset it was trained on, `art.build_safety`): for every scenario
`warmstart.compare` solves CVX, rolls ART out, applies the post hoc check and runs SCVx* from
both warm starts (PS-CVX-D / PS-ART-D with a deterministic model, PS-CVX-C / PS-ART-C with a
chance-constrained one). The (model, scenario) pairs are numbered 0..M-1 in the order of the
models, then the datasets, then the sample index; chunks of them run on the engines of
`jobs` (`run_missing`: a local process pool or Ray; one worker runs in this process)
and every finished chunk is committed as one shard of the output directory, with the storage
of `data.storage` (atomic shards, JSON-lines manifest, lock). Re-running the same command
resumes and skips the committed pairs; a different command on the same directory is refused.
Each pair's result depends on its inputs alone (1 torch thread per worker), so the worker count
and the chunking change the timings only.

Output directory::

    manifest.jsonl, shard-*.npz   the per-scenario rows (`warmstart.ROW_FIELDS` and the ids)
    summary.json                  per model: `warmstart.summarize`, throughput, checksums
    examples/example-<k>.npz      model k's scenario with the largest ART gain, recomputed
    figures/*.png                 `eval.figures`

The inputs (models, datasets, held-out scenarios) are `eval.inputs`; reading, summarising and
drawing an evaluation directory is `eval.results`.
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.config import GuidanceConfig
from art_guidance.data.storage import MANIFEST, DatasetWriter, read_manifest, sha256_bytes
from art_guidance.errors import InputError
from art_guidance.eval.warmstart import columns, compare
from art_guidance.eval.inputs import (
    FORMAT, KIND, DatasetInfo, ModelInfo, dataset_info, heldout, load_model, model_info,
    problem_of,
)
from art_guidance.eval.results import build_summary, log_run, render, write_summary
from art_guidance.jobs import check_run_options, run_missing
from art_guidance.optim.problem import SubproblemPool
from art_guidance.planning.warm_up import warm_up


THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class EvaluationSpec:
    """Everything a worker needs (picklable). Arrays run over the M (model, scenario) pairs.

    Attributes:
        models: the checkpoints.
        config: SCP, post hoc and planning settings.
        model: (M,) model number of each pair.
        dataset: (M,) dataset number.
        sample: (M,) sample index in that dataset.
        roe0_m: (M, 6) initial a-scaled ROE [m].
        target_rtn: (M, 6) terminal RTN state [m, m/s].
        single_rollout: the paper's single rollout at R(t_1) = -J_CVX instead of the in-flight
            provider's conditioning sweep.
    """

    models: tuple[ModelInfo, ...]
    config: GuidanceConfig
    model: np.ndarray
    dataset: np.ndarray
    sample: np.ndarray
    roe0_m: np.ndarray
    target_rtn: np.ndarray
    single_rollout: bool = False


# --------------------------------------------------------------------------- worker side
def single_thread() -> None:
    """One thread for BLAS/OpenMP libraries started from now on, and for torch where it is
    installed (a flight install evaluates and flies the exported models without it)."""
    from art_guidance.extras import installed

    for var in THREAD_VARS:
        os.environ[var] = "1"
    if installed("torch"):
        import torch

        torch.set_num_threads(1)


def evaluate_chunk(spec: EvaluationSpec, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """The task the engines run: compare the warm starts of the pairs `indices`.

    Returns:
        {field: (K,) array}: the `warmstart.ROW_FIELDS`, the ids (ID_FIELDS), "roe0_m",
        "target_rtn" and "ms_task" (wall time of the pair in the worker [ms]).
    """
    single_thread()
    idx = np.asarray(indices, dtype=np.int64)
    rows, ms = [], []
    pool = SubproblemPool()  # SCVx*'s subproblems, set up once per model's horizon
    warmed: set[int] = set()
    for i in idx:
        provider, safety = load_model(spec.models[spec.model[i]], spec.single_rollout)
        if id(provider) not in warmed:  # one-time costs out of the timed pairs
            warmed.add(id(provider))
            warm_up(provider, problem_of(spec.roe0_m[i], spec.target_rtn[i], safety),
                    spec.config.planning)
        t0 = time.perf_counter()
        problem = problem_of(spec.roe0_m[i], spec.target_rtn[i], safety)
        rows.append(compare(problem, provider, spec.config, pool))
        ms.append(1e3 * (time.perf_counter() - t0))
    return {"index": idx, "model": spec.model[idx], "dataset": spec.dataset[idx],
            "sample": spec.sample[idx], "roe0_m": spec.roe0_m[idx],
            "target_rtn": spec.target_rtn[idx], "ms_task": np.array(ms), **columns(rows)}


# --------------------------------------------------------------------------- inputs
def _pairs(models: Sequence[ModelInfo], datasets: Sequence[DatasetInfo]) -> list[list[int]]:
    """For each model, the datasets of its mode (InputError if there is none)."""
    out = []
    for m in models:
        same = [j for j, d in enumerate(datasets) if d.mode == m.mode]
        if not same:
            given = ", ".join(f"{d.path} ({d.mode})" for d in datasets)
            raise InputError("--model", f"{m.path} was trained on {m.mode} data, and no --data "
                             f"dataset is {m.mode} (given: {given}); add a {m.mode} dataset "
                             "or leave the model out")
        out.append(same)
    return out


def build_spec(models: Sequence[ModelInfo], datasets: Sequence[DatasetInfo], n: int | None,
               config: GuidanceConfig, split: str = "test", single_rollout: bool = False
               ) -> tuple[EvaluationSpec, list[dict]]:
    """Number the (model, held-out scenario) pairs: per model, per dataset of its mode, the
    first `n` held-out scenarios by sample index (all if n is None); `split` "all" takes every
    scenario of datasets none of the models was trained on (refused otherwise).

    Returns:
        The spec and, per dataset, {"n_heldout": held-out scenarios with a CVX solution}.

    Raises:
        InputError: a model without a dataset of its mode, or no held-out scenario at all.
        DatasetError: an incomplete or corrupt dataset.
    """
    pairs = _pairs(models, datasets)
    if split == "all":
        for k, js in enumerate(pairs):
            seen = [datasets[j].path for j in js if models[k].saw(datasets[j])]
            if seen:
                raise InputError("--split", f"{models[k].path} was trained on {seen[0]} or on "
                                 "scenarios of its seed: they are not all held out", split)
    held = {j: heldout(datasets[j].path, split)
            for j in sorted({j for p in pairs for j in p})}
    parts: dict[str, list] = {k: [] for k in ("model", "dataset", "sample", "roe0", "target")}
    for k, js in enumerate(pairs):
        for j in js:
            m = held[j]["index"].size if n is None else min(n, held[j]["index"].size)
            for key, value in (("model", np.full(m, k)), ("dataset", np.full(m, j)),
                               ("sample", held[j]["index"][:m]),
                               ("roe0", held[j]["roe0_m"][:m]),
                               ("target", held[j]["target_rtn"][:m])):
                parts[key].append(value)
    if not sum(p.size for p in parts["model"]):
        raise InputError("--data", "no held-out scenario with a CVX solution to evaluate")
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    spec = EvaluationSpec(tuple(models), config, cat["model"].astype(np.int64),
                          cat["dataset"].astype(np.int64), cat["sample"].astype(np.int64),
                          cat["roe0"].astype(float), cat["target"].astype(float),
                          bool(single_rollout))
    return spec, [{"n_heldout": int(held[j]["index"].size) if j in held else 0}
                  for j in range(len(datasets))]


# --------------------------------------------------------------------------- identity
def header(spec: EvaluationSpec, datasets: Sequence[DatasetInfo], n: int | None,
           split: str = "test") -> dict:
    """The manifest header of an evaluation; "config_sha256" fingerprints what decides the
    results (model and dataset checksums in order, n, the configuration), so a resume with
    another command is refused."""
    identity = {"format": FORMAT, "models": [[m.sha256, m.mode] for m in spec.models],
                "datasets": [d.sha256 for d in datasets], "n": n,
                **({"split": split} if split != "test" else {}),
                **({"single_rollout": True} if spec.single_rollout else {}),
                "guidance_config_sha256": spec.config.sha256()}
    return {"mode": KIND, "base_seed": 0, "n": int(spec.model.size),
            "seed_rule": "pair i: model[i], held-out sample sample[i] of dataset[i]",
            "config_sha256": sha256_bytes(json.dumps(identity, sort_keys=True).encode()),
            "evaluation": {"identity": identity,
                           "models": [m.__dict__ for m in spec.models],
                           "datasets": [d.__dict__ for d in datasets],
                           "config": spec.config.to_json()},
            "art_guidance_version": __version__,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def check_out(out: Path, head: dict) -> None:
    """Refuse an output directory that holds a dataset or another command's evaluation.

    Raises:
        InputError: naming what differs.
    """
    if not (out / MANIFEST).exists():
        return
    stored = read_manifest(out)[0]
    if stored.get("mode") != KIND:
        raise InputError("--out", "holds a dataset, not an evaluation; use another --out",
                         str(out))
    if stored.get("config_sha256") == head["config_sha256"]:
        return
    was = stored.get("evaluation", {}).get("identity", {})
    now = head["evaluation"]["identity"]
    diff = [k for k in now if was.get(k) != now[k]] or ["format"]
    names = {"models": "--model checkpoints", "datasets": "--data datasets", "n": "--n",
             "guidance_config_sha256": "configuration (YAML)", "format": "format"}
    stored_models = [Path(m["path"]).name
                     for m in stored.get("evaluation", {}).get("models", [])]
    raise InputError("--out", "holds an evaluation started by another command (it differs in "
                     f"{', '.join(names[k] for k in diff)}; stored models {stored_models}, "
                     f"n {was.get('n')}). Re-run the command that started it to resume, or "
                     "use a new --out", str(out))


# --------------------------------------------------------------------------- driver
def run_evaluation(out: str | Path, data_dirs: Sequence[str | Path],
                   model_paths: Sequence[str | Path], *, n: int | None = None,
                   workers: int = 1, engine: str = "local", ray_address: str | None = None,
                   shard_size: int = 4, config: GuidanceConfig | None = None,
                   figures: bool = True, progress: bool = True,
                   command: Sequence[str] | None = None, split: str = "test",
                   single_rollout: bool = False, log: Callable[[str], None] = print) -> dict:
    """Evaluate (or resume evaluating) models against CVX on held-out scenarios.

    Args:
        out: output directory (created, or resumed if it holds this evaluation).
        data_dirs: dataset directories (a chance and/or a deterministic one).
        model_paths: checkpoints; each is evaluated on the datasets of its training mode.
        n: at most this many held-out scenarios per (model, dataset) pair (the first by
            sample index); None: all.
        workers: processes (local; 1 runs in this process) or CPUs of a local Ray instance.
        engine: "local" or "ray".
        ray_address: Ray cluster address (engine "ray"); None starts a local instance.
        shard_size: scenarios per task and per committed shard.
        config: SCP and post hoc settings (default: the packaged YAML files).
        figures: write the figures and the recomputed example when complete.
        progress: tqdm progress bar on stderr.
        command: the command line, recorded in the summary.
        split: "test" (each dataset's test split) or "all" (every scenario of datasets the
            models never saw).
        single_rollout: the paper's single rollout instead of the in-flight conditioning sweep.
        log: where the one-line messages go.

    Returns:
        The summary (also OUT/summary.json), "status" "complete", "already_complete" or
        "interrupted".

    Raises:
        InputError: bad options, a model whose mode matches no dataset, an output directory of
            another command or a dataset.
        DatasetError, CheckpointError: corrupt inputs.
    """
    check_run_options({"--workers": workers, "--shard-size": shard_size,
                       **({} if n is None else {"--n": n})}, engine)
    single_thread()
    out = Path(out)
    datasets = [dataset_info(d) for d in data_dirs]
    models = [model_info(p) for p in model_paths]
    spec, held = build_spec(models, datasets, n, config or GuidanceConfig.load(), split,
                            single_rollout)
    head = header(spec, datasets, n, split)
    check_out(out, head)
    with DatasetWriter(out, head) as writer:
        def commit(arrays: dict) -> None:
            writer.write_shard(arrays, {"n": int(arrays["index"].size),
                                        "ms_task": float(arrays["ms_task"].sum())})

        status, wall, done0 = run_missing(
            writer, int(spec.model.size), evaluate_chunk, spec, commit, shard_size=shard_size,
            workers=workers, engine=engine, ray_address=ray_address, unit="scenario",
            desc="evaluate", progress=progress, log=log, where=out, noun="scenarios")
        this = {"command": list(command or sys.argv), "engine": engine, "workers": workers,
                "scenarios": int(len(writer.done_indices) - done0), "wall_s": wall,
                "status": status,
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                             time.gmtime(time.time() - wall))}
        this["scenarios_per_s"] = this["scenarios"] / wall if wall > 0 else None
        summary = build_summary(out, this, held)
        write_summary(out, summary)
    if summary["complete"] and figures:
        summary["figures"] = render(out, summary, recompute=True)
        write_summary(out, summary)
    log_run(summary, log)
    if status == "interrupted":
        log("interrupted: re-run the same command to resume")
    return summary
