"""`art-guidance demo`: the closed-loop rendezvous (node + simulator over DDS, or offline)."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys

import numpy as np

from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic


def _offline_demo(args: argparse.Namespace) -> int:
    """Plan the paper's nominal transfer: free drift, CVX, then chance-constrained SCVx*."""
    from art_guidance.config import GuidanceConfig, ScenarioConfig
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
    result = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario)).plan(request)
    rtn = result.rtn
    print(f"target {args.waypoint}: CVX lower bound {result.cvx.cost_mps:.4f} m/s; "
          f"chance-constrained SCP {result.status.name} in {result.scp.iterations} iterations, "
          f"{result.cost_mps:.4f} m/s, min passive-safety margin "
          f"{result.constraint_margin_m:.2f} m, {result.timings.total:.0f} ms")
    print(f"{'t [s]':>8} {'r_R [m]':>9} {'r_T [m]':>9} {'r_N [m]':>8} {'|dv| [mm/s]':>12}")
    dv_mm = 1e3 * np.linalg.norm(result.dv_rtn_mps, axis=1)
    for k in range(0, horizon.n_nodes, max(1, horizon.n_nodes // 10)):
        print(f"{horizon.epochs_s[k]:8.0f} {rtn[k, 0]:9.1f} {rtn[k, 1]:9.1f} {rtn[k, 2]:8.1f} "
              f"{dv_mm[k]:12.2f}")
    if args.json:
        write_json_atomic(args.json, result.to_json())
        print(f"plan written to {args.json}")
    return 0 if result.scp.feasible else 1


def run(args: argparse.Namespace) -> int:
    """Closed-loop rendezvous: the guidance node (shipped ART model, warm start auto) and the
    simulator as two processes over DDS; then the same seed flown in-process with CVX warm
    starts only, to report how many replans accepted ART and the delta-v difference."""
    if args.offline:
        if args.fault:
            raise InputError("--fault", "needs the closed loop; drop --offline")
        return _offline_demo(args)
    import os
    import signal
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
    if args.replan_window_nodes is not None:  # else the node's default (guidance_node.yaml)
        node_cmd += ["-p", f"replan_window_nodes:={int(args.replan_window_nodes)}"]
    if args.terminal_target is not None:
        node_cmd += ["-p", f"terminal_target:={args.terminal_target}"]
    if args.replan_warm_start is not None:  # else planning.yaml's
        node_cmd += ["-p", f"replan_warm_start:={args.replan_warm_start}"]
    sim_cmd = [sys.executable, "-m", "art_guidance.ros.sim_node", "--ros-args",
               "-p", f"waypoint:={args.waypoint}", "-p", f"seed:={args.seed}",
               "-p", f"png_path:={run / 'rendezvous.png'}",
               "-p", f"summary_path:={run / 'summary.json'}"]
    if args.fault:
        sim_cmd += ["-p", f"fault:={args.fault}", "-p", f"fault_node:={args.fault_node}"]
    print(f"guidance node and simulator on ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}; logs in {run}")
    with open(run / "node.log", "w") as node_log, open(run / "sim.out", "w+") as sim_out:
        node = subprocess.Popen(node_cmd, env=env, stdout=node_log, stderr=subprocess.STDOUT)
        try:
            sim = subprocess.Popen(sim_cmd, env=env, stdout=sim_out, text=True)
            died = _wait_for_sim(sim, node, args.timeout)
        except subprocess.TimeoutExpired:
            print(f"the flight ran past --timeout {args.timeout:g} s and was stopped; logs in "
                  f"{run}", file=sys.stderr)
            return 1
        finally:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(timeout=30)
            except subprocess.TimeoutExpired:
                node.kill()
        sim_out.seek(0)
        sim_text = sim_out.read()
    if died is not None:
        tail = "".join((run / "node.log").read_text(errors="replace").splitlines(True)[-15:])
        print(f"the guidance node exited with code {died} while the simulator was flying; the "
              f"flight was stopped. Last lines of {run / 'node.log'}:\n{tail}", file=sys.stderr)
        return 1
    summary = _last_json_line(sim_text)
    if bag.is_dir() and "total_dv_mps" in summary and not args.no_compare:
        summary.update(_warm_start_comparison(bag, args, summary["total_dv_mps"]))
        write_json_atomic(run / "demo_summary.json", summary)
    for key, value in summary.items():
        shown = f"{value:.4g}" if isinstance(value, float) else value
        print(f"  {key}: {shown}")
    print(f"MCAP log (rosbag2 bag): {bag}\nplot: {run / 'rendezvous.png'}\n"
          f"node log: {run / 'node.log'}\nreplay it: art-guidance replay {bag}")
    return sim.returncode


def _wait_for_sim(sim: subprocess.Popen, node: subprocess.Popen,
                  timeout_s: float) -> int | None:
    """Wait for the simulator to end; None, or the node's exit code if the node ended first
    (the simulator is then stopped: without guidance it would only wait for plans).

    Raises:
        subprocess.TimeoutExpired: the simulator ran past `timeout_s` (it is stopped).
    """
    import time

    deadline = time.monotonic() + timeout_s
    while sim.poll() is None:
        code = node.poll()
        if code is not None or time.monotonic() > deadline:
            sim.terminate()
            try:
                sim.wait(timeout=10)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
            if code is not None:
                return code
            raise subprocess.TimeoutExpired(sim.args, timeout_s)
        time.sleep(0.2)
    return None


def _warm_start_comparison(bag: object, args: argparse.Namespace, total_dv_mps: float) -> dict:
    """How many replans of the recorded run accepted ART, and the delta-v of the same seed flown
    with CVX warm starts only (in-process, no DDS: same simulator, policy and pipeline)."""
    import logging

    from art_guidance.planning import GuidancePipeline
    from art_guidance.record.replay import read_log
    from art_guidance.record.recorder import SOLVE_RECORD_TYPE
    from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
    from art_guidance.sim.inprocess import InProcessGuidance

    log = read_log(bag)
    records = log.of_type(SOLVE_RECORD_TYPE)
    out = {"model_sha256": log.metadata.get("model_checksum", "none"),
           "n_solves": len(records),
           "n_art_proposed": sum(bool(len(r.warm_start_art_dv_rtn_mps)) for r in records),
           "n_art_accepted": sum(r.warm_start == "art" for r in records)}
    print("flying the same seed with CVX warm starts only (in-process) for comparison ...")
    params = dict(PARAMETERS, rtn0=None, waypoint=args.waypoint, seed=args.seed, warm_start="cvx",
                  png_path="", summary_path="", fault=args.fault or "",
                  fault_node=args.fault_node)
    loop = ClosedLoop(InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS), params,
                      logging.getLogger("art_guidance.demo"), settle_s=0.0)
    cvx_summary, _ = loop.finish(loop.run(), 0.0)
    if "fault" in cvx_summary:
        out["cvx_only_fault"] = cvx_summary["fault"]
    out.update(cvx_only_total_dv_mps=cvx_summary["total_dv_mps"],
               cvx_only_miss_m=cvx_summary["miss_m"],
               dv_saved_vs_cvx_only_mps=cvx_summary["total_dv_mps"] - total_dv_mps)
    return out


def _last_json_line(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        try:
            data = json.loads(line)
        except ValueError:
            continue
        if isinstance(data, dict):
            return data
    return {"error": "the simulator printed no summary", "output": text[-2000:]}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    from art_guidance.cli.sim import add_fault_options

    p = sub.add_parser("demo", help="closed-loop rendezvous: node + simulator over DDS",
                       description=run.__doc__ + " Exit 0 when the waypoint is reached (with "
                       "--fault loss: when the post-fault drift stays outside the ellipsoid in "
                       "force). Example: art-guidance demo --fault loss --fault-node 50")
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.add_argument("--waypoint", default="plus_vbar", help="terminal waypoint name")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (initial state, errors)")
    p.add_argument("--replan-window-nodes", type=int, default=None, metavar="H",
                   help="the node's replan_window_nodes: each replan optimises H nodes ahead "
                   "to a terminal target (0 = the whole remainder; default: the node's)")
    p.add_argument("--replan-warm-start", choices=("carry", "fresh"), default=None,
                   help="the node's replan_warm_start: a replan with a plan in force starts "
                   "from it (carry) or solves afresh (fresh; default: planning.yaml's)")
    p.add_argument("--terminal-target", choices=("art", "cvx", "carry"), default=None,
                   help="the node's terminal_target: where a window ends (default: the "
                   "node's)")
    p.add_argument("--out", default="out/demo", help="where the run folder goes")
    p.add_argument("--timeout", type=float, default=900.0, help="wall-clock limit [s]")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: "
                   "derived from the process id)")
    p.add_argument("--offline", action="store_true",
                   help="only plan the nominal transfer in-process (no ROS)")
    p.add_argument("--json", default=None, help="with --offline: also write the plan as JSON")
    p.add_argument("--no-compare", action="store_true", help="skip the comparison run of the "
                   "same seed with CVX warm starts only")
    add_fault_options(p)
    p.set_defaults(func=run)
