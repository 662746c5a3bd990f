"""Randomised rendezvous scenarios and the paper's 3-stage dataset pipeline.

A dataset of n samples draws its transfers with `scenarios.sample_scenario` from the seeds of
`scenarios.SEED_RULE`; every sample is solved in three stages (paper,
"Dataset generation"): the convex TPBVP (CVX), a collision-avoidance SCP warm-started by it, and
the passive-safety SCP (deterministic or chance-constrained) warm-started by that; the last
feasible solution is stored with its reward-to-go and constraint-to-go. Every record depends on
its seed and the configuration alone, so the local process pool and Ray, run in any chunking
and resumed any number of times, produce identical data (timings aside). Storage and
`load_dataset`: `art_guidance.data.storage`; driver and CLI: `art_guidance.data.generate`.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.config import MODES, GuidanceConfig, ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
from art_guidance.errors import GuidanceError, InputError
from art_guidance.optim import ScpStatus, TransferProblem
from art_guidance.optim.problem import SubproblemPool
from art_guidance.safety import PassiveSafety
from art_guidance.scenarios import SEED_RULE, SEED_STRIDE, sample_scenario, sample_seed

__all__ = ["FIELDS", "STAGES", "TIMING_FIELDS", "GenerationSpec", "Stage", "generate_chunk",
           "infeasible_trajectory_fields",
           "solve_sample", "solve_stages", "stage_fields", "trajectory_fields"]


# =========================================================================== 3-stage pipeline
STAGES = ("cvx", "collision_avoidance", "passive_safety")
# Bump when a code change alters the stored data of a given seed. 2: passive safety over the
# continuous drift arc (certified t*): new SCP solutions, constraint-to-go and margins.
# 3: SCVx* plans with B at the deputy's state and the second-order along-track drift
# (`Horizon.propagate_nonlinear`): new SCP solutions and trajectories.
PIPELINE_VERSION = 3
KEPT_INFEASIBLE = 0
TIMING_FIELDS = ("stage_time_ms",)  # the only stored fields that differ between runs

# Stored per sample (one entry each, stacked along a leading sample axis in shards and in
# `load_dataset`). N = number of nodes. Infeasible samples (kept_stage 0) hold NaN in the
# trajectory fields and -1 in constraint_to_go.
FIELDS = {
    "index": "() int64, sample index i in 0..n-1",
    "seed": "() int64, scenario seed (SEED_RULE)",
    "waypoint": "() str, terminal waypoint name",
    "rtn0": "(6,) initial RTN state [m, m/s]",
    "target_rtn": "(6,) terminal RTN state after the last burn [m, m/s]",
    "roe0_m": "(6,) initial a-scaled ROE [m]",
    "roe_f_m": "(6,) terminal post-burn a-scaled ROE [m]",
    "kept_stage": "() int8, stage of the stored trajectory: 3 passive safety, 2 collision "
                  "avoidance, 0 none feasible",
    "feasible": "() bool, kept_stage > 0",
    "roe_m": "(N, 6) pre-burn a-scaled ROE of the stored trajectory [m]",
    "rtn": "(N, 6) pre-burn RTN states, horizon.to_rtn(roe_m) [m, m/s]",
    "dv_rtn_mps": "(N, 3) impulsive delta-v in RTN [m/s]",
    "cost_mps": "() sum of ||dv||_2 [m/s]",
    "reward_to_go_mps": "(N,) R(t_i) = -sum_{j>=i} ||dv_j||_2 [m/s]",
    "constraint_to_go": "(N,) int32, C(t_i) under the mode's passive-safety model (minimum "
                        "margin over the continuous drift arc)",
    "margin_m": "(N,) passive-safety margin under the mode's model [m], >= 0 safe (certified "
                "lower bound of the minimum over the continuous drift arc)",
    "cvx_roe_m": "(N, 6) CVX (stage 1) pre-burn ROE [m]",
    "cvx_dv_rtn_mps": "(N, 3) CVX delta-v in RTN [m/s]",
    "cvx_cost_mps": "() CVX cost, the lower bound [m/s]",
    "cvx_constraint_to_go0": "() int32, C_CVX(t_1): constraint-to-go at node 0 of the CVX "
                             "trajectory under the stage-3 model (-1 if CVX failed)",
    "stage_status": "(3,) int8, ScpStatus value per stage (cvx, ca, ps)",
    "stage_iterations": "(3,) int32, convex subproblems solved per stage",
    "stage_cost_mps": "(3,) cost of each stage's returned trajectory [m/s]",
    "stage_time_ms": "(3,) wall time per stage [ms] (not reproducible)",
}


@dataclass(frozen=True)
class GenerationSpec:
    """Everything a generation task needs; picklable, identical on every worker.

    Attributes:
        mode: "deterministic" or "chance" (the stage-3 passive-safety model).
        base_seed: dataset seed S >= 0 (sample seeds follow SEED_RULE).
        config: the configuration bundle (scenario, uncertainty, SCP, samples per node).
    """

    mode: str
    base_seed: int
    config: GuidanceConfig

    @classmethod
    def build(cls, mode: str, base_seed: int,
              config: GuidanceConfig | None = None) -> "GenerationSpec":
        """Validate the options; `config` defaults to the packaged YAML files."""
        if mode not in MODES:
            raise InputError("--mode", f"must be one of {MODES}", mode)
        if isinstance(base_seed, bool) or not isinstance(base_seed, (int, np.integer)) \
                or not 0 <= base_seed < 2**63 // SEED_STRIDE - 1:
            raise InputError("--seed", "must be an integer in [0, 2^63 / 1000003 - 1) (the "
                             "sample seeds are int64)", base_seed)
        return cls(mode, int(base_seed), config or GuidanceConfig.load())

    @property
    def scenario(self) -> ScenarioConfig:
        """The scenario (Table I)."""
        return self.config.scenario

    @property
    def uncertainty(self) -> UncertaintyConfig | None:
        """The stage-3 uncertainty model (None in deterministic mode)."""
        return self.config.uncertainty if self.mode == "chance" else None

    @property
    def config_sha256(self) -> str:
        """Fingerprint of everything but the seed that determines the stored data."""
        return hashlib.sha256(json.dumps(self._config(), sort_keys=True).encode()).hexdigest()

    def _config(self) -> dict:
        return {"mode": self.mode, "guidance_config": self.config.to_json(),
                "guidance_config_sha256": self.config.sha256(),
                "pipeline_version": PIPELINE_VERSION}

    def header(self, n: int) -> dict:
        """Manifest header of a dataset of `n` samples."""
        return {"mode": self.mode, "base_seed": self.base_seed, "n": int(n),
                "seed_rule": SEED_RULE, "config_sha256": self.config_sha256,
                "config": self._config(), "stages": list(STAGES), "fields": FIELDS,
                "art_guidance_version": __version__,
                "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


@dataclass(frozen=True)
class _Models:
    """Per-process cache: the horizon and both safety models (built once, ~20 ms)."""

    chief: np.ndarray
    horizon: Horizon
    collision: PassiveSafety   # stage 2: deterministic, T_safety = 0
    passive: PassiveSafety     # stage 3: the mode's model (deterministic or chance)
    pool: SubproblemPool       # both stages' SCVx* subproblems, set up once per process


_MODELS: dict[str, _Models] = {}


def _models(spec: GenerationSpec) -> _Models:
    key = spec.config_sha256
    if key not in _MODELS:
        sc = spec.scenario
        chief = np.array(sc.chief_oe)
        horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
        _MODELS.clear()
        _MODELS[key] = _Models(chief, horizon, PassiveSafety(horizon, sc, None, t_safety_s=0.0),
                               PassiveSafety(horizon, sc, spec.uncertainty), SubproblemPool())
    return _MODELS[key]


@dataclass(frozen=True)
class Stage:
    """Outcome of one pipeline stage: status, trajectory (None unless usable), cost, effort."""

    status: ScpStatus
    roe_m: np.ndarray | None       # (N, 6) pre-burn a-scaled ROE [m]
    dv_rtn_mps: np.ndarray | None  # (N, 3) impulsive delta-v in RTN [m/s]
    cost_mps: float
    iterations: int
    time_ms: float

    @property
    def feasible(self) -> bool:
        """True when the stage's trajectory satisfies its constraints."""
        return self.status.feasible


