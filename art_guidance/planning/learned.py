"""The learned warm-start step of a plan: ask the provider, validate, check post hoc, decide.

`learned_warm_start` is the whole step: the pipeline calls it in line, and its proposal worker
process (`planning.worker`) calls the same function on another core, so the decision
(`Learned`: the warm start SCVx* starts from, and why in words) is the same bit for bit
wherever it is made. It never raises for model trouble: a provider that fails, answers with
something that is not a finite (N, 3) control sequence, or runs out of time leaves the plan to
CVX, and the reason says so.

The paper's post hoc check (E_R, E_C) is here too: `check_proposal` is what the pipeline, the
provider's candidate ranking and the warm-start evaluation apply: `posthoc_check` on the
trajectory `judged_trajectory` selects by the planning configuration's `posthoc_subject`:

- "warm_start" (default): the rollout's controls corrected onto the terminal condition with
  the smallest burn-weighted change (`optim.TransferProblem.terminal_warm_start`), which is
  exactly where SCVx* starts from. The rollouts miss the target (by a median 1.7 km for the
  shipped model), so the rollout's own cost and C(t_1) say little about the warm start SCVx*
  receives: the correction adds cost and moves drift arcs into the keep-out region.
- "rollout": the rollout as the model produced it (the paper's check).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import PlanningConfig, PosthocThresholds
from art_guidance.deadline import Deadline
from art_guidance.errors import InputError
from art_guidance.optim import ConvexSolution, ScpWarmStart, Trajectory, TransferProblem
from art_guidance.optim.scp import TERMINAL_TOL_M
from art_guidance.planning.transfer import Transfer
from art_guidance.planning.request import WarmStart, WarmStartSource
from art_guidance.planning.result import PosthocDecision, WarmStartProposal, WarmStartProvider
from art_guidance.safety import PassiveSafety

ART, CVX = WarmStartSource.ART, WarmStartSource.CVX
DEADLINE_REASON = "the plan's deadline (solve_deadline_s) passed"
# The decision's reason when `skip_art_when_cvx_safe` left ART out.
CVX_SAFE_REASON = ("CVX is passively safe (C_CVX(t_1) = 0), so SCVx* from it is the plan: ART "
                   "not run, CVX warm start")


@dataclass(frozen=True)
class Learned:
    """What the learned warm-start step decided.

    Attributes:
        source: the warm start SCVx* starts from.
        reason: why, in words.
        posthoc: the post hoc decision (None: the check was not run).
        proposal: the provider's proposal as it came (None: none was made).
        dv: (N, 3) the validated proposed controls [m/s] (None: no valid proposal).
        warm_start: their terminal warm start if it was made (by the provider or the check):
            SCVx* from ART starts there.
    """

    source: WarmStartSource
    reason: str
    posthoc: PosthocDecision | None = None
    proposal: WarmStartProposal | None = None
    dv: np.ndarray | None = None
    warm_start: Trajectory | None = None

    @property
    def scvx_start(self) -> ScpWarmStart | None:
        """SCVx*'s warm start from ART (`Scvx.solve`): the terminal warm start where it was
        made, else the proposed controls (None: no valid proposal)."""
        return self.dv if self.warm_start is None else self.warm_start


def learned_warm_start(provider: WarmStartProvider | None, transfer: Transfer,
                       cvx: ConvexSolution, planning: PlanningConfig,
                       deadline: Deadline | None = None,
                       cvx_safe: CvxSafety | None = None) -> Learned:
    """Ask `provider` for a learned warm start of `transfer` and check it post hoc under
    `planning` (its region, its `posthoc_subject`, `skip_art_when_cvx_safe`).

    Args:
        provider: the learned model, or None (CVX only).
        transfer: the plan's problem.
        cvx: the plan's CVX solution (the post hoc reference, R_des = -J_CVX).
        planning: the planning options the candidates are ranked and checked by.
        deadline: the plan's deadline, or None.
        cvx_safe: whether the CVX plan is passively safe, the plan's one answer (None: asked
            here where needed).
    """
    request, problem = transfer.request, transfer.problem
    if request.warm_start is WarmStart.CVX:
        return Learned(CVX, "CVX warm start requested")
    if provider is None:
        return Learned(CVX, f"{request.warm_start} requested but no learned model is "
                       "loaded: CVX warm start")
    if not cvx.status.feasible:
        return Learned(CVX, f"CVX ended {cvx.status.name}: no reference for the post hoc "
                       "check, CVX warm start")
    if request.warm_start is WarmStart.AUTO and planning.skip_art_when_cvx_safe \
            and (CvxSafety(cvx, problem.safety) if cvx_safe is None else cvx_safe)():
        return Learned(CVX, CVX_SAFE_REASON)
    t0 = time.perf_counter()
    if deadline is not None and deadline.passed():
        return Learned(CVX, f"{DEADLINE_REASON} before ART: CVX warm start")
    try:
        # the flown steps, where the request carries them (a provider without a context
        # argument is asked as before)
        past = {} if request.context is None else {"context": request.context}
        proposal = provider.propose(problem, cvx, planning=planning, deadline=deadline,
                                    **past)
    except Exception as exc:  # a model never takes the plan down
        return Learned(CVX, f"ART not run ({error_text(exc)}): CVX warm start")
    if not isinstance(proposal, WarmStartProposal):
        proposal = WarmStartProposal(proposal, rollout_ms=1e3 * (time.perf_counter() - t0))
    try:
        dv = as_finite_array("ART warm start", proposal.dv_rtn_mps,
                             (problem.horizon.n_nodes, 3))
    except InputError as exc:  # a broken model output is rejected, never flown
        return Learned(CVX, f"ART output rejected ({error_text(exc)}): CVX warm start",
                       PosthocDecision(float("nan"), float("nan"), False), proposal)
    warm = carried_warm_start(problem, proposal)
    if warm is None and planning.posthoc_subject == "warm_start":  # the check judges it
        warm = problem.terminal_warm_start(dv)
    posthoc = check_proposal(problem, dv, cvx.cost_mps, planning, warm)
    if posthoc.accepted:
        return Learned(ART, f"ART accepted by the post hoc check ({posthoc.text()})",
                       posthoc, proposal, dv, warm)
    if request.warm_start is WarmStart.ART:
        return Learned(ART, f"ART forced although the post hoc check rejects it "
                       f"({posthoc.text()})", posthoc, proposal, dv, warm)
    return Learned(CVX, f"ART rejected by the post hoc check ({posthoc.text()}): CVX "
                   "warm start", posthoc, proposal, dv, warm)


def carried_warm_start(problem: TransferProblem, proposal: WarmStartProposal
                       ) -> Trajectory | None:
    """The terminal warm start a proposal carries, if it is one: finite, of the problem's
    shape, its states those of its controls under the deputy-aware model, meeting the terminal
    condition (TERMINAL_TOL_M); else None (the caller computes it). One propagation, against
    the Gauss-Newton of `TransferProblem.terminal_warm_start`."""
    warm = proposal.warm_start
    if warm is None or warm.dv_rtn_mps is None or warm.roe_m is None:
        return None
    horizon, n = problem.horizon, problem.horizon.n_nodes
    try:
        dv = as_finite_array("terminal warm start", warm.dv_rtn_mps, (n, 3))
        roe = as_finite_array("terminal warm start states", warm.roe_m, (n, 6))
    except InputError:
        return None
    if not np.array_equal(horizon.propagate_nonlinear(problem.roe0_m, dv), roe):
        return None
    miss = horizon.final_post_burn_nonlinear(roe, dv) - problem.roe_f_m
    return Trajectory(dv, roe) if float(np.abs(miss).max()) <= TERMINAL_TOL_M else None


def timed_learned_warm_start(*args: object, **kwargs: object) -> tuple[Learned, float]:
    """`learned_warm_start` and its wall time [ms]."""
    t = time.perf_counter()
    learned = learned_warm_start(*args, **kwargs)
    return learned, 1e3 * (time.perf_counter() - t)


class CvxSafety:
    """Whether one plan's CVX solution is passively safe (`cvx_is_safe`), asked once per plan:
    the carried run, the choice of where to propose and the learned step read this one
    answer, evaluated at the first question (a plan that asks none pays nothing).

    Args:
        cvx: the plan's CVX solution.
        safety: its passive-safety model.
        known: the answer where the caller has it already (None: not asked yet).
    """

    def __init__(self, cvx: ConvexSolution | None, safety: PassiveSafety | None,
                 known: bool | None = None) -> None:
        self._cvx, self._safety, self._known = cvx, safety, known

    @classmethod
    def answered(cls, safe: bool) -> "CvxSafety":
        """An answer the caller has already (a worker's job, a benchmark's unsafe cases)."""
        return cls(None, None, bool(safe))

    def __call__(self) -> bool:
        """The answer (evaluated at the first call)."""
        if self._known is None:
            self._known = cvx_is_safe(self._cvx, self._safety)
        return self._known

    @property
    def known(self) -> bool | None:
        """The answer where it was asked already (None: not yet; what a worker's job carries)."""
        return self._known


def cvx_is_safe(cvx: ConvexSolution, safety: PassiveSafety) -> bool:
    """Whether the CVX plan already satisfies the passive-safety constraint at every node
    (C_CVX(t_1) = 0). CVX is the problem without that constraint, so SCVx* from it keeps it
    (one iteration) and no warm start can do better: on 96 such held-out scenarios of the
    warm-start analysis `auto` with ART gained nothing; in the closed loop 55-58 % of the
    replans are such, and ART's proposal there only adds latency (`skip_art_when_cvx_safe`)."""
    return int(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0]) == 0


