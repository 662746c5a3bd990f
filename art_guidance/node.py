"""ROS 2 guidance node entry point (`ros2 run art_guidance guidance_node`).

The rclpy node (topics `nav/relative_state`, `guidance/replan_request`,
`guidance/maneuver_plan`, `/diagnostics`) is not implemented yet. Until it is, the entry point
exists so the package installs as ROS 2 expects, and it refuses to start with a clear message
instead of pretending to guide.
"""
from __future__ import annotations

import sys
from typing import Sequence

NOT_AVAILABLE = ("guidance_node: the ROS 2 guidance node is not implemented in this version; "
                 "plan offline with `art-guidance plan --help`.")


def main(argv: Sequence[str] | None = None) -> int:
    """Print why the node cannot start and exit with status 2."""
    print(NOT_AVAILABLE, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
