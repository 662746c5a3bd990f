"""`art-guidance`: one command-line entry point with subcommands."""
from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.errors import GuidanceError, InputError
from art_guidance.files import write_json_atomic
from art_guidance.data.generate import add_generate_parser as _add_generate

Handler = Callable[[argparse.Namespace], int]


def _offline_demo(args: argparse.Namespace) -> int:
    """Plan the paper's nominal transfer: free drift, CVX, then chance-constrained SCVx*."""
    from art_guidance.config import ScenarioConfig
    from art_guidance.dynamics import Horizon, roe_from_rtn_linear, time_grid_s
    from art_guidance.planning import GuidancePipeline, PlanRequest

    scenario = ScenarioConfig.from_yaml(args.scenario)
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    roe0 = roe_from_rtn_linear(chief, scenario.rtn0_nominal)
    drift = horizon.to_rtn(horizon.propagate(roe0, np.zeros((horizon.n_nodes, 3))))
    print(f"free drift over {scenario.n_orbits} orbits ({horizon.n_nodes} nodes): range "
          f"{np.linalg.norm(drift[0, :3]):.0f} m -> {np.linalg.norm(drift[-1, :3]):.0f} m")
    request = PlanRequest(chief, roe0, np.asarray(scenario.waypoints_rtn[args.waypoint]),
                          chance_constrained=True, warm_start="cvx")
    result = GuidancePipeline(scenario).plan(request)
    rtn = result.rtn
    print(f"target {args.waypoint}: CVX lower bound {result.cvx.cost_mps:.4f} m/s; "
          f"chance-constrained SCP {result.status.name} in {result.scp.iterations} iterations, "
          f"{result.cost_mps:.4f} m/s, min passive-safety margin "
          f"{result.constraint_margin_m:.2f} m, {result.timings_ms['total']:.0f} ms")
    print(f"{'t [s]':>8} {'r_R [m]':>9} {'r_T [m]':>9} {'r_N [m]':>8} {'|dv| [mm/s]':>12}")
    dv_mm = 1e3 * np.linalg.norm(result.dv_rtn_mps, axis=1)
    for k in range(0, horizon.n_nodes, max(1, horizon.n_nodes // 10)):
        print(f"{horizon.epochs_s[k]:8.0f} {rtn[k, 0]:9.1f} {rtn[k, 1]:9.1f} {rtn[k, 2]:8.1f} "
              f"{dv_mm[k]:12.2f}")
    if args.json:
        write_json_atomic(args.json, result.to_json())
        print(f"plan written to {args.json}")
    return 0 if result.scp.feasible else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    """Closed-loop rendezvous: the guidance node and the simulator as two processes over DDS."""
    if args.offline:
        return _offline_demo(args)
    import os
    import signal
    import subprocess
    import time
    from pathlib import Path

    from art_guidance.ros.env import isolated_ros_env

    out = Path(args.out).resolve()
    run = out / time.strftime("run_%Y%m%dT%H%M%S")
    run.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, **isolated_ros_env(run / "ros",
                                              args.domain_id or 30 + os.getpid() % 60))
    bag = run / "mcap"
    node_cmd = [sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                "-p", "stamp_check:=order", "-p", f"record_dir:={bag}",
                "-p", f"default_waypoint:={args.waypoint}"]
    sim_cmd = [sys.executable, "-m", "art_guidance.ros.sim_node", "--ros-args",
               "-p", f"waypoint:={args.waypoint}", "-p", f"seed:={args.seed}",
               "-p", f"png_path:={run / 'rendezvous.png'}",
               "-p", f"summary_path:={run / 'summary.json'}"]
    print(f"guidance node and simulator on ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}; logs in {run}")
    with open(run / "node.log", "w") as node_log:
        node = subprocess.Popen(node_cmd, env=env, stdout=node_log, stderr=subprocess.STDOUT)
        try:
            sim = subprocess.run(sim_cmd, env=env, stdout=subprocess.PIPE, text=True,
                                 timeout=args.timeout)
        finally:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(timeout=30)
            except subprocess.TimeoutExpired:
                node.kill()
    summary = _last_json_line(sim.stdout)
    for key, value in summary.items():
        shown = f"{value:.4g}" if isinstance(value, float) else value
        print(f"  {key}: {shown}")
    print(f"MCAP log (rosbag2 bag): {bag}\nplot: {run / 'rendezvous.png'}\n"
          f"node log: {run / 'node.log'}\nreplay it: art-guidance replay {bag}")
    return sim.returncode


def _last_json_line(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        try:
            data = json.loads(line)
        except ValueError:
            continue
        if isinstance(data, dict):
            return data
    return {"error": "the simulator printed no summary", "output": text[-2000:]}


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="closed-loop rendezvous: node + simulator over DDS",
                       description=_cmd_demo.__doc__ + " Exit 0 when the waypoint is reached.")
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.add_argument("--waypoint", default="plus_vbar", help="terminal waypoint name")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (initial state, errors)")
    p.add_argument("--out", default="out/demo", help="where the run folder goes")
    p.add_argument("--timeout", type=float, default=900.0, help="wall-clock limit [s]")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: "
                   "derived from the process id)")
    p.add_argument("--offline", action="store_true",
                   help="only plan the nominal transfer in-process (no ROS)")
    p.add_argument("--json", default=None, help="with --offline: also write the plan as JSON")
    p.set_defaults(func=_cmd_demo)


