"""Closed-loop simulator as a ROS 2 process that drives the guidance node in lockstep.

Run the guidance node with ``-p stamp_check:=order`` (or ``off``): the simulator stamps its
messages with *sim* time, ``epoch0_s + t`` (default SIM_EPOCH0_NS), which its default
wall-clock check rejects. With ``order`` the node also rejects stamps not newer than the last
one it saw: a second run against the same node needs a larger ``epoch0_s`` (or a fresh node).

Topics (all RELIABLE, VOLATILE, keep-last; the replan request is TRANSIENT_LOCAL, depth 1):

* publishes ``nav/relative_state`` (art_guidance_msgs/RelativeNavState: ROE representation,
  frame "chief_roe", chief mean elements at the stamp, 6x6 covariance row-major) and, once at
  the start, ``guidance/replan_request`` (waypoint, chance_constrained, warm_start);
* publishes ``sim/viz/truth_path`` (nav_msgs/Path, TRANSIENT_LOCAL depth 1): the truth
  trajectory so far in frame ``chief_rtn`` (x = R, y = T, z = N), at most 1,000 poses,
  stamped in sim time, once per step;
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
(`run_outcome` plus run fields) goes to stdout and `summary_path`, the PNG to `png_path`; exit 0
if the run reached the final epoch within `miss_tolerance_m` of the waypoint, 1 otherwise
(also on timeouts, SIGINT/SIGTERM: a partial summary is still written once the run is under
way, from its "waiting for a guidance node" log line; a stop while it is set up ends with exit
1 and no run), 2 on bad parameters.
"""
from __future__ import annotations

import json
import sys
import threading
import time
from typing import Callable, Sequence

import numpy as np
import rclpy
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from art_guidance import topics
from art_guidance.errors import GuidanceError
from art_guidance.ros.adapters import link_plan_from_msg, ns_to_stamp, stamp_to_ns
from art_guidance.ros.visualization import truth_path_msg
from art_guidance.sim.closed_loop import FLOAT_PARAMETERS, PARAMETERS, ClosedLoop
from art_guidance.sim.link import LinkPlan

DIAG_NAME = "art_guidance/nav"
POLL_S = 0.1               # wait granularity for shutdown checks [s]


class SimNode(Node):
    """rclpy side of the simulator: the `GuidanceLink` over DDS (publishers, subscriptions and
    thread-safe mailboxes)."""

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
        self.nav_pub = self.create_publisher(RelativeNavState, topics.NAV, qos)
        self.truth_pub = self.create_publisher(Path, topics.TRUTH_PATH, latched)
        self.req_pub = self.create_publisher(ReplanRequest, topics.REPLAN_REQUEST, latched)
        self.create_subscription(ManeuverPlan, topics.MANEUVER_PLAN, self._on_plan,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag,
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
                    and self.count_publishers(topics.MANEUVER_PLAN) > 0
                    and self.count_publishers(topics.DIAGNOSTICS) > 0)
        return bool(self._wait(matched, timeout_s))

    def wait_decision(self, stamp_ns: int, timeout_s: float) -> dict[str, str] | None:
        """The diagnostic key-values answering nav `stamp_ns`, or None on timeout."""
        return self._wait(lambda: self._decisions.get(stamp_ns), timeout_s)

    def wait_plan(self, stamp_ns: int, timeout_s: float) -> bool:
        """True once a plan (not a rejection notice) stamped `stamp_ns` has arrived."""
        return bool(self._wait(lambda: stamp_ns in self._plan_stamps, timeout_s))

    def take_plans(self, start: int) -> list[LinkPlan]:
        """Plans received from index `start` on (arrival order)."""
        with self._cv:
            return [link_plan_from_msg(m) for m in self._plans[start:]]

    # ------------------------------------------------------------------ publishing
    def publish_request(self, waypoint: str, chance_constrained: bool, warm_start: str) -> None:
        """The replanning request (waypoint, chance-constrained flag, warm start)."""
        msg = ReplanRequest()
        ns_to_stamp(msg.header.stamp, self.epoch0_ns)
        msg.waypoint = waypoint
        msg.chance_constrained = bool(chance_constrained)
        msg.horizon_orbits = 0.0
        msg.warm_start = warm_start
        self.req_pub.publish(msg)

    def publish_truth(self, t_s: Sequence[float], rtn: Sequence[np.ndarray]) -> None:
        """The truth trajectory so far on sim/viz/truth_path (frame chief_rtn, sim stamps)."""
        self.truth_pub.publish(truth_path_msg(np.asarray(t_s), np.asarray(rtn), self.epoch0_ns))

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
        loop = ClosedLoop(node, node.p, node.get_logger())
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


if __name__ == "__main__":
    sys.exit(main())