def error_text(exc: BaseException) -> str:
    """An exception in one short line: its type and the first line of its message."""
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text[:200]}"


def posthoc_check(dv_rtn_mps: np.ndarray, roe_m: np.ndarray, cvx_cost_mps: float,
                  safety: PassiveSafety, thresholds: PosthocThresholds) -> PosthocDecision:
    """Compare a rollout's realised performance with the desired one (paper eq. for E_P).

    The desired reward-to-go is the CVX lower bound (R_des = -J_CVX) and the desired
    constraint-violation budget is zero, so E_R = (R - R_des) / R_des and E_C = C(t1).

    Args:
        dv_rtn_mps: (N, 3) rollout controls [m/s].
        roe_m: (N, 6) rollout states [m] (dynamics in the loop).
        cvx_cost_mps: J_CVX [m/s].
        safety: the plan's passive-safety model (gives C(t1)).
        thresholds: acceptance region.
    """
    r_des = -float(cvx_cost_mps)
    r_art = -float(np.linalg.norm(dv_rtn_mps, axis=1).sum())
    e_r = (r_art - r_des) / r_des if abs(r_des) > 1e-12 else float("inf")
    e_c = float(safety.evaluate(roe_m, dv_rtn_mps).constraint_to_go[0])
    accepted = bool(thresholds.contains(100.0 * e_r, e_c))
    return PosthocDecision(float(e_r), e_c, accepted)


