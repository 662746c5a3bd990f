"""Training data: dataset directories -> normalised tensors, a validation split, batches.

Only the dataset's own train split is read (`is_test` False) and infeasible samples are
skipped. A seeded share of it is held out for validation and early stopping; the
normalisation statistics come from the rest. Every stored quantity is used as written by the
generator (see `art_guidance.data.stages.FIELDS`): R(t_i) = -sum_{j >= i} ||dv_j||, C(t_i) =
sum_{j >= i} v_j with v_j = [margin_j < 0] under the dataset's passive-safety model. The goal
is the terminal post-burn state: `roe_f_m` in the ROE representation, `target_rtn` (= Psi_N
roe_f_m) in RTN; the RTN states are `rtn` = Psi_i x_i.

Batches are sequences of the N nodes of a trajectory or, for a share of them, suffixes starting
at a random node k (teaching replans over the remaining horizon); suffixes are shifted to the
front and padded at the end, where causality keeps the padding out of every valid prediction
and the loss mask out of the loss. Rows of DAgger datasets (`art_guidance.data.dagger`) carry
`train_from`, the first node whose control is an expert label: their earlier nodes (the
model's own rollout) are context only, kept out of the loss mask (`valid_mask`); rows of
ordinary datasets have train_from 0 (a missing field reads as 0). Time-step indices follow
the end-aligned rule of `ArtConfig.context`. All randomness derives from (seed, epoch) and
(seed, step), so a resumed or data-parallel run draws exactly the batches of an uninterrupted
single process.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from art_guidance.art.config import MODALITIES
from art_guidance.art.normalization import Normalizer
from art_guidance.config import GuidanceConfig
from art_guidance.scenarios import SEED_STRIDE
from art_guidance.data.storage import MANIFEST, load_dataset, read_manifest
from art_guidance.errors import InputError

_VAL_STREAM, _EPOCH_STREAM, _STEP_STREAM = 0xA1, 0xE9, 0x57


@dataclass(frozen=True)
class TrainingData:
    """Normalised training and validation tensors of one or more dataset directories.

    Attributes:
        tensors: {"goal": (M, 6), "reward": (M, N), "constraint": (M, N),
            "state": (M, N, 6), "control": (M, N, 3)} float32, normalised,
            "burn_mps" (M, N) float32, the raw ||u|| [m/s] (target of the burn gate), and
            "train_from" (M,) int64, the first node of each row inside the loss (0 but for
            DAgger rows).
        train_rows, val_rows: int64 row indices into the tensors (disjoint).
        normalizer: statistics of the train rows.
        n_nodes: N, nodes per trajectory.
        provenance: dataset mode, config fingerprint and bundle (GuidanceConfig.to_json),
            manifests (path, sha256), counts; stored in the checkpoint.
    """

    tensors: dict[str, torch.Tensor]
    train_rows: np.ndarray
    val_rows: np.ndarray
    normalizer: Normalizer
    n_nodes: int
    provenance: dict


def _raw_arrays(data: dict[str, np.ndarray], representation: str) -> dict[str, np.ndarray]:
    rtn = representation == "rtn"
    return {"goal": data["target_rtn"] if rtn else data["roe_f_m"],
            "reward": data["reward_to_go_mps"],
            "constraint": data["constraint_to_go"].astype(np.float64),
            "state": data["rtn"] if rtn else data["roe_m"],
            "control": data["dv_rtn_mps"]}


def _train_from(data: dict[str, np.ndarray]) -> np.ndarray:
    """(M,) int64 first node inside the loss of each row (0 where the field is missing)."""
    n_rows = data["roe_m"].shape[0]
    if "train_from" not in data:
        return np.zeros(n_rows, dtype=np.int64)
    return np.asarray(data["train_from"], dtype=np.int64).reshape(n_rows)


def manifest_digest(root: str) -> str:
    """sha256 of a dataset directory's manifest (what checkpoints record of their data)."""
    _, _, valid = read_manifest(root)
    return hashlib.sha256((Path(root) / MANIFEST).read_bytes()[:valid]).hexdigest()


def trained_manifests(meta: dict) -> tuple[str, ...]:
    """Manifest sha256 of every dataset a checkpoint's provenance (`meta`) was trained on,
    including those of the model it was fine-tuned from (`train --init`), and of that
    model's, recorded when it was fine-tuned."""
    own = tuple(m.get("manifest_sha256", "") for m in _manifests(meta))
    return own + tuple(h for h in _init(meta).get("trained_on", []) if h not in own)


