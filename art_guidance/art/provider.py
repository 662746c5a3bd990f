"""The learned warm start in flight: `ArtWarmStart`, the `WarmStartProvider` over a trained ART.

`GuidancePipeline(provider=ArtWarmStart.load())` rolls the model out from the request's state
with C(t_1) = 0 and the request's target as goal, over the request's horizon (a replan over the
remaining k nodes is the tail of a training trajectory: the rollout uses the last k time-step
embeddings). The pipeline validates the proposal and applies the post hoc check; this module
only proposes.

Conditioning sweep: one batched rollout per reward-to-go R(t_1) = -s J_CVX for each s of
`reward_scales` (default `DEFAULT_REWARD_SCALES`; (1.0,) is the paper's single rollout). The
candidates differ in where and how much they burn, and the one proposed is the best by the
post hoc criteria, judged as the pipeline's check judges them (by default on each candidate's
terminal warm start, `planning.learned`; E_R against R_des = -J_CVX whatever s was): inside
the acceptance region first, then the smallest E_C, then the smallest |E_R|; when no candidate
is inside, the cheapest passively safe one, else the cheapest (`best_candidate`). On 300 held-out
scenarios eight scales give a passively safe rollout in 67 % (one rollout: 38 %) and one inside
the region in 38 % (13 %), at about twice the rollout time; judging the terminal warm starts
adds one correction and one safety evaluation per candidate (docs/art_training.md).

The model is loaded once (`load`, typically at node start-up) and checked against its
checksum. It runs on one of two runtimes (`runtime`): "torch" (the checkpoint, `TrainedArt`,
on `threads` threads, default 1: at batch 1 that is the fastest, and the result does not depend
on the machine's core count, so a replay on another machine reproduces it) or "onnx" (the
exported file beside it, `onnx_art.ExportedArt`, on ONNX Runtime with one thread, without
torch). "auto" takes "onnx" where ONNX Runtime is installed and the checkpoint's exported file
is there, else "torch" (`resolve_runtime`). With "auto" the checkpoint and its exported file
are a pair, whichever of them is named: a refused exported file gives way to the checkpoint on
torch, and a refused checkpoint beside an exported file that flies is named (`note`).
"""
from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from art_guidance.art.checkpoint_header import header_sha256
from art_guidance.art.model_files import (  # noqa: F401 (the models.json readers, as before)
    DEFAULTS_KEY, checkpoint_beside, checkpoint_problem, models_dir, pinned_sha256,
    shipped_defaults, shipped_model_with_sha256, shipped_models,
)
from art_guidance.art.onnx_art import (
    ONNX_SUFFIX, RUNTIMES, exported_path, installed, load_exported,
)
from art_guidance.art.policies import fitted_context
from art_guidance.art.rollout import RolloutResult, rollout, training_config
from art_guidance.config import PlanningConfig, PosthocThresholds, mode_name
from art_guidance.deadline import Deadline
from art_guidance.dynamics import orbital_period_s
from art_guidance.errors import CheckpointError, InputError, ModelError
from art_guidance.optim import ConvexSolution, Trajectory, TransferProblem
from art_guidance.planning.learned import judged_trajectory
from art_guidance.planning.result import WarmStartProposal
from art_guidance.safety import PassiveSafety

# The shipped default per passive-safety mode (the mode of the model's training data), chosen by
# what the node flies on >= 2,000 fresh scenarios per mode (benchmarks/analyses/default_models.py:
# never worse than CVX alone by > 1 mm/s, a mean flown saving within the paired 95 % interval of
# the best's, then the cheapest proposal; docs/results.md "Shipped defaults"), not by the rollout
# metrics. models.json says the same under "defaults", with the reasons. The defaults are the
# one-token students of the RTN (chance-constrained) and ROE (deterministic) teachers; the teachers
# stay shipped beside them (TEACHERS), loadable by path.
DEFAULT_MODEL = "art_slim1e40_chance_rtn.pt"
DEFAULT_MODELS = {"chance": DEFAULT_MODEL, "deterministic": "art_slim1e40_det_roe.pt"}
TEACHERS = {"chance": "art_small_chance_rtn.pt", "deterministic": "art_small_det_roe.pt"}
SPACING_REL_TOL = 0.01  # node spacing of a request vs the training horizon's [-]
DEFAULT_REWARD_SCALES = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2)  # R(t_1) = -s J_CVX


