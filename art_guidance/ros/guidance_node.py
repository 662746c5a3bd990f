"""ROS 2 guidance node: `ros2 run art_guidance guidance_node` (or `art-guidance node`).

Subscribes `nav/relative_state` and `guidance/replan_request`; publishes
`guidance/maneuver_plan` and `/diagnostics`. Callbacks only validate and decide; all solving
runs in one worker thread that always takes the newest job (a queued job is superseded, never
queued without bound). Every nav message gets a `/diagnostics` status named "art_guidance/nav"
with `nav_stamp_ns` and `decision` in {replanning, on_plan, rejected}; "replanning" is followed
by a ManeuverPlan whose header.stamp is that nav stamp. That status, and "art_guidance/stats"
every STATS_PERIOD_S while planning, carry the counts since configure (`fix_counts`): a client
tells a fix that never reached the node (dropped by DDS) from one not answered yet.
"""
from __future__ import annotations

import signal
import sys
import threading
from typing import Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node

from art_guidance.errors import GuidanceError
from art_guidance.ros.managed_node import ManagedGuidanceNode
from art_guidance.ros.node_base import (  # noqa: F401 (the node's names, importable from here)
    PARAMETERS, STATS_PERIOD_S, GuidanceNodeBase, solver_error_text,
)

SPIN_PERIOD_S = 0.1  # the executor wakes this often to notice SIGINT/SIGTERM [s]


class GuidanceNode(GuidanceNodeBase, Node):
    """The guidance node: configured and planning as soon as it is constructed."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self._configure()
        self._create_publishers(self.create_publisher)
        self._create_subscriptions()
        self._start_worker()


def main(argv: Sequence[str] | None = None, managed: bool = False) -> int:
    """Run the node until SIGINT/SIGTERM.

    The signals only set a flag: the executor stops, the worker finishes its solve (recorded
    and published), the recorder closes, and only then is the ROS context shut down, so
    nothing logs or publishes into a dead context.

    Args:
        argv: full argument vector (program name first); None uses sys.argv.
        managed: run the lifecycle node (starts unconfigured) instead of the plain one.
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rclpy.init(args=list(argv) if argv is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = SingleThreadedExecutor()
    try:
        node = ManagedGuidanceNode() if managed else GuidanceNode()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            try:
                executor.spin_once(timeout_sec=SPIN_PERIOD_S)
            except ExternalShutdownException:
                raise
            except Exception as exc:  # every callback is a boundary; should one leak, the
                # node logs it and keeps serving instead of dying with the plan in force
                node.get_logger().error(f"a callback raised {type(exc).__name__}: {exc}; "
                                        "the node keeps serving", throttle_duration_sec=5.0)
    except ExternalShutdownException:
        pass
    except (GuidanceError, ValueError) as exc:
        print(f"guidance_node: {exc}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.shutdown_worker()
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main_managed(argv: Sequence[str] | None = None) -> int:
    """`ros2 run art_guidance guidance_managed_node`: the lifecycle guidance node."""
    return main(argv, managed=True)


if __name__ == "__main__":
    sys.exit(main(managed="--managed" in sys.argv))
