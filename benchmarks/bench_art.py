"""Benchmark: ART rollouts (KV cache vs recomputing the context), batch throughput, training.

All in one process, on the paper scenario's 100-node horizon with the chance-constrained
passive-safety model, for the default (`small`) and the paper-size model on 1 and 2 torch
threads:
- `*_rollout_ms`: median wall time of one 100-step rollout as the planner runs it (KV cache,
  dynamics in the loop, R and C updated every step), and `*_c_update_ms` the part of it spent
  in the safety module's violation decisions (`PassiveSafety.violated`);
- `*_cached_model_ms` / `*_recompute_model_ms`: the same rollout with the recorded decisions
  replayed, i.e. transformer + dynamics alone, with the KV cache and recomputing the whole
  context at every step; `*_cache_speedup` is their ratio;
- `*_sweep_ms`: the in-flight provider's conditioning sweep, one batched rollout of the
  default model per reward scale (`DEFAULT_REWARD_SCALES`), with the C update;
- `*_propose_ms`: the whole proposal of the in-flight provider (`ArtWarmStart.propose`): the
  sweep plus the post hoc judging of its candidates as the pipeline's check judges them (by
  default each candidate's terminal warm start: one correction and one safety evaluation), over
  the first 8 scenarios (median);
- batch-64 rollout throughput (rollouts/s) of the default model, with and without the C update;
- training throughput (trajectories/s at the preset's batch, 100-step sequences);
- the default model's training wall time, read from its checkpoint (ART_BENCH_CHECKPOINT, the
  `checkpoint` argument, or the shipped default model; without one the timings use random
  weights, which cost the same).
numpy's OpenBLAS threads (used by the safety module) busy-wait between calls; run with
OPENBLAS_NUM_THREADS=1 for the numbers the planner sees with one core per process.

The kernels are loaded before anything is timed (`common.warm_up`; `warm_up_ms`).
"""
from __future__ import annotations

import os
from pathlib import Path
import time

import numpy as np
import torch

from art_guidance.art import ArtModel, TrainedArt, build_safety, load, preset
from art_guidance.art.model import loss_terms
from art_guidance.art.provider import DEFAULT_REWARD_SCALES, ArtWarmStart, default_model_path
from art_guidance.art.normalization import Normalizer
from art_guidance.art.rollout import rollout
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.optim import TransferProblem
from art_guidance.planning.request import PlanRequest
from common import warm_up


class _RecordedSafety:
    """Delegates to a PassiveSafety; times its violation decisions, or replays recorded ones.

    Replaying gives the same rollout (same decisions, hence the same C history and controls)
    without the safety module's cost, so the transformer + dynamics time is measured alone.
    """

    def __init__(self, safety) -> None:
        self._safety, self.seconds, self.replay = safety, 0.0, False
        self._tape: list[np.ndarray] = []
        self._next = 0

    def __getattr__(self, name: str):
        return getattr(self._safety, name)

    def rewind(self, replay: bool) -> None:
        """Start a rollout: record (real decisions, timed) or replay the last recording."""
        self.replay, self.seconds, self._next = replay, 0.0, 0
        if not replay:
            self._tape = []

    def violated(self, nodes, roe_m, dv_rtn_mps, z_m=None):  # the rollout loop's decision
        return self._decide(self._safety.violated, nodes, roe_m, dv_rtn_mps, z_m)

    def _decide(self, decide, *args):
        if self.replay:
            self._next += 1
            return self._tape[self._next - 1]
        t = time.perf_counter()
        out = decide(*args)
        self.seconds += time.perf_counter() - t
        self._tape.append(out)
        return out


def _random_art(name: str) -> TrainedArt:
    torch.manual_seed(0)
    scales = {"goal": [500.0, 1000.0, 100.0, 100.0, 50.0, 50.0], "reward": [0.2],
              "constraint": [2.0], "state": [1000.0, 8000.0, 300.0, 300.0, 50.0, 50.0],
              "control": [0.01, 0.01, 0.005]}
    mean = {k: np.zeros(len(v)) for k, v in scales.items()}
    mean["reward"] = np.array([-0.3])
    return TrainedArt(ArtModel(preset(name)[0]), Normalizer(
        mean, {k: np.array(v) for k, v in scales.items()}), {"dataset": {"mode": "chance"}})


def _scenarios(n: int) -> tuple[np.ndarray, np.ndarray]:
    sc = ScenarioConfig()
    rng = np.random.default_rng(0)
    rtn0 = np.asarray(sc.rtn0_nominal) + rng.uniform(-1, 1, (n, 6)) * np.asarray(
        sc.rtn0_half_width)
    x0 = np.array([roe_from_rtn_linear(np.asarray(sc.chief_oe), r) for r in rtn0])  # (n, 6)
    names = sorted(sc.waypoints_rtn)
    targets = np.array([sc.waypoints_rtn[names[i % len(names)]] for i in range(n)])  # (n, 6)
    return x0, targets


