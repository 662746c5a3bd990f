"""Test-side rclpy client of the guidance node: publishes nav/requests, collects replies."""
from __future__ import annotations

import threading
import time

import numpy as np
import rclpy
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy

from art_guidance import topics
from art_guidance.config import ScenarioConfig


def nav_msg(stamp_ns: int, rtn: np.ndarray, chief_oe=None, cov=None,
            representation: int = RelativeNavState.REPRESENTATION_RTN,
            frame_id: str = "chief_rtn") -> RelativeNavState:
    """A RelativeNavState; covariance defaults to a plausible diagonal in RTN units."""
    msg = RelativeNavState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.chief_oe = list(chief_oe if chief_oe is not None else ScenarioConfig().chief_oe)
    msg.representation = representation
    msg.mean = [float(v) for v in rtn]
    if cov is None:
        cov = np.diag([25.0, 400.0, 25.0, 1e-4, 1e-4, 1e-4])
    msg.covariance = [float(v) for v in np.asarray(cov).reshape(-1)]
    return msg


class Client:
    """Spins its own executor thread; thread-safe accessors for what arrived."""

    def __init__(self, name: str = "art_guidance_test_client", namespace: str = "") -> None:
        if not rclpy.ok():
            rclpy.init()
        self.node = rclpy.create_node(name, namespace=namespace)  # relative topics under it
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.nav_pub = self.node.create_publisher(RelativeNavState, topics.NAV, qos)
        self.req_pub = self.node.create_publisher(ReplanRequest, topics.REPLAN_REQUEST, qos)
        self.plans: list[tuple[float, ManeuverPlan]] = []
        self.diags: list[tuple[float, dict, str]] = []
        self._cv = threading.Condition()
        self.plan_sub = self.node.create_subscription(ManeuverPlan, topics.MANEUVER_PLAN,
                                                      self._on_plan, qos)
        self.diag_sub = self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                                      self._on_diag, qos)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def _on_plan(self, msg: ManeuverPlan) -> None:
        with self._cv:
            self.plans.append((time.monotonic(), msg))
            self._cv.notify_all()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        with self._cv:
            for st in msg.status:
                self.diags.append((time.monotonic(), {kv.key: kv.value for kv in st.values},
                                   st.name))
            self._cv.notify_all()

    def wait_matched(self, timeout_s: float = 15.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            # both directions matched at the endpoint level, not just seen in the graph
            if (self.nav_pub.get_subscription_count() > 0
                    and self.req_pub.get_subscription_count() > 0
                    and self.plan_sub.get_publisher_count() > 0
                    and self.diag_sub.get_publisher_count() > 0):
                return True
            time.sleep(0.05)
        return False

    def wait_for(self, predicate, timeout_s: float):
        """Wait until predicate(plans, diags) returns a truthy value; return it (or None)."""
        end = time.monotonic() + timeout_s
        with self._cv:
            while True:
                value = predicate(self.plans, self.diags)
                if value or time.monotonic() >= end:
                    return value
                self._cv.wait(timeout=max(0.0, min(0.2, end - time.monotonic())))

    def plan_for(self, stamp_ns: int, timeout_s: float = 30.0) -> ManeuverPlan | None:
        def find(plans, _):
            for _, p in reversed(plans):
                if p.header.stamp.sec * 1_000_000_000 + p.header.stamp.nanosec == stamp_ns:
                    return p
            return None
        return self.wait_for(find, timeout_s)

    def decision_for(self, stamp_ns: int, timeout_s: float = 15.0) -> str | None:
        answered = self._first_decision([stamp_ns], timeout_s)
        return None if answered is None else answered[1]

    def send_nav(self, rtn: np.ndarray, attempts: int = 5, wait_s: float = 3.0,
                 first_wait_s: float = 12.0, **kwargs) -> tuple[int, str | None]:
        """Publish a nav fix until the node answers it; returns (stamp, decision).

        The first sample after an endpoint match can be lost while discovery completes on the
        other side, so an unanswered fix is sent again. An answer that is only late (a node
        still warming up on a loaded machine) must not be taken for a loss, or the node plans
        twice: the first fix gets `first_wait_s`, each resend `wait_s`, and an answer to any
        fix sent so far ends the wait (the stamp returned is the answered one).
        """
        sent: list[int] = []
        for attempt in range(attempts):
            stamp = time.time_ns()
            sent.append(stamp)
            self.nav_pub.publish(nav_msg(stamp, rtn, **kwargs))
            answered = self._first_decision(sent, first_wait_s if attempt == 0 else wait_s)
            if answered is not None:
                return answered
        return sent[-1], None

    def _first_decision(self, stamps: list[int], timeout_s: float) -> tuple[int, str] | None:
        """(stamp, decision) of the first of `stamps` the node has answered, waiting up to
        `timeout_s`."""
        wanted = {str(s): s for s in stamps}

        def find(_, diags):
            for _, values, name in diags:
                stamp = wanted.get(values.get("nav_stamp_ns", ""))
                if name == "art_guidance/nav" and stamp is not None:
                    return stamp, values.get("decision")
            return None
        return self.wait_for(find, timeout_s)

    def close(self, shutdown: bool = True) -> None:
        """Stop spinning and destroy the node; `shutdown`: also shut rclpy down (False while
        other clients of this process still spin)."""
        self.executor.shutdown()
        self._thread.join(timeout=5)
        self.node.destroy_node()
        if shutdown:
            rclpy.try_shutdown()
