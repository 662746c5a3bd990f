"""Benchmark: nav message in -> plan out latency of the guidance node over real DDS.

The node runs in its own process (as `ros2 run` would start it) with every nav message forced to
replan; the client publishes a nav state, waits for the plan with that stamp, and repeats. Three
nodes are up at once, each in its own namespace: with the learned warm start (`warm_start
auto`, the shipped model), CVX only, and `auto` with the proposal made in a worker process
(`propose_concurrently`); each state goes to the three in turn (the order rotating), so the
ratios compare plans made within a second of each other.
The reference is the same `GuidancePipeline.plan` called in-process on the same states, so the
difference is the node and middleware overhead; its timings give the split per stage (CVX,
ART rollout + post hoc check, SCP).
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
from art_guidance.planning import GuidancePipeline, PlanRequest, WarmStartSource
from art_guidance.ros.env import isolated_ros_env

REPO = Path(__file__).resolve().parents[1]


def _states(repeats: int) -> list[np.ndarray]:
    scenario = ScenarioConfig.from_yaml()
    rng = np.random.default_rng(11)
    half = np.asarray(scenario.rtn0_half_width)
    return [np.asarray(scenario.rtn0_nominal) + rng.uniform(-1, 1, 6) * half
            for _ in range(repeats + 1)]


CONFIGS = (("auto", False), ("cvx", False), ("auto", True))  # (warm_start, worker)


def _label(warm_start: str, concurrent: bool) -> str:
    return f"{warm_start}_concurrent" if concurrent else warm_start


def _start_node(warm_start: str, concurrent: bool) -> subprocess.Popen:
    """A guidance node process in its own namespace (`/bench_<label>`), every fix replanned."""
    return subprocess.Popen(
        [sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
         "-r", f"__ns:=/bench_{_label(warm_start, concurrent)}",
         "-p", "replan_sigma_threshold:=1e-9", "-p", "record:=false",
         "-p", f"warm_start:={warm_start}",
         "-p", f"propose_concurrently:={str(concurrent).lower()}"],
        env=dict(os.environ), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _node_latencies(states: list[np.ndarray], client_cls, nav_msg) -> dict[str, list[float]]:
    """Nav -> plan latency [ms] of one node process per configuration of CONFIGS, all up at
    once and asked in turn, state by state (the order rotating), so that a machine whose
    speed drifts during the run slows every configuration alike; the first plan of each is
    excluded (it includes the per-horizon set-up of a cold process)."""
    procs = [_start_node(ws, conc) for ws, conc in CONFIGS]
    clients = [client_cls(f"art_guidance_bench_client_{_label(ws, conc)}",
                          namespace=f"/bench_{_label(ws, conc)}") for ws, conc in CONFIGS]
    latency: dict[str, list[float]] = {_label(ws, conc): [] for ws, conc in CONFIGS}
    try:
        for client in clients:
            if not client.wait_matched(60.0):
                raise RuntimeError("a guidance node did not come up")
        for k, rtn in enumerate(tqdm(states, desc="bench node", unit="state")):
            for j in range(len(CONFIGS)):
                i = (j + k) % len(CONFIGS)
                client = clients[i]
                if k == 0:  # the first fix may be lost while discovery completes
                    stamp, _ = client.send_nav(rtn)
                else:
                    stamp = time.time_ns()
                    t0 = time.perf_counter()
                    client.nav_pub.publish(nav_msg(stamp, rtn))
                if client.plan_for(stamp, timeout_s=60.0) is None:
                    raise RuntimeError(f"no plan for nav {k} ({_label(*CONFIGS[i])})")
                if k > 0:
                    latency[_label(*CONFIGS[i])].append(1e3 * (time.perf_counter() - t0))
    finally:
        for i, client in enumerate(clients):
            client.close(shutdown=i == len(clients) - 1)
        for proc in procs:
            proc.send_signal(signal.SIGINT)
        for proc in procs:
            proc.wait(timeout=30)
    return latency


def run(repeats: int = 30) -> dict:
    """Latency over `repeats` plans with the learned warm start (auto, shipped model) and with
    CVX only; p50/p95 [ms], the in-process reference and the split per stage."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_bench_"),
                           150 + os.getpid() % 50)
    os.environ.update(ros)  # this process is the client
    sys.path.insert(0, str(REPO / "test"))  # the tests' DDS client (helpers.ros_client)
    from helpers.ros_client import Client, nav_msg

    from art_guidance.art.provider import ArtWarmStart

    states = _states(repeats)
    out: dict = {"plans": repeats}
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    target = np.asarray(scenario.waypoints_rtn["plus_vbar"])
    provider = ArtWarmStart.load()
    latencies = _node_latencies(states, Client, nav_msg)
    for warm_start in ("auto", "cvx"):
        latency = latencies[warm_start]
        pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario),
                                    provider=provider if warm_start == "auto" else None)
        stages: dict[str, list[float]] = {k: [] for k in ("cvx", "art", "scp", "total")}
        accepted = 0
        for rtn in states[1:]:
            res = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, rtn), target,
                                            warm_start=warm_start))
            accepted += res.warm_start is WarmStartSource.ART
            for key in stages:
                stages[key].append(res.timings_ms[key])
        p50 = float(np.percentile(latency, 50))
        ref50 = float(np.percentile(stages["total"], 50))
        out.update({f"{warm_start}_latency_p50_ms": p50,
                    f"{warm_start}_latency_p95_ms": float(np.percentile(latency, 95)),
                    f"{warm_start}_in_process_plan_p50_ms": ref50,
                    f"{warm_start}_node_overhead_p50_ms": p50 - ref50,
                    **{f"{warm_start}_{k}_p50_ms": float(np.percentile(v, 50))
                       for k, v in stages.items() if k != "total"}})
        if warm_start == "auto":
            out["auto_art_accepted"] = f"{accepted}/{repeats}"
    out["auto_over_cvx_latency_p50"] = out["auto_latency_p50_ms"] / out["cvx_latency_p50_ms"]
    latency = latencies["auto_concurrent"]
    out.update(auto_concurrent_latency_p50_ms=float(np.percentile(latency, 50)),
               auto_concurrent_latency_p95_ms=float(np.percentile(latency, 95)),
               auto_concurrent_over_cvx_latency_p50=float(np.percentile(latency, 50))
               / out["cvx_latency_p50_ms"])
    return out


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
