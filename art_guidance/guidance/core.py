"""The guidance's decision sequence without ROS: check -> decide -> request -> plan -> keep.

One `GuidanceCore` holds a guidance instance's state: the replan policy, the target, the job
mailbox and the plan ids. The ROS 2 node (plain and lifecycle) wires it to topics and runs
`take_job` / `solve` in its worker thread; the simulator's in-process link
(`sim.inprocess.InProcessGuidance`) calls the same methods synchronously, so both follow the
same sequence:

1. `on_nav`: refuse a stale, out-of-order or future stamp (GuidanceError), accept the fix,
   decide between replanning and staying on the plan in force; a replan becomes a `Job` over the
   remaining window in the mailbox (newest wins: a queued job is superseded, never queued
   without bound).
2. `on_target`: a new target restarts the horizon and replans from the newest fix.
3. `take_job` / `job_done`: the worker's side of the mailbox.
4. `solve`: plan the job and put a usable plan in force (an unusable one never replaces the
   plan in force); returns what happened, with the status text to publish.

Thread-safe: every method takes the core's lock except the planning itself.
"""
from __future__ import annotations

import collections
import dataclasses
import itertools
import threading
from dataclasses import dataclass
from typing import Any

from art_guidance.deadline import Deadline
from art_guidance.planning.endgame import Endgame, InForceCheck, in_set_under
from art_guidance.planning.pipeline import GuidancePipeline
from art_guidance.guidance.replan import (
    Action, Decision, ReplanPolicy, ReplanSettings, ReplanWindow, check_target, request_for,
    unusable_text,
)
from art_guidance.planning.request import NavState, PlanRequest, Target
from art_guidance.planning.result import PlanResult


class ReplanBudget:
    """How a replan's wall-clock budget (`solve_deadline_s`) is shared between planning and
    what follows it before the plan is published (the plan and view messages, the recorded
    and fsync'ed solve).

    The pipeline's deadline is the budget less the longest of the last `WINDOW` post-solve
    times (at most `MAX_SHARE` of the budget, so a stalled disk never leaves planning nothing):
    a node whose recording slows down plans a little less long instead of publishing late.
    """

    WINDOW = 20
    MAX_SHARE = 0.5

    def __init__(self) -> None:
        self._recent: collections.deque[float] = collections.deque(maxlen=self.WINDOW)

    def add_post_solve_s(self, seconds: float) -> None:
        """Record how long one solve's messages and recording took [s]."""
        if seconds >= 0.0:
            self._recent.append(float(seconds))

    @property
    def allowance_s(self) -> float:
        """The longest recent post-solve time [s] (0 before the first solve)."""
        return max(self._recent, default=0.0)

    def planning_s(self, budget_s: float) -> float:
        """The pipeline's deadline out of a replan budget of `budget_s` [s]."""
        return budget_s - min(self.allowance_s, self.MAX_SHARE * budget_s)


@dataclass(frozen=True)
class Job:
    """A planning job.

    Attributes:
        nav: the fix it plans from.
        request: the planning request over the remaining window.
        trigger: "nav" (a fix) or "request" (a new target).
        nav_payload, request_payload: what the caller attached to the fix and to the target
            (the node: the ROS messages it records with the solve).
        in_force: the end game's check of the plan in force from the fix, made when it
            decided this replan (`planning.endgame`; None: not made), read again by the cost
            cap instead of being made a second time.
    """

    nav: NavState
    request: PlanRequest
    trigger: str
    nav_payload: Any = None
    request_payload: Any = None
    in_force: InForceCheck | None = None


@dataclass(frozen=True)
class Solved:
    """A finished job.

    Attributes:
        plan_id: the new plan's id.
        result: the pipeline's result.
        action: what it did to the plan in force.
        active_id: the plan in force afterwards ("" = none).
        status_text: the plan's status in words (why it is not in force, if it is not).
    """

    plan_id: str
    result: PlanResult
    action: Action
    active_id: str
    status_text: str