def default_model_path(mode: str = "chance") -> Path:
    """The shipped default model of a passive-safety mode ("chance" or "deterministic"),
    trained on data of that mode (`DEFAULT_MODELS`: the one-token students of the RTN teacher
    for "chance" and of the ROE teacher for "deterministic").

    Raises:
        ValueError: an unknown mode.
    """
    if mode not in DEFAULT_MODELS:
        raise ValueError(f"unknown passive-safety mode {mode!r}; choose from "
                         f"{sorted(DEFAULT_MODELS)}")
    return models_dir() / DEFAULT_MODELS[mode]


def resolve_model_path(spec: str | None, chance_constrained: bool = True) -> Path | None:
    """A model path from a parameter value: "" or None = the shipped default of the planning
    mode (chance-constrained or deterministic), "none" = no model (CVX only), anything else a
    file path."""
    if spec is None or str(spec).strip() == "":
        return default_model_path(mode_name(chance_constrained))
    if str(spec).strip().lower() == "none":
        return None
    return Path(spec).expanduser()


def _without_onnx_runtime(path: Path, runtime: str) -> tuple[Path, str]:
    """On "auto", an .onnx `path` without ONNX Runtime gives way to the checkpoint beside it on
    torch (where torch is there), as a refused .onnx does: (file to load, why not `path`)."""
    if runtime != "auto" or path.suffix != ONNX_SUFFIX or installed("onnxruntime"):
        return path, ""
    beside = checkpoint_beside(path)
    if not beside.is_file() or not installed("torch"):
        return path, ""
    return beside, (f"{path.name} refused: it runs on ONNX Runtime, which is not installed; "
                    f"the checkpoint beside it, {beside.name}, flies on torch")


def resolve_runtime(runtime: str, path: str | Path) -> str:
    """The runtime a model file flies on: "torch" or "onnx" (module docstring).

    Raises:
        InputError: an unknown runtime, or "torch" asked of an exported (.onnx) file.
        ModelError: the runtime is not installed.
    """
    if runtime not in RUNTIMES:
        raise InputError("art_runtime", f"must be one of {', '.join(RUNTIMES)}", runtime)
    path = Path(path)
    onnx_ok = installed("onnxruntime")
    if path.suffix == ONNX_SUFFIX:
        if runtime == "torch":
            raise InputError("art_runtime", f"{path.name} is an exported model: it runs on the "
                             "onnx runtime (give the checkpoint for torch)", runtime)
        runtime = "onnx"
    elif runtime == "auto":
        runtime = "onnx" if onnx_ok and exported_path(path).is_file() else "torch"
    if runtime == "torch" and not installed("torch"):
        raise ModelError("the torch runtime needs torch, which is not installed: fly an "
                         "exported model on the onnx runtime (art-guidance export)")
    if runtime == "onnx" and not onnx_ok:
        raise ModelError("the onnx runtime needs the Python package onnxruntime, which is "
                         "not installed")
    return runtime


def _load_file(path: Path, runtime: str, expected: str | None):
    """The model of file `path` on `runtime`: on "onnx" the .onnx `path` itself or the exported
    file beside checkpoint `path`, checked against `expected` (else the checkpoint header's
    checksum); on "torch" the checkpoint."""
    if runtime == "torch":
        from art_guidance.art.checkpoint import load as load_checkpoint

        art = load_checkpoint(path, expected_sha256=expected)
        art.decoder  # pack the cached decoder now, not in the first plan
        return art
    if path.suffix != ONNX_SUFFIX:
        expected = expected or header_sha256(path)
        path = exported_path(path)
        if not path.is_file():
            raise CheckpointError(path, "no exported model here: run `art-guidance export` on "
                                        "the checkpoint")
    return load_exported(path, expected, pinned_sha256(path))


