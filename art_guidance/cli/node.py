"""`art-guidance node`: the ROS 2 guidance node."""
from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    """Run the ROS 2 guidance node (same as `ros2 run art_guidance guidance_node`)."""
    from art_guidance.ros.guidance_node import main as node_main

    ros = ["--ros-args", *args.ros_args] if args.ros_args is not None else []
    return node_main(["guidance_node", *args.rest, *ros], managed=args.managed)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand; --help lists every parameter with its meaning and default."""
    from art_guidance.config import node_parameter_defaults
    from art_guidance.ros.parameters import SPECS

    defaults = node_parameter_defaults()
    lines = []
    for name, spec in SPECS.items():
        default = repr(defaults[name]) if name in defaults else "planning.yaml"
        extra = f"; {spec.constraints}" if spec.constraints else ""
        mode = "dynamic" if spec.dynamic else "read-only"
        lines.append(f"  {name} (default {default}, {mode}{extra}): {spec.description}")
    p = sub.add_parser(
        "node", help="run the ROS 2 guidance node",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=f"{run.__doc__}\n\nParameters (-p name:=value after --ros-args):\n"
        + "\n".join(lines) + "\n\nExample: art-guidance node --ros-args -p stamp_check:=order")
    p.add_argument("--managed", action="store_true",
                   help="run the lifecycle node (ros2 run art_guidance guidance_managed_node): "
                   "it starts unconfigured and plans only once configured and activated")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=None,
                   help="everything after it goes to rclpy, e.g. --ros-args -p name:=value")
    p.add_argument("rest", nargs="*", help="after `--`: passed to rclpy as they are")
    p.set_defaults(func=run)
