"""ROS 2 guidance node: `ros2 run art_guidance guidance_node` (or `art-guidance node`).

Subscribes `nav/relative_state` and `guidance/replan_request`; publishes
`guidance/maneuver_plan` and `/diagnostics`. Callbacks only validate and decide; all solving
runs in one worker thread that always takes the newest job (a queued job is superseded, never
queued without bound). Every nav message gets a `/diagnostics` status named "art_guidance/nav"
with `nav_stamp_ns` and `decision` in {replanning, on_plan, rejected}; "replanning" is followed
by a ManeuverPlan whose header.stamp is that nav stamp.
"""
from __future__ import annotations

import itertools
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import rclpy
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.dynamics import control_matrix, orbital_period_s, propagate_mean_oe, stm_j2
from art_guidance.errors import ConfigError, GuidanceError
from art_guidance.planning.pipeline import GuidancePipeline, PlanRequest, PlanResult
from art_guidance.record.recorder import McapRecorder, default_log_dir
from art_guidance.ros.env import use_fast_discovery
from art_guidance.ros.adapters import (
    NavState, Target, diagnostics_msg, nav_from_msg, plan_to_msg, solve_record_msg,
    status_plan_msg, target_from_msg,
)

OK, WARN, ERROR = 0, 1, 2
STAMP_CHECKS = ("wallclock", "order", "off")
PARAMETERS = {
    "config_dir": "",                 # "" = packaged config/
    "default_waypoint": "plus_vbar",  # target until a replan request names one
    "chance_constrained": True,
    "warm_start": "auto",
    "replan_sigma_threshold": 3.0,    # replan if any ROE axis deviates more than this [sigma]
    "replan_period_s": 0.0,           # > 0: also replan this often (stamp time) [s]
    "stamp_check": "wallclock",       # wallclock | order (monotonic only) | off
    "max_nav_age_s": 5.0,
    "max_nav_future_s": 1.0,
    "solve_deadline_s": 5.0,
    "min_remaining_nodes": 3,         # below this the active plan is flown out, not replanned
    "samples_per_node": 3,
    "record": True,                   # write every solve to MCAP
    "record_dir": "",                 # "" = <ROS_HOME or ~/.ros>/art_guidance_logs/<run>
    "record_max_bytes": 268435456,    # rotate MCAP files at this size [bytes]
}


@dataclass(frozen=True)
class Job:
    """A planning job for the worker."""

    nav: NavState
    target: Target
    trigger: str
    nav_msg: RelativeNavState
    request_msg: ReplanRequest | None
    n_nodes: int | None
    n_orbits: float | None
    koz_switch_node: int | None


@dataclass
class ActivePlan:
    """The newest successful plan, in absolute time."""

    plan_id: str
    t0_ns: int
    result: PlanResult
    end_ns: int
    dt_s: float
    switch_ns: int