def _load_pair(path: Path, expected: str | None) -> tuple[object, str]:
    """"auto" where ONNX Runtime and an exported file are there: the pair of the checkpoint and
    its exported file beside it, whichever of them `path` names. The exported model flies on
    onnx; where it is refused, the checkpoint on torch (where it is intact and torch is
    installed). Returns (model, note): the note names a refused file of the pair and why
    ("" = none was).

    Raises:
        CheckpointError: neither file loads (the message names both and why).
    """
    if path.suffix == ONNX_SUFFIX:
        checkpoint, exported = checkpoint_beside(path), path
    else:
        checkpoint, exported = path, exported_path(path)
    # the checkpoint named is checked whole, one beside the export given where there is one
    damage = (checkpoint_problem(checkpoint, expected)
              if checkpoint == path or checkpoint.is_file() else None)
    source = expected
    if source is None and checkpoint == path:
        with contextlib.suppress(CheckpointError):
            source = header_sha256(checkpoint)  # the export must come from this checkpoint
    try:
        art = load_exported(exported, source, pinned_sha256(exported))
    except CheckpointError as exc:
        if damage is not None:
            raise CheckpointError(exc.path, f"{exc.reason}; and {checkpoint}: {damage}") from exc
        if not (checkpoint.is_file() and installed("torch")):
            raise
        try:
            art = _load_file(checkpoint, "torch", expected)
        except CheckpointError as torch_exc:
            raise CheckpointError(exc.path, f"{exc.reason}; and {torch_exc}") from exc
        return art, (f"the exported model was refused ({exc}); flying the checkpoint on "
                     f"torch instead: {checkpoint}")
    if damage is None:
        return art, ""
    unchecked = (" (not checked against it: its checksum is unreadable)"
                 if checkpoint == path and source is None else "")
    return art, (f"the checkpoint was refused ({checkpoint}: {damage}); flying its exported "
                 f"model on onnx{unchecked}, without a torch fallback: {exported}")