class GuidanceCore:
    """A guidance instance without ROS (see the module docstring).

    Args:
        pipeline: the planner.
        settings: the replan policy's settings.
        target: the target until `on_target` names another.
    """

    def __init__(self, pipeline: GuidancePipeline, settings: ReplanSettings,
                 target: Target) -> None:
        self.pipeline = pipeline
        self.policy = ReplanPolicy(settings)
        self.target = target
        self.stats = {"nav": 0, "rejected": 0, "plans": 0, "superseded": 0, "kept": 0,
                      "capped": 0, "aimed": 0, "in_set": 0}
        # why the last `on_nav` stayed on the plan in force although the fix deviates ("" =
        # it did not: read by its caller right after the call)
        self.why_on_plan = ""
        self._lock = threading.Condition()
        self._job: Job | None = None
        self._busy = False
        self._stop = False
        self._latest: tuple[NavState, Any] | None = None
        self._target_payload: Any = None
        self._ids = itertools.count(1)

    # ------------------------------------------------------------------ decisions
    def on_nav(self, nav: NavState, now_ns: int, payload: Any = None) -> tuple[Decision, float]:
        """Check, accept and decide on a fix; a replan is queued as a job.

        Returns:
            The decision and the largest per-axis deviation from the plan [nav sigma] (NaN
            if not computed).

        Raises:
            GuidanceError: a stale, out-of-order or future stamp (nothing changes).
        """
        with self._lock:
            self.policy.check_stamp(nav.stamp_ns, now_ns)
            # validated as a fresh plan's request before anything is stored: a fix the
            # planner would refuse never becomes the newest state or the stamp floor
            request_for(nav, self.target, ReplanWindow(None, self.target.n_orbits, None))
            self._latest = (nav, payload)
            self.policy.accept(nav)
            decision, deviation = self.policy.decide(nav, self._busy or self._job is not None)
            self.why_on_plan = ""
            if decision is Decision.REPLANNING:
                job = self._job_for(nav, payload, "nav")
                job, self.why_on_plan = (self._end_game(job) if self.policy.deviation_only
                                         else (job, ""))
                if self.why_on_plan:
                    self.stats["kept"] += 1
                    decision = Decision.ON_PLAN
                else:
                    self._submit(job)
        return decision, deviation

    def _end_game(self, job: Job) -> tuple[Job, str]:
        """The end game's answer to the replan `job` (`planning.endgame`): why the plan in
        force stays in force (passively safe and on target from the fix), or "" and the job
        to solve: as it is, or, when the plan in force is on target but not safe from the fix
        and `aim_within_tolerance` is set, aimed at the plan in force's own predicted end
        (within the tolerance of the waypoint: the replan restores passive safety without
        paying to null an error that does not matter); with `terminal_set_nodes` nodes left
        or fewer, ending within the terminal set of the tolerances (`endgame.in_set_under`)."""
        planning = self.pipeline.config.planning
        if not Endgame(planning.endgame).keeps:
            return job, ""
        check = self.pipeline.check_in_force(job.request, job.nav.cov_m2)
        if check is None:
            return job, ""
        n_left = len(job.request.carry.dv_rtn_mps)
        if check.kept_under(planning, n_left):
            return job, f"endgame {planning.endgame}: the error does not matter, {check.text()}"
        job = dataclasses.replace(job, in_force=check)
        if planning.aim_within_tolerance and check.on_target_under(planning, n_left) \
                and not job.request.window_nodes:
            self.stats["aimed"] += 1
            return dataclasses.replace(job, request=dataclasses.replace(
                job.request, target_rtn=check.terminal_rtn)), ""
        terminal_set = in_set_under(planning, n_left)
        if terminal_set is not None and not job.request.window_nodes:
            self.stats["in_set"] += 1
            return dataclasses.replace(job, request=dataclasses.replace(
                job.request, terminal_set=terminal_set)), ""
        return job, ""

    def _capped(self, job: Job, result: PlanResult) -> str:
        """Why a usable replan is not put in force (`endgame: keep_cap`: it costs more above
        the plan in force's remaining burns than the terminal error it removes is worth,
        `InForceCheck.worth_mps`, while the plan in force is passively safe from the fix), or
        "" (put it in force)."""
        planning = self.pipeline.config.planning
        carry = job.request.carry
        if not Endgame(planning.endgame).caps or carry is None or not result.scp.feasible \
                or self.policy.active is None or carry.plan_id != self.policy.active_id:
            return ""
        growth = float(result.cost_mps) - carry.remaining_mps
        if growth <= planning.endgame_cost_cap_mps:
            return ""
        check = job.in_force or self.pipeline.check_in_force(job.request)
        if check is None or not check.safe:
            return ""
        worth = check.worth_mps(planning)
        if growth <= worth:
            return ""
        return (f"not put in force (endgame keep_cap): it costs {1e3 * growth:.0f} mm/s above "
                f"the plan in force's remaining burns, more than the "
                f"{check.terminal_error_m:.1f} m it removes is worth ({1e3 * worth:.0f} mm/s: "
                f"endgame_cost_cap_mps + endgame_cost_per_m x the error); {check.text()}")

    def on_target(self, target: Target, payload: Any = None) -> None:
        """A new target: restart the horizon and the stamp sequence, replan from the newest
        fix (if any).

        Raises:
            InputError: the target makes no valid request (checked with the newest fix, or
                a reference one); nothing changes.
        """
        with self._lock:
            fresh = ReplanWindow(None, target.n_orbits, None)  # the horizon restarts
            job = None
            if self._latest is not None:
                nav, nav_payload = self._latest
                job = Job(nav, request_for(nav, target, fresh, self.policy.settings,
                                           no_carry="a new target"), "request",
                          nav_payload, payload)
            else:
                check_target(target)
            self.target, self._target_payload = target, payload
            self.policy.reset()
            if job is not None:
                self._submit(job)

    def update_settings(self, settings: ReplanSettings) -> None:
        """New policy settings (the AE -> KOZ switch node of the plans in force stays)."""
        with self._lock:
            self.policy.settings = dataclasses.replace(
                settings, ae_to_koz_node=self.policy.settings.ae_to_koz_node,
                horizon_nodes=self.policy.settings.horizon_nodes)

    def _job_for(self, nav: NavState, payload: Any, trigger: str) -> Job:
        window = self.policy.window(nav, self.target.n_orbits)
        request = request_for(nav, self.target, window, self.policy.settings,
                              self.policy.context_at(nav), *self.policy.carry_at(nav, window))
        return Job(nav, request, trigger, payload, self._target_payload)

    def _submit(self, job: Job) -> None:
        """Called with the lock held: replace any queued job, wake the worker."""
        if self._job is not None:
            self.stats["superseded"] += 1
        self._job = job
        self._lock.notify()

    # ------------------------------------------------------------------ the mailbox
    def take_job(self, wait: bool = True) -> Job | None:
        """The newest queued job (marked busy until its plan is decided in `solve`, or until
        `job_done`); None once stopped, or when nothing is queued and `wait` is False."""
        with self._lock:
            while wait and self._job is None and not self._stop:
                self._lock.wait()
            if self._stop or self._job is None:
                return None
            job, self._job, self._busy = self._job, None, True
            return job

    def job_done(self) -> None:
        """The worker finished its job (solved or failed)."""
        with self._lock:
            self._busy = False

    def job_queued(self) -> bool:
        """A newer job waits (the one being solved will be replaced at once)."""
        with self._lock:
            return self._job is not None

    def start(self) -> None:
        """Accept jobs (again)."""
        with self._lock:
            self._stop = False

    def stop(self) -> None:
        """Drop the queued job and wake a waiting worker: `take_job` returns None."""
        with self._lock:
            self._stop = True
            self._job = None
            self._lock.notify_all()

    # ------------------------------------------------------------------ planning
    def solve(self, job: Job, deadline: Deadline | None = None) -> Solved:
        """Plan a job (outside the lock) by `deadline` (None: the pipeline's default budget)
        and put a usable plan in force."""
        result = self.pipeline.plan(job.request, deadline)
        plan_id = self.next_id()
        with self._lock:  # an unusable replan never replaces the plan in force
            capped = self._capped(job, result)
            if capped:
                self.stats["capped"] += 1
                action = Action.KEPT_ACTIVE_PLAN
            else:
                action = self.policy.on_result(plan_id, job.nav.stamp_ns, result)
            active_id = self.policy.active_id
            # the solve is over once its plan is decided: a fix that arrives while the node
            # records, publishes and draws it is judged against the plan in force (not
            # replanned as if a solve were under way)
            self._busy = False
        text = (result.status.name if action is Action.ACTIVATED
                else f"{result.status.name}: replan {capped}; plan {active_id} stays in force"
                if capped else unusable_text(result, active_id))
        self.stats["plans"] += 1
        return Solved(plan_id, result, action, active_id, text)

    def next_id(self) -> str:
        """A new plan id (also for status-only plans: rejections, failures)."""
        return f"plan-{next(self._ids)}"

    @property
    def active_id(self) -> str:
        """Id of the plan in force ("" = none)."""
        with self._lock:
            return self.policy.active_id
