"""`art-guidance sim`: the closed-loop simulator against a running guidance node."""
from __future__ import annotations

import argparse
import json


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


def run(args: argparse.Namespace) -> int:
    """Closed-loop rendezvous simulation against a running guidance node (over ROS 2)."""
    from art_guidance.ros.sim_node import main

    return main(sim_argv(args))


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `art-guidance sim` (options map to the simulator's ROS parameters)."""
    p = sub.add_parser(
        "sim", help="closed-loop simulation against the guidance node",
        description=run.__doc__ + " Start the guidance node first with "
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
    p.set_defaults(func=run)
