"""The guidance called directly, without DDS: a `GuidanceLink` for Monte Carlo closed loops.

`InProcessGuidance` runs the guidance node's `GuidanceCore` (replan policy and pipeline)
synchronously: `publish_nav` validates the fix, decides, and (when replanning) plans before it
returns, so the `wait_*` calls answer at once. Plans it publishes are kept with their
`PlanResult`.
"""
from __future__ import annotations

import time

import numpy as np

from art_guidance.checks import as_finite_array, check_psd
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import check_oe
from art_guidance.errors import GuidanceError, InputError
from art_guidance.planning import GuidancePipeline, NavState, PlanResult, Target
from art_guidance.guidance.core import GuidanceCore
from art_guidance.guidance.replan import Action, Decision, ReplanSettings
from art_guidance.sim.link import LinkPlan

_EMPTY = np.zeros(0)


def default_settings(scenario: ScenarioConfig) -> ReplanSettings:
    """The replan policy `InProcessGuidance` flies by default: the node's defaults with the
    stamp-order check (simulated stamps are not wall-clock time) and the scenario's switch
    node."""
    return ReplanSettings(stamp_check="order", ae_to_koz_node=scenario.ae_to_koz_node)


class InProcessGuidance:
    """A guidance instance in this process (see the module docstring): the node's
    `GuidanceCore`, called synchronously.

    Args:
        pipeline: the planner.
        epoch0_ns: stamp of sim time 0 [ns].
        settings: the replan policy; default: the node's defaults with the stamp-order check
            (simulated stamps are not wall-clock time).
    """

    def __init__(self, pipeline: GuidancePipeline, epoch0_ns: int,
                 settings: ReplanSettings | None = None) -> None:
        self.pipeline = pipeline
        self.epoch0_ns = int(epoch0_ns)
        self.core: GuidanceCore | None = None
        self._settings = settings or default_settings(pipeline.scenario)
        self.results: list[tuple[str, PlanResult]] = []
        self.actions: list[Action] = []  # what each result did to the plan in force
        self._decisions: dict[int, dict[str, str]] = {}
        self._plans: list[LinkPlan] = []

    def wait_matched(self, timeout_s: float) -> bool:
        """Always reachable."""
        return True

    def publish_request(self, waypoint: str, chance_constrained: bool, warm_start: str) -> None:
        """Set the target (a configured waypoint) and restart the horizon; as the node does, a
        later request replans from the newest fix before returning."""
        waypoints = self.pipeline.scenario.waypoints_rtn
        if waypoint not in waypoints:
            raise InputError("waypoint", f"unknown; choose from {sorted(waypoints)}", waypoint)
        target = Target(waypoint, np.asarray(waypoints[waypoint], float),
                        bool(chance_constrained), warm_start, None)
        if self.core is None:
            self.core = GuidanceCore(self.pipeline, self._settings, target)
        else:
            self.core.on_target(target)
            self._solve_queued()

    def publish_nav(self, stamp_ns: int, chief_oe: np.ndarray, roe_m: np.ndarray,
                    cov_m2: np.ndarray) -> None:
        """Decide on a fix and, when replanning, plan before returning."""
        try:
            if self.core is None:
                raise GuidanceError("no replan request received yet")
            nav = NavState(int(stamp_ns), check_oe(chief_oe),
                           as_finite_array("roe_m", roe_m, (6,)),
                           check_psd("cov_m2", as_finite_array("cov_m2", cov_m2, (6, 6))))
            decision, deviation = self.core.on_nav(nav, time.time_ns())
        except GuidanceError as exc:
            active = "" if self.core is None else self.core.active_id
            self._decisions[int(stamp_ns)] = {"decision": Decision.REJECTED.value,
                                              "reason": str(exc)}
            self._plans.append(LinkPlan(int(stamp_ns), "rejected", None, str(exc), active,
                                        _EMPTY, _EMPTY, _EMPTY))
            return
        self._decisions[nav.stamp_ns] = {"decision": decision.value,
                                         "deviation_sigma": f"{deviation:.3f}"}
        if self.core.why_on_plan:
            self._decisions[nav.stamp_ns]["endgame"] = self.core.why_on_plan
        self._solve_queued()

    def _solve_queued(self) -> None:
        """Solve the job the core queued, if any (what the node's worker does), and keep the
        plan it publishes."""
        job = self.core.take_job(wait=False)
        if job is None:
            return
        try:
            solved = self.core.solve(job)
        finally:
            self.core.job_done()
        result = solved.result
        self.results.append((solved.plan_id, result))
        self.actions.append(solved.action)
        self._plans.append(LinkPlan(job.nav.stamp_ns, solved.plan_id, result.status,
                                    solved.status_text, solved.active_id, result.epochs_s,
                                    result.dv_rtn_mps.ravel(), result.rtn.ravel()))

    def wait_decision(self, stamp_ns: int, timeout_s: float) -> dict[str, str] | None:
        """The decision made on fix `stamp_ns` (None if it was never published)."""
        return self._decisions.get(int(stamp_ns))

    def wait_plan(self, stamp_ns: int, timeout_s: float) -> bool:
        """True if a plan answered fix `stamp_ns`."""
        return any(p.stamp_ns == stamp_ns and not p.rejection for p in self._plans)

    def take_plans(self, start: int) -> list[LinkPlan]:
        """Plans from index `start` on, in publication order."""
        return list(self._plans[start:])

    def publish_truth(self, t_s: object, rtn: object) -> None:
        """Nothing to show in-process."""
