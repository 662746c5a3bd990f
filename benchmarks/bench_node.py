"""Benchmark: nav message in -> plan out latency of the guidance node over real DDS.

The node runs in its own process (as `ros2 run` would start it) with every nav message forced to
replan; the client publishes a nav state, waits for the plan with that stamp (the latency), then
for the node to be idle (its plan diagnostic, the last work of a plan), and repeats. Three
configurations: with the learned warm start (`warm_start auto`, the shipped model or `--model`),
CVX only, and `auto` with the proposal made in a worker process (`propose_concurrently`), each
run in ROUNDS rounds over its share of the states (the order rotating), so that the machine's drift
over the run reaches all three alike.
The reference is the same `GuidancePipeline.plan` called in-process on the same states, so the
difference is the node and middleware overhead; its timings give the split per stage (CVX,
ART rollout + post hoc check, SCP).

The in-process pipelines are warmed up before their first plan (`common.warm_up`;
`warm_up_ms`); each node start's first plan is left out of the node's latencies.
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
from common import use_test_helpers, warm_up


def _states(repeats: int) -> list[np.ndarray]:
    scenario = ScenarioConfig.from_yaml()
    rng = np.random.default_rng(11)
    half = np.asarray(scenario.rtn0_half_width)
    return [np.asarray(scenario.rtn0_nominal) + rng.uniform(-1, 1, 6) * half
            for _ in range(repeats + 1)]


CONFIGS = (("auto", False), ("cvx", False), ("auto", True))  # (warm_start, worker)
ROUNDS = 4  # each configuration's node is started this many times, in turn


def _label(warm_start: str, concurrent: bool) -> str:
    return f"{warm_start}_concurrent" if concurrent else warm_start


def _node_latency(warm_start: str, states: list[np.ndarray], client_cls, nav_msg,
                  concurrent: bool = False, model: str | None = None) -> list[float]:
    """Nav -> plan latency [ms] of a node process with `warm_start` over `states` (the first
    plan excluded: it includes the per-horizon set-up of a cold process); `concurrent`: with
    `propose_concurrently` (the proposal in a worker process); `model`: its `model_path`
    (None: the shipped default)."""
    label = _label(warm_start, concurrent)
    params = ["-p", "replan_sigma_threshold:=1e-9", "-p", "record:=false",
              "-p", f"warm_start:={warm_start}",
              "-p", f"propose_concurrently:={str(concurrent).lower()}"]
    if model:
        params += ["-p", f"model_path:={Path(model).resolve()}"]
    proc = subprocess.Popen([sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             *params], env=dict(os.environ), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    client = client_cls(f"art_guidance_bench_client_{label}")
    latency = []
    try:
        if not client.wait_matched(60.0):
            raise RuntimeError("guidance node did not come up")
        for k, rtn in enumerate(tqdm(states, desc=f"bench node ({label})", unit="plan")):
            if k == 0:  # the first fix may be lost while discovery completes
                stamp, _ = client.send_nav(rtn)
                t0 = time.perf_counter()
            else:
                stamp = time.time_ns()
                t0 = time.perf_counter()
                client.nav_pub.publish(nav_msg(stamp, rtn))
            if client.plan_for(stamp, timeout_s=60.0) is None:
                raise RuntimeError(f"no plan for nav {k}")
            if k > 0:
                latency.append(1e3 * (time.perf_counter() - t0))
            _wait_idle(client, stamp)
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    return latency


def _wait_idle(client, stamp_ns: int, timeout_s: float = 30.0) -> None:
    """Wait for the "art_guidance/plan" status of the plan for `stamp_ns`: the node's last
    work of a plan (its views come before it), so the next fix finds the node idle, as a fix
    every few seconds does in flight. Without it the views of one plan, drawn after it is
    published, would be counted in the next plan's latency."""
    def done(_, diags):
        return any(name == "art_guidance/plan" and v.get("nav_stamp_ns") == str(stamp_ns)
                   for _, v, name in diags)
    client.wait_for(done, timeout_s)


def _node_latencies(states: list[np.ndarray], client_cls, nav_msg,
                    model: str | None = None) -> dict[str, list[float]]:
    """The latencies of every configuration of CONFIGS over `states`[1:], in ROUNDS rounds:
    each round starts each configuration's node in turn for its share of the states (plus a
    first, excluded plan), so a machine whose speed drifts during the run slows every
    configuration alike. (One node per configuration up at once, asked in turn, was tried:
    the idle nodes and the client's three executors added ~150 ms to every plan.)"""
    chunks = np.array_split(np.arange(1, len(states)), ROUNDS)
    latency: dict[str, list[float]] = {_label(*c): [] for c in CONFIGS}
    for r, chunk in enumerate(chunks):
        for i in range(len(CONFIGS)):
            ws, conc = CONFIGS[(i + r) % len(CONFIGS)]
            latency[_label(ws, conc)] += _node_latency(
                ws, [states[0]] + [states[k] for k in chunk], client_cls, nav_msg, conc, model)
    return latency


def run(repeats: int = 30, model: str | None = None) -> dict:
    """Latency over `repeats` plans with the learned warm start (auto, the shipped model or
    `model`) and with CVX only; p50/p95 [ms], the in-process reference and the split per
    stage."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_bench_"),
                           150 + os.getpid() % 50)
    os.environ.update(ros)  # this process is the client
    use_test_helpers()
    from helpers import ros_client  # the tests' DDS client

    from art_guidance.art.provider import ArtWarmStart

    states = _states(repeats)
    out: dict = {"plans": repeats}
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    target = np.asarray(scenario.waypoints_rtn["plus_vbar"])
    provider = ArtWarmStart.load(model or None)
    out["model"] = Path(provider.path).name
    latencies = _node_latencies(states, ros_client.Client, ros_client.nav_msg, model)
    out["warm_up_ms"] = 0.0
    for warm_start in ("auto", "cvx"):
        latency = latencies[warm_start]
        pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario),
                                    provider=provider if warm_start == "auto" else None)
        out["warm_up_ms"] += warm_up(pipeline)  # before the first in-process plan
        stages: dict[str, list[float]] = {k: [] for k in ("cvx", "art", "scp", "total")}
        accepted = 0
        for rtn in states[1:]:
            res = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, rtn), target,
                                            warm_start=warm_start))
            accepted += res.warm_start is WarmStartSource.ART
            t = res.timings
            for key, value in (("cvx", t.cvx), ("art", t.art), ("scp", t.scp),
                               ("total", t.total)):
                stages[key].append(value)
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
