"""Benchmark: nav message in -> plan out latency of the guidance node over real DDS.

The node runs in its own process (as `ros2 run` would start it) with every nav message forced to
replan; the client publishes a nav state, waits for the plan with that stamp, and repeats. The
reference is the same `GuidancePipeline.plan` called in-process on the same states, so the
difference is the node and middleware overhead.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.ros.env import isolated_ros_env

REPO = Path(__file__).resolve().parents[1]


def run(repeats: int = 30) -> dict:
    """Latency over `repeats` plans; returns p50/p95 [ms] and the in-process reference."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_bench_"),
                           150 + os.getpid() % 50)
    os.environ.update(ros)  # this process is the client
    env = dict(os.environ)
    sys.path.insert(0, str(REPO / "test"))  # the tests' DDS client (helpers.ros_client)
    from helpers.ros_client import Client, nav_msg

    proc = subprocess.Popen([sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "replan_sigma_threshold:=1e-9"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    client = Client("art_guidance_bench_client")
    try:
        if not client.wait_matched(30.0):
            raise RuntimeError("guidance node did not come up")
        scenario = ScenarioConfig.from_yaml()
        rng = np.random.default_rng(11)
        half = np.asarray(scenario.rtn0_half_width)
        states = [np.asarray(scenario.rtn0_nominal) + rng.uniform(-1, 1, 6) * half
                  for _ in range(repeats + 1)]
        latency = []
        for k, rtn in enumerate(tqdm(states, desc="bench node", unit="plan")):
            if k == 0:  # the first fix may be lost while discovery completes
                stamp, _ = client.send_nav(rtn)
                t0 = time.perf_counter()
            else:
                stamp = time.time_ns()
                t0 = time.perf_counter()
                client.nav_pub.publish(nav_msg(stamp, rtn))
            if client.plan_for(stamp, timeout_s=60.0) is None:
                raise RuntimeError(f"no plan for nav {k}")
            if k > 0:  # the first includes the per-horizon set-up of a cold process
                latency.append(1e3 * (time.perf_counter() - t0))
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario))
    chief = np.array(scenario.chief_oe)
    target = np.asarray(scenario.waypoints_rtn["plus_vbar"])
    ref = []
    for rtn in states[1:]:
        t0 = time.perf_counter()
        pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, rtn), target))
        ref.append(1e3 * (time.perf_counter() - t0))
    p50, ref50 = float(np.percentile(latency, 50)), float(np.percentile(ref, 50))
    return {"plans": len(latency), "latency_p50_ms": p50,
            "latency_p95_ms": float(np.percentile(latency, 95)),
            "in_process_plan_p50_ms": ref50,
            "in_process_plan_p95_ms": float(np.percentile(ref, 95)),
            "node_overhead_p50_ms": p50 - ref50, "latency_over_in_process": p50 / ref50}


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