def judged_trajectory(problem: TransferProblem, dv_rtn_mps: np.ndarray,
                      subject: str) -> Trajectory:
    """The trajectory the check judges for a rollout's controls `dv_rtn_mps` (N, 3) [m/s]:
    the terminal warm start ("warm_start") or the rollout ("rollout"), both propagated with
    the deputy-aware model."""
    if subject == "rollout":
        return problem.propagate(dv_rtn_mps)
    return problem.terminal_warm_start(dv_rtn_mps)


def check_proposal(problem: TransferProblem, dv_rtn_mps: np.ndarray, cvx_cost_mps: float,
                   planning: PlanningConfig, warm_start: Trajectory | None = None
                   ) -> PosthocDecision:
    """The post hoc decision on a rollout's controls for `problem` under `planning` (its
    region and its `posthoc_subject`).

    `warm_start`: the controls' terminal warm start when the caller has it; judged under
    "warm_start" instead of computing it again (`judged_trajectory`)."""
    if warm_start is not None and planning.posthoc_subject == "warm_start":
        dv, roe = warm_start
    else:
        dv, roe = judged_trajectory(problem, dv_rtn_mps, planning.posthoc_subject)
    return posthoc_check(dv, roe, cvx_cost_mps, problem.safety, planning.posthoc)