def _cmd_plan(args: argparse.Namespace) -> int:
    """Plan one randomised transfer of the paper scenario and write it as JSON."""
    from art_guidance.config import ScenarioConfig
    from art_guidance.data.stages import sample_scenario
    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.planning import GuidancePipeline, PlanRequest

    scenario = ScenarioConfig.from_yaml(args.scenario)
    sample = sample_scenario(scenario, args.seed)
    target = sample.target_rtn
    if args.waypoint:
        if args.waypoint not in scenario.waypoints_rtn:
            raise InputError("waypoint", f"unknown; choose from {sorted(scenario.waypoints_rtn)}",
                             args.waypoint)
        target = np.asarray(scenario.waypoints_rtn[args.waypoint])
    chief = np.array(scenario.chief_oe)
    request = PlanRequest(chief, roe_from_rtn_linear(chief, sample.rtn0), target,
                          chance_constrained=not args.deterministic, warm_start=args.warm_start)
    result = GuidancePipeline(scenario).plan(request)
    data = result.to_json()
    data.update(seed=args.seed, waypoint=args.waypoint or sample.waypoint,
                mode="deterministic" if args.deterministic else "chance")
    write_json_atomic(args.json, data)
    print(f"{result.status.name}: cost {result.cost_mps:.4f} m/s (CVX {result.cvx.cost_mps:.4f}),"
          f" {result.scp.iterations} SCP iterations, margin {result.constraint_margin_m:.2f} m, "
          f"{result.timings_ms['total']:.0f} ms -> {args.json}")
    return 0 if result.scp.feasible else 1


def _add_plan(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="plan one transfer and write JSON",
                       description=_cmd_plan.__doc__ + " Exit 0 feasible, 1 infeasible, "
                       "2 bad input.")
    p.add_argument("--seed", type=int, required=True, help="scenario seed (initial state and "
                   "waypoint drawn from the paper's Table I ranges)")
    p.add_argument("--deterministic", action="store_true",
                   help="deterministic passive safety (default: chance-constrained)")
    p.add_argument("--warm-start", choices=["auto", "cvx", "art"], default="auto",
                   help="warm start for SCP (auto: ART if a model is loaded and accepted)")
    p.add_argument("--waypoint", default=None, help="override the sampled waypoint")
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.add_argument("--json", required=True, help="output path of the plan JSON")
    p.set_defaults(func=_cmd_plan)


