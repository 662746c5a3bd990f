"""The ROS wiring the guidance node's two forms share (`GuidanceNodeBase`): parameters,
publishers and subscriptions, the worker thread, the recorder, diagnostics and visualisation
around a `guidance.core.GuidanceCore`. The forms are `guidance_node.GuidanceNode` (plain)
and `managed_node.ManagedGuidanceNode` (lifecycle); `guidance_node` runs either (its docstring
holds the node's interface).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from typing import Any, Callable

import numpy as np
import rclpy
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.qos import QoSProfile, ReliabilityPolicy

from art_guidance import topics
from art_guidance.config import GuidanceConfig, ScenarioConfig, node_parameter_defaults
from art_guidance.deadline import Deadline
from art_guidance.errors import ConfigError, GuidanceError
from art_guidance.planning import GuidancePipeline, Target
from art_guidance.guidance.core import GuidanceCore, Job, ReplanBudget
from art_guidance.guidance.replan import Action
from art_guidance.ros.adapters import (
    nav_from_msg, plan_to_msg, status_plan_msg, target_from_msg,
)
from art_guidance.ros.node_outputs import ERROR, OK, WARN, NodeOutputs
from art_guidance.ros.parameters import (
    PLANNING_PARAMETERS, SPECS, NodeParameters, check_table, descriptor, shown_value,
)
from art_guidance.ros.node_status import (
    fix_counts, load_model, model_values, numerics_values, prepare_numerics,
)
from art_guidance.ros.solve_recording import SolveRecording, bag_folder

STATS_PERIOD_S = 1.0  # "art_guidance/stats" is published this often while planning [s]
PARAMETERS = node_parameter_defaults()  # config/guidance_node.yaml: the one table


def solver_error_text(exc: BaseException, active_id: str) -> str:
    """The status text of a plan whose solve raised: what happened, what stays in force and
    what to check."""
    kept = f"plan {active_id} stays in force" if active_id else "no plan is in force"
    return (f"planning failed ({type(exc).__name__}: {exc}); {kept}. The fix was accepted but "
            "the planner could not solve from it: check its chief elements, state and "
            "covariance and the target against the limits in docs/node.md, and report the "
            "recorded solve if they are within them")


class GuidanceNodeBase:
    """The ROS wiring of a `guidance.core.GuidanceCore`, mixed into an rclpy `Node`
    (`GuidanceNode`) or a `LifecycleNode` (`ManagedGuidanceNode`): parameters, publishers and
    subscriptions, the worker thread, the recorder, diagnostics and visualisation. The decision
    sequence itself is the core's.

    The parameters are read once (`params`, replaced whole on an accepted run-time change);
    what `_configure` builds is None until then (and again after a lifecycle cleanup).
    """

    def __init__(self, **kwargs) -> None:
        super().__init__("guidance_node", **kwargs)
        check_table(PARAMETERS)
        for name, default in PARAMETERS.items():
            self._declare(name, default)
        config = GuidanceConfig.load(self.get_parameter("config_dir").value or None)
        for name in PLANNING_PARAMETERS:
            self._declare(name, getattr(config.planning, name))
        self.params = NodeParameters.from_values(
            {name: self.get_parameter(name).value for name in SPECS})
        # built by _configure (None: not configured)
        self.core: GuidanceCore | None = None
        self.pipeline: GuidancePipeline | None = None
        self.scenario: ScenarioConfig | None = None
        self.provider: object | None = None
        self.model_status = ""
        self.budget = ReplanBudget()
        self.recording: SolveRecording | None = None
        self._recorded_before = False  # a configure of this node run has opened a recorder
        # publishers (_create_publishers), subscriptions and the worker (while planning)
        self.out: NodeOutputs | None = None
        self.nav_sub = self.request_sub = None
        self._worker: threading.Thread | None = None
        self._stats_timer = None  # publishes "art_guidance/stats" while planning
        self._worker_deaths = 0  # proposal worker deaths logged so far
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def _declare(self, name: str, default: Any) -> None:
        """Declare a parameter. A start-up value of another type than its default's
        (`-p numerics:=7`), which rclpy refuses with InvalidParameterTypeException, is refused
        as an invalid value is: a ConfigError naming the parameter, the type it must have and
        the value given (`ParamSpec.type_refusal`)."""
        try:
            self.declare_parameter(name, default, descriptor(name))
        except InvalidParameterTypeException:
            # declared once more, untyped, only to read the value as given: the node stops
            loose = descriptor(name)
            loose.dynamic_typing = True
            given = self.declare_parameter(name, default, loose).value
            raise SPECS[name].type_refusal(name, given) from None

    def _configure(self) -> None:
        """Load the configuration (and, with the learned warm start, the model); build the
        pipeline, the replan policy and the recorder. Raises GuidanceError on bad config."""
        p = self.params
        config = GuidanceConfig.load(p.config_dir or None)
        config = config.replace(planning=dataclasses.replace(
            config.planning, samples_per_node=p.samples_per_node,
            propose_concurrently=p.propose_concurrently, numerics=p.numerics,
            replan_warm_start=p.replan_warm_start, endgame=p.endgame,
            terminal_tolerance_m=p.terminal_tolerance_m,
            terminal_tolerance_mps=p.terminal_tolerance_mps,
            endgame_cost_cap_mps=p.endgame_cost_cap_mps,
            endgame_cost_per_m=p.endgame_cost_per_m, terminal_set_nodes=p.terminal_set_nodes))
        self.scenario = config.scenario
        if p.default_waypoint not in self.scenario.waypoints_rtn:
            raise ConfigError(f"default_waypoint {shown_value(p.default_waypoint)} is not one of "
                              f"{sorted(self.scenario.waypoints_rtn)}")
        settings = p.replan_settings(ae_to_koz_node=self.scenario.ae_to_koz_node,
                                     horizon_nodes=self.scenario.n_nodes)  # checked first
        bag = bag_folder(p, again=self._recorded_before)  # so is the recording's folder
        self.provider, self.model_status = load_model(self.params, self.get_logger())
        self.pipeline = GuidancePipeline(config, provider=self.provider,
                                         deadline_s=p.solve_deadline_s)
        prepare_numerics(p.numerics, self.get_logger())  # /diagnostics: _publish_numerics
        if config.planning.propose_concurrently and self.provider is not None:
            if self.pipeline.start_proposal_worker():
                self.get_logger().info("learned proposals are made in a worker process")
            else:
                self.get_logger().warning(f"the proposal worker process did not start, "
                                          f"proposals are made in line: "
                                          f"{self.pipeline.proposal_worker_error}")
        target = Target(p.default_waypoint,
                        np.asarray(self.scenario.waypoints_rtn[p.default_waypoint]),
                        p.chance_constrained, p.warm_start, None)
        self.core = GuidanceCore(self.pipeline, settings, target)
        self._worker, self._worker_deaths = None, 0
        self.budget = ReplanBudget()
        self.recording = SolveRecording(self.resolve_topic_name, p, self.pipeline,
                                        self.provider, self.model_status, self.get_logger(),
                                        bag, again=self._recorded_before)
        self._recorded_before = self.recording.recorder is not None

    def _model_values(self) -> dict:
        """Model key-values for the diagnostics."""
        return model_values(self.provider, self.model_status)

    def _create_publishers(self, create: Callable) -> None:
        self.out = NodeOutputs(create, self.params.visualization)

    def _create_subscriptions(self) -> None:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        nav_qos = QoSProfile(depth=10, reliability=(
            ReliabilityPolicy.BEST_EFFORT if self.params.nav_qos_reliability == "best_effort"
            else ReliabilityPolicy.RELIABLE))
        self.nav_sub = self.create_subscription(RelativeNavState, topics.NAV,
                                                self._on_nav, nav_qos)
        self.request_sub = self.create_subscription(ReplanRequest, topics.REPLAN_REQUEST,
                                                    self._on_request, qos)

    def _destroy_subscriptions(self) -> None:
        """Unsubscribe (idempotent)."""
        for sub in (self.nav_sub, self.request_sub):
            if sub is not None:
                self.destroy_subscription(sub)
        self.nav_sub = self.request_sub = None

    def _start_worker(self) -> None:
        self.core.start()
        self._worker = threading.Thread(target=self._work, name="guidance_worker", daemon=True)
        self._worker.start()
        self._stats_timer = self.create_timer(STATS_PERIOD_S, self._publish_stats)
        self.get_logger().info(f"guidance_node planning (target {self.core.target.waypoint}, "
                               f"stamp_check {self.params.stamp_check}, warm start "
                               f"{self.params.warm_start}, {self.model_status})")
        self.out.diag("art_guidance/model", OK if self.provider is not None else WARN,
                      self.model_status, self._model_values())
        self._numerics_shown = None
        self._publish_numerics()
        where = self.recording.directory
        self.out.diag("art_guidance/recording", OK,
                      f"recording to {where}" if where else "not recording",
                      {"record_dir": where})

    def _stop_worker(self) -> None:
        """Stop taking jobs; the running solve finishes (and is recorded and published)."""
        if self._worker is None:
            return
        self.destroy_timer(self._stats_timer)
        self._stats_timer = None
        self.core.stop()
        self._worker.join(timeout=30.0)
        self._worker = None

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """Validate and apply run-time parameter changes (all or none)."""
        try:
            new = self.params.changed({prm.name: prm.value for prm in params})
            if self.core is not None:  # a window no longer than this scenario's horizon
                settings = new.replan_settings(horizon_nodes=self.scenario.n_nodes)
        except ConfigError as exc:
            self.get_logger().warning(f"parameter change refused: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        self.params = new
        if self.core is not None:  # not configured yet: the values are used at configure
            self.core.update_settings(settings)
        changed = ", ".join(f"{p.name}={getattr(new, p.name)!r}" for p in params)
        self.get_logger().info(f"parameters changed: {changed}")
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ callbacks
    def _on_nav(self, msg: RelativeNavState) -> None:
        core = self.core
        if core is None or self.out is None:  # a fix taken between unsubscribe and delivery
            return
        core.stats["nav"] += 1
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        try:
            nav = nav_from_msg(msg)
            decision, deviation = core.on_nav(nav, time.time_ns(), msg)
            why = core.why_on_plan
        except GuidanceError as exc:
            self._reject(stamp_ns, str(exc))
            return
        except Exception as exc:  # never die on a message
            self._reject(stamp_ns, f"unexpected {type(exc).__name__}: {exc}")
            return
        self.out.publish_deputy(nav, self.get_logger())
        extra = {"endgame": why} if why else {}
        self.out.nav_diag(nav.stamp_ns, OK, decision.value,
                          {"deviation_sigma": round(deviation, 3), **extra, **fix_counts(core)})

    def _on_request(self, msg: ReplanRequest) -> None:
        if self.core is None or self.out is None:  # taken between unsubscribe and delivery
            return
        try:
            target = target_from_msg(msg, self.scenario.waypoints_rtn)
            self.core.on_target(target, msg)  # restarts the horizon, replans the newest fix
        except Exception as exc:  # never die on a message; a refused target changes nothing
            reason = (str(exc) if isinstance(exc, GuidanceError)
                      else f"unexpected {type(exc).__name__}: {exc}")
            self.get_logger().warning(f"replan request rejected: {reason}")
            self.out.diag("art_guidance/replan_request", WARN, reason, {"reason": reason})
            return
        self.out.diag("art_guidance/replan_request", OK, f"target {target.waypoint}",
                      {"waypoint": target.waypoint})

    # ------------------------------------------------------------------ worker
    def _work(self) -> None:
        while (job := self.core.take_job()) is not None:
            try:
                self._solve(job)
            except Exception as exc:  # the worker must survive anything
                if not self.context.ok():
                    return  # shutting down under a running solve: nothing left to tell
                text = solver_error_text(exc, self.core.active_id)
                self._log().error(f"planning failed: {text}")
                self.out.plan_pub.publish(status_plan_msg(
                    job.nav.stamp_ns, self.core.next_id(), ManeuverPlan.STATUS_SOLVER_ERROR,
                    text, self.core.active_id))
            finally:
                self.core.job_done()

    def _solve(self, job: Job) -> None:
        """Solve a job, record it, publish the plan; then, after the plan is out, its
        visualisation (published and recorded), the log line and the diagnostic."""
        # solve_deadline_s bounds the replan up to its publication: the plan gets what the
        # recent recordings leave of it
        solved = self.core.solve(job, Deadline.after(
            self.budget.planning_s(self.params.solve_deadline_s)))
        t_solved = time.perf_counter()
        result, plan_id, action, active_id = (solved.result, solved.plan_id, solved.action,
                                              solved.active_id)
        plan_msg = plan_to_msg(result, job.nav.stamp_ns, plan_id)
        plan_msg.active_plan_id = active_id
        if action is not Action.ACTIVATED:
            plan_msg.status_text = solved.status_text
        # recorded (and fsync'ed) before it is published: a crash never loses a published plan
        self._recorded(self.recording.record(job, result, plan_id, plan_msg))
        self.out.plan_pub.publish(plan_msg)
        self.budget.add_post_solve_s(time.perf_counter() - t_solved)
        # a plan a queued solve replaces at once is not drawn (bursts)
        if action is Action.ACTIVATED and not self.core.job_queued():
            views = self.out.plan_views(job.nav, result, plan_id,
                                        lambda: self.pipeline.safety_model(job.request),
                                        self.scenario, self._log())
            self.out.publish_views(views)
            self._recorded(self.recording.record_views(views))
        level = OK if result.scp.feasible else WARN
        t = result.timings
        self._log().info(
            f"{plan_id} ({job.trigger}): {result.status.name}, {result.cost_mps:.4f} m/s, "
            f"{result.scp.iterations} it from {result.warm_start.label}, margin "
            f"{result.constraint_margin_m:.2f} m, {t.total:.0f} ms; {action.value} "
            f"(in force: {active_id or 'none'}); {result.warm_start_reason}")
        self.out.diag("art_guidance/plan", level, f"{result.status.name}: {action.value}",
                      {"plan_id": plan_id, "nav_stamp_ns": str(job.nav.stamp_ns),
                       "action": action.value, "active_plan_id": active_id,
                       "cost_mps": result.cost_mps, "warm_start": result.warm_start.value,
                       "warm_start_reason": result.warm_start_reason,
                       "solve_time_ms": t.total, "cvx_ms": round(t.cvx, 2),
                       "art_ms": round(t.art, 2), "scp_ms": round(t.scp, 2),
                       "record_dir": self.recording.directory,
                       **self._model_values(), **self._proposal_worker_values()})

    def _recorded(self, ok: bool) -> None:
        """Report a recording that failed (guidance goes on)."""
        if ok:
            return
        recorder = self.recording.recorder
        self._log().error(f"recording failed, guidance continues: {recorder.last_error}")
        self.out.diag("art_guidance/recorder", ERROR, recorder.last_error,
                      {"errors": recorder.errors})

    def _proposal_worker_values(self) -> dict:
        """The proposal worker process for the plan diagnostic (none: no values); a death
        since the last plan is logged once."""
        state, deaths = self.pipeline.proposal_worker_state
        if not state:
            return {}
        if deaths > self._worker_deaths:
            self._log().warning(f"the proposal worker process died or stalled ({deaths} in "
                                f"all): "
                                f"{self.pipeline.proposal_worker_error}; proposals are made "
                                f"in line until it runs again")
            self._worker_deaths = deaths
        made, taken = self.pipeline.proposal_worker_scvx_runs
        return {"proposal_worker": state, "proposal_worker_deaths": deaths,
                "proposal_worker_error": self.pipeline.proposal_worker_error,
                "proposal_worker_scvx_runs": made, "proposal_worker_scvx_runs_taken": taken}

    # ------------------------------------------------------------------ publishing
    def _reject(self, stamp_ns: int, reason: str) -> None:
        self.core.stats["rejected"] += 1
        self.get_logger().warning(f"nav message rejected: {reason}")
        self.out.plan_pub.publish(status_plan_msg(stamp_ns, self.core.next_id(),
                                                  ManeuverPlan.STATUS_REJECTED_INPUT, reason,
                                                  self.core.active_id))
        self.out.nav_diag(stamp_ns, WARN, "rejected", {"reason": reason,
                                                       **fix_counts(self.core)})

    def _publish_numerics(self) -> None:
        """The "art_guidance/numerics" status, when it changed (the kernels ready after a
        background compile: logged too)."""
        ok, text, values = numerics_values(self.params.numerics)
        if text == self._numerics_shown:
            return
        if self._numerics_shown is not None:
            self._log().info(text)
        self._numerics_shown = text
        self.out.diag("art_guidance/numerics", OK if ok else WARN, text, values)

    def _publish_stats(self) -> None:
        """The "art_guidance/stats" status, and the numerics' when they changed (timer
        callback: nothing escapes it)."""
        try:
            self._publish_numerics()
            counts = fix_counts(self.core)
            self.out.diag("art_guidance/stats", OK, ", ".join(
                f"{k.replace('_', ' ')} {v}" for k, v in counts.items()), counts)
        except Exception as exc:  # a timer callback is a boundary
            self._log().warning(f"stats not published: {type(exc).__name__}: {exc}")

    def shutdown_worker(self) -> None:
        """Stop the worker thread (after the running solve), the proposal worker process and
        finish the recording (each what was built of it; idempotent)."""
        self._stop_worker()
        if self.pipeline is not None:
            self.pipeline.close()
        if self.recording is not None:
            self.recording.finish(self._log())

    def _log(self):
        """The node's logger while its context lives; after SIGINT/SIGTERM (context shut down,
        rosout gone) a console-only logger, so a solve finishing during shutdown logs no rosout
        error. Used from the worker thread and at shutdown."""
        if self.context.ok():
            return self.get_logger()
        return rclpy.logging.get_logger("art_guidance.shutdown")
