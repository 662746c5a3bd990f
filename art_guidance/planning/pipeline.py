"""`GuidancePipeline.plan(request) -> PlanResult`: warm start -> post hoc check -> SCP.

Every stage solves the request's one `Transfer` (`planning.transfer`). The convex TPBVP ("CVX")
is always solved: it is the fallback and the post hoc reference (R_des = -J_CVX). The learned
step (`planning.learned.learned_warm_start`, in line or in the proposal worker process) asks a
`WarmStartProvider` (ART, `art_guidance.art.provider`) for controls, validates them and applies
the post hoc check (`planning.learned.check_proposal`: accept when E_R and E_C of the warm start
SCVx* would start from, or of the rollout itself, are inside the configured region); an
accepted (or, with warm_start "art", forced) proposal warm-starts SCVx*, otherwise CVX does.
Every plan says in words which warm start it used and why (`PlanResult.warm_start_reason`).

A replan whose request carries the plan in force (`planning.carry`, `replan_warm_start:
carry`) starts SCVx* from that plan first; the fresh solve above runs only where the carried
run does not converge (the rescue), where the guard against a locked basin fires, or where
there is nothing to carry (`PlanResult.carry` says which).

A windowed request (`planning.window`) is driven here too: the reference, then the window's
own plan (the same steps over the window's transfer), spliced onto the reference. The learned
step lives in `planning.producers`, the runs and the record in `planning.runs`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import threading
import time
from typing import Iterator

import numpy as np

from art_guidance import kernels
from art_guidance.config import GuidanceConfig
from art_guidance.deadline import Deadline
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import ScpStatus
from art_guidance.optim.problem import REFERENCE_OPTIONS, SubproblemOptions, SubproblemPool
from art_guidance.planning import window
from art_guidance.planning.carry import refusal
from art_guidance.planning.choice import choose
from art_guidance.planning.endgame import InForceCheck, check_in_force
from art_guidance.planning.learned import CvxSafety
from art_guidance.planning.producers import Producers
from art_guidance.planning.runs import carried_run, fresh_runs, plan_result
from art_guidance.planning.transfer import Transfer, Transfers
from art_guidance.planning.request import PlanRequest, TerminalTarget, WarmStart
from art_guidance.planning.result import PlanResult, Timings, WarmStartProvider
from art_guidance.planning.warm_up import seed_request, warm_up
from art_guidance.safety import PassiveSafety


class GuidancePipeline:
    """Plans with CVX -> (optional learned warm start + post hoc) -> SCVx*.

    The pipeline changes no process state: the per-step numerics are chosen once at the
    process's entry (`kernels.choose`, then `kernels.prepare`: the node at configure, the
    CLI in `main`, the proposal worker at its start); `config.planning.numerics` records the
    choice.

    Attributes:
        producers: the learned step, in line or in the proposal worker (`planning.producers`);
            its `solve_art_in_worker` False keeps every SCVx* run here (the same plans,
            later: the reference of `bench plan_auto`).
    """

    def __init__(self, config: GuidanceConfig | None = None,
                 provider: WarmStartProvider | None = None,
                 deadline_s: float | None = None,
                 subproblem: SubproblemOptions | None = None) -> None:
        """Args:
            config: the configuration bundle (default: the packaged YAML files).
            provider: a learned warm-start provider, or None (CVX only).
            deadline_s: the default wall-clock budget of one whole plan [s] (CVX, the learned
                proposal and every SCVx* run, counted from the call of `plan`) for a `plan`
                given no deadline, or None (recorded with the configuration).
            subproblem: how SCVx*'s subproblem is posed (`optim.problem.SubproblemOptions`;
                None: the default); recorded with the configuration (`config_json`).
        """
        self.config = config or GuidanceConfig.load()
        self._config_sha256 = self.config.sha256()
        self.scenario = self.config.scenario
        self.provider = provider
        self.deadline_s = deadline_s
        self.subproblem = subproblem or SubproblemOptions()
        self.producers = Producers(self.config, provider, self.subproblem)
        self._transfers = Transfers(self.scenario, self.config.uncertainty)
        # SCVx*'s subproblems, set up once per horizon and shape and updated run after run;
        # one pool per plan in progress (plans on several threads never share one)
        self._pools: list[SubproblemPool] = []
        self._pools_lock = threading.Lock()

    def config_json(self) -> dict:
        """The configuration this pipeline plans with (recorded with every run), sealed by
        `record_sha256` (`config_json_sha256`: the recording keeps it outside any CRC)."""
        data = {**self.config.to_json(), "deadline_s": self.deadline_s,
                "config_sha256": self.config.sha256(),
                "scp_subproblem": dataclasses.asdict(self.subproblem)}
        return {**data, "record_sha256": config_json_sha256(data)}

    @classmethod
    def from_config_json(cls, data: dict, provider: WarmStartProvider | None = None,
                         time_boxed: bool = True) -> "GuidancePipeline":
        """Rebuild a pipeline from `config_json` output (for replay), with `provider`; with
        `time_boxed` False its plans have no default deadline (the recorded one is dropped).
        A record from before the subproblem's options were recorded was solved with
        `REFERENCE_OPTIONS`, and is replayed with them."""
        try:
            sub = data.get("scp_subproblem")
            options = REFERENCE_OPTIONS if sub is None else SubproblemOptions(**sub)
            deadline_s = data["deadline_s"] if time_boxed else None
            return cls(GuidanceConfig.from_json(data), provider, deadline_s=deadline_s,
                       subproblem=options)
        except (KeyError, TypeError, ConfigError, InputError) as exc:
            raise InputError("config", f"recorded configuration is malformed: {exc!r}") from exc

    def transfer(self, request: PlanRequest) -> Transfer:
        """The problem every stage of a plan of `request` solves (horizon and passive-safety
        model cached)."""
        return self._transfers.get(request)

    def check_in_force(self, request: PlanRequest, cov_m2: np.ndarray | None = None
                       ) -> InForceCheck | None:
        """The plan the request carries (the plan in force) flown from the request's fix over
        its remaining horizon, judged by this planner's passive-safety model and terminal
        condition (`planning.endgame`; `cov_m2`: the fix's covariance); None when the request
        carries none, or one of another length or mode."""
        carry = request.carry
        if carry is None or carry.chance_constrained != request.chance_constrained:
            return None
        transfer = self.transfer(request)
        if carry.dv_rtn_mps.shape[0] != transfer.horizon.n_nodes:
            return None
        return check_in_force(transfer, carry, cov_m2)

    def safety_model(self, request: PlanRequest) -> PassiveSafety:
        """The passive-safety model a request is planned with (cached with its horizon)."""
        return self.transfer(request).safety

    def plan(self, request: PlanRequest, deadline: Deadline | None = None) -> PlanResult:
        """Plan one transfer; never raises for solver or model trouble (see
        `PlanResult.status` and `PlanResult.warm_start_reason`).

        When the first SCVx* run (from the chosen warm start) does not converge and the other
        warm start exists (CVX always; ART when the model proposed valid controls, even if the
        post hoc check rejected them), SCVx* is retried from the other one in the time left and
        the better feasible plan (then the lower cost) is kept.

        `deadline` bounds the whole plan (None: `deadline_s` from now, the pipeline's default
        budget, if it has one): the learned proposal is not started once it has passed and
        stops at the first rollout step after it (the plan is then warm-started from CVX), each
        SCVx* run gets what is left of it (the first run `art_deadline_share` of that when a
        retry is possible) and returns its best feasible iterate on expiry (status TIMEOUT).
        It is overrun by at most one SCVx* iteration, one rollout step and the final safety
        evaluation. A windowed request is planned over its window (`planning.window`), or
        whole where its window says why.
        """
        t0 = time.perf_counter()
        if deadline is None and self.deadline_s is not None:
            deadline = Deadline(t0 + self.deadline_s)
        before = kernels.compiled()
        result = self._plan_request(request, deadline, t0)
        after = kernels.compiled()
        path = ("compiled" if before else "numpy") if before == after else "mixed"
        hit = (deadline is not None and deadline.hit) or result.scp.status is ScpStatus.TIMEOUT
        return dataclasses.replace(result, numerics=path, deadline_hit=bool(hit))

    def _plan_request(self, request: PlanRequest, deadline: Deadline | None,
                      t0: float) -> PlanResult:
        """`plan` without the record of how it ran (its numerics, a deadline hit)."""
        transfer = self.transfer(request)
        n_nodes = transfer.horizon.n_nodes
        h, why = window.window_size(request, n_nodes, self.scenario.n_orbits,
                                    self._no_window_target(request, n_nodes))
        with self._pool() as pool:
            windowed = self._windowed(transfer, deadline, pool) if h else None
            if windowed is not None and windowed.scp.feasible:
                return windowed
            if windowed is not None:
                why = (f"the window's plan ended {windowed.status.name}: the whole remainder "
                       "is planned")
                if deadline is not None and deadline.passed():
                    why += " (its retry cut by the plan's deadline, solve_deadline_s)"
            whole = self._plan(transfer, deadline, pool, t0)
        if request.window_nodes == 0:
            return whole
        whole = dataclasses.replace(whole, window=window.waypoint_window(request, n_nodes, why))
        return whole if windowed is None or whole.scp.feasible else windowed

    @contextlib.contextmanager
    def _pool(self) -> Iterator[SubproblemPool]:
        """SCVx*'s subproblems for one plan, given back to the pipeline after it."""
        with self._pools_lock:
            pool = self._pools.pop() if self._pools else SubproblemPool()
        try:
            yield pool
        finally:
            with self._pools_lock:
                self._pools.append(pool)

    def _no_window_target(self, request: PlanRequest, n_nodes: int) -> str:
        """Why a windowed request has no target and is planned whole ("" = it has one): with
        `terminal_target` carry, nothing to carry."""
        if request.terminal_target is not TerminalTarget.CARRY or not request.window_nodes:
            return ""
        why = refusal(request.carry, request.no_carry, "carry", request.chance_constrained,
                      self._config_sha256, n_nodes)
        return why and f"no plan in force to track ({why}): the whole remainder is planned"

    def _plan(self, transfer: Transfer, deadline: Deadline | None, pool: SubproblemPool,
              t0: float) -> PlanResult:
        """One plan of `transfer` (set up since `t0`), as its steps: CVX, the carried run
        (where there is a plan in force to carry), the fresh runs with the learned step (where
        they are needed), the choice, the record."""
        planning = self.config.planning
        t_setup = time.perf_counter()
        cvx = transfer.problem.cvx()
        t_cvx = time.perf_counter()
        scvx = transfer.scvx(self.config, self.subproblem, pool)
        cvx_safe = CvxSafety(cvx, transfer.safety)  # asked once, where a step needs it
        step = carried_run(transfer, cvx, cvx_safe, scvx, deadline, planning,
                           self._config_sha256)
        fresh = None
        if step.fresh_why is not None:
            fresh = fresh_runs(transfer, cvx, cvx_safe, scvx, deadline, planning,
                               self.producers)
        run = choose(step, fresh, planning.art_min_gain_mps)
        return plan_result(transfer, cvx, run, fresh, (t0, t_setup, t_cvx, time.perf_counter()))

    def _windowed(self, transfer: Transfer, deadline: Deadline | None,
                  pool: SubproblemPool) -> PlanResult:
        """`transfer` (the whole remainder) planned over its request's window: the reference,
        the window's plan to its state at node H (again to CVX's where the window to a learned
        or carried target is infeasible), the splice."""
        t0 = time.perf_counter()
        request = transfer.request
        cvx = transfer.problem.cvx()
        t_cvx = time.perf_counter()
        learned = full = None
        if window.wants_learned(request, cvx):
            learned = self.producers.learned(dataclasses.replace(
                transfer, request=window.learned_request(request)), cvx, deadline)[0]
        if request.terminal_target is TerminalTarget.SCVX and cvx.status.feasible:
            full_request = dataclasses.replace(request, window_nodes=0,
                                               warm_start=WarmStart.CVX)
            full = self._plan(self.transfer(full_request), deadline, pool, t_cvx)
        ref = window.reference(request, cvx, learned, full)
        t_art = time.perf_counter()
        result = self._window_plan(transfer, ref, deadline, pool)
        if not (result.scp.feasible or ref.source == "cvx" or not cvx.status.feasible
                or (deadline is not None and deadline.passed())):
            ref = window.cvx_reference(cvx, ref, result.status.name)
            result = self._window_plan(transfer, ref, deadline, pool)
        t_end = time.perf_counter()
        timings = Timings(cvx=1e3 * (t_cvx - t0), art=1e3 * (t_art - t_cvx),
                          scp=1e3 * (t_end - t_art), total=1e3 * (t_end - t0))
        return window.splice(transfer, result, ref, cvx, timings)

    def _window_plan(self, transfer: Transfer, ref: window.Reference,
                     deadline: Deadline | None, pool: SubproblemPool) -> PlanResult:
        """The plan of the window [0, H] of `transfer` to `ref`'s post-burn state at node H."""
        t0 = time.perf_counter()
        request, n_nodes = transfer.request, transfer.horizon.n_nodes
        shape = window.window_request(request, n_nodes, self.scenario,
                                      tracking=ref.source == "carry")
        target = window.target_roe(transfer, ref, int(request.window_nodes))
        return self._plan(self._transfers.in_roe(shape, target), deadline, pool, t0)

    @property
    def proposal_worker_error(self) -> str:
        """Why the worker process last failed ("" = it did not, or there is none)."""
        return self.producers.worker_error

    @property
    def proposal_worker_state(self) -> tuple[str, int]:
        """The worker process in words (running, loading, stopped and when it starts again;
        "" = there is none) and how many times it was found dead."""
        return self.producers.worker_state

    @property
    def proposal_worker_scvx_runs(self) -> tuple[int, int]:
        """SCVx* runs from the proposal the worker process answered with, and those of them the
        plans took (they needed that run: the check accepted ART, or the retry); (0, 0) with no
        worker."""
        return self.producers.worker_scvx_runs

    def start_proposal_worker(self) -> bool:
        """Start the worker process and load the model in it now, not in the first plan
        (`propose_concurrently` with a model loaded from a file; True if it runs, False and
        `proposal_worker_error` if it could not start; a no-op returning False otherwise)."""
        return self.producers.start_worker()

    def warm_up(self, wait: bool = False) -> float:
        """Pay this process's one-time costs before the first timed plan: the kernels loaded
        (`planning.warm_up`; compiled first on a cold cache with `wait`), then one throwaway
        plan of the scenario's canned transfer, in line, from the learned proposal where there
        is a provider (the runtime's first inference, SCVx*'s subproblems set up for the
        horizon, the solver's first call). The wall time taken [ms]."""
        t0 = time.perf_counter()
        warm_up(wait=wait)
        self.plan(seed_request(self.scenario, warm_start=(
            WarmStart.CVX if self.provider is None else WarmStart.ART)))
        return 1e3 * (time.perf_counter() - t0)

    def close(self) -> None:
        """Stop the proposal worker process, if any (the pipeline stays usable: a later
        concurrent proposal starts it again)."""
        self.producers.close()


# The seal of a recorded configuration (`GuidancePipeline.config_json`): its fingerprint and
# the check replay makes before it trusts it.
_RECORD_EXTRAS = ("deadline_s", "config_sha256", "scp_subproblem", "record_sha256")


def _canonical_sha256(data: dict) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def config_json_sha256(data: dict) -> str:
    """Fingerprint of a recorded configuration (`GuidancePipeline.config_json`): the sha256 of
    its canonical JSON without the `record_sha256` entry itself."""
    return _canonical_sha256({k: v for k, v in data.items() if k != "record_sha256"})


def recorded_config_problem(data: dict) -> str:
    """Why a recorded configuration cannot be trusted ("" = it can): its `record_sha256` does
    not match its content, or, in a record from before that seal, the configuration bundle as
    recorded does not match its `config_sha256` (`GuidanceConfig.sha256`, computed on the
    bundle as it was written, so a field added since does not count as a change)."""
    sealed, bundle = data.get("record_sha256"), data.get("config_sha256")
    if sealed is not None:
        ok, name = sealed == config_json_sha256(data), "record_sha256"
    elif bundle is not None:
        recorded = {k: v for k, v in data.items() if k not in _RECORD_EXTRAS}
        ok, name = bundle == _canonical_sha256(recorded), "config_sha256"
    else:
        return ""
    return "" if ok else (f"the recorded configuration does not match its {name}: it was "
                          "altered after recording")
