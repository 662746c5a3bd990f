"""Distilling a slim ART from a trained teacher (`art-guidance distill`).

The student imitates the teacher as the planner flies it: on fresh scenarios (seeds from
`first_seed`, apart from every dataset and benchmark of this project) the teacher rolls out the
conditioning sweep it proposes with (`provider.DEFAULT_REWARD_SCALES`: R(t_1) = -s J_CVX,
C(t_1) = 0, the C update at every step, `rollout.rollout`), and each of those rollouts is one
training sequence: the goal, the R and C the teacher was fed at every step, its states and the
controls it applied (its burn gate's coasts as zero burns). The student, conditioned the same
way, learns the teacher's controls (and next states, and the gate) with the training loss of
`model.loss_terms`, on the teacher's normalisation statistics, so its inputs are the teacher's.

Teacher rollouts are made in worker processes (`workers`, progress bar) and kept beside the
output (`<out>.sequences.npz`, reused by a re-run with the same teacher and scenarios); the
student is trained on `threads` threads with a 5 % validation split of the scenarios and the
best validation loss kept; the checkpoint is written atomically after every epoch, with the
teacher's sha256, the scenarios, the command, the wall time and the hardware in its
provenance.
"""
from __future__ import annotations

import json
import math
import multiprocessing
import platform
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from art_guidance import __version__
from art_guidance.art import checkpoint
from art_guidance.art.config import DISTILL_FIRST_SEED, FEATURES, preset
from art_guidance.art.model import ArtModel, combined_loss, loss_counts, loss_terms
from art_guidance.errors import InputError

VAL_FRACTION = 0.05
GATE_WEIGHT = 0.1
BURN_THRESHOLD_MPS = 1e-3


def teacher_sequences(teacher_path: str, seeds: Sequence[int]) -> dict[str, np.ndarray]:
    """The teacher's sweep rollouts on scenarios `seeds` (module docstring), as arrays.

    Returns:
        {"seed": (M,), "target_rtn": (M, 6), "reward": (M, T), "constraint": (M, T),
        "roe_m": (M, T, 6), "dv_rtn_mps": (M, T, 3)} over the M = K x (feasible scenarios)
        rollouts (K reward scales each).
    """
    from art_guidance.art.provider import ArtWarmStart
    from art_guidance.art.rollout import build_safety, rollout, training_config
    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.optim import TransferProblem
    from art_guidance.scenarios import sample_scenario

    torch.set_num_threads(1)
    teacher = ArtWarmStart.load(teacher_path, runtime="torch")
    safety = build_safety(teacher.art)
    scenario = training_config(teacher.art).scenario
    chief = np.array(scenario.chief_oe)
    scales = np.array(teacher.reward_scales)
    k = scales.size
    out: dict[str, list] = {n: [] for n in ("seed", "target_rtn", "reward", "constraint",
                                            "roe_m", "dv_rtn_mps")}
    for seed in seeds:
        s = sample_scenario(scenario, int(seed))
        roe0 = roe_from_rtn_linear(chief, s.rtn0)
        problem = TransferProblem.to_target(safety, roe0, s.target_rtn)
        cvx = problem.cvx()
        if not cvx.status.feasible:
            continue
        res = rollout(teacher.art, safety, np.tile(roe0, (k, 1)), problem.target_rtn,
                      -float(cvx.cost_mps) * scales, 0.0)
        out["seed"].append(np.full(k, int(seed)))
        out["target_rtn"].append(np.tile(s.target_rtn, (k, 1)))
        out["reward"].append(res.reward_to_go_mps)
        out["constraint"].append(res.constraint_to_go)
        out["roe_m"].append(res.roe_m)
        out["dv_rtn_mps"].append(res.dv_rtn_mps)
    return {n: np.concatenate(v) if v else np.empty(0) for n, v in out.items()}


def _generate(teacher_path: str, seeds: np.ndarray, workers: int,
              progress: bool) -> dict[str, np.ndarray]:
    """`teacher_sequences` over `seeds` in `workers` processes, in chunks, with a progress bar."""
    from tqdm import tqdm

    chunks = [c for c in np.array_split(seeds, max(1, math.ceil(seeds.size / 16))) if c.size]
    parts = []
    bar = tqdm(total=seeds.size, desc="teacher rollouts", unit="scenario", disable=not progress)
    if workers <= 1:
        for c in chunks:
            parts.append(teacher_sequences(teacher_path, c.tolist()))
            bar.update(c.size)
    else:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers) as pool:
            jobs = [pool.apply_async(teacher_sequences, (teacher_path, c.tolist()))
                    for c in chunks]
            for c, job in zip(chunks, jobs):
                parts.append(job.get())
                bar.update(c.size)
    bar.close()
    parts = [p for p in parts if p["seed"].size]
    return {n: np.concatenate([p[n] for p in parts]) for n in parts[0]}


