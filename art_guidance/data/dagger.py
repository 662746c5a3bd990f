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
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.config import MODES, GuidanceConfig
from art_guidance.data import stages as _stages
from art_guidance.data.generate import shard_stats
from art_guidance.jobs import check_run_options, default_workers, run_missing
from art_guidance.data.stages import (
    KEPT_INFEASIBLE, STAGES, GenerationSpec, Stage, infeasible_trajectory_fields,
    solve_stages, stage_fields, trajectory_fields,
)
from art_guidance.data.storage import (
    SUMMARY, DatasetWriter, aggregate_stats, complete_shards, read_manifest,
)
from art_guidance.dynamics import Horizon
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus
from art_guidance.safety import PassiveSafety

DAGGER_STREAM = 0xDA66  # second SeedSequence word of the node draw
SEED_RULE = ("scenario of sample i: pool[i mod P], pool = SRC's feasible train-split samples "
             "with a CVX solution, by index; node k_i = 1 + default_rng(SeedSequence([seed, "
             f"{DAGGER_STREAM:#x}, i])).integers(N - 3)")
FORMAT = 1

# Stored per sample; the generator's FIELDS with these meanings, plus train_from and src_index.
FIELDS = dict(_stages.FIELDS)
FIELDS.update({
    "index": "() int64, DAgger sample index i in 0..n-1",
    "seed": "() int64, scenario seed of the SRC sample (SRC's seed rule)",
    "kept_stage": "() int8, stage of the expert's re-solve from node train_from: 3 passive "
                  "safety, 2 collision avoidance, 0 none feasible",
    "roe_m": "(N, 6) pre-burn a-scaled ROE [m]: the rollout's before train_from, the expert's "
             "from it",
    "dv_rtn_mps": "(N, 3) impulsive delta-v in RTN [m/s]: the rollout's before train_from, "
                  "the expert's from it",
    "constraint_to_go": "(N,) int32, C(t_i) of the stitched row under the mode's full-horizon "
                        "passive-safety model",
    "margin_m": "(N,) passive-safety margin of the stitched row under the mode's full-horizon "
                "model [m], >= 0 safe",
    "cvx_roe_m": "(N, 6) CVX (stage 1) pre-burn ROE of the SRC scenario [m]",
    "cvx_dv_rtn_mps": "(N, 3) CVX delta-v of the SRC scenario in RTN [m/s]",
    "cvx_cost_mps": "() CVX cost of the SRC scenario, the rollout's -R(t_1) [m/s]",
    "cvx_constraint_to_go0": "() int32, C_CVX(t_1) of the SRC scenario",
    "stage_status": "(3,) int8, ScpStatus value per stage of the re-solve (cvx, ca, ps)",
    "stage_iterations": "(3,) int32, convex subproblems solved per stage of the re-solve",
    "stage_cost_mps": "(3,) cost of each re-solve stage over nodes train_from..N-1 [m/s]",
    "stage_time_ms": "(3,) wall time per re-solve stage [ms] (not reproducible)",
    "train_from": "() int64, k in 1..N-3: first node whose control is an expert label (the "
                  "nodes before it are context only)",
    "src_index": "() int64, sample index of the scenario in SRC",
})
# What a worker returns; the driver adds the scenario's fields from SRC (SCENARIO_FIELDS).
ROW_FIELDS = ("index", "train_from", "kept_stage", "feasible", "roe_m", "rtn", "dv_rtn_mps",
              "cost_mps", "reward_to_go_mps", "constraint_to_go", "margin_m", "stage_status",
              "stage_iterations", "stage_cost_mps", "stage_time_ms")
SCENARIO_FIELDS = ("seed", "waypoint", "rtn0", "target_rtn", "roe0_m", "roe_f_m", "cvx_roe_m",
                   "cvx_dv_rtn_mps", "cvx_cost_mps", "cvx_constraint_to_go0")
_ROLLOUT_FIELDS = ("roe0_m", "target_rtn", "roe_f_m", "cvx_cost_mps")


