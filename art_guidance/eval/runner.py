"""The warm-start evaluation driver: held-out scenarios x models, resumable and parallel.

Every model is evaluated on the held-out (test) split of each dataset of its own mode (the
mode of the dataset it was trained on, `art.build_safety`): for every scenario
`warmstart.compare` solves CVX, rolls ART out, applies the post hoc check and runs SCVx* from
both warm starts (PS-CVX-D / PS-ART-D with a deterministic model, PS-CVX-C / PS-ART-C with a
chance-constrained one). The (model, scenario) pairs are numbered 0..M-1 in the order of the
models, then the datasets, then the sample index; chunks of them run on the engines of
`data.generate` (`run_chunks`: a local process pool or Ray; one worker runs in this process)
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
from art_guidance.config import GuidanceConfig, mode_name
from art_guidance.data.storage import (
    MANIFEST, SUMMARY, DatasetWriter, complete_shards, load_dataset, read_manifest,
    sha256_bytes,
)
from art_guidance.errors import DatasetError, InputError
from art_guidance.eval import example as ex_io
from art_guidance.eval.warmstart import ROW_FIELDS, columns, compare, gains, summarize
from art_guidance.jobs import check_run_options, run_missing

KIND = "evaluation"   # the manifest header's "mode" of an evaluation directory
FORMAT = 1
EXAMPLES = "examples"
FIGURES = "figures"
ID_FIELDS = ("index", "model", "dataset", "sample")
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class ModelInfo:
    """A checkpoint under evaluation.

    Attributes:
        path: checkpoint file.
        sha256: its payload checksum (workers refuse a file that changed since).
        mode: "deterministic" or "chance", the mode of its training data.
        representation: "roe" or "rtn", its state representation.
        train_n: trajectories it was trained on (train + validation share; 0: not recorded).
        n_parameters: its parameter count.
        trained_on: manifest sha256 of each dataset it was trained on.
    """

    path: str
    sha256: str
    mode: str
    representation: str
    train_n: int = 0
    n_parameters: int = 0
    trained_on: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """Short name for figures and logs, e.g. "roe-chance (art.pt)"."""
        return f"{self.representation}-{self.mode} ({Path(self.path).name})"


@dataclass(frozen=True)
class DatasetInfo:
    """A dataset directory whose held-out split is evaluated."""

    path: str
    sha256: str  # of its manifest (which holds every shard's sha256)
    mode: str
    n_samples: int


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
_LOADED: dict[tuple[str, bool], tuple] = {}


def single_thread() -> None:
    """One thread for torch and for BLAS/OpenMP libraries started from now on."""
    import torch

    for var in THREAD_VARS:
        os.environ[var] = "1"
    torch.set_num_threads(1)


def load_model(info: ModelInfo, single_rollout: bool = False) -> tuple:
    """(ArtWarmStart on 1 thread, its PassiveSafety), cached per process; `single_rollout`:
    conditioned on R(t_1) = -J_CVX alone (the paper), else the provider's default sweep."""
    from art_guidance.art.provider import DEFAULT_REWARD_SCALES, ArtWarmStart
    from art_guidance.art.rollout import build_safety

    key = (info.sha256, single_rollout)
    if key not in _LOADED:
        scales = (1.0,) if single_rollout else DEFAULT_REWARD_SCALES
        provider = ArtWarmStart.load(info.path, expected_sha256=info.sha256, threads=1,
                                     reward_scales=scales)
        _LOADED[key] = (provider, build_safety(provider.art))
    return _LOADED[key]


def request_of(roe0_m: np.ndarray, target_rtn: np.ndarray, safety: object) -> object:
    """The plan request from `roe0_m` (6,) [m] to `target_rtn` (6,) [m, m/s] on `safety`'s
    horizon and mode."""
    from art_guidance.planning.types import PlanRequest

    return PlanRequest(safety.horizon.chief_oe[0], roe0_m, target_rtn,
                       chance_constrained=safety.uncertainty is not None)


