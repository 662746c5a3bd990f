"""Closed-loop simulator as a ROS 2 process that drives the guidance node in lockstep.

Run the guidance node with ``-p stamp_check:=order`` (or ``off``): the simulator stamps its
messages with *sim* time, ``epoch0_s + t`` (default SIM_EPOCH0_NS), which its default
wall-clock check rejects. With ``order`` the node also rejects stamps not newer than the last
one it saw: a second run against the same node needs a larger ``epoch0_s`` (or a fresh node).

Topics (all RELIABLE, VOLATILE, keep-last; the replan request is TRANSIENT_LOCAL, depth 1):

* publishes ``nav/relative_state`` (art_guidance_msgs/RelativeNavState: ROE representation,
  frame "chief_roe", chief mean elements at the stamp, 6x6 covariance row-major) and, once at
  the start, ``guidance/replan_request`` (waypoint, chance_constrained, warm_start);
* subscribes ``guidance/maneuver_plan`` (ManeuverPlan) and ``/diagnostics``.

Protocol (what the guidance node promises): for every nav message it processes it publishes a
DiagnosticStatus named "art_guidance/nav" (a "<node>: " prefix is accepted) with the key-values
``nav_stamp_ns`` (str of the integer nanoseconds of the nav stamp) and ``decision`` in
{replanning, on_plan, rejected}; after "replanning" a ManeuverPlan with ``header.stamp`` equal to
that nav stamp follows (a non-zero status on failure). Plan epochs are relative to its stamp.

Loop, one step per plan node: publish the nav fix at the current sim time; wait (wall-clock
``step_timeout_s``) for its decision and, after "replanning", for its plan; adopt every plan
received so far in arrival order (a CONVERGED or MAX_ITERATIONS plan with valid arrays becomes
the active plan); execute the active plan's burn whose epoch is within 1 s of now (each node
once, with Gates errors); stop after the burn at the active plan's final epoch; otherwise
advance the truth to the plan's next epoch. Without an active plan the truth drifts for one
nominal node spacing and the next fix is published (five rejected fixes in a row without a plan
end the run). The request and the first fix are re-sent every 2 s until the first answer (a
message published right after discovery can be lost). Plans answering stamps this run never
sent (e.g. a node replanning an earlier run's last fix on our request) are ignored, and
rejection notices (STATUS_REJECTED_INPUT) do not count as replans. At the end one JSON line
(`summarize` plus run fields) goes to stdout and `summary_path`, the PNG to `png_path`; exit 0
if the run reached the final epoch within `miss_tolerance_m` of the waypoint, 1 otherwise
(also on timeouts, SIGINT/SIGTERM: a partial summary is still written), 2 on bad parameters.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import rclpy
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.data.stages import sample_scenario
from art_guidance.dynamics import orbital_period_s
from art_guidance.errors import GuidanceError, InputError
from art_guidance.ros.adapters import ns_to_stamp, stamp_to_ns
from art_guidance.sim.simulator import (
    EPOCH_MATCH_S, RendezvousSim, koz_switch_time_s, run_safety_model,
    summarize,
)
from art_guidance.files import write_json_atomic
from art_guidance.ros.env import use_fast_discovery
from art_guidance.sim.plot import plot_rendezvous

SIM_EPOCH0_NS = 1_000_000_000 * 1_000_000_000  # sim t = 0 is stamped 1e9 s (2001-09-09)
DIAG_NAME = "art_guidance/nav"
DECISIONS = ("replanning", "on_plan", "rejected")
WARM_STARTS = ("auto", "cvx", "art")
USABLE_STATUSES = (ManeuverPlan.STATUS_CONVERGED, ManeuverPlan.STATUS_MAX_ITERATIONS)
MAX_REJECTED_IDLE = 5      # consecutive rejected fixes without an active plan -> give up
SETTLE_S = 0.2             # pause after discovery and after the replan request [s]
POLL_S = 0.1               # wait granularity for shutdown checks [s]
FIRST_RETRY_S = 2.0        # re-send the request and the first fix after this [s]
PARAMETERS: dict[str, object] = {
    "waypoint": "plus_vbar",
    "seed": 0,
    "chance_constrained": True,
    "warm_start": "auto",
    "step_timeout_s": 30.0,
    "max_steps": 200,
    "miss_tolerance_m": 50.0,
    "png_path": "out/rendezvous.png",
    "summary_path": "out/sim_summary.json",
    "errors": True,          # navigation (ARTMS) and actuation (Gates) errors
    "mean_elements": True,   # mean-element chief model and mean-ROE navigation (sim.py)
    "config_dir": "",        # "" = packaged config/
    "epoch0_s": SIM_EPOCH0_NS // 1_000_000_000,  # stamp of sim t = 0 [s]
}
FLOAT_PARAMETERS = ("step_timeout_s", "miss_tolerance_m")


@dataclass(frozen=True)
class ActivePlan:
    """A usable plan in sim time.

    Attributes:
        stamp_ns: the plan's header stamp (the nav stamp it answers) [ns].
        plan_id: the guidance's plan id.
        epochs_s: (N,) absolute node epochs in sim time [s].
        dv_rtn_mps: (N, 3) delta-v per node [m/s].
        rtn: (N, 6) predicted RTN trajectory, or None if the plan carries none.
    """

    stamp_ns: int
    plan_id: str
    epochs_s: np.ndarray
    dv_rtn_mps: np.ndarray
    rtn: np.ndarray | None

    def index_at(self, t_s: float) -> int | None:
        """Index of the node within EPOCH_MATCH_S of `t_s` (the closest), or None."""
        k = int(np.argmin(np.abs(self.epochs_s - t_s)))
        return k if abs(self.epochs_s[k] - t_s) <= EPOCH_MATCH_S else None

    def next_epoch_after(self, t_s: float) -> float | None:
        """First node epoch later than `t_s` + EPOCH_MATCH_S [s], or None."""
        later = self.epochs_s[self.epochs_s > t_s + EPOCH_MATCH_S]
        return float(later[0]) if later.size else None


def sim_time_s(stamp_ns: int, epoch0_ns: int = SIM_EPOCH0_NS) -> float:
    """Sim time [s] of a stamp [ns]."""
    return (int(stamp_ns) - int(epoch0_ns)) * 1e-9


def sim_stamp_ns(t_s: float, epoch0_ns: int = SIM_EPOCH0_NS) -> int:
    """Stamp [ns] of a sim time [s]."""
    return int(epoch0_ns) + int(round(float(t_s) * 1e9))


def parse_plan(msg: ManeuverPlan, epoch0_ns: int = SIM_EPOCH0_NS) -> ActivePlan:
    """Validate a ManeuverPlan's arrays and convert its epochs to sim time.

    Raises:
        InputError: on empty, non-finite, mis-sized arrays or non-increasing epochs.
    """
    stamp = stamp_to_ns(msg.header.stamp)
    epochs = np.asarray(msg.epochs_s, dtype=float)
    n = epochs.size
    if n == 0 or not np.all(np.isfinite(epochs)) or np.any(np.diff(epochs) <= 0):
        raise InputError("epochs_s", "need >= 1 finite, strictly increasing epochs", n)
    dv = np.asarray(msg.dv_rtn_mps, dtype=float)
    if dv.size != 3 * n or not np.all(np.isfinite(dv)):
        raise InputError("dv_rtn_mps", f"need {3 * n} finite values", dv.size)
    rtn = np.asarray(msg.rtn, dtype=float)
    rtn_ok = rtn.size == 6 * n and np.all(np.isfinite(rtn))
    return ActivePlan(stamp, msg.plan_id, sim_time_s(stamp, epoch0_ns) + epochs,
                      dv.reshape(n, 3), rtn.reshape(n, 6) if rtn_ok else None)


def exit_code(outcome: str, miss_m: float, tolerance_m: float) -> int:
    """0 if the run reached the active plan's final epoch within tolerance, else 1."""
    return 0 if outcome == "final_epoch" and miss_m <= tolerance_m else 1


