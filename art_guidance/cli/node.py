"""`art-guidance node`: the ROS 2 guidance node."""
from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    """Run the ROS 2 guidance node (same as `ros2 run art_guidance guidance_node`)."""
    from art_guidance.ros.guidance_node import main as node_main

    return node_main(["guidance_node", *args.ros_args])


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    from art_guidance.config import node_parameter_defaults

    params = ", ".join(f"{k} ({v!r})" for k, v in node_parameter_defaults().items())
    p = sub.add_parser(
        "node", help="run the ROS 2 guidance node",
        description=f"{run.__doc__} Parameters (default): {params}. Example: "
        "art-guidance node --ros-args -p stamp_check:=order")
    p.add_argument("ros_args", nargs=argparse.REMAINDER,
                   help="passed to rclpy, e.g. --ros-args -p name:=value")
    p.set_defaults(func=run)
