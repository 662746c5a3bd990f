"""The worker side of `art-guidance dagger` (see `data.dagger` for the sample rule): roll the
model out on a whole batch group, draw the takeover node k, re-solve the 3-stage expert from the
rollout's state at k over the remaining horizon, and stitch the row. Each worker process loads
the model once and runs with one torch thread, so the rows do not depend on the engine, the
worker count or the chunking.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np

from art_guidance.data.stages import (
    KEPT_INFEASIBLE, GenerationSpec, Stage, infeasible_trajectory_fields, solve_stages,
    stage_fields, trajectory_fields,
)
from art_guidance.dynamics import Horizon
from art_guidance.optim import ScpStatus, TransferProblem
from art_guidance.safety import PassiveSafety

DAGGER_STREAM = 0xDA66  # second SeedSequence word of the node draw
# What a worker returns; the driver adds the scenario's fields from SRC (SCENARIO_FIELDS).
ROW_FIELDS = ("index", "train_from", "kept_stage", "feasible", "roe_m", "rtn", "dv_rtn_mps",
              "cost_mps", "reward_to_go_mps", "constraint_to_go", "margin_m", "stage_status",
              "stage_iterations", "stage_cost_mps", "stage_time_ms")


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
    return solve_stages(spec, TransferProblem(passive, roe_k_m, roe_f_m), collision)


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
