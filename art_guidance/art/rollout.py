"""Autoregressive ART rollouts with the dynamics in the loop (paper section III, "Inference").

At every planned node i (from `start_node` to the last node N - 1), for a batch of scenarios:

1. the transformer predicts the control u_i from the goal, R(t_i), C(t_i) and the state x(t_i)
   (and everything before them in the context);
2. the violation indicator v_i = [margin < 0] of node i is decided for (x_i, u_i) with the
   project's safety model (chance-constrained with the covariance recovered from x_i and u_i,
   or deterministic, whichever `safety` is), by its sign-only search
   (`PassiveSafety.violated`: the continuous minimum of `evaluate`, stopped once its sign is
   known);
3. the performance parameters are updated, R(t_{i+1}) = R(t_i) + ||u_i||,
   C(t_{i+1}) = C(t_i) - v_i, and the state propagated in ROE with the planner's own
   deputy-aware model (`Horizon.post_burn_at` and `Horizon.drift_step`, one step of
   `Horizon.propagate_nonlinear` for a batch:
   B at the deputy's pre-burn state, second-order along-track drift), the model the dataset's
   trajectories were planned with (the RTN representation feeds Psi_{i+1} x_{i+1}). Driven by a
   plan's own controls, the rollout reproduces the plan's states and constraint-to-go.

Step 2 is decided for several steps at once by default (`_run_speculative`): a window of steps
is decoded with each candidate's C updated by its last decided v_i, then their arcs are searched
in one call, and the steps after the first missed prediction are decoded again; the result is
the step-by-step loop's (`_run`, `speculate=False`) bit for bit.

Conditioning for a warm start: R(t_1) = -J_CVX, C(t_1) = 0, goal = the request's target. The
horizon may be shorter than the context K; its nodes use the last time-step indices
(K - n .. K - 1), so a replan from node k over the remaining horizon looks like the tail of a
training trajectory. `use_cache=False` recomputes the whole context at every step through the
module's forward pass (the reference the KV cache is tested against).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from art_guidance.art.policies import CachedPolicy, History, RecomputePolicy
from art_guidance.checks import as_finite_array
from art_guidance.config import GuidanceConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.errors import DeadlineError, InputError
from art_guidance.optim.transfer import terminal_roe
from art_guidance.safety import PassiveSafety

# A burn-gate model coasts at a node where its gate logit is at most this (0: p(burn) <= 0.5).
GATE_LOGIT_THRESHOLD = 0.0


@dataclass(frozen=True)
class RolloutResult:
    """A batch of rollouts over nodes `nodes` (T of them) of the horizon.

    Attributes:
        nodes: (T,) horizon node indices planned.
        dv_rtn_mps: (B, T, 3) planned impulsive delta-v in RTN [m/s].
        roe_m: (B, T, 6) pre-burn a-scaled ROE at the planned nodes [m].
        reward_to_go_mps: (B, T) R(t_i) fed to the model (conditioning history) [m/s].
        constraint_to_go: (B, T) C(t_i) fed to the model (conditioning history).
        violation: (B, T) int 0/1 violation indicator v_i.
    """

    nodes: np.ndarray
    dv_rtn_mps: np.ndarray
    roe_m: np.ndarray
    reward_to_go_mps: np.ndarray
    constraint_to_go: np.ndarray
    violation: np.ndarray

    @property
    def cost_mps(self) -> np.ndarray:
        """(B,) sum of ||dv|| [m/s]."""
        return np.linalg.norm(self.dv_rtn_mps, axis=-1).sum(axis=-1)

    @property
    def realised_reward_to_go_mps(self) -> np.ndarray:
        """(B, T) realised R(t_i) = -sum_{j >= i} ||u_j|| of the rollout [m/s]."""
        norms = np.linalg.norm(self.dv_rtn_mps, axis=-1)
        return -np.cumsum(norms[:, ::-1], axis=1)[:, ::-1]

    @property
    def realised_constraint_to_go(self) -> np.ndarray:
        """(B, T) realised C(t_i) = sum_{j >= i} v_j of the rollout (C(t_1): column 0)."""
        return np.cumsum(self.violation[:, ::-1], axis=1)[:, ::-1]


def training_config(art) -> GuidanceConfig | None:
    """The configuration bundle of the dataset the model was trained on (None if the
    checkpoint does not record one).

    Raises:
        ConfigError: a recorded bundle that is malformed.
    """
    bundle = art.meta.get("dataset", {}).get("guidance_config")
    return GuidanceConfig.from_json(bundle) if bundle else None


def build_safety(art, chance_constrained: bool | None = None) -> PassiveSafety:
    """The horizon and passive-safety model of the dataset the model was trained on.

    Args:
        art: a model whose meta holds the dataset's configuration bundle (else the packaged
            defaults are used).
        chance_constrained: override the dataset's mode (None: chance if the dataset was).
    """
    data = art.meta.get("dataset", {})
    config = training_config(art) or GuidanceConfig()
    chance = data.get("mode") == "chance" if chance_constrained is None else chance_constrained
    scenario = config.scenario
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    return PassiveSafety(horizon, scenario, config.uncertainty if chance else None)


def _history(art, history: object, t0: int, b: int) -> History:
    """The flown steps of `history` as the policies' normalised, batch-tiled tokens at the
    time indices t0 - h .. t0 - 1.

    Raises:
        InputError: malformed arrays, or more steps than fit before t0.
    """
    states = history.rtn if art.config.representation == "rtn" else history.roe_m
    h = int(np.shape(states)[0]) if np.ndim(states) == 2 else -1
    if not 1 <= h <= t0:
        raise InputError("history", f"needs 1..{t0} flown steps of (h, 6) states "
                         "(the context left before the first planned node)", np.shape(states))
    states = as_finite_array("history states", states, (h, 6))
    dv = as_finite_array("history dv_rtn_mps", history.dv_rtn_mps, (h, 3))
    r = as_finite_array("history reward_mps", history.reward_mps, (h,))
    c = as_finite_array("history constraint", history.constraint, (h,))
    norm, times = art.normalizer, np.arange(t0 - h, t0)

    def tiled(name: str, values: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        z = np.asarray(norm.normalize(name, values, t), dtype=float)
        return np.broadcast_to(z, (b, *z.shape)).copy()

    return History(tiled("reward", r), tiled("constraint", c), tiled("state", states, times),
                   tiled("control", dv, times))


def _batch(field: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """`value` broadcast to the batch `shape` as a finite float array (a copy)."""
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), shape)
    except ValueError as exc:
        raise InputError(field, f"cannot broadcast to {shape}: {exc}") from exc
    return as_finite_array(field, arr, shape).copy()


def rollout(art, safety: PassiveSafety, roe_m: object, target_rtn: object,
            reward_mps: object, constraint: object = 0.0, start_node: int = 0,
            use_cache: bool = True, deadline: float | None = None,
            speculate: bool = True, history: object = None) -> RolloutResult:
    """Roll the model out over nodes start_node .. N - 1 of `safety.horizon` for a batch.

    Args:
        art: the trained model (`TrainedArt`, torch) or an exported one (`ExportedArt`, ONNX
            Runtime; KV-cached only).
        safety: passive-safety model of the horizon (chance-constrained or deterministic); its
            `horizon` gives the dynamics and Psi.
        roe_m: (B, 6) or (6,) pre-burn a-scaled ROE at `start_node` [m].
        target_rtn: (B, 6) or (6,) terminal RTN state after the last burn [m, m/s] (the goal).
        reward_mps: (B,) or scalar R at `start_node`, e.g. -J_CVX [m/s].
        constraint: (B,) or scalar C at `start_node` (0 asks for a passively safe plan).
        start_node: first node to plan (a replan over the remaining horizon).
        use_cache: KV-cached incremental decoding (default) or recompute the whole context.
        deadline: a `time.perf_counter()` instant after which no further step is started
            (None: no limit).
        speculate: decode several steps ahead and decide their violations in one search
            (`_run_speculative`, the default with the cache); False: one step at a time
            (`_run`, its oracle: the same result bit for bit, tested).
        history: the steps flown before `start_node` (the replan's context, `art.policies`),
            or None: anything with (h, 6) `roe_m` and `rtn`, (h, 3) `dv_rtn_mps`, (h,)
            `reward_mps` and `constraint`; they take the h time-step indices before the
            first planned node's (h + the planned nodes <= K).

    Returns:
        RolloutResult over the T = N - start_node planned nodes.

    Raises:
        InputError: bad shapes or values, or more steps than the model's context K.
        DeadlineError: the deadline passed before the last step.
    """
    horizon = safety.horizon
    x, target, r, c, start = _inputs(horizon, roe_m, target_rtn, reward_mps, constraint,
                                     start_node, art.config.context)
    n_steps = horizon.n_nodes - start
    rtn_repr = art.config.representation == "rtn"
    goal = target if rtn_repr else terminal_roe(horizon, target)  # (B, 6)
    norm = art.normalizer
    t0 = art.config.context - n_steps  # time-step index of the first planned node
    gate = art.config.burn_gate
    if not use_cache and getattr(art, "runtime", "torch") != "torch":
        raise InputError("use_cache", "recomputing the whole context needs the torch model",
                         use_cache)
    past = None if history is None else _history(art, history, t0, x.shape[0])
    policy = (CachedPolicy if use_cache else RecomputePolicy)(
        art, norm.normalize("goal", goal), t0, n_steps, past)

    def control(j: int, node: int, x: np.ndarray, r: np.ndarray, c: np.ndarray,
                u_prev: np.ndarray | None) -> np.ndarray:
        t = t0 + j
        state = x @ horizon.psi[node].T if rtn_repr else x  # (B, 6)
        prev = None if u_prev is None else norm.normalize("control", u_prev, t - 1)
        out = policy.control(j, norm.normalize("reward", r), norm.normalize("constraint", c),
                             norm.normalize("state", state, t), prev)  # (B, 3 (+1))
        u = norm.denormalize("control", out[:, :3].astype(float), t)  # (B, 3) [m/s]
        if gate:  # coast where the gate says no burn
            u[out[:, 3] <= GATE_LOGIT_THRESHOLD] = 0.0
        return u

    run = _run_speculative if speculate and use_cache else _run
    return run(safety, x, r, c, start, control, deadline)


def replay(safety: PassiveSafety, roe_m: object, dv_rtn_mps: object, reward_mps: object,
           constraint: object = 0.0, start_node: int = 0) -> RolloutResult:
    """The rollout machinery driven by given controls instead of a model (the oracle).

    Same propagation, R and C updates as `rollout`: fed a plan's own controls, it must give
    the plan's states and constraint-to-go, so a perfect model is judged as its teacher.

    Args:
        safety: passive-safety model of the horizon.
        roe_m: (B, 6) or (6,) pre-burn a-scaled ROE at `start_node` [m].
        dv_rtn_mps: (B, T, 3) or (T, 3) controls for nodes start_node .. N - 1 [m/s].
        reward_mps: (B,) or scalar R at `start_node` [m/s].
        constraint: (B,) or scalar C at `start_node`.
        start_node: first node.

    Raises:
        InputError: bad shapes or values.
    """
    horizon = safety.horizon
    x, _, r, c, start = _inputs(horizon, roe_m, np.zeros(6), reward_mps, constraint,
                                start_node, horizon.n_nodes)
    n_steps = horizon.n_nodes - start
    u = np.asarray(dv_rtn_mps, dtype=float)
    u = as_finite_array("dv_rtn_mps", u[None] if u.ndim == 2 else u, (x.shape[0], n_steps, 3))
    return _run(safety, x, r, c, start, lambda j, node, x, r, c, u_prev: u[:, j])


def _inputs(horizon: Horizon, roe_m: object, target_rtn: object, reward_mps: object,
            constraint: object, start_node: int, k: int) -> tuple:
    """Validated batch inputs of a rollout: (x, target, r, c, start)."""
    n_nodes = horizon.n_nodes
    x = as_finite_array("roe_m", np.atleast_2d(np.asarray(roe_m, dtype=float)), (None, 6))
    b = x.shape[0]
    target = _batch("target_rtn", target_rtn, (b, 6))
    r, c = _batch("reward_mps", reward_mps, (b,)), _batch("constraint", constraint, (b,))
    if isinstance(start_node, bool) or int(start_node) != start_node \
            or not 0 <= start_node < n_nodes or n_nodes - start_node > k:
        raise InputError("start_node", f"must be an integer leaving 1..{k} nodes of the "
                         f"{n_nodes}-node horizon", start_node)
    return x.copy(), target, r, c, int(start_node)


def _run(safety: PassiveSafety, x: np.ndarray, r: np.ndarray, c: np.ndarray, start: int,
         control, deadline: float | None = None) -> RolloutResult:
    """The rollout loop: control, violation, R/C update, deputy-aware propagation.

    `control(j, node, x, r, c, u_prev)` returns the (B, 3) burn [m/s] of step j at `node`
    (`u_prev`: the burn applied at step j - 1, None at step 0); a step is not started after
    `deadline` (a `time.perf_counter()` instant; DeadlineError).
    """
    horizon = safety.horizon
    n_nodes = horizon.n_nodes
    b, n_steps = x.shape[0], n_nodes - start
    dv, roe = np.empty((b, n_steps, 3)), np.empty((b, n_steps, 6))
    rs, cs = np.empty((b, n_steps)), np.empty((b, n_steps))
    viol = np.empty((b, n_steps), dtype=int)
    for j, node in enumerate(range(start, n_nodes)):
        if deadline is not None and time.perf_counter() > deadline:
            raise DeadlineError(f"rollout stopped at step {j} of {n_steps}: the deadline "
                                "passed")
        u = control(j, node, x, r, c, dv[:, j - 1] if j else None)  # (B, 3) [m/s]
        z = horizon.post_burn_at(node, x, u)  # (B, 6) post-burn, deputy-aware
        v = safety.violated(node, x, u, z)  # (B,) bool
        dv[:, j], roe[:, j], rs[:, j], cs[:, j], viol[:, j] = u, x, r, c, v
        r = r + np.sqrt(np.einsum("bi,bi->b", u, u))  # R(t_{i+1}) = R(t_i) + ||u_i||
        c = c - v  # C(t_{i+1}) = C(t_i) - v_i
        if node < n_nodes - 1:
            x = horizon.drift_step(node, z)  # (B, 6): one step of propagate_nonlinear
    return RolloutResult(np.arange(start, n_nodes), dv, roe, rs, cs, viol)


# Speculative steps decoded before their violations are searched: the window doubles while
# the predictions hold, up to this many steps, and starts again from one after a miss. Paired
# CPU of the learned step against one step at a time (12 chance-constrained scenarios, 3
# repeats): windows of 4, 6, 8, 16 steps 0.83, 0.82, 0.83, 0.89x with the default model and
# 0.75, 0.73, 0.74, 0.78x with the slim one (longer windows decode more steps again after a
# miss: 110 and 120 steps of 100 at 8 and 16; halving the window after a miss instead: same).
SPECULATE_MAX_STEPS = 8


def _run_speculative(safety: PassiveSafety, x: np.ndarray, r: np.ndarray, c: np.ndarray,
                     start: int, control, deadline: float | None = None) -> RolloutResult:
    """`_run`'s result, with the violations of several steps decided in one search.

    Only C feeds a step's violation back into the model, and violations come in runs: a
    window of steps is decoded and propagated with each candidate's C updated by its last
    decided v_i (the prediction), then the window's arcs are searched at once
    (`PassiveSafety.violated` of any mix of nodes, a few dozen numpy calls instead of a few
    hundred per step). The steps up to and including the first where a prediction missed are
    kept; the rollout goes on from the next, whose C is now known. The decoders write the
    tokens by position, so decoding a step again overwrites what the miss left. A kept step
    had the inputs `_run` would have given it, hence the same numbers.
    """
    horizon = safety.horizon
    n_nodes = horizon.n_nodes
    b, n_steps = x.shape[0], n_nodes - start
    dv, roe = np.empty((b, n_steps, 3)), np.empty((b, n_steps, 6))
    rs, cs = np.empty((b, n_steps)), np.empty((b, n_steps))
    z_all = np.empty((b, n_steps, 6))
    viol = np.empty((b, n_steps), dtype=int)
    v_last = np.zeros(b, dtype=bool)  # the last decided violation of each candidate
    nodes = np.arange(start, n_nodes)
    j, width = 0, 1
    while j < n_steps:
        end = min(j + width, n_steps)
        xk, rk, ck = x, r, c
        for k in range(j, end):
            if deadline is not None and time.perf_counter() > deadline:
                raise DeadlineError(f"rollout stopped at step {k} of {n_steps}: the deadline "
                                    "passed")
            node = start + k
            u = control(k, node, xk, rk, ck, dv[:, k - 1] if k else None)  # (B, 3) [m/s]
            z = horizon.post_burn_at(node, xk, u)  # (B, 6) post-burn, deputy-aware
            dv[:, k], roe[:, k], rs[:, k], cs[:, k], z_all[:, k] = u, xk, rk, ck, z
            rk = rk + np.sqrt(np.einsum("bi,bi->b", u, u))
            ck = ck - v_last  # predicted: C(t_{k+1}) = C(t_k) - v_k with v_k = v_last
            if node < n_nodes - 1:
                xk = horizon.drift_step(node, z)
        w = end - j
        v = safety.violated(np.repeat(nodes[j:end][None], b, 0).ravel(),
                            roe[:, j:end].reshape(-1, 6), dv[:, j:end].reshape(-1, 3),
                            z_all[:, j:end].reshape(-1, 6)).reshape(b, w)
        missed = np.flatnonzero((v != v_last[:, None]).any(axis=0))
        keep = w if missed.size == 0 else int(missed[0]) + 1  # steps j .. j + keep - 1 hold
        viol[:, j:j + keep] = v[:, :keep]
        v_last = v[:, keep - 1].copy()
        c = cs[:, j + keep - 1] - v_last
        if keep == w:
            x, r = xk, rk
        else:  # the next step's state and R, already propagated (they do not depend on C)
            x, r = roe[:, j + keep].copy(), rs[:, j + keep].copy()
        j += keep
        width = min(2 * width, SPECULATE_MAX_STEPS) if missed.size == 0 else 1
    return RolloutResult(nodes, dv, roe, rs, cs, viol)