def _cmd_bench(args: argparse.Namespace) -> int:
    """Run benchmarks from benchmarks/ and print medians and ratios against references."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "benchmarks"
    names = sorted(p.stem[len("bench_"):] for p in root.glob("bench_*.py"))
    if not names:
        raise InputError("bench", "benchmarks/ not found (run from a source checkout)")
    chosen = names if args.name == "all" else [args.name]
    if str(root) not in sys.path:  # benchmarks share modules (e.g. the cvxpy reference)
        sys.path.insert(0, str(root))
    report = {}
    for name in chosen:
        path = root / f"bench_{name}.py"
        if not path.is_file():
            raise InputError("bench", f"unknown benchmark; choose from {names + ['all']}", name)
        spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        kwargs = {"repeats": args.repeats} if args.repeats else {}
        print(f"== {name}")
        report[name] = module.run(**kwargs)
        for key, value in report[name].items():
            print(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")
    if args.json:
        write_json_atomic(args.json, report)
    return 0


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run benchmarks", description=_cmd_bench.__doc__)
    p.add_argument("name", nargs="?", default="all", help="benchmark name or 'all'")
    p.add_argument("--repeats", type=int, default=None, help="samples per benchmark")
    p.add_argument("--json", default=None, help="also write the numbers as JSON")
    p.set_defaults(func=_cmd_bench)


def _cmd_node(args: argparse.Namespace) -> int:
    """Run the ROS 2 guidance node (same as `ros2 run art_guidance guidance_node`)."""
    from art_guidance.ros.guidance_node import main as node_main

    return node_main(["guidance_node", *args.ros_args])


def _add_node(sub: argparse._SubParsersAction) -> None:
    from art_guidance.ros.guidance_node import PARAMETERS

    params = ", ".join(f"{k} ({v!r})" for k, v in PARAMETERS.items())
    p = sub.add_parser(
        "node", help="run the ROS 2 guidance node",
        description=f"{_cmd_node.__doc__} Parameters (default): {params}. Example: "
        "art-guidance node --ros-args -p stamp_check:=order")
    p.add_argument("ros_args", nargs=argparse.REMAINDER,
                   help="passed to rclpy, e.g. --ros-args -p name:=value")
    p.set_defaults(func=_cmd_node)


def _cmd_replay(args: argparse.Namespace) -> int:
    """Re-solve every request recorded in an MCAP log (file or bag folder) and compare plans."""
    from art_guidance.record.replay import replay

    report = replay(args.log)
    if args.json:
        write_json_atomic(args.json, report)
    for row in report["per_solve"]:
        verdict = {True: "match", False: "MISMATCH", None: "skipped"}[row["match"]]
        extra = (f"cost diff {row['cost_rel_diff']:.1e}, dv diff {row['dv_max_abs_diff_mps']:.1e}"
                 if row["match"] is not None else row.get("reason", ""))
        print(f"{row['plan_id']:>12} {row['status']:<15} {verdict:<8} {extra}")
    print(f"{report['matched']}/{report['compared']} matched "
          f"({report['solves']} solves, {len(report['truncated'])} truncated file(s))")
    return 0 if report["mismatched"] == 0 else 1


def _add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="re-solve a recorded MCAP log and compare",
                       description=_cmd_replay.__doc__ + " Exit 0 when every compared solve "
                       "matches (cost to 1e-6 relative, delta-v to 1e-5 m/s), 1 otherwise.")
    p.add_argument("log", help="an .mcap file or a bag folder of them")
    p.add_argument("--json", default=None, help="also write the report as JSON")
    p.set_defaults(func=_cmd_replay)


def _add_sim(sub: argparse._SubParsersAction) -> None:
    from art_guidance.ros.sim_node import add_sim_parser

    add_sim_parser(sub)


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="art-guidance",
        description="Onboard rendezvous guidance: ART warm start, post hoc check, robust SCP.",
    )
    parser.add_argument("--version", action="version", version=f"art-guidance {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_demo, _add_plan, _add_bench, _add_node, _add_replay, _add_generate, _add_sim]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (2 for bad input, 1 for failures)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except GuidanceError as exc:
        print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0