def _run_cvx(problem: TransferProblem) -> Stage:
    t0 = time.perf_counter()
    try:
        sol = problem.cvx()
    except GuidanceError:
        return Stage(ScpStatus.SOLVER_ERROR, None, None, math.nan, 1,
                     1e3 * (time.perf_counter() - t0))
    ok = sol.status is ScpStatus.CONVERGED
    return Stage(sol.status, sol.roe_m if ok else None, sol.dv_rtn_mps if ok else None,
                 sol.cost_mps, 1, sol.solve_time_ms)


def _run_scp(spec: GenerationSpec, problem: TransferProblem, warm: np.ndarray,
             pool: SubproblemPool | None) -> Stage:
    t0 = time.perf_counter()
    try:
        res = problem.scvx(spec.config.scp, spec.config.planning.samples_per_node,
                           pool=pool).solve(warm)
    except GuidanceError:
        return Stage(ScpStatus.SOLVER_ERROR, None, None, math.nan, 0,
                     1e3 * (time.perf_counter() - t0))
    return Stage(res.status, res.roe_m, res.dv_rtn_mps, res.cost_mps, res.iterations,
                 res.solve_time_ms)


def solve_stages(spec: GenerationSpec, problem: TransferProblem, collision: PassiveSafety,
                 pool: SubproblemPool | None = None
                 ) -> tuple[tuple[Stage, Stage, Stage], int]:
    """The three stages of the pipeline on the horizon of `problem`.

    Stage 1 solves the convex TPBVP (CVX); stage 2 the collision-avoidance SCP `collision`
    (deterministic, T_safety = 0) warm-started by CVX (zeros if CVX failed); stage 3 the
    passive-safety SCP of `problem` warm-started by stage 2's returned trajectory.

    Args:
        spec: SCP and planning settings.
        problem: the transfer with the stage-3 passive-safety model (N nodes).
        collision: stage-2 model on the same horizon.
        pool: the caller's SCVx* subproblems (None: each stage sets up its own).

    Returns:
        (cvx, collision avoidance, passive safety) stages and the kept stage: 3 if stage 3 is
        feasible, else 2 if stage 2 is, else KEPT_INFEASIBLE (CVX is never kept: it ignores
        safety).
    """
    cvx = _run_cvx(problem)
    warm = cvx.dv_rtn_mps if cvx.dv_rtn_mps is not None \
        else np.zeros((problem.horizon.n_nodes, 3))
    ca = _run_scp(spec, dataclasses.replace(problem, safety=collision), warm, pool)
    ps = _run_scp(spec, problem, ca.dv_rtn_mps if ca.dv_rtn_mps is not None else warm, pool)
    kept = 3 if ps.feasible else 2 if ca.feasible else KEPT_INFEASIBLE
    return (cvx, ca, ps), kept