def dagger_node(seed: int, index: int, n_nodes: int) -> int:
    """Node k in 1 .. n_nodes - 3 where the expert takes over in sample `index` (SEED_RULE)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), DAGGER_STREAM, int(index)]))
    return 1 + int(rng.integers(int(n_nodes) - 3))


@dataclass(frozen=True)
class DaggerSpec:
    """Everything a worker needs (picklable, identical for every chunk).

    Attributes:
        generation: SRC's mode and configuration (the expert's SCP and scenario settings).
        model_path: the checkpoint rolled out.
        model_sha256: its payload sha256 (workers refuse a file that changed since).
        seed: seeds the node draws.
        n: number of DAgger samples.
        batch: B, rollouts per batch (samples g B .. g B + B - 1 together).
        scenarios: the P' = min(n, P) pool scenarios used, in pool order: "roe0_m" (P', 6)
            initial ROE [m], "target_rtn" (P', 6) [m, m/s], "roe_f_m" (P', 6) terminal
            post-burn ROE [m], "cvx_cost_mps" (P',) J_CVX [m/s].
    """

    generation: GenerationSpec
    model_path: str
    model_sha256: str
    seed: int
    n: int
    batch: int
    scenarios: dict

    @property
    def n_scenarios(self) -> int:
        """P', the scenarios cycled through."""
        return int(self.scenarios["cvx_cost_mps"].size)


# --------------------------------------------------------------------------- worker side
_LOADED: dict[str, tuple] = {}


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """One torch thread while a task runs (results must not depend on the thread count)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _load(spec: DaggerSpec) -> tuple:
    """(TrainedArt on the CPU, its full-horizon PassiveSafety), cached per process."""
    from art_guidance.art.checkpoint import load
    from art_guidance.art.rollout import build_safety

    if spec.model_sha256 not in _LOADED:
        _LOADED.clear()
        art = load(spec.model_path, "cpu", expected_sha256=spec.model_sha256)
        _LOADED[spec.model_sha256] = (art, build_safety(art))
    return _LOADED[spec.model_sha256]


def _rollouts(spec: DaggerSpec, art: object, safety: PassiveSafety,
              indices: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{i: (roe (N, 6) [m], dv (N, 3) [m/s])} of the rollouts of samples `indices`.

    Every batch is a whole group g B .. g B + B - 1 (clipped to n), so a sample's rollout is
    computed on the same batch whichever chunk asks for it.
    """
    from art_guidance.art.rollout import rollout

    sc, wanted, out = spec.scenarios, set(indices.tolist()), {}
    for g in sorted({int(i) // spec.batch for i in indices}):
        members = np.arange(g * spec.batch, min((g + 1) * spec.batch, spec.n))
        s = members % spec.n_scenarios
        res = rollout(art, safety, sc["roe0_m"][s], sc["target_rtn"][s],
                      -sc["cvx_cost_mps"][s], 0.0)
        for j, i in enumerate(members.tolist()):
            if i in wanted:
                out[i] = (res.roe_m[j], res.dv_rtn_mps[j])
    return out


def expert_from(spec: GenerationSpec, horizon: Horizon, k: int, roe_k_m: np.ndarray,
                roe_f_m: np.ndarray) -> tuple[tuple[Stage, Stage, Stage], int]:
    """The 3-stage expert from node `k` of `horizon` over the remaining nodes k .. N - 1.

    Args:
        spec: mode and configuration (scenario, uncertainty, SCP settings).
        horizon: the full N-node horizon.
        k: first node of the re-solve, 0 <= k <= N - 2.
        roe_k_m: (6,) pre-burn a-scaled ROE at node k [m].
        roe_f_m: (6,) terminal post-burn a-scaled ROE [m].

    Returns:
        `stages.solve_stages` on the sub-horizon of N - k nodes (stage trajectories over it)
        and the kept stage.
    """
    sub = Horizon.build(horizon.chief_oe[k], horizon.epochs_s[k:] - horizon.epochs_s[k])
    switch = max(0, spec.scenario.ae_to_koz_node - k)
    collision = PassiveSafety(sub, spec.scenario, None, t_safety_s=0.0, koz_switch_node=switch)
    passive = PassiveSafety(sub, spec.scenario, spec.uncertainty, koz_switch_node=switch)
    return solve_stages(spec, collision, passive, roe_k_m, roe_f_m)


def _row(spec: DaggerSpec, safety: PassiveSafety, index: int, roe_roll: np.ndarray,
         dv_roll: np.ndarray) -> dict[str, np.ndarray]:
    """The ROW_FIELDS of sample `index` from its rollout (roe (N, 6) [m], dv (N, 3) [m/s])."""
    horizon = safety.horizon
    n = horizon.n_nodes
    k = dagger_node(spec.seed, index, n)
    x_k = roe_roll[k]
    roe_f = spec.scenarios["roe_f_m"][index % spec.n_scenarios]
    if np.all(np.isfinite(x_k)):
        stages, kept = expert_from(spec.generation, horizon, k, x_k, roe_f)
    else:  # a diverged rollout: nothing to re-solve from
        failed = Stage(ScpStatus.SOLVER_ERROR, None, None, np.nan, 0, 0.0)
        stages, kept = (failed, failed, failed), KEPT_INFEASIBLE
    rec = {"index": np.int64(index), "train_from": np.int64(k), "kept_stage": np.int8(kept),
           "feasible": np.bool_(kept != KEPT_INFEASIBLE), **stage_fields(stages)}
    if kept:
        expert = stages[kept - 1]
        roe = np.concatenate([roe_roll[:k], expert.roe_m])  # (N, 6)
        dv = np.concatenate([dv_roll[:k], expert.dv_rtn_mps])  # (N, 3)
        cost = float(np.linalg.norm(dv, axis=1).sum())
        rec.update(trajectory_fields(horizon, safety, roe, dv, cost))
    else:
        rec.update(infeasible_trajectory_fields(n))
    return rec


def dagger_chunk(spec: DaggerSpec, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """The task both engines run: roll out and re-solve the DAgger samples `indices`.

    Args:
        spec: the run (model, scenarios, seed, batch).
        indices: DAgger sample indices (a shard's worth).

    Returns:
        {field: (M, ...) array} with the ROW_FIELDS of every sample, in the order of
        `indices` (the driver adds the SCENARIO_FIELDS and "src_index").
    """
    idx = np.asarray(indices, dtype=np.int64)
    with _one_thread():
        art, safety = _load(spec)
        rolled = _rollouts(spec, art, safety, idx)
        rows = [_row(spec, safety, int(i), *rolled[int(i)]) for i in idx]
    return {k: np.stack([r[k] for r in rows]) for k in ROW_FIELDS}


# --------------------------------------------------------------------------- inputs
def scenario_pool(src: str | Path, n: int) -> dict[str, np.ndarray]:
    """The first min(n, P) scenarios of SRC's pool (feasible, train split, CVX solved), read
    shard by shard (only their SCENARIO_FIELDS are kept), in sample-index order.

    Returns:
        {"src_index": (P',), SCENARIO_FIELDS...} and "pool_size": () P.

    Raises:
        DatasetError: an incomplete or corrupt SRC.
        InputError: SRC has no usable scenario.
    """
    parts = []
    for a in complete_shards(src):
        cost = a["cvx_cost_mps"]
        keep = (a["feasible"] & ~a["is_test"] & (a["cvx_constraint_to_go0"] >= 0)
                & np.isfinite(cost) & (np.nan_to_num(cost) > 0))
        parts.append({"src_index": a["index"][keep],
                      **{k: a[k][keep] for k in SCENARIO_FIELDS}})
    pool = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    size = int(pool["src_index"].size) if pool else 0
    if size == 0:
        raise InputError("--data", "holds no feasible train-split scenario with a CVX solution",
                         str(src))
    used = np.argsort(pool["src_index"], kind="stable")[:min(int(n), size)]
    return dict({k: v[used] for k, v in pool.items()}, pool_size=np.int64(size))


def _check_model(art: object, generation: GenerationSpec, model: str) -> None:
    """Refuse a model trained on data of another mode or configuration than SRC's."""
    from art_guidance.art.rollout import training_config

    data = art.meta.get("dataset", {}) if isinstance(art.meta, dict) else {}
    config = training_config(art)
    if config is None or data.get("mode") not in MODES:
        raise InputError("--model", "records no training data mode and configuration; "
                         "DAgger needs a model trained with `art-guidance train`", model)
    trained = GenerationSpec.build(data["mode"], 0, config).config_sha256
    # the same rule as `train --init`: the planning choices only flight uses may differ (a
    # model's bundle written before such an option existed records none of it)
    diff = config.data_differences(generation.config)
    if data["mode"] != generation.mode or diff:
        raise InputError("--model", f"was trained on {data['mode']} data of config "
                         f"{trained[:12]}; --data is {generation.mode} data of config "
                         f"{generation.config_sha256[:12]} (differing: "
                         f"{', '.join(diff) or 'mode'}): roll out a model of SRC's kind",
                         model)
    if art.config.context < generation.scenario.n_nodes:
        raise InputError("--model", f"context K = {art.config.context} is shorter than the "
                         f"{generation.scenario.n_nodes}-node horizon", model)


def _generation(src: str | Path, header: dict) -> GenerationSpec:
    """SRC's mode and configuration, checked against what this code would generate."""
    if "dagger" in header:
        raise InputError("--data", "is a DAgger dataset; pass the dataset its scenarios come "
                         f"from ({header['dagger'].get('src_dir')})", str(src))
    bundle = header.get("config", {}).get("guidance_config")
    if bundle is None or header.get("mode") not in MODES:
        raise InputError("--data", "is not a dataset of `art-guidance generate` (no mode or "
                         "configuration bundle in its header)", str(src))
    spec = GenerationSpec.build(header["mode"], 0, GuidanceConfig.from_json(bundle))
    if spec.scenario.n_nodes < 4:
        raise InputError("--data", "needs a horizon of at least 4 nodes (takeover nodes "
                         "1..N-3)", spec.scenario.n_nodes)
    if spec.config_sha256 != header.get("config_sha256"):
        raise ConfigError(f"{src}: its configuration fingerprint "
                          f"{str(header.get('config_sha256'))[:12]} differs from this code's "
                          f"{spec.config_sha256[:12]} for the same configuration (another "
                          "pipeline version): the expert would label with another pipeline; "
                          "regenerate SRC")
    return spec


def _header(spec: DaggerSpec, src: str | Path, src_header: dict, src_digest: str,
            pool_size: int) -> dict:
    """Manifest header of the DAgger directory (resume keys: see `_check_dagger`)."""
    return {"mode": src_header["mode"], "base_seed": spec.seed, "n": spec.n,
            "seed_rule": SEED_RULE, "config_sha256": src_header["config_sha256"],
            "config": src_header["config"], "stages": list(STAGES), "fields": FIELDS,
            "test_fraction": 0.0,
            "dagger": {"format": FORMAT, "model_sha256": spec.model_sha256,
                       "model_path": str(spec.model_path), "src_dir": str(src),
                       "src_manifest_sha256": src_digest, "seed": spec.seed,
                       "rollout_batch": spec.batch, "pool_size": int(pool_size)},
            "art_guidance_version": __version__,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


_DAGGER_KEYS = (("model_sha256", "--model"), ("src_manifest_sha256", "--data"),
                ("rollout_batch", "--batch"), ("format", "--out"))


def _check_dagger(root: Path, stored: dict, wanted: dict) -> None:
    """Refuse to resume a directory made with another model, SRC or batch."""
    have = stored.get("dagger")
    if not isinstance(have, dict):
        raise InputError("--out", "holds a dataset that is not a DAgger dataset; use a new "
                         "--out", str(root))
    for key, option in _DAGGER_KEYS:
        if have.get(key) != wanted["dagger"][key]:
            raise InputError(option, f"the directory holds DAgger data with {key} = "
                             f"{have.get(key)!r}; this run asks for "
                             f"{wanted['dagger'][key]!r}. Re-run with the same options or use "
                             "a new --out")


# --------------------------------------------------------------------------- driver
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
    generation = _generation(src, src_header)
    art = load(model)
    _check_model(art, generation, str(model))
    pool = scenario_pool(src, n)
    spec = DaggerSpec(generation, str(model), str(art.sha256), int(seed), int(n), int(batch),
                      {k: pool[k] for k in _ROLLOUT_FIELDS})
    del art
    header = _header(spec, src, src_header, manifest_digest(str(src)), int(pool["pool_size"]))
    with DatasetWriter(out_dir, header) as writer:
        _check_dagger(writer.root, writer.header, header)
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
