"""What the guidance node publishes: plans, `/diagnostics` and the visualisation.

`NodeOutputs` holds the node's publishers (made at start-up or at the lifecycle's configure,
destroyed at its cleanup) and the helpers that fill them: the diagnostic statuses, the plan's
visualisation messages and the navigated deputy at most every DEPUTY_VIZ_PERIOD_S of stamp
time. A picture never stops a plan: a visualisation that fails is logged and skipped.
"""
from __future__ import annotations

import time
from typing import Any, Callable

from art_guidance_msgs.msg import ManeuverPlan
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from art_guidance import topics
from art_guidance.config import ScenarioConfig
from art_guidance.plan_view import nav_position, plan_view
from art_guidance.planning import NavState, PlanResult
from art_guidance.ros import visualization as viz
from art_guidance.ros.adapters import diagnostics_msg
from art_guidance.safety import PassiveSafety

OK, WARN, ERROR = 0, 1, 2
DEPUTY_VIZ_PERIOD_S = 0.5  # smallest stamp-time spacing of the deputy's visualisation [s]
VIZ_TYPES = {topics.PLAN_PATH: Path, topics.PLAN_MARKERS: MarkerArray,
             topics.DEPUTY_MARKERS: MarkerArray, topics.DEPUTY_POSE: PoseWithCovarianceStamped}
VIZ_TYPE_NAMES = {topic: f"{t.__module__.split('.')[0]}/msg/{t.__name__}"
                  for topic, t in VIZ_TYPES.items()}


class NodeOutputs:
    """The guidance node's publishers and what it publishes on them.

    Args:
        create: the node's `create_publisher` (or `create_lifecycle_publisher`).
        visualization: publish the visualisation topics (guidance/viz/*) too.
    """

    def __init__(self, create: Callable, visualization: bool) -> None:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.plan_pub = create(ManeuverPlan, topics.MANEUVER_PLAN, qos)
        self.diag_pub = create(DiagnosticArray, topics.DIAGNOSTICS, qos)
        self.viz_pubs: dict[str, Any] = {}
        self._deputy_viz_ns: int | None = None  # stamp of the last deputy drawn
        if visualization:
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.viz_pubs = {topic: create(msg_type, topic, latched)
                             for topic, msg_type in VIZ_TYPES.items()}

    def publishers(self) -> list:
        """Every publisher (to destroy them)."""
        return [self.plan_pub, self.diag_pub, *self.viz_pubs.values()]

    def diag(self, name: str, level: int, message: str, values: dict) -> None:
        """One `/diagnostics` status."""
        self.diag_pub.publish(diagnostics_msg(time.time_ns(), name, level, message, values))

    def nav_diag(self, stamp_ns: int, level: int, decision: str, extra: dict) -> None:
        """The "art_guidance/nav" status of a fix: its stamp and the decision."""
        values = {"nav_stamp_ns": str(stamp_ns), "decision": decision, **extra}
        self.diag("art_guidance/nav", level, decision, values)

    def publish_views(self, views: list[tuple[str, object]]) -> None:
        """A plan's visualisation messages (`plan_views`)."""
        for topic, msg in views:
            self.viz_pubs[topic].publish(msg)

    def plan_views(self, nav: NavState, result: PlanResult, plan_id: str,
                   safety: Callable[[], PassiveSafety], scenario: ScenarioConfig,
                   log: Any) -> list[tuple[str, object]]:
        """The visualisation messages of a plan put in force, [(topic, msg)] (none when off;
        `safety` gives the plan's passive-safety model; a failure is logged on `log` and never
        stops the plan)."""
        if not self.viz_pubs:
            return []
        try:
            view = plan_view(result, safety(), scenario)
            t0 = nav.stamp_ns
            markers, pose = _deputy_view(nav)
            text = viz.status_line(plan_id, result)
            return [(topics.PLAN_PATH, viz.path_msg(view, t0)),
                    (topics.PLAN_MARKERS, viz.plan_markers(view, t0, text)),
                    (topics.DEPUTY_MARKERS, markers), (topics.DEPUTY_POSE, pose)]
        except Exception as exc:  # a picture never takes the plan down
            log.warning(f"visualisation of {plan_id} failed: {type(exc).__name__}: {exc}")
            return []

    def publish_deputy(self, nav: NavState, log: Any) -> None:
        """The navigated deputy on guidance/viz/deputy*: accepted fixes at least
        DEPUTY_VIZ_PERIOD_S apart in stamp time (a 100 Hz burst costs the callbacks nothing)."""
        if not self.viz_pubs:
            return
        last = self._deputy_viz_ns
        if last is not None and 0 <= nav.stamp_ns - last < DEPUTY_VIZ_PERIOD_S * 1e9:
            return
        self._deputy_viz_ns = nav.stamp_ns
        try:
            markers, pose = _deputy_view(nav)
        except Exception as exc:  # never die on a message
            log.warning(f"deputy visualisation failed: {exc}")
            return
        self.viz_pubs[topics.DEPUTY_MARKERS].publish(markers)
        self.viz_pubs[topics.DEPUTY_POSE].publish(pose)


def _deputy_view(nav: NavState) -> tuple:
    position, cov = nav_position(nav.chief_oe, nav.roe_m, nav.cov_m2)
    return viz.deputy_msgs(position, cov, nav.stamp_ns)