class ArtWarmStart:
    """Proposes ART rollouts as SCP warm starts (a `planning.WarmStartProvider`).

    Attributes:
        art: the trained model (`TrainedArt`) or its exported file (`ExportedArt`).
        runtime: "torch" or "onnx".
        sha256: its checkpoint's payload checksum, the model's identity on either runtime
            ("" if built in memory).
        runtime_sha256: the checksum of what the runtime runs: the exported file's on "onnx",
            the checkpoint's on "torch".
        path: the file it was loaded from ("" if built in memory).
        load_ms: wall time of loading and checking the checkpoint [ms].
        node_spacing_s: node spacing of the training horizon [s] (None: not recorded).
        reward_scales: the conditioning sweep, R(t_1) = -s J_CVX for each s (one batched
            rollout; the best candidate is proposed).
    """

    def __init__(self, art, load_ms: float = 0.0, threads: int = 1,
                 reward_scales: tuple[float, ...] = DEFAULT_REWARD_SCALES) -> None:
        scales = tuple(float(x) for x in reward_scales)
        if not scales or not all(np.isfinite(x) and x > 0 for x in scales):
            raise ModelError(f"reward_scales must be positive numbers, got {reward_scales!r}")
        self.reward_scales = scales
        self.art = art
        self.runtime = getattr(art, "runtime", "torch")
        self.sha256 = art.sha256 or ""
        self.runtime_sha256 = getattr(art, "file_sha256", self.sha256)
        self.path = art.path or ""
        self.load_ms = float(load_ms)
        self.threads = int(threads)
        self._lock = threading.Lock()  # one KV cache per model: one rollout at a time
        self.note = ""  # a file of the pair "auto" refused, and what flies ("" = none)
        self.node_spacing_s = _training_spacing_s(art)

    @classmethod
    def load(cls, path: str | Path | None = None, expected_sha256: str | None = None,
             threads: int = 1, reward_scales: tuple[float, ...] = DEFAULT_REWARD_SCALES,
             runtime: str = "auto") -> "ArtWarmStart":
        """Load and check a model (default: the shipped model) for a runtime
        (`resolve_runtime`). A shipped file is also checked against the checksum pinned in
        `models/models.json`, so a swapped or damaged file is refused. On "onnx" the exported
        file (the .onnx given, or the one beside the checkpoint) must have been exported from
        the checkpoint (`expected_sha256`, else the pinned or the checkpoint header's checksum).
        On "auto" with an exported file (the .onnx given, or the one beside the checkpoint
        given) each file of the pair stands in for the other (`_load_pair`): a refused
        exported file gives way to the intact checkpoint beside it on torch, and an exported
        file flies beside a refused checkpoint; `note` names the refused file and why.

        Raises:
            InputError: an unknown runtime, or torch asked of an exported file.
            ModelError: the runtime is not installed.
            CheckpointError: missing, corrupt, truncated, tampered, wrong-version or
                wrong-shape file, or an exported file of another checkpoint (the message names
                the file and the reason; on "auto", both files of a pair neither of which
                loads).
        """
        t0 = time.perf_counter()
        path = Path(path or default_model_path())
        path, moved = _without_onnx_runtime(path, runtime)
        asked, runtime = runtime, resolve_runtime(runtime, path)
        expected = expected_sha256 or pinned_sha256(
            checkpoint_beside(path) if path.suffix == ONNX_SUFFIX else path)
        if asked == "auto" and runtime == "onnx":
            art, note = _load_pair(path, expected)
        else:
            art, note = _load_file(path, runtime, expected), ""
        provider = cls(art, 1e3 * (time.perf_counter() - t0), threads, reward_scales)
        provider.note = "; ".join(filter(None, (moved, note)))
        return provider

    def describe(self) -> str:
        """One line: file, preset size, representation, checksum, runtime."""
        cfg = self.art.config
        n_params = self.art.n_parameters
        return (f"{Path(self.path).name or 'in-memory model'}: {cfg.n_layers}x{cfg.width} "
                f"({n_params / 1e6:.2f} M parameters), {cfg.representation.upper()} states, "
                f"sha256 {self.sha256[:12] or '-'}, runtime {self.runtime}")

    def check_domain(self, safety: PassiveSafety) -> None:
        """Raise ModelError if the horizon is outside what the model was trained on."""
        horizon = safety.horizon
        n, k = horizon.n_nodes, self.art.config.context
        if n > k:
            raise ModelError(f"a {n}-node horizon is longer than the model's context of {k} "
                             "steps")
        if self.node_spacing_s is not None and n >= 2:
            spacing = float(np.mean(np.diff(horizon.epochs_s)))
            if abs(spacing / self.node_spacing_s - 1.0) > SPACING_REL_TOL:
                raise ModelError(f"node spacing {spacing:.1f} s differs from the training "
                                 f"horizon's {self.node_spacing_s:.1f} s")

    def propose(self, problem: TransferProblem, cvx: ConvexSolution,
                planning: PlanningConfig | None = None,
                deadline: Deadline | None = None, context: object = None
                ) -> WarmStartProposal:
        """Roll the model out from `problem.roe0_m` to its RTN target over its horizon.

        Args:
            planning: the planning options whose post hoc check ranks the candidates (its
                region and `posthoc_subject`; None: the packaged defaults).
            deadline: the plan's deadline: the rollout stops at its first step after it
                (None: none).
            context: the steps flown before the horizon's first node
                (`planning.request.RolloutContext`), fed to the model before them (the last
                K - N of them where they do not all fit the context K), or None.

        Raises:
            ModelError: the horizon is outside the model's domain.
            InputError: non-finite conditioning (e.g. a non-finite J_CVX), or a problem
                without an RTN target.
            DeadlineError: the deadline passed during the rollout.
        """
        safety = problem.safety
        self.check_domain(safety)
        if problem.target_rtn is None:
            raise InputError("target_rtn", "the proposal's goal is the problem's RTN target: "
                             "build the problem with TransferProblem.to_target")
        t0 = time.perf_counter()
        j_cvx = float(cvx.cost_mps)
        k = len(self.reward_scales)
        history = fitted_context(context, self.art.config.context - safety.horizon.n_nodes)
        with self._lock, _threads(self.runtime, self.threads):
            res = rollout(self.art, safety, np.tile(problem.roe0_m, (k, 1)),
                          problem.target_rtn, -j_cvx * np.array(self.reward_scales), 0.0,
                          deadline=None if deadline is None else deadline.at_s,
                          history=history)
        planning = planning or PlanningConfig()
        judged = judge_candidates(res, problem, planning.posthoc_subject)
        b = best_candidate(judged.cost_mps, judged.c_t1, j_cvx, planning.posthoc)
        warm = None
        if planning.posthoc_subject == "warm_start":  # the one the check and SCVx* start from:
            warm = Trajectory(judged.dv_rtn_mps[b], judged.roe_m[b])  # projected once
        return WarmStartProposal(res.dv_rtn_mps[b], res.realised_reward_to_go_mps[b],
                                 res.realised_constraint_to_go[b].astype(float), self.sha256,
                                 1e3 * (time.perf_counter() - t0), warm)


@dataclass(frozen=True)
class JudgedCandidates:
    """K candidates as the post hoc check judges them.

    Attributes:
        cost_mps: (K,) cost of the judged trajectory [m/s].
        c_t1: (K,) its C(t_1) (sign-only search: the check's except where a node's minimum is
            within the certification tolerance of zero).
        dv_rtn_mps: (K, N, 3) the judged controls [m/s] (the terminal warm starts, or the
            rollouts' own controls), None when only the rollout's figures were used.
        roe_m: (K, N, 6) their states [m], or None likewise.
    """

    cost_mps: np.ndarray
    c_t1: np.ndarray
    dv_rtn_mps: np.ndarray | None = None
    roe_m: np.ndarray | None = None