class GuidanceNode(Node):
    """Thin rclpy shell around `GuidancePipeline`."""

    def __init__(self, **kwargs) -> None:
        super().__init__("guidance_node", **kwargs)
        for name, default in PARAMETERS.items():
            self.declare_parameter(name, default)
        self.p = {name: self.get_parameter(name).value for name in PARAMETERS}
        self._validate_parameters()
        cfg_dir = self.p["config_dir"] or None
        path = (lambda f: None) if cfg_dir is None else (lambda f: f"{cfg_dir}/{f}")
        self.scenario = ScenarioConfig.from_yaml(path("scenario.yaml"))
        self.pipeline = GuidancePipeline(
            self.scenario, UncertaintyConfig.from_yaml(path("uncertainty.yaml")),
            ScpConfig.from_yaml(path("scp.yaml")), samples_per_node=self.p["samples_per_node"],
            deadline_s=self.p["solve_deadline_s"])
        if self.p["default_waypoint"] not in self.scenario.waypoints_rtn:
            raise ConfigError(f"default_waypoint {self.p['default_waypoint']!r} is not one of "
                              f"{sorted(self.scenario.waypoints_rtn)}")
        self.target = Target(self.p["default_waypoint"],
                             np.asarray(self.scenario.waypoints_rtn[self.p["default_waypoint"]]),
                             self.p["chance_constrained"], self.p["warm_start"], None)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.plan_pub = self.create_publisher(ManeuverPlan, "guidance/maneuver_plan", qos)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos)
        self.create_subscription(RelativeNavState, "nav/relative_state", self._on_nav, qos)
        self.create_subscription(ReplanRequest, "guidance/replan_request", self._on_request, qos)
        self._lock = threading.Condition()
        self._job: Job | None = None
        self._busy = False
        self._stop = False
        self._latest_nav: NavState | None = None
        self._latest_nav_msg: RelativeNavState | None = None
        self._stamp_floor_ns: int | None = None
        self._active: ActivePlan | None = None
        self._last_plan_ns: int | None = None
        self._ids = itertools.count(1)
        self._request_msg: ReplanRequest | None = None
        self.recorder = self._make_recorder()
        self.stats = {"nav": 0, "rejected": 0, "plans": 0, "superseded": 0}
        self._worker = threading.Thread(target=self._work, name="guidance_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(f"guidance_node ready (target {self.target.waypoint}, "
                               f"stamp_check {self.p['stamp_check']})")

    def _make_recorder(self) -> McapRecorder | None:
        if not self.p["record"]:
            return None
        directory = self.p["record_dir"] or str(default_log_dir())
        meta = {"config": self.pipeline.config_json(), "versions": _versions(),
                "model_checksum": "none", "parameters": self.p}
        self.get_logger().info(f"recording every solve to {directory}")
        return McapRecorder(directory, meta, max_bytes=int(self.p["record_max_bytes"]))

    def _validate_parameters(self) -> None:
        if self.p["stamp_check"] not in STAMP_CHECKS:
            raise ConfigError(f"stamp_check must be one of {STAMP_CHECKS}")
        for name in ("replan_sigma_threshold", "max_nav_age_s", "max_nav_future_s",
                     "solve_deadline_s"):
            if not float(self.p[name]) > 0:
                raise ConfigError(f"parameter {name} must be > 0, got {self.p[name]}")
        if self.p["warm_start"] not in ("auto", "cvx", "art"):
            raise ConfigError("warm_start must be auto, cvx or art")
        if int(self.p["min_remaining_nodes"]) < 2 or int(self.p["samples_per_node"]) < 1:
            raise ConfigError("min_remaining_nodes must be >= 2 and samples_per_node >= 1")
        if int(self.p["record_max_bytes"]) < 4096:
            raise ConfigError("record_max_bytes must be >= 4096")

    # ------------------------------------------------------------------ callbacks
    def _on_nav(self, msg: RelativeNavState) -> None:
        self.stats["nav"] += 1
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        try:
            nav = nav_from_msg(msg)
            self._check_stamp(nav.stamp_ns)
        except GuidanceError as exc:
            self._reject(stamp_ns, str(exc))
            return
        except Exception as exc:  # never die on a message
            self._reject(stamp_ns, f"unexpected {type(exc).__name__}: {exc}")
            return
        with self._lock:
            self._latest_nav, self._latest_nav_msg = nav, msg
            self._stamp_floor_ns = nav.stamp_ns
            decision, deviation = self._decide(nav)
            if decision == "replanning":
                self._submit(self._job_for(nav, msg, "nav"))
        self._diag(nav.stamp_ns, OK, decision, {"deviation_sigma": round(deviation, 3)})

    def _on_request(self, msg: ReplanRequest) -> None:
        try:
            target = target_from_msg(msg, self.scenario.waypoints_rtn)
        except GuidanceError as exc:
            self.get_logger().warning(f"replan request rejected: {exc}")
            self._publish_diag("art_guidance/replan_request", WARN, str(exc), {})
            return
        with self._lock:
            self.target, self._request_msg = target, msg
            self._active = None  # a new target restarts the horizon
            self._stamp_floor_ns = None  # and a new stamp sequence (e.g. a new simulation)
            if self._latest_nav is not None:
                self._submit(self._job_for(self._latest_nav, self._latest_nav_msg, "request"))
        self._publish_diag("art_guidance/replan_request", OK, f"target {target.waypoint}",
                           {"waypoint": target.waypoint})

    # ------------------------------------------------------------------ decisions
    def _check_stamp(self, stamp_ns: int) -> None:
        mode = self.p["stamp_check"]
        if mode == "off":
            return
        floor = self._stamp_floor_ns
        if floor is not None and stamp_ns <= floor:
            raise GuidanceError(f"stale stamp: {stamp_ns} ns is not newer than {floor} ns")
        if mode == "wallclock":
            age_s = (time.time_ns() - stamp_ns) * 1e-9
            if age_s > self.p["max_nav_age_s"]:
                raise GuidanceError(f"stale stamp: {age_s:.3f} s old")
            if -age_s > self.p["max_nav_future_s"]:
                raise GuidanceError(f"stamp {-age_s:.3f} s in the future")

    def _decide(self, nav: NavState) -> tuple[str, float]:
        """Replan when nothing is active, a solve is under way, the state deviates or is due."""
        active = self._active
        if active is None or self._busy or self._job is not None:
            return "replanning", math.nan
        remaining = (active.end_ns - nav.stamp_ns) * 1e-9
        if remaining < (self.p["min_remaining_nodes"] - 1) * active.dt_s:
            return "on_plan", math.nan
        deviation = self._deviation_sigma(active, nav)
        period = self.p["replan_period_s"]
        due = period > 0 and (nav.stamp_ns - (self._last_plan_ns or 0)) * 1e-9 >= period
        if deviation > self.p["replan_sigma_threshold"] or due:
            return "replanning", deviation
        return "on_plan", deviation

    @staticmethod
    def _deviation_sigma(active: ActivePlan, nav: NavState) -> float:
        """Largest per-axis |nav - predicted| in navigation sigmas."""
        res = active.result
        tau = (nav.stamp_ns - active.t0_ns) * 1e-9
        k = int(np.searchsorted(res.epochs_s, tau + 0.5, side="right")) - 1
        k = min(max(k, 0), len(res.epochs_s) - 1)
        dt = tau - res.epochs_s[k]
        if abs(dt) < 0.5:
            predicted = res.roe_m[k]
        else:
            oe_k = propagate_mean_oe(res.chief_oe, res.epochs_s[k])
            post = res.roe_m[k] + control_matrix(oe_k) @ res.dv_rtn_mps[k]
            predicted = stm_j2(oe_k, dt) @ post
        sigma = np.sqrt(np.maximum(np.diag(nav.cov_m2), 1e-12))
        return float(np.max(np.abs(nav.roe_m - predicted) / sigma))

    def _job_for(self, nav: NavState, msg: RelativeNavState, trigger: str) -> Job:
        active = self._active
        if active is None:
            return Job(nav, self.target, trigger, msg, self._request_msg, None,
                       self.target.n_orbits, None)
        remaining_s = (active.end_ns - nav.stamp_ns) * 1e-9
        n_nodes = int(round(remaining_s / active.dt_s)) + 1
        period = orbital_period_s(nav.chief_oe[0])
        switch = max(0, math.ceil((active.switch_ns - nav.stamp_ns) * 1e-9 / active.dt_s))
        return Job(nav, self.target, trigger, msg, self._request_msg, max(n_nodes, 3),
                   max(remaining_s, 2 * active.dt_s) / period, switch)

    def _submit(self, job: Job) -> None:
        """Called with the lock held: replace any queued job, wake the worker."""
        if self._job is not None:
            self.stats["superseded"] += 1
        self._job = job
        self._lock.notify()

    # ------------------------------------------------------------------ worker
    def _work(self) -> None:
        while True:
            with self._lock:
                while self._job is None and not self._stop:
                    self._lock.wait()
                if self._stop:
                    return
                job, self._job, self._busy = self._job, None, True
            try:
                self._solve(job)
            except Exception as exc:  # the worker must survive anything
                self.get_logger().error(f"planning failed: {type(exc).__name__}: {exc}")
                self.plan_pub.publish(status_plan_msg(
                    job.nav.stamp_ns, self._next_id(), ManeuverPlan.STATUS_SOLVER_ERROR,
                    f"{type(exc).__name__}: {exc}", self._active_id()))
            finally:
                with self._lock:
                    self._busy = False

    def _solve(self, job: Job) -> None:
        request = PlanRequest(job.nav.chief_oe, job.nav.roe_m, job.target.target_rtn,
                              chance_constrained=job.target.chance_constrained,
                              warm_start=job.target.warm_start, n_nodes=job.n_nodes,
                              n_orbits=job.n_orbits, koz_switch_node=job.koz_switch_node)
        result = self.pipeline.plan(request)
        plan_id = self._next_id()
        plan_msg = plan_to_msg(result, job.nav.stamp_ns, plan_id)
        with self._lock:
            # An unusable replan never replaces the plan in force: the node keeps flying it.
            if result.scp.feasible:
                self._activate(job, result, plan_id)
            active_id = self._active_id()
        plan_msg.active_plan_id = active_id
        if result.scp.feasible:
            action = "activated"
        else:
            action = "kept_active_plan" if active_id else "no_plan"
            plan_msg.status_text = (
                f"{result.status.name}: replan not usable (margin "
                f"{result.constraint_margin_m:.2f} m after {result.scp.iterations} "
                f"iterations); " + (f"plan {active_id} stays in force" if active_id
                                    else "no plan is in force"))
        # recorded (and fsync'ed) before it is published: a crash never loses a published plan
        self._record(job, result, plan_id, plan_msg)
        self.plan_pub.publish(plan_msg)
        self.stats["plans"] += 1
        level = OK if result.scp.feasible else WARN
        self.get_logger().info(
            f"{plan_id} ({job.trigger}): {result.status.name}, {result.cost_mps:.4f} m/s, "
            f"{result.scp.iterations} it, margin {result.constraint_margin_m:.2f} m, "
            f"{result.timings_ms['total']:.0f} ms; {action} (in force: {active_id or 'none'})")
        self._publish_diag("art_guidance/plan", level, f"{result.status.name}: {action}",
                           {"plan_id": plan_id, "nav_stamp_ns": str(job.nav.stamp_ns),
                            "action": action, "active_plan_id": active_id,
                            "cost_mps": result.cost_mps,
                            "solve_time_ms": result.timings_ms["total"]})

    def _record(self, job: Job, result: PlanResult, plan_id: str, plan_msg: ManeuverPlan) -> None:
        if self.recorder is None:
            return
        msgs = [("/nav/relative_state", job.nav_msg)]
        if job.request_msg is not None:
            msgs.append(("/guidance/replan_request", job.request_msg))
        msgs += [("/guidance/solve_record",
                  solve_record_msg(result, job.nav.stamp_ns, plan_id, job.trigger)),
                 ("/guidance/maneuver_plan", plan_msg)]
        if not self.recorder.record_solve(msgs, time.time_ns()):
            self.get_logger().error(f"recording failed, guidance continues: "
                                    f"{self.recorder.last_error}")
            self._publish_diag("art_guidance/recorder", ERROR, self.recorder.last_error,
                               {"errors": self.recorder.errors})

    def _activate(self, job: Job, result: PlanResult, plan_id: str) -> None:
        dt_s = float(result.epochs_s[1] - result.epochs_s[0])
        t0 = job.nav.stamp_ns
        if self._active is None:
            switch_ns = t0 + int(self.scenario.ae_to_koz_node * dt_s * 1e9)
        else:
            switch_ns = self._active.switch_ns
        self._active = ActivePlan(plan_id, t0, result,
                                  t0 + int(round(result.epochs_s[-1] * 1e9)), dt_s, switch_ns)
        self._last_plan_ns = t0

    def _active_id(self) -> str:
        """Id of the plan in force ("" = none)."""
        active = self._active
        return "" if active is None else active.plan_id

    def _next_id(self) -> str:
        return f"plan-{next(self._ids)}"

    # ------------------------------------------------------------------ publishing
    def _reject(self, stamp_ns: int, reason: str) -> None:
        self.stats["rejected"] += 1
        self.get_logger().warning(f"nav message rejected: {reason}")
        self.plan_pub.publish(status_plan_msg(stamp_ns, "rejected",
                                              ManeuverPlan.STATUS_REJECTED_INPUT, reason,
                                              self._active_id()))
        self._diag(stamp_ns, WARN, "rejected", {"reason": reason})

    def _diag(self, stamp_ns: int, level: int, decision: str, extra: dict) -> None:
        values = {"nav_stamp_ns": str(stamp_ns), "decision": decision, **extra}
        self._publish_diag("art_guidance/nav", level, decision, values)

    def _publish_diag(self, name: str, level: int, message: str, values: dict) -> None:
        self.diag_pub.publish(diagnostics_msg(time.time_ns(), name, level, message, values))

    def shutdown_worker(self) -> None:
        """Stop the worker thread (after the running solve)."""
        with self._lock:
            self._stop = True
            self._lock.notify()
        self._worker.join(timeout=30.0)
        if self.recorder is not None:
            self.recorder.finish()
            self.get_logger().info(f"recorded {self.recorder.solves} solves to "
                                   f"{self.recorder.directory}")


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("art_guidance", "clarabel", "osqp", "numpy", "scipy", "mcap",
                "mcap-ros2-support", "torch", "rclpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "absent"
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node until SIGINT/SIGTERM (Jazzy-correct shutdown order)."""
    use_fast_discovery()
    rclpy.init(args=list(argv) if argv is not None else sys.argv)
    node = None
    executor = SingleThreadedExecutor()
    try:
        node = GuidanceNode()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (GuidanceError, ValueError) as exc:
        print(f"guidance_node: {exc}", file=sys.stderr)
        return 2
    finally:
        executor.shutdown()
        if node is not None:
            node.shutdown_worker()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