def stage_fields(stages: Sequence[Stage]) -> dict[str, np.ndarray]:
    """The per-stage FIELDS (status, iterations, cost, time) of the three stages."""
    return {"stage_status": np.array([s.status.value for s in stages], np.int8),
            "stage_iterations": np.array([s.iterations for s in stages], np.int32),
            "stage_cost_mps": np.array([s.cost_mps for s in stages]),
            "stage_time_ms": np.array([s.time_ms for s in stages])}


def solve_sample(spec: GenerationSpec, index: int) -> dict[str, np.ndarray]:
    """Run the paper's three stages for sample `index` and build its record (see FIELDS).

    Stage 1 solves the convex TPBVP (CVX); stage 2 the collision-avoidance SCP (deterministic,
    T_safety = 0) warm-started by CVX (zeros if CVX failed); stage 3 the mode's passive-safety
    SCP warm-started by stage 2's returned trajectory. Kept: stage 3 if feasible (SCVx*
    CONVERGED or MAX_ITERATIONS with the constraints met), else stage 2 if feasible, else none
    (the CVX solution is never kept: it ignores safety); the sample is then recorded as
    infeasible with `kept_stage` 0 (`solve_stages`).
    """
    m = _models(spec)
    n = m.horizon.n_nodes
    sample = sample_scenario(spec.scenario, sample_seed(spec.base_seed, index))
    problem = TransferProblem.to_target(m.passive, roe_from_rtn_linear(m.chief, sample.rtn0),
                                        sample.target_rtn)
    roe0, roe_f = problem.roe0_m, problem.roe_f_m
    stages, kept = solve_stages(spec, problem, m.collision, m.pool)
    cvx = stages[0]
    rec = {
        "index": np.int64(index), "seed": np.int64(sample.seed),
        "waypoint": np.str_(sample.waypoint), "rtn0": sample.rtn0,
        "target_rtn": sample.target_rtn, "roe0_m": roe0, "roe_f_m": roe_f,
        "kept_stage": np.int8(kept), "feasible": np.bool_(kept != KEPT_INFEASIBLE),
        **stage_fields(stages),
    }
    if kept:
        stage = stages[kept - 1]
        rec.update(trajectory_fields(m.horizon, m.passive, stage.roe_m, stage.dv_rtn_mps,
                                     stage.cost_mps))
    else:
        rec.update(infeasible_trajectory_fields(n))
    if cvx.roe_m is not None:
        c_cvx = m.passive.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0]
        rec.update(cvx_roe_m=cvx.roe_m, cvx_dv_rtn_mps=cvx.dv_rtn_mps,
                   cvx_cost_mps=np.float64(cvx.cost_mps), cvx_constraint_to_go0=np.int32(c_cvx))
    else:
        rec.update(cvx_roe_m=np.full((n, 6), np.nan), cvx_dv_rtn_mps=np.full((n, 3), np.nan),
                   cvx_cost_mps=np.float64(np.nan), cvx_constraint_to_go0=np.int32(-1))
    return rec