def _time_proposals(art: TrainedArt, x0: np.ndarray, targets: np.ndarray,
                    threads: int) -> float:
    """Median wall time [ms] of `ArtWarmStart.propose` (sweep and candidate judging) over
    the scenarios, after one warm-up."""
    safety = build_safety(art, chance_constrained=True)
    horizon = safety.horizon
    provider = ArtWarmStart(art, threads=threads)
    times = []
    for k, (x, target) in enumerate(zip(x0, targets)):
        request = PlanRequest(horizon.chief_oe[0], x, target, chance_constrained=True)
        problem = TransferProblem.to_target(safety, request.roe0_m, request.target_rtn)
        cvx = problem.cvx()
        if k == 0:
            provider.propose(problem, cvx)
        t = time.perf_counter()
        provider.propose(problem, cvx)
        times.append(1e3 * (time.perf_counter() - t))
    return float(np.median(times))


def _time_rollouts(art: TrainedArt, safety: _RecordedSafety, x0: np.ndarray,
                   targets: np.ndarray, repeats: int, use_cache: bool,
                   replay: bool) -> tuple[float, float]:
    """Median wall time [ms] of a rollout and of the safety module's share of it."""
    total, part = [], []
    for k in range(repeats + 1):  # the first run warms up (and records the decisions)
        safety.rewind(replay)
        t = time.perf_counter()
        rollout(art, safety, x0, targets, -0.3, use_cache=use_cache)
        if k:
            total.append(1e3 * (time.perf_counter() - t))
            part.append(1e3 * safety.seconds)
    return float(np.median(total)), float(np.median(part))


def _train_rate(name: str, steps: int) -> float:
    """Trajectories per second of training steps (forward, backward, clip, AdamW) at the
    preset's batch size on full 100-step sequences."""
    torch.manual_seed(0)
    cfg, tcfg = preset(name)
    batch = tcfg.batch_size
    model = ArtModel(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    t_len = 100
    data = {"goal": torch.randn(batch, t_len, 6), "reward": torch.randn(batch, t_len),
            "constraint": torch.randn(batch, t_len), "state": torch.randn(batch, t_len, 6),
            "control": torch.randn(batch, t_len, 3),
            "timestep": torch.arange(t_len).expand(batch, t_len),
            "mask": torch.ones(batch, t_len, dtype=torch.bool)}
    times = []
    for _ in range(steps + 1):
        t = time.perf_counter()
        sse_u, sse_x, _ = loss_terms(model, data)
        (sse_u + sse_x).backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)
        times.append(time.perf_counter() - t)
    return batch / float(np.median(times[1:]))


def _shown(path: str) -> str:
    """A checkpoint path as recorded: relative to the working directory when inside it (no
    machine paths in committed results), else its file name."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd()))
    except ValueError:
        return p.name


def run(repeats: int = 20, checkpoint: str | None = None) -> dict:
    """Time ART rollouts and training; returns medians [ms], speed-ups and rates."""
    warm_up_ms = warm_up()  # the kernels (the C update's), before the first timed rollout
    checkpoint = checkpoint or os.environ.get("ART_BENCH_CHECKPOINT")
    if checkpoint is None and default_model_path().is_file():
        checkpoint = str(default_model_path())
    default = load(checkpoint) if checkpoint else _random_art("small")
    models = {"default": default, "paper": _random_art("paper")}
    safety = _RecordedSafety(build_safety(default, chance_constrained=True))
    x0, targets = _scenarios(64)
    out: dict = {"checkpoint": _shown(checkpoint) if checkpoint else "random weights",
                 "warm_up_ms": warm_up_ms,
                 "default_n_parameters": default.model.n_parameters(),
                 "paper_n_parameters": models["paper"].model.n_parameters()}
    threads_before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for name, art in models.items():
                key, slow = f"{name}_{threads}thr", max(2, repeats // 10)
                full, c_update = _time_rollouts(art, safety, x0[:1], targets[:1], repeats, True,
                                                False)
                cached, _ = _time_rollouts(art, safety, x0[:1], targets[:1], repeats, True, True)
                again, _ = _time_rollouts(art, safety, x0[:1], targets[:1], slow, False, True)
                out.update({f"{key}_rollout_ms": full, f"{key}_c_update_ms": c_update,
                            f"{key}_cached_model_ms": cached, f"{key}_recompute_model_ms": again,
                            f"{key}_cache_speedup": again / cached})
            key = f"default_{threads}thr"
            sweep = np.tile(x0[:1], (len(DEFAULT_REWARD_SCALES), 1))
            out[f"{key}_sweep_ms"], out[f"{key}_sweep_c_update_ms"] = _time_rollouts(
                default, safety, sweep, targets[:1], repeats, True, False)
            out[f"{key}_propose_ms"] = _time_proposals(default, x0[:8], targets[:8], threads)
            full, c_update = _time_rollouts(default, safety, x0, targets, slow, True, False)
            cached, _ = _time_rollouts(default, safety, x0, targets, slow, True, True)
            out[f"{key}_batch64_rollouts_per_s"] = 64e3 / full
            out[f"{key}_batch64_c_update_ms"] = c_update
            out[f"{key}_batch64_model_rollouts_per_s"] = 64e3 / cached
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out[f"train_default_{threads}thr_traj_per_s"] = _train_rate("small", 3)
        out["train_paper_2thr_traj_per_s"] = _train_rate("paper", 2)
    finally:
        torch.set_num_threads(threads_before)
    training = default.meta.get("training", {})
    out["default_training_wall_time_s"] = float(training.get("wall_time_s", float("nan")))
    return out


if __name__ == "__main__":
    for k, v in run().items():
        print(f"{k}: {v}")
