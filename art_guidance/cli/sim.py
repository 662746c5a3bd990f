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
        "fault": json.dumps(args.fault or ""),
        "fault_node": str(int(args.fault_node)),
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
        "input; with --fault loss, 0 if the post-fault drift stayed outside the ellipsoid in "
        "force. More ROS parameters (rtn0, errors, mean_elements, warm_start, config_dir, "
        "max_steps, ...) after --ros-args (last).")
    from art_guidance.sim.closed_loop import PARAMETERS as P

    p.add_argument("--waypoint", default=P["waypoint"], help="terminal waypoint name")
    p.add_argument("--seed", type=int, default=P["seed"],
                   help="initial state (Table I ranges) and error samples")
    p.add_argument("--deterministic", action="store_true",
                   help="request deterministic passive safety (default: chance-constrained)")
    p.add_argument("--png", default=P["png_path"], help="plot path ('' = none)")
    p.add_argument("--summary-json", default=P["summary_path"],
                   help="summary JSON path ('' = none)")
    p.add_argument("--step-timeout", type=float, default=P["step_timeout_s"],
                   help="wall-clock wait for each decision/plan [s]")
    p.add_argument("--max-steps", type=int, default=P["max_steps"], help="nav fixes at most")
    p.add_argument("--miss-tolerance", type=float, default=P["miss_tolerance_m"],
                   help="largest final position error counted as reached [m]")
    add_fault_options(p)
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="everything after it goes to rclpy, e.g. --ros-args -p errors:=false")
    p.set_defaults(func=run)


def add_fault_options(p: argparse.ArgumentParser) -> None:
    """--fault and --fault-node (the simulator's `fault` and `fault_node` parameters)."""
    p.add_argument("--fault", choices=("loss", "missed"), default=None,
                   help="inject a thruster fault at node --fault-node: 'loss' (no burn from "
                   "that node on; the run stops and the truth drifts for one orbit, checked "
                   "against the ellipsoid in force) or 'missed' (that burn is not executed, "
                   "control resumes and the guidance replans); the summary's 'fault' object "
                   "gives min_margin_m, t_closest_s and entered")
    from art_guidance.sim.closed_loop import PARAMETERS

    p.add_argument("--fault-node", type=int, default=PARAMETERS["fault_node"], metavar="K",
                   help="burn opportunity the fault hits, counted from 0 along the flown "
                   "trajectory (default 1: right after the first burn)")