def evaluate_chunk(spec: EvaluationSpec, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """The task the engines run: compare the warm starts of the pairs `indices`.

    Returns:
        {field: (K,) array}: the `warmstart.ROW_FIELDS`, the ids (ID_FIELDS), "roe0_m",
        "target_rtn" and "ms_task" (wall time of the pair in the worker [ms]).
    """
    single_thread()
    idx = np.asarray(indices, dtype=np.int64)
    rows, ms = [], []
    for i in idx:
        provider, safety = load_model(spec.models[spec.model[i]], spec.single_rollout)
        t0 = time.perf_counter()
        request = request_of(spec.roe0_m[i], spec.target_rtn[i], safety)
        rows.append(compare(request, safety, provider, spec.config))
        ms.append(1e3 * (time.perf_counter() - t0))
    return {"index": idx, "model": spec.model[idx], "dataset": spec.dataset[idx],
            "sample": spec.sample[idx], "roe0_m": spec.roe0_m[idx],
            "target_rtn": spec.target_rtn[idx], "ms_task": np.array(ms), **columns(rows)}


# --------------------------------------------------------------------------- inputs
def dataset_info(path: str | Path) -> DatasetInfo:
    """Mode, size and checksum of a dataset directory (its manifest is read, not the shards).

    Raises:
        DatasetError: not a dataset directory, or a corrupt manifest.
        InputError: an evaluation directory given as a dataset.
    """
    header, _, valid = read_manifest(path)
    if header.get("mode") == KIND:
        raise InputError("--data", "is an evaluation output directory, not a dataset", str(path))
    digest = sha256_bytes((Path(path) / MANIFEST).read_bytes()[:valid])
    return DatasetInfo(str(path), digest, str(header["mode"]), int(header["n"]))


def model_info(path: str | Path) -> ModelInfo:
    """Checksum, mode and representation of a checkpoint (loaded and verified once).

    Raises:
        CheckpointError: missing, corrupt or incompatible file.
    """
    from art_guidance.art.checkpoint import load
    from art_guidance.art.data import trained_manifests
    from art_guidance.art.rollout import build_safety

    art = load(path)
    mode = mode_name(build_safety(art).uncertainty is not None)
    data = (art.meta or {}).get("dataset", {})
    train_n = int(data.get("n_train", 0)) + int(data.get("n_val", 0))
    return ModelInfo(str(path), str(art.sha256), mode, art.config.representation, train_n,
                     art.model.n_parameters(), trained_manifests(art.meta))


def heldout(path: str | Path, split: str = "test") -> dict[str, np.ndarray]:
    """`art.scoring.heldout_scenarios` of a complete dataset, read shard by shard so that only
    the held-out rows of the fields it selects are kept in memory (sorted by sample index).
    `split` "all" takes every scenario (a dataset no model under evaluation was trained on).

    Raises:
        DatasetError: an incomplete or corrupt dataset.
    """
    from art_guidance.art.scoring import heldout_scenarios

    parts = [heldout_scenarios(arrays, split=split) for arrays in complete_shards(path)]
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(cols["index"], kind="stable")
    return {k: v[order] for k, v in cols.items()}


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
            seen = [datasets[j].path for j in js if datasets[j].sha256 in models[k].trained_on]
            if seen:
                raise InputError("--split", f"{models[k].path} was trained on {seen[0]}: its "
                                 "scenarios are not all held out", split)
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


# --------------------------------------------------------------------------- results
def read_results(out: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and the committed rows of an evaluation directory, sorted by pair index.

    Raises:
        DatasetError: not an evaluation directory, or corrupt shards.
    """
    head = read_manifest(out)[0]
    if head.get("mode") != KIND:
        raise DatasetError(f"{out}: holds a dataset, not an evaluation")
    return head, load_dataset(out, require_complete=False)


def model_summaries(head: dict, cols: dict[str, np.ndarray]) -> list[dict]:
    """Per model: what it is, how far the run is, its throughput and `summarize` of its rows."""
    ev = head["evaluation"]
    out = []
    for k, m in enumerate(ev["models"]):
        sel = cols["model"] == k if cols else np.zeros(0, bool)
        rows = {f: v[sel] for f, v in cols.items()}
        worker_s = float(rows["ms_task"].sum()) / 1e3 if cols else 0.0
        info = ModelInfo(**m)
        entry = {"k": k, "label": info.label, "name": Path(info.path).name, **m,
                 "datasets": sorted({int(d) for d in rows.get("dataset", [])}),
                 "n_done": int(sel.sum()), "worker_s": worker_s,
                 "scenarios_per_worker_s": int(sel.sum()) / worker_s if worker_s else None}
        entry.update(summarize(rows) if sel.any() else {"n": 0, "bins": {}})
        out.append(entry)
    return out


def example_index(cols: dict[str, np.ndarray], k: int) -> int | None:
    """Pair index of model k's scenario with the largest J_SCP,CVX - J_SCP,ART (None: none
    with both SCVx* runs converged)."""
    sel = np.flatnonzero(cols["model"] == k) if cols else np.zeros(0, int)
    if not sel.size:
        return None
    gain = gains({f: cols[f][sel] for f in ROW_FIELDS})["gain_mps"]
    if not np.isfinite(gain).any():
        return None
    return int(cols["index"][sel[int(np.nanargmax(gain))]])


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
    _report(summary, log)
    if status == "interrupted":
        log("interrupted: re-run the same command to resume")
    return summary


def build_summary(out: Path, this: dict | None, held: list[dict] | None = None) -> dict:
    """summary.json from the committed rows; `this` (the run's numbers) is appended to the
    runs recorded in an existing summary.json."""
    head, cols = read_results(out)
    previous = _read_summary(out)
    runs = previous.get("runs", []) + ([this] if this else [])
    datasets = head["evaluation"]["datasets"]
    for j, d in enumerate(datasets):
        d = dict(d, **(held[j] if held else previous.get("datasets", [{}] * len(datasets))[j]))
        d["n_evaluated"] = int(np.sum(cols["dataset"] == j)) if cols else 0
        datasets[j] = d
    n_done = int(cols["index"].size) if cols else 0
    _, shards, _ = read_manifest(out)
    return {
        "out": str(out), "kind": KIND, "format": FORMAT, "n_scenarios": head["n"],
        "n_done": n_done, "complete": n_done == head["n"],
        "status": this["status"] if this else previous.get("status", "complete"),
        "this_run": this or previous.get("this_run"), "runs": runs,
        "wall_s_total": float(sum(r.get("wall_s", 0.0) for r in runs)),
        "datasets": datasets, "models": model_summaries(head, cols),
        "sizes": {"shards": len(shards), "bytes": int(sum(e["bytes"] for e in shards))},
        "config_sha256": head["config_sha256"], "art_guidance_version": __version__,
        "definitions": DEFINITIONS, "figures": previous.get("figures", []),
    }


DEFINITIONS = {
    "bins": "cumulative: scenarios with C_CVX(t_1) >= the bin value (paper section V)",
    "subopt_*_mps": "J_SCP - J_CVX over the scenarios where both SCVx* runs converged [m/s]",
    "improvement_ratio": "(J_SCP,CVX - J_SCP,ART) / (J_SCP,CVX - J_CVX): per-scenario mean and "
                         "median (where J_SCP,CVX - J_CVX > 1e-6 m/s), and the ratio of sums",
    "iterations_*": "convex subproblems solved by SCVx* from that warm start",
    "runtime_ms_median": "ws_cvx: CVX solve; ws_art: ART rollout + post hoc check; total_cvx: "
                         "CVX + SCP from CVX; total_art: CVX (J_CVX conditions the rollout) + "
                         "rollout + SCP from ART; measured in the same worker",
    "infeasible_rate_*": "share of scenarios whose SCVx* run did not converge (infeasible, "
                         "solver error or iteration limit)",
    "gain_histogram": "J_SCP,CVX - J_SCP,ART [m/s], both converged; > 0: ART better",
    "gain_histogram_posthoc": "the same for the plan flown with the post hoc check (rejected "
                              "rollout: PS-CVX, difference 0)",
    "posthoc_maps": "cells of (100 E_R [%], E_C): population, mean improvement ratio, mean "
                    "SCP iterations saved by ART",
}


def _read_summary(out: Path) -> dict:
    try:
        data = json.loads((out / SUMMARY).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) and data.get("kind") == KIND else {}


def write_summary(out: str | Path, summary: dict) -> None:
    """Atomically (re)write OUT/summary.json and OUT/report.md."""
    from art_guidance.files import write_atomic

    write_atomic(Path(out) / SUMMARY, json.dumps(summary, indent=1, sort_keys=True).encode())
    write_report(out, summary)


def write_report(out: str | Path, summary: dict) -> None:
    """Atomically (re)write OUT/report.md (`eval.report`: our numbers beside the paper's)."""
    from art_guidance.eval.report import REPORT, report_markdown
    from art_guidance.files import write_atomic

    write_atomic(Path(out) / REPORT, report_markdown(summary).encode())


def rerender(out: str | Path, log: Callable[[str], None] = print) -> dict:
    """Rebuild summary.json and the figures from the stored rows and examples (no solving).

    Raises:
        DatasetError: not an evaluation directory.
    """
    out = Path(out)
    summary = build_summary(out, None)
    summary["figures"] = render(out, summary, recompute=False)
    write_summary(out, summary)
    log(f"{len(summary['figures'])} figures -> {out / FIGURES}")
    return summary


def _report(summary: dict, log: Callable[[str], None]) -> None:
    this = summary["this_run"]
    rate = this.get("scenarios_per_s")
    log(f"evaluated {this['scenarios']} scenarios in {this['wall_s']:.1f} s"
        + (f" ({rate:.3f} scenarios/s, {this['engine']} engine, {this['workers']} workers)"
           if rate else "")
        + f"; {summary['n_done']} of {summary['n_scenarios']} done")
    for m in summary["models"]:
        b = m["bins"].get(">=0")
        if not b:
            continue
        h = m.get("gain_histogram") or {}
        log(f"{m['label']}: {m['n']} scenarios, ART accepted {m['accepted']}, "
            f"J_SCP,CVX - J_SCP,ART [mm/s] min {1e3 * h.get('min_mps', np.nan):.1f} "
            f"median {1e3 * h.get('median_mps', np.nan):.1f} max "
            f"{1e3 * h.get('max_mps', np.nan):.1f}; iterations CVX "
            f"{b['iterations_cvx']['mean']:.1f} ART {b['iterations_art']['mean']:.1f}; "
            f"not converged CVX {100 * b['infeasible_rate_cvx']:.0f} % ART "
            f"{100 * b['infeasible_rate_art']:.0f} %")


def _example(out: Path, head: dict, cols: dict, m: dict, recompute: bool) -> dict | None:
    """Model k's example: stored, or recomputed (and stored) when asked and missing."""
    k = m["k"]
    i = example_index(cols, k)
    if i is None:
        return None
    path = example_path(out, k)
    ex = ex_io.load(path)
    if (ex is None or int(ex["index"]) != i) and recompute:
        info = ModelInfo(**head["evaluation"]["models"][k])
        provider, safety = load_model(info)
        pos = int(np.flatnonzero(cols["index"] == i)[0])
        config = GuidanceConfig.from_json(head["evaluation"]["config"])
        request = request_of(cols["roe0_m"][pos], cols["target_rtn"][pos], safety)
        ex = ex_io.recompute(request, safety, provider, config,
                             {f: cols[f][pos] for f in cols})
        ex_io.save(path, ex, i)
        ex = ex_io.load(path)
    if ex is None or int(ex["index"]) != i:
        return None
    pos = int(np.flatnonzero(cols["index"] == i)[0])
    m["example"] = {"pair_index": i, "dataset": int(cols["dataset"][pos]),
                    "sample": int(cols["sample"][pos]),
                    "gain_mps": float(ex["j_scp_cvx"] - ex["j_scp_art"]),
                    "reproduced": bool(ex["reproduced"]),
                    "file": str(path.relative_to(out))}
    return ex


def render(out: str | Path, summary: dict, recompute: bool = True) -> list[str]:
    """Write every figure of an evaluation directory (`eval.figures`); returns the file names.

    Args:
        out: the evaluation directory (its figures go to `out/figures`).
        summary: its summary (`build_summary`); each model's "example" entry is set.
        recompute: solve the example scenarios that are not stored yet (else skip them).
    """
    from art_guidance.eval.figures import render_model

    out = Path(out)
    head, cols = read_results(out)
    thresholds = head["evaluation"]["config"]["planning"]["posthoc"]
    names = []
    for m in summary["models"]:
        if m.get("n"):
            ex = _example(out, head, cols, m, recompute)
            names += render_model(out / FIGURES, m, thresholds, ex)
    return names


def example_path(out: str | Path, k: int) -> Path:
    """Where model k's recomputed example is stored."""
    return Path(out) / EXAMPLES / f"example-{k}.npz"