def judged_candidates(res: RolloutResult, problem: TransferProblem,
                      subject: str) -> tuple[np.ndarray, np.ndarray]:
    """(K,) cost [m/s] and (K,) C(t_1) of each candidate as the post hoc check judges it
    (`judge_candidates`)."""
    judged = judge_candidates(res, problem, subject)
    return judged.cost_mps, judged.c_t1


def judge_candidates(res: RolloutResult, problem: TransferProblem,
                     subject: str) -> JudgedCandidates:
    """The candidates of a rollout as the post hoc check judges them
    (`planning.learned.judged_trajectory`): the rollout's own figures (realised in the
    rollout) or those of each terminal warm start (`judge_controls`)."""
    if subject == "rollout":
        return JudgedCandidates(res.cost_mps, res.realised_constraint_to_go[:, 0])
    return judge_controls(problem, res.dv_rtn_mps, subject)


def judged_controls(problem: TransferProblem, dv_rtn_mps: np.ndarray,
                    subject: str) -> tuple[np.ndarray, np.ndarray]:
    """(K,) cost [m/s] and (K,) C(t_1) of K candidate controls (`judge_controls`)."""
    judged = judge_controls(problem, dv_rtn_mps, subject)
    return judged.cost_mps, judged.c_t1


def judge_controls(problem: TransferProblem, dv_rtn_mps: np.ndarray,
                   subject: str) -> JudgedCandidates:
    """K candidate controls (K, N, 3) [m/s] of `problem` as the check judges them under
    `subject`: the trajectory `planning.learned.judged_trajectory` gives (one correction
    each), then one sign-only safety search over the arcs of all K
    (`PassiveSafety.violations_batch`)."""
    judged = [judged_trajectory(problem, dv, subject) for dv in dv_rtn_mps]
    dv_w = np.stack([dv for dv, _ in judged])  # (K, N, 3) [m/s]
    roe_w = np.stack([roe for _, roe in judged])  # (K, N, 6) [m]
    cost = np.linalg.norm(dv_w, axis=2).sum(axis=1)
    # the candidates' C(t_1) counts signs only: one sign-only search over all K N arcs
    c_t1 = problem.safety.violations_batch(roe_w, dv_w).sum(axis=1)
    return JudgedCandidates(cost, c_t1.astype(float), dv_w, roe_w)


def best_candidate(cost_mps: np.ndarray, c_t1: np.ndarray, j_cvx: float,
                   thresholds: PosthocThresholds) -> int:
    """Index of the rollout to propose among candidates of one request.

    Ranked by the post hoc criteria as realised: a candidate inside the acceptance region
    first (among those, the smallest E_C = C(t_1), then the smallest |E_R|,
    E_R = (J - J_CVX) / J_CVX). When none is inside, the check will reject the proposal
    whatever it is, and what it is still worth is as a start for SCVx* (the fallback's retry,
    the warm-start analysis): then a passively safe candidate (E_C = 0) if there is one, and
    the cheapest of those, which SCVx* converges from to cheaper plans than from the least
    violating one (on 300 fresh scenarios per mode: the improvement over SCVx* from CVX over
    all scenarios -13.6 -> -0.2 % chance-constrained, -6.0 -> +12.3 % deterministic, against
    the smallest E_C first; docs/art_training.md). Ties go to the first candidate.

    Args:
        cost_mps: (K,) candidate costs sum ||dv|| [m/s].
        c_t1: (K,) realised C(t_1) of each candidate.
        j_cvx: J_CVX [m/s].
        thresholds: the acceptance region.
    """
    cost = np.asarray(cost_mps, dtype=float)
    e_r_pct = 100.0 * (cost - j_cvx) / j_cvx if j_cvx > 0 else np.full(len(cost), np.inf)
    e_c = np.asarray(c_t1, dtype=float)
    inside = thresholds.contains(e_r_pct, e_c)
    if inside.any():
        order = np.lexsort((np.abs(e_r_pct), e_c, ~inside))  # last key is the primary one
    else:
        order = np.lexsort((cost, e_c > 0))  # safe first, then the cheapest
    return int(order[0])


@contextlib.contextmanager
def _threads(runtime: str, threads: int):
    """torch on `threads` threads for the block (ONNX Runtime's session has its own: 1)."""
    if runtime != "torch":
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _training_spacing_s(art) -> float | None:
    """Node spacing of the horizon the model's dataset was generated on [s]."""
    try:
        config = training_config(art)
    except Exception:  # provenance is informative; a model without it is still usable
        return None
    if config is None:
        return None
    sc = config.scenario
    return sc.n_orbits * orbital_period_s(sc.chief_oe[0]) / (sc.n_nodes - 1)