def features(teacher, data: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The training batch of `loss_terms` from teacher sequences, normalised with the
    teacher's statistics (goal and state in the teacher's representation)."""
    from art_guidance.art.rollout import build_safety
    from art_guidance.optim import terminal_roe

    art = teacher.art
    norm = art.normalizer
    horizon = build_safety(art).horizon
    m, t = data["reward"].shape
    rtn = art.config.representation == "rtn"
    target = data["target_rtn"]
    goal = target if rtn else terminal_roe(horizon, target)
    state = np.einsum("nij,mnj->mni", horizon.psi, data["roe_m"]) if rtn else data["roe_m"]
    steps = np.arange(art.config.context - t, art.config.context)
    tt = np.broadcast_to(steps, (m, t))
    f32 = dict(dtype=torch.float32)
    return {"goal": torch.as_tensor(np.broadcast_to(norm.normalize("goal", goal)[:, None],
                                                    (m, t, 6)).copy(), **f32),
            "reward": torch.as_tensor(norm.normalize("reward", data["reward"]), **f32),
            "constraint": torch.as_tensor(norm.normalize("constraint", data["constraint"]),
                                          **f32),
            "state": torch.as_tensor(norm.normalize("state", state, tt), **f32),
            "control": torch.as_tensor(norm.normalize("control", data["dv_rtn_mps"], tt),
                                       **f32),
            "timestep": torch.as_tensor(tt.copy(), dtype=torch.int64),
            "mask": torch.ones(m, t, dtype=torch.bool),
            "burn_mps": torch.as_tensor(np.linalg.norm(data["dv_rtn_mps"], axis=-1), **f32)}


def _split(seeds: np.ndarray, seed: int) -> np.ndarray:
    """(M,) bool: the rollouts whose scenario is in the validation split (VAL_FRACTION of the
    scenarios, seeded)."""
    uniq = np.unique(seeds)
    rng = np.random.default_rng(seed)
    val = rng.permutation(uniq)[:max(1, int(round(VAL_FRACTION * uniq.size)))]
    return np.isin(seeds, val)


def _loss(model: ArtModel, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    sse_u, sse_x, bce = loss_terms(model, batch, BURN_THRESHOLD_MPS)
    return combined_loss(sse_u, sse_x, bce, loss_counts(batch["mask"]), GATE_WEIGHT)


def distill(teacher_path: str | Path, out: str | Path, student: str = "slim",
            scenarios: int = 1500, first_seed: int = DISTILL_FIRST_SEED, epochs: int = 8,
            batch_size: int = 32, lr: float = 1e-3, workers: int = 2, threads: int = 2,
            seed: int = 0, progress: bool = True, command: str = "") -> dict[str, Any]:
    """Distil a student of preset `student` from the teacher checkpoint (module docstring).

    Returns:
        A summary: the output, the sequences, the best validation loss and epoch, the wall
        times.

    Raises:
        InputError: bad counts, or an output that exists (a checkpoint is never overwritten).
        CheckpointError: the teacher does not load.
    """
    from art_guidance.art.provider import ArtWarmStart

    for name, value in (("scenarios", scenarios), ("epochs", epochs),
                        ("batch_size", batch_size), ("workers", workers),
                        ("threads", threads)):
        if int(value) < 1:
            raise InputError(name, "must be >= 1", value)
    out = Path(out)
    if out.exists():
        raise InputError("out", "exists; a checkpoint is never overwritten", str(out))
    teacher = ArtWarmStart.load(teacher_path, runtime="torch")
    t0 = time.perf_counter()
    seeds = np.arange(int(first_seed), int(first_seed) + int(scenarios))
    cache = out.with_name(out.name + ".sequences.npz")
    key = f"{teacher.sha256}:{int(first_seed)}:{int(scenarios)}"
    data = None
    if cache.is_file():
        with np.load(cache) as z:
            if str(z["key"]) == key:
                data = {n: z[n] for n in z.files if n != "key"}
    if data is None:
        data = _generate(str(teacher_path), seeds, int(workers), progress)
        tmp = cache.with_name(cache.name + ".tmp.npz")
        np.savez(tmp, key=key, **data)
        tmp.replace(cache)
    gen_s = time.perf_counter() - t0
    torch.manual_seed(seed)
    torch.set_num_threads(int(threads))
    base = teacher.art.config
    cfg, _ = preset(student, base.representation, burn_gate=base.burn_gate,
                    normalization=base.normalization)
    model = ArtModel(cfg)
    batch_all = features(teacher, data)
    val = torch.as_tensor(_split(data["seed"], seed))
    train_idx, val_idx = torch.nonzero(~val)[:, 0], torch.nonzero(val)[:, 0]
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.01)
    steps_per_epoch = max(1, math.ceil(train_idx.numel() / batch_size))
    total = steps_per_epoch * int(epochs)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / 100) * (
        0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(s, total) / total))))
    history, best = [], (math.inf, -1, None)
    t1 = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=total, desc="distil", unit="batch", disable=not progress)
    gen = torch.Generator().manual_seed(seed)
    for epoch in range(1, int(epochs) + 1):
        model.train()
        order = train_idx[torch.randperm(train_idx.numel(), generator=gen)]
        train_loss = []
        for i in range(0, order.numel(), batch_size):
            idx = order[i:i + batch_size]
            loss = _loss(model, {n: v[idx] for n, v in batch_all.items()})
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            train_loss.append(float(loss.detach()))
            bar.update(1)
        model.eval()
        with torch.no_grad():
            val_loss = float(np.mean([float(_loss(model, {n: v[val_idx[i:i + 256]]
                                                          for n, v in batch_all.items()}))
                                      for i in range(0, val_idx.numel(), 256)]))
        history.append([epoch, float(np.mean(train_loss)), val_loss])
        bar.set_postfix(train=f"{history[-1][1]:.4f}", val=f"{val_loss:.4f}")
        if val_loss < best[0]:
            best = (val_loss, epoch, {k: v.detach().clone() for k, v in
                                      model.state_dict().items()})
        meta = _meta(teacher, model.n_parameters(), data, first_seed, scenarios, epochs,
                     batch_size, lr, seed, threads, workers, history, best, gen_s,
                     time.perf_counter() - t1, command)
        checkpoint.save(out, checkpoint.model_payload(model, teacher.art.normalizer, meta,
                                                      state_dict=best[2]))
    bar.close()
    return {"out": str(out), "sequences": int(data["seed"].size),
            "scenarios": int(np.unique(data["seed"]).size), "best_val_loss": best[0],
            "best_epoch": best[1], "teacher_rollouts_s": round(gen_s, 1),
            "train_s": round(time.perf_counter() - t1, 1),
            "n_parameters": model.n_parameters()}


def _meta(teacher, n_parameters: int, data: dict, first_seed: int, scenarios: int, epochs: int,
          batch_size: int, lr: float, seed: int, threads: int, workers: int, history: list,
          best: tuple, gen_s: float, train_s: float, command: str) -> dict[str, Any]:
    """The student's provenance (its dataset is the teacher's: the configuration the
    horizon and safety model are built from)."""
    dataset = json.loads(json.dumps(teacher.art.meta.get("dataset", {})))
    return {"dataset": dataset, "distillation": {
        "teacher": Path(teacher.path).name, "teacher_sha256": teacher.sha256,
        "scenario_seeds": [int(first_seed), int(first_seed) + int(scenarios) - 1],
        "reward_scales": list(teacher.reward_scales),
        "sequences": int(data["seed"].size), "val_fraction": VAL_FRACTION,
        "epochs": int(epochs), "batch_size": int(batch_size), "lr": float(lr),
        "seed": int(seed), "threads": int(threads), "workers": int(workers),
        "history_epoch_train_val": history, "best_val_loss": best[0], "best_epoch": best[1],
        "teacher_rollouts_wall_s": round(gen_s, 1), "train_wall_s": round(train_s, 1),
        "n_parameters": int(n_parameters),
        "hardware": f"{platform.machine()} CPU, {multiprocessing.cpu_count()} cores, no GPU",
        "torch_version": str(torch.__version__), "art_guidance_version": __version__,
        "command": command}, "training": {"preset": "distilled", "features": FEATURES}}
