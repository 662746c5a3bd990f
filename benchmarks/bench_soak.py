"""Benchmark: a soak of one guidance node, closed-loop flights back to back over DDS.

One node process (as `ros2 run` starts it: shipped model, warm start auto, stamp-order check,
recording on with `record_max_bytes` 1 MiB and a `record_max_total_bytes` cap of 8 MiB, so the
retention rule runs) serves `repeats` closed-loop flights of the simulator node, one after the
other (seeds 0.., the plus_vbar waypoint; each flight sends its replan request first, which
starts a new stamp sequence). A passive listener on the same domain times every nav fix ->
plan answer (matched by stamp within the flight, wall clock at the listener; fixes the node
keeps its plan for get no answer and are not counted). Every 5 s the node's resident
memory, open file descriptors and threads are sampled, and the bag folder's size.

Reports: flights reached / run, solves, latency p50 / p95 / max [ms], the memory slope after
the first fifth of the run [MB/min], descriptors and threads at start and end, the largest
bag size on disk against the cap, the files the retention rule dropped, whether the final bag
reads back complete (`read_log`: no damage, nothing lost against metadata.yaml), the node's exit
code and tracebacks in its log.

    art-guidance bench soak --repeats 150 --json benchmarks/results/reliability/soak.json
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from art_guidance.ros.env import isolated_ros_env
from common import REPO, use_test_helpers

MAX_BYTES = 1 << 20
CAP_BYTES = 8 << 20
SAMPLE_S = 5.0


class _Listener:
    """Times nav fix -> plan answers on the guidance topics (wall clock, by stamp)."""

    def __init__(self) -> None:
        import rclpy
        from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from art_guidance import topics

        if not rclpy.ok():
            rclpy.init()
        self.node = rclpy.create_node("art_guidance_soak_listener")
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.nav_t: dict[int, float] = {}
        self.latency_ms: list[float] = []
        self.lock = threading.Lock()
        self.node.create_subscription(RelativeNavState, topics.NAV, self._on_nav, qos)
        self.node.create_subscription(ManeuverPlan, topics.MANEUVER_PLAN, self._on_plan, qos)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    @staticmethod
    def _ns(header: object) -> int:
        return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec

    def _on_nav(self, msg: object) -> None:
        with self.lock:
            self.nav_t.setdefault(self._ns(msg.header), time.perf_counter())

    def _on_plan(self, msg: object) -> None:
        now = time.perf_counter()
        with self.lock:
            t = self.nav_t.pop(self._ns(msg.header), None)
            if t is not None:
                self.latency_ms.append(1e3 * (now - t))

    def new_flight(self) -> None:
        """Forget the fixes of the previous flight (each flight's stamps start anew)."""
        with self.lock:
            self.nav_t.clear()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def _bag_bytes(bag: Path) -> int:
    return sum(p.stat().st_size for p in bag.glob("*.mcap")) if bag.is_dir() else 0


def run(repeats: int = 150, first_seed: int = 0) -> dict:
    """`repeats` flights (seeds from `first_seed`) through one node; see the module."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_soak_"),
                           100 + (os.getpid() + 53) % 100)
    os.environ.update(ros)
    use_test_helpers()
    from helpers.processes import interrupt, process_stats

    work = Path(tempfile.mkdtemp(prefix="art_guidance_soak_run_"))
    bag = work / "bag"
    env = {**os.environ, **ros, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    node_log = open(work / "node.log", "w")
    node = subprocess.Popen(
        [sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
         "-p", "stamp_check:=order", "-p", f"record_dir:={bag}",
         "-p", f"record_max_bytes:={MAX_BYTES}", "-p", f"record_max_total_bytes:={CAP_BYTES}"],
        env=env, stdout=node_log, stderr=subprocess.STDOUT, cwd=REPO)
    listener = _Listener()
    samples: list[tuple[float, float, int, int, int]] = []  # t, rss, fds, threads, bag bytes
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set() and node.poll() is None:
            try:
                samples.append((time.perf_counter(), *process_stats(node.pid), _bag_bytes(bag)))
            except OSError:
                return
            stop.wait(SAMPLE_S)

    sampler = threading.Thread(target=sample, daemon=True)
    reached, codes, t0 = 0, [], time.perf_counter()
    try:
        time.sleep(5.0)  # the node loads its model
        sampler.start()
        for seed in tqdm(range(int(first_seed), int(first_seed) + int(repeats)),
                         desc="soak flights", unit="flight"):
            if node.poll() is not None:
                raise RuntimeError(f"the guidance node exited with {node.returncode}")
            listener.new_flight()
            sim = subprocess.run(
                [sys.executable, "-m", "art_guidance.ros.sim_node", "--ros-args",
                 "-p", "waypoint:=plus_vbar", "-p", f"seed:={seed}"],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                timeout=600)
            codes.append(sim.returncode)
            reached += sim.returncode == 0
    finally:
        wall = time.perf_counter() - t0
        stop.set()
        listener.close()
        interrupt(node, 60)
        node_log.close()
    from art_guidance.record.replay import read_log

    log = read_log(bag)
    meta = log.lost.get("metadata", "")
    t, rss, fds, threads, sizes = (np.array(x) for x in zip(*samples))
    later = t >= t[0] + 0.2 * (t[-1] - t[0])
    slope = float(np.polyfit((t[later] - t[0]) / 60.0, rss[later], 1)[0]) \
        if later.sum() >= 3 else float("nan")
    lat = np.array(listener.latency_ms)
    text = (work / "node.log").read_text(errors="replace")
    return {"flights": int(repeats), "reached": int(reached),
            "exit_codes": sorted(set(codes)), "wall_s": wall,
            "answers_timed": int(lat.size),
            "latency_p50_ms": float(np.percentile(lat, 50)),
            "latency_p95_ms": float(np.percentile(lat, 95)),
            "latency_max_ms": float(lat.max()),
            "rss_start_mb": float(rss[0]), "rss_end_mb": float(rss[-1]),
            "rss_slope_after_warmup_mb_per_min": slope,
            "fds_start": int(fds[0]), "fds_end": int(fds[-1]),
            "threads_start": int(threads[0]), "threads_end": int(threads[-1]),
            "bag_bytes_max": int(sizes.max()), "bag_bytes_cap": CAP_BYTES,
            "bag_bytes_final": _bag_bytes(bag),
            "solves_in_final_bag": len(log.solves()), "final_bag_data_lost": log.data_lost,
            "final_bag_metadata": meta, "node_exit_code": node.returncode,
            "tracebacks": text.count("Traceback")}