def infeasible_trajectory_fields(n: int) -> dict[str, np.ndarray]:
    """The trajectory FIELDS of a sample without a kept trajectory (NaN, C = -1), N = `n`."""
    return {"roe_m": np.full((n, 6), np.nan), "rtn": np.full((n, 6), np.nan),
            "dv_rtn_mps": np.full((n, 3), np.nan), "cost_mps": np.float64(np.nan),
            "reward_to_go_mps": np.full(n, np.nan),
            "constraint_to_go": np.full(n, -1, np.int32), "margin_m": np.full(n, np.nan)}


def trajectory_fields(horizon: Horizon, passive: PassiveSafety, roe_m: np.ndarray,
                      dv_rtn_mps: np.ndarray, cost_mps: float) -> dict[str, np.ndarray]:
    """The trajectory FIELDS of a kept trajectory over `horizon` (N nodes).

    Args:
        horizon: the horizon of the trajectory (RTN states by its Psi).
        passive: the mode's passive-safety model on that horizon (constraint-to-go, margins).
        roe_m: (N, 6) pre-burn a-scaled ROE [m].
        dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        cost_mps: the stored cost [m/s].

    Returns:
        "roe_m", "rtn", "dv_rtn_mps", "cost_mps", "reward_to_go_mps" (R(t_i) = -sum_{j >= i}
        ||dv_j||), "constraint_to_go" and "margin_m" (the model's evaluation of the trajectory).
    """
    ev = passive.evaluate(roe_m, dv_rtn_mps)
    norms = np.linalg.norm(dv_rtn_mps, axis=1)
    return {"roe_m": roe_m, "rtn": horizon.to_rtn(roe_m), "dv_rtn_mps": dv_rtn_mps,
            "cost_mps": np.float64(cost_mps),
            "reward_to_go_mps": -np.cumsum(norms[::-1])[::-1],
            "constraint_to_go": ev.constraint_to_go.astype(np.int32), "margin_m": ev.margin_m}


def generate_chunk(spec: GenerationSpec, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """The task both engines run: solve the samples `indices` and stack their records.

    Args:
        spec: generation options and configuration.
        indices: sample indices (a shard's worth).

    Returns:
        {field: (M, ...) array} with the FIELDS of every sample, in the order of `indices`.
    """
    records = [solve_sample(spec, int(i)) for i in indices]
    return {k: np.stack([r[k] for r in records]) for k in FIELDS}