class SimNode(Node):
    """rclpy side of the simulator: publishers, subscriptions and thread-safe mailboxes."""

    def __init__(self) -> None:
        super().__init__("art_guidance_sim")
        dynamic = ParameterDescriptor(dynamic_typing=True)
        for name, default in PARAMETERS.items():
            if name in FLOAT_PARAMETERS:
                self.declare_parameter(name, default, dynamic)  # accepts 30 as well as 30.0
            else:
                self.declare_parameter(name, default)
        self.declare_parameter("rtn0", Parameter.Type.DOUBLE_ARRAY)  # unset: from the seed
        self.p = {name: self.get_parameter(name).value for name in PARAMETERS}
        for name in FLOAT_PARAMETERS:
            self.p[name] = float(self.p[name])
        try:
            self.p["rtn0"] = list(self.get_parameter("rtn0").value)
        except ParameterUninitializedException:
            self.p["rtn0"] = None
        self.epoch0_ns = int(self.p["epoch0_s"]) * 1_000_000_000
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.nav_pub = self.create_publisher(RelativeNavState, "nav/relative_state", qos)
        self.req_pub = self.create_publisher(ReplanRequest, "guidance/replan_request", latched)
        self.create_subscription(ManeuverPlan, "guidance/maneuver_plan", self._on_plan,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self._cv = threading.Condition()
        self._decisions: dict[int, dict[str, str]] = {}
        self._plans: list[ManeuverPlan] = []  # arrival order
        self._plan_stamps: set[int] = set()

    # ------------------------------------------------------------------ callbacks
    def _on_plan(self, msg: ManeuverPlan) -> None:
        with self._cv:
            self._plans.append(msg)
            if msg.status != ManeuverPlan.STATUS_REJECTED_INPUT:  # not a rejection notice
                self._plan_stamps.add(stamp_to_ns(msg.header.stamp))
            self._cv.notify_all()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        with self._cv:
            for status in msg.status:
                if status.name != DIAG_NAME and not status.name.endswith(": " + DIAG_NAME):
                    continue
                values = {kv.key: kv.value for kv in status.values}
                try:
                    stamp = int(values.get("nav_stamp_ns", ""))
                except ValueError:
                    continue
                self._decisions.setdefault(stamp, values)  # the first answer counts
            self._cv.notify_all()

    # ------------------------------------------------------------------ waiting
    def _wait(self, predicate: Callable[[], object], timeout_s: float) -> object:
        """Wait for a truthy predicate() (checked under the lock); None on timeout.

        Raises:
            ExternalShutdownException: if the ROS context shuts down while waiting.
        """
        end = time.monotonic() + timeout_s
        with self._cv:
            while True:
                if not self.context.ok():
                    raise ExternalShutdownException()
                value = predicate()
                if value:
                    return value
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._cv.wait(timeout=min(POLL_S, left))

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until the guidance node's endpoints are discovered in both directions."""
        def matched() -> bool:
            return (self.nav_pub.get_subscription_count() > 0
                    and self.req_pub.get_subscription_count() > 0
                    and self.count_publishers("guidance/maneuver_plan") > 0
                    and self.count_publishers("/diagnostics") > 0)
        return bool(self._wait(matched, timeout_s))

    def wait_decision(self, stamp_ns: int, timeout_s: float) -> dict[str, str] | None:
        """The diagnostic key-values answering nav `stamp_ns`, or None on timeout."""
        return self._wait(lambda: self._decisions.get(stamp_ns), timeout_s)

    def wait_plan(self, stamp_ns: int, timeout_s: float) -> bool:
        """True once a plan (not a rejection notice) stamped `stamp_ns` has arrived."""
        return bool(self._wait(lambda: stamp_ns in self._plan_stamps, timeout_s))

    def take_plans(self, start: int) -> list[ManeuverPlan]:
        """Plans received from index `start` on (arrival order)."""
        with self._cv:
            return list(self._plans[start:])

    # ------------------------------------------------------------------ publishing
    def publish_request(self) -> None:
        """The replanning request (waypoint, chance-constrained flag, warm start)."""
        msg = ReplanRequest()
        ns_to_stamp(msg.header.stamp, self.epoch0_ns)
        msg.waypoint = self.p["waypoint"]
        msg.chance_constrained = bool(self.p["chance_constrained"])
        msg.horizon_orbits = 0.0
        msg.warm_start = self.p["warm_start"]
        self.req_pub.publish(msg)

    def publish_nav(self, stamp_ns: int, chief_oe: np.ndarray, roe_m: np.ndarray,
                    cov_m2: np.ndarray) -> None:
        """A RelativeNavState in ROE at `stamp_ns`."""
        msg = RelativeNavState()
        ns_to_stamp(msg.header.stamp, stamp_ns)
        msg.header.frame_id = "chief_roe"
        msg.chief_oe = [float(v) for v in chief_oe]
        msg.representation = RelativeNavState.REPRESENTATION_ROE
        msg.mean = [float(v) for v in roe_m]
        msg.covariance = [float(v) for v in np.asarray(cov_m2).reshape(-1)]
        self.nav_pub.publish(msg)


class ClosedLoop:
    """The lockstep loop (main thread) over a spinning `SimNode`."""

    def __init__(self, node: SimNode) -> None:
        p = node.p
        self.node = node
        self.log = node.get_logger()
        cfg_dir = p["config_dir"] or None
        path = (lambda f: None) if cfg_dir is None else (lambda f: Path(cfg_dir) / f)
        self.scenario = ScenarioConfig.from_yaml(path("scenario.yaml"))
        if p["waypoint"] not in self.scenario.waypoints_rtn:
            raise InputError("waypoint", f"unknown; choose from "
                             f"{sorted(self.scenario.waypoints_rtn)}", p["waypoint"])
        for name in ("step_timeout_s", "miss_tolerance_m"):
            if not p[name] > 0:
                raise InputError(name, "must be > 0", p[name])
        if int(p["max_steps"]) < 1:
            raise InputError("max_steps", "must be >= 1", p["max_steps"])
        if p["warm_start"] not in WARM_STARTS:
            raise InputError("warm_start", f"must be one of {WARM_STARTS}", p["warm_start"])
        self.target = np.asarray(self.scenario.waypoints_rtn[p["waypoint"]], dtype=float)
        rtn0 = p["rtn0"]
        if rtn0 is None:
            rtn0 = sample_scenario(self.scenario, int(p["seed"])).rtn0
        uncertainty = UncertaintyConfig.from_yaml(path("uncertainty.yaml")) if p["errors"] \
            else None
        self.sim = RendezvousSim(self.scenario, uncertainty, rtn0, int(p["seed"]),
                                 mean_elements=bool(p["mean_elements"]))
        a_m = float(self.sim.chief_mean_oe0[0])
        self.idle_dt_s = (self.scenario.n_orbits * orbital_period_s(a_m)
                          / (self.scenario.n_nodes - 1))
        self.active: ActivePlan | None = None
        self.first_plan_t_s: float | None = None
        self.executed: set[tuple[int, int]] = set()
        self.sent: set[int] = set()  # nav stamps published by this run
        self.counts = {"steps": 0, "plans_received": 0, "replans": 0, "plans_failed": 0,
                       "replans_kept_active": 0,
                       "plans_foreign": 0, "idle_steps": 0, **{d: 0 for d in DECISIONS}}
        self._seen_plans = 0

    # ------------------------------------------------------------------ loop
    def run(self) -> str:
        """Run to the end; returns the outcome (final_epoch, max_steps, no_guidance, ...)."""
        p = self.node.p
        timeout = p["step_timeout_s"]
        if not self.node.wait_matched(timeout):
            self.log.error("no guidance node matched (nav/relative_state, "
                           "guidance/maneuver_plan, /diagnostics)")
            return "no_guidance"
        time.sleep(SETTLE_S)
        self.node.publish_request()
        time.sleep(SETTLE_S)
        rejected_idle = 0
        for _ in range(int(p["max_steps"])):
            self.counts["steps"] += 1
            sim = self.sim
            stamp = sim_stamp_ns(sim.t_s, self.node.epoch0_ns)
            self.sent.add(stamp)
            roe, cov = sim.nav_estimate()
            self.node.publish_nav(stamp, sim.chief_mean_oe(), roe, cov)
            if self.counts["steps"] == 1:
                values = self._first_decision(stamp, sim.chief_mean_oe(), roe, cov, timeout)
            else:
                values = self.node.wait_decision(stamp, timeout)
            if values is None:
                self.log.error(f"no decision for nav stamp {stamp} within {timeout} s")
                return "timeout_decision"
            decision = values.get("decision", "")
            self.counts[decision if decision in DECISIONS else "on_plan"] += 1
            if decision == "rejected":
                self.log.warning(f"nav at t = {sim.t_s:.1f} s rejected: "
                                 f"{values.get('reason', '')}")
            if decision == "replanning" and not self.node.wait_plan(stamp, timeout):
                self.log.error(f"no plan for nav stamp {stamp} within {timeout} s")
                return "timeout_plan"
            self._adopt_plans()
            if self.active is None:
                rejected_idle = rejected_idle + 1 if decision == "rejected" else 0
                if rejected_idle >= MAX_REJECTED_IDLE:
                    self.log.error("every nav fix is rejected: a guidance node with its "
                                   "wall-clock stamp check (use -p stamp_check:=order) or one "
                                   "that saw later stamps (restart it or raise epoch0_s)?")
                    return "rejected"
                self.counts["idle_steps"] += 1
                sim.advance(self.idle_dt_s)
                continue
            rejected_idle = 0
            if self._burn_now():
                return "final_epoch"
            nxt = self.active.next_epoch_after(sim.t_s)
            if nxt is None:
                return "plan_ended"
            sim.advance(nxt - sim.t_s)
        return "max_steps"

    def _first_decision(self, stamp: int, chief_oe: np.ndarray, roe: np.ndarray,
                        cov: np.ndarray, timeout_s: float) -> dict[str, str] | None:
        """Wait for the first answer, re-sending request and fix every FIRST_RETRY_S.

        Right after discovery the guidance side may not have matched our writers yet, and a
        volatile reader never sees what was published before it matched. A repeated fix has
        the same stamp: the guidance answers the first copy it gets (a later copy is stale to
        it), and only the first answer per stamp counts here.
        """
        end = time.monotonic() + timeout_s
        while True:
            left = end - time.monotonic()
            values = self.node.wait_decision(stamp, min(FIRST_RETRY_S, max(left, 0.0)))
            if values is not None or left <= FIRST_RETRY_S:
                return values
            self.log.warning("no answer to the first nav fix yet; sending request and fix "
                             "again")
            self.node.publish_request()
            time.sleep(SETTLE_S)
            self.node.publish_nav(stamp, chief_oe, roe, cov)

    def _adopt_plans(self) -> None:
        """Count new plans; the newest usable one (arrival order) becomes active."""
        for msg in self.node.take_plans(self._seen_plans):
            self._seen_plans += 1
            self.counts["plans_received"] += 1
            if stamp_to_ns(msg.header.stamp) not in self.sent:
                self.counts["plans_foreign"] += 1  # answers a fix this run never sent
                continue
            if msg.status == ManeuverPlan.STATUS_REJECTED_INPUT:
                continue  # the answer to a rejected nav fix, not a replan
            self.counts["replans"] += 1
            if msg.status not in USABLE_STATUSES:
                kept = self.active is not None and msg.active_plan_id == self.active.plan_id
                # the guidance keeps the plan in force: so does the simulator
                self.counts["replans_kept_active" if kept else "plans_failed"] += 1
                self.log.warning(f"plan {msg.plan_id} not usable: {msg.status_text}")
                continue
            try:
                plan = parse_plan(msg, self.node.epoch0_ns)
            except InputError as exc:
                self.counts["plans_failed"] += 1
                self.log.warning(f"plan {msg.plan_id} malformed: {exc}")
                continue
            if self.active is not None and plan.stamp_ns < self.active.stamp_ns:
                continue  # an older answer arriving late
            self.active = plan
            if self.first_plan_t_s is None:
                self.first_plan_t_s = sim_time_s(plan.stamp_ns, self.node.epoch0_ns)
            self.log.info(f"t = {self.sim.t_s:.1f} s: active plan {plan.plan_id} "
                          f"({plan.epochs_s.size} nodes, cost "
                          f"{np.linalg.norm(plan.dv_rtn_mps, axis=1).sum():.4f} m/s)")

    def _burn_now(self) -> bool:
        """Execute the active plan's burn at the current time; True after its last node."""
        plan = self.active
        k = plan.index_at(self.sim.t_s)
        if k is None or (plan.stamp_ns, k) in self.executed:
            return False
        self.executed.add((plan.stamp_ns, k))
        self.sim.execute_burn(plan.dv_rtn_mps[k])
        return k == plan.epochs_s.size - 1

    # ------------------------------------------------------------------ report
    def finish(self, outcome: str, wall_s: float) -> tuple[dict, int]:
        """Summary dict and exit code; writes the JSON summary and the PNG."""
        p = self.node.p
        switch = koz_switch_time_s(self.scenario, self.sim.chief_mean_oe0[0],
                                   self.first_plan_t_s or 0.0)
        summary = summarize(self.sim, self.target,
                            run_safety_model(self.sim, koz_switch_t_s=switch),
                            self.counts["replans"])
        code = exit_code(outcome, summary["miss_m"], p["miss_tolerance_m"])
        summary.update(
            outcome=outcome, reached=code == 0, waypoint=p["waypoint"], seed=int(p["seed"]),
            chance_constrained=bool(p["chance_constrained"]),
            miss_tolerance_m=p["miss_tolerance_m"], errors=bool(p["errors"]),
            mean_elements=bool(p["mean_elements"]), wall_time_s=round(wall_s, 3),
            png_path=p["png_path"] or None, **{f"n_{k}": v for k, v in self.counts.items()
                                               if k != "replans"})
        if p["png_path"]:
            plot_rendezvous(p["png_path"], self.sim, self.scenario,
                            None if self.active is None else self.active.rtn,
                            target_rtn=self.target, summary=summary)
        if p["summary_path"]:
            write_json_atomic(p["summary_path"], summary)
        return summary, code


def _spin(executor: SingleThreadedExecutor) -> None:
    try:
        executor.spin()
    except (ExternalShutdownException, KeyboardInterrupt):
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Run the closed-loop simulation; exit code as in the module docstring.

    Args:
        argv: full argument vector (program name first), e.g. ``["sim", "--ros-args", "-p",
            "seed:=3"]``; None uses sys.argv.
    """
    use_fast_discovery()
    try:
        rclpy.init(args=list(argv) if argv is not None else sys.argv)
    except Exception as exc:  # RCLError on unparsable --ros-args (e.g. `-p name:=`)
        print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
        return 2
    node: SimNode | None = None
    executor = SingleThreadedExecutor()
    thread: threading.Thread | None = None
    code = 1
    try:
        node = SimNode()
        loop = ClosedLoop(node)
        executor.add_node(node)
        thread = threading.Thread(target=_spin, args=(executor,), name="sim_executor",
                                  daemon=True)
        thread.start()
        start = time.monotonic()
        try:
            outcome = loop.run()
        except KeyboardInterrupt:
            outcome = "interrupted"
        except ExternalShutdownException:
            outcome = "shutdown"
        except Exception:
            if node.context.ok():
                raise
            outcome = "shutdown"  # SIGINT/SIGTERM: rclpy invalidated the context mid-call
        summary, code = loop.finish(outcome, time.monotonic() - start)
        print(json.dumps(summary), flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 1
    except GuidanceError as exc:
        print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
        code = 2
    finally:
        executor.shutdown()
        if thread is not None:
            thread.join(timeout=5.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


# --------------------------------------------------------------------------- CLI
def sim_argv(args: argparse.Namespace) -> list[str]:
    """The rclpy argument vector for `art-guidance sim` options (values YAML-quoted)."""
    params = {
        "waypoint": json.dumps(args.waypoint),
        "seed": str(int(args.seed)),
        "chance_constrained": "false" if args.deterministic else "true",
        "png_path": json.dumps(args.png),
        "summary_path": json.dumps(args.summary_json),
        "step_timeout_s": repr(float(args.step_timeout)),
        "max_steps": str(int(args.max_steps)),
        "miss_tolerance_m": repr(float(args.miss_tolerance)),
    }
    argv = ["art_guidance_sim", "--ros-args"]
    for name, value in params.items():
        argv += ["-p", f"{name}:={value}"]
    return argv + list(args.ros_args or [])


def _cmd_sim(args: argparse.Namespace) -> int:
    """Closed-loop rendezvous simulation against a running guidance node (over ROS 2)."""
    return main(sim_argv(args))


def add_sim_parser(sub: argparse._SubParsersAction) -> None:
    """Register `art-guidance sim` (options map to the simulator's ROS parameters)."""
    p = sub.add_parser(
        "sim", help="closed-loop simulation against the guidance node",
        description=_cmd_sim.__doc__ + " Start the guidance node first with "
        "`--ros-args -p stamp_check:=order` (sim-time stamps). Prints one JSON summary line; "
        "exit 0 if the waypoint was reached within the miss tolerance, 1 if not, 2 on bad "
        "input. More ROS parameters (rtn0, errors, mean_elements, warm_start, config_dir, "
        "max_steps, ...) after --ros-args (last).")
    p.add_argument("--waypoint", default="plus_vbar", help="terminal waypoint name")
    p.add_argument("--seed", type=int, default=0,
                   help="initial state (Table I ranges) and error samples")
    p.add_argument("--deterministic", action="store_true",
                   help="request deterministic passive safety (default: chance-constrained)")
    p.add_argument("--png", default="out/rendezvous.png", help="plot path ('' = none)")
    p.add_argument("--summary-json", default="out/sim_summary.json",
                   help="summary JSON path ('' = none)")
    p.add_argument("--step-timeout", type=float, default=30.0,
                   help="wall-clock wait for each decision/plan [s]")
    p.add_argument("--max-steps", type=int, default=200, help="nav fixes at most")
    p.add_argument("--miss-tolerance", type=float, default=50.0,
                   help="largest final position error counted as reached [m]")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="everything after it goes to rclpy, e.g. --ros-args -p errors:=false")
    p.set_defaults(func=_cmd_sim)


if __name__ == "__main__":
    sys.exit(main())