def seed_bases(scenario_seeds: np.ndarray) -> list[int]:
    """The dataset seeds S whose scenarios `scenario_seeds` are (scenario seed S * SEED_STRIDE
    + i, `scenarios.SEED_RULE`): two datasets of one mode share scenarios exactly when they
    share one, whatever their manifests."""
    return sorted({int(s) // SEED_STRIDE for s in np.asarray(scenario_seeds).ravel()})


def trained_seed_bases(meta: dict) -> tuple[int, ...]:
    """The dataset seeds of every scenario a checkpoint was trained on (its manifests', those
    of the model it was fine-tuned from, and those whose scenarios a distilled student's
    teacher rolled out: `art.distill`'s scenario seed range), where its provenance records
    them (models trained before it did record none)."""
    own = {int(b) for m in _manifests(meta) for b in m.get("scenario_seed_bases", [])}
    distilled = ((meta or {}).get("distillation") or {}).get("scenario_seeds")
    if distilled:  # [first, last] scenario seed: every dataset seed they belong to
        lo, hi = (int(s) for s in distilled)
        own |= set(range(lo // SEED_STRIDE, hi // SEED_STRIDE + 1))
    return tuple(sorted(own | {int(b) for b in _init(meta).get("seed_bases", [])}))


def _manifests(meta: dict | None) -> list[dict]:
    """The training datasets' entries of a checkpoint's provenance."""
    return (meta or {}).get("dataset", {}).get("manifests", [])


def _init(meta: dict | None) -> dict:
    """What a checkpoint's provenance records of the model it was fine-tuned from ({}: none)."""
    return ((meta or {}).get("training") or {}).get("init") or {}


def fed_reward_to_go(dv_rtn_mps: np.ndarray, cvx_cost_mps: np.ndarray) -> np.ndarray:
    """(M, N) R(t_i) as a rollout conditioned on R(t_1) = -J_CVX is fed along controls
    (M, N, 3) [m/s]: R(t_1) = -J_CVX, R(t_{i+1}) = R(t_i) + ||u_i|| [m/s] (the rollout's own
    update; `rollout.replay` gives the same)."""
    norms = np.linalg.norm(np.asarray(dv_rtn_mps, float), axis=-1)  # (M, N)
    spent = np.concatenate([np.zeros_like(norms[:, :1]), np.cumsum(norms, axis=1)[:, :-1]],
                           axis=1)
    return spent - np.asarray(cvx_cost_mps, float).reshape(-1, 1)


def _read_dir(root: str, dagger_max_cost_ratio: float = 0.0, dagger_reward: str = "hindsight"
              ) -> tuple[dict, dict[str, np.ndarray], dict]:
    header, _, _ = read_manifest(root)
    digest = manifest_digest(root)
    data = load_dataset(root)
    keep = ~data["is_test"] & data["feasible"]
    train_from = _train_from(data)
    dropped = 0
    if dagger_max_cost_ratio > 0 and (train_from > 0).any():
        rows = np.arange(train_from.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = -data["reward_to_go_mps"][rows, train_from] / data["cvx_cost_mps"]
        over = keep & (train_from > 0) & ~(ratio <= dagger_max_cost_ratio)
        dropped, keep = int(over.sum()), keep & ~over
    if dagger_reward == "fed" and (train_from > 0).any():
        rows = np.flatnonzero(keep & (train_from > 0))
        reward = np.array(data["reward_to_go_mps"], float)
        reward[rows] = fed_reward_to_go(data["dv_rtn_mps"][rows], data["cvx_cost_mps"][rows])
        data = {**data, "reward_to_go_mps": reward}
    info = {"dir": str(root), "manifest_sha256": digest, "n": int(header["n"]),
            "train_feasible": int(keep.sum()), "test_skipped": int(data["is_test"].sum()),
            "dagger_rows": int((train_from > 0)[keep].sum()),
            "dagger_rows_over_cost_ratio": dropped,
            "scenario_seed_bases": seed_bases(data["seed"][keep]) if "seed" in data else []}
    return header, {k: v[keep] for k, v in data.items()}, info


def load_training_data(dirs: list[str], representation: str, val_fraction: float,
                       seed: int, normalization: str = "feature", context: int | None = None,
                       max_train: int = 0, normalizer: Normalizer | None = None,
                       dagger_max_cost_ratio: float = 0.0,
                       dagger_reward: str = "hindsight") -> TrainingData:
    """Read dataset directories, keep their feasible train-split samples, split, normalise.

    Args:
        dirs: dataset directories of one mode and one configuration.
        representation: "roe" or "rtn".
        val_fraction: share of the kept samples held out for validation.
        seed: seeds the validation split.
        normalization: "feature" or "timestep" (see `Normalizer.fit`).
        context: the model's K (time-step indices of the "timestep" scheme; default N).
        max_train: keep at most this many training rows (a seeded subset; 0: all); the
            validation rows do not change with it.
        normalizer: normalise with these statistics instead of fitting them to the training
            rows (fine-tuning keeps the initial model's; its scheme must be `normalization`).
        dagger_max_cost_ratio: leave out DAgger rows whose expert costs more than this many
            times J_CVX from the takeover node on (0: keep all).
        dagger_reward: the reward-to-go of the DAgger rows: "hindsight" (as stored:
            -sum_{j >= i} ||u_j|| of the stitched row) or "fed" (as the rollout was fed:
            -J_CVX plus what the row spent before node i, `fed_reward_to_go`; the prefix is
            then exactly the context the model saw, and the expert's suffix follows it).

    Raises:
        InputError: no directory, directories of different modes or configurations, or fewer
            than 2 usable trajectories.
        DatasetError: a corrupt or incomplete directory.
    """
    if not dirs:
        raise InputError("--data", "at least one dataset directory is required")
    parts, train_from, infos, first = [], [], [], None
    for root in dirs:
        header, data, info = _read_dir(root, dagger_max_cost_ratio, dagger_reward)
        first = first or header
        diff = data_differences(header, first)
        if diff:
            raise InputError("--data", f"{root} holds a {header['mode']} dataset of config "
                             f"{header['config_sha256'][:12]}, the first a {first['mode']} one"
                             f" of {first['config_sha256'][:12]} (differing: "
                             f"{', '.join(diff)}); train on one kind at a time")
        parts.append(_raw_arrays(data, representation))
        train_from.append(_train_from(data))
        infos.append(info)
    raw = {m: np.concatenate([p[m] for p in parts]) for m in MODALITIES}
    m_rows = raw["goal"].shape[0]
    if m_rows < 2:
        raise InputError("--data", f"{m_rows} feasible training trajectories; need at least 2")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _VAL_STREAM]))
    perm = rng.permutation(m_rows)
    n_val = min(max(1, int(round(val_fraction * m_rows))), m_rows - 1)
    val_rows, train_rows = np.sort(perm[:n_val]), perm[n_val:]
    if max_train:
        train_rows = train_rows[:max_train]
    train_rows = np.sort(train_rows)
    n_nodes = int(raw["state"].shape[1])
    k = n_nodes if context is None else int(context)
    if normalizer is None:
        normalizer = Normalizer.fit({m: raw[m][train_rows] for m in MODALITIES}, normalization,
                                    k)
    t_index = np.arange(n_nodes) + (k - n_nodes)  # (N,) time-step index of each node
    tensors = {m: torch.from_numpy(np.ascontiguousarray(
        normalizer.normalize(m, raw[m], t_index if normalizer.per_step(m) else None),
        dtype=np.float32)) for m in MODALITIES}
    tensors["burn_mps"] = torch.from_numpy(np.linalg.norm(raw["control"], axis=-1)
                                           .astype(np.float32))  # (M, N) ||u|| [m/s]
    tensors["train_from"] = torch.from_numpy(np.concatenate(train_from))  # (M,) int64
    provenance = {"mode": first["mode"], "config_sha256": first["config_sha256"],
                  "guidance_config": _guidance_config(first["config"]),
                  "manifests": infos, "n_nodes": int(raw["state"].shape[1]),
                  "n_train": int(train_rows.size), "n_val": int(val_rows.size),
                  "representation": representation, "normalization": normalization,
                  "max_train": int(max_train),
                  "dagger_max_cost_ratio": float(dagger_max_cost_ratio),
                  "dagger_reward": dagger_reward}
    return TrainingData(tensors, train_rows.astype(np.int64), val_rows.astype(np.int64),
                        normalizer, int(raw["state"].shape[1]), provenance)


def data_differences(a: dict, b: dict) -> list[str]:
    """What makes the data of two dataset headers differ: "mode", "pipeline_version" and the
    parts of `GuidanceConfig.data_json` (scenario, uncertainty, SCVx*, samples per node); the
    planning choices only flight uses do not count (a header written before one existed
    records none of it). [] for the same data."""
    if a["config_sha256"] == b["config_sha256"] and a["mode"] == b["mode"]:
        return []
    out = [k for k in ("mode",) if a["mode"] != b["mode"]]
    ca, cb = a.get("config", {}), b.get("config", {})
    if ca.get("pipeline_version") != cb.get("pipeline_version"):
        out.append("pipeline_version")
    have, want = (GuidanceConfig.from_json(_guidance_config(c)) for c in (ca, cb))
    return out + have.data_differences(want)


def _guidance_config(config: dict) -> dict:
    """The configuration bundle (GuidanceConfig.to_json) of a dataset header's config."""
    if "guidance_config" in config:
        return config["guidance_config"]
    bundle = GuidanceConfig().to_json()  # headers written before the bundle existed
    bundle.update({k: config[k] for k in ("scenario", "uncertainty", "scp") if config.get(k)})
    return bundle


def epoch_order(seed: int, epoch: int, rows: np.ndarray) -> np.ndarray:
    """The train rows in the (seeded) order of `epoch`."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _EPOCH_STREAM, int(epoch)]))
    return rows[rng.permutation(rows.size)]


def suffix_starts(seed: int, step: int, size: int, n_nodes: int, fraction: float) -> np.ndarray:
    """(size,) start nodes of the sequences of training step `step`.

    0, or with probability `fraction` a node in 1 .. N - 2 (at least two steps remain, so
    the next-state loss has a target).
    """
    return _starts([int(seed), _STEP_STREAM, int(step)], size, n_nodes, fraction)


def validation_starts(seed: int, size: int, n_nodes: int, fraction: float) -> np.ndarray:
    """(size,) fixed start nodes of the validation sequences (same law as in training)."""
    return _starts([int(seed), _VAL_STREAM, 1], size, n_nodes, fraction)


def _starts(entropy: list[int], size: int, n_nodes: int, fraction: float) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence(entropy))
    use = rng.random(size) < fraction
    late = rng.integers(1, max(n_nodes - 1, 2), size)
    return np.where(use & (n_nodes > 2), late, 0).astype(np.int64)


def valid_mask(starts: np.ndarray, n_nodes: int,
               train_from: np.ndarray | torch.Tensor | None = None) -> torch.Tensor:
    """(b, N) bool: the steps of sequences starting at `starts` that enter the loss.

    Step j of the sequence starting at node s_b is node s_b + j; it is valid when it exists
    (s_b + j < N, no padding) and is not context only (s_b + j >= train_from_b): the mask of
    nodes >= max(s_b, train_from_b), shifted to the front. The same mask as `make_batch`'s.

    Args:
        starts: (b,) int start node of each sequence.
        n_nodes: N, nodes per trajectory.
        train_from: (b,) int first node of each row inside the loss (None: 0 for all); a
            tensor keeps the mask on its device.
    """
    if isinstance(train_from, torch.Tensor):
        where = train_from.device
        node = torch.as_tensor(starts, dtype=torch.long, device=where)[:, None] \
            + torch.arange(n_nodes, device=where)  # (b, N)
        return (node < n_nodes) & (node >= train_from.long()[:, None])
    node = np.asarray(starts, dtype=np.int64)[:, None] + np.arange(n_nodes)  # (b, N)
    mask = node < n_nodes
    if train_from is not None:
        mask &= node >= np.asarray(train_from, dtype=np.int64)[:, None]
    return torch.from_numpy(mask)


def make_batch(tensors: dict[str, torch.Tensor], rows: np.ndarray, starts: np.ndarray,
               context: int, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Gather the sequences of `rows` starting at `starts`, front-aligned and end-padded.

    Args:
        tensors: normalised data (see TrainingData.tensors).
        rows: (b,) row indices.
        starts: (b,) start node of each sequence.
        context: the model's K (time index of node i is K - N + i).
        device: where the batch goes.

    Returns:
        "goal" (b, N, 6), "reward" (b, N), "constraint" (b, N), "state" (b, N, 6),
        "control" (b, N, 3), "burn_mps" (b, N) ||u|| [m/s], "timestep" (b, N) int64,
        "mask" (b, N) bool (`valid_mask`: existing nodes >= the row's train_from, if the
        tensors hold "train_from").
    """
    n = tensors["state"].shape[1]
    where = tensors["state"].device  # gather where the data lives (the GPU keeps it resident)
    r = torch.as_tensor(rows, dtype=torch.long, device=where)
    node = torch.as_tensor(starts, dtype=torch.long, device=where)[:, None] \
        + torch.arange(n, device=where)  # (b, N)
    mask = node < n  # (b, N)
    if "train_from" in tensors:  # DAgger rows: the rollout prefix is context, not a label
        mask &= node >= tensors["train_from"][r][:, None]
    node = node.clamp(max=n - 1)
    rr = r[:, None].expand_as(node)  # (b, N)
    batch = {m: tensors[m][rr, node] for m in ("reward", "constraint", "state", "control",
                                               "burn_mps")}
    batch["goal"] = tensors["goal"][r][:, None].expand(len(r), n, -1)  # (b, N, 6)
    batch["timestep"] = node + (context - n)  # (b, N)
    batch["mask"] = mask
    return {k: v.to(device) for k, v in batch.items()}
