"""Benchmark: the fuzz campaign of `test/ros/test_fuzz.py` at scale, against a node process.

The guidance node runs as `ros2 run` would start it, with the stamp-order check (simulated
time, the mode where a future stamp once poisoned the stamp floor), the shipped default model
and recording on; the campaign (`test/helpers/fuzz_messages.py`) sends `repeats` seeded cases
of field-level mutations of RelativeNavState and ReplanRequest over DDS, waits for every
answer, and after each case checks that a valid request and fix still get a usable plan. A
failure names its seed (`case(seed)` replays it). Reports the messages sent, the answers by
decision, the median nav -> answer time, and the node's memory before and after.

    art-guidance bench fuzz --repeats 900 --first-seed 0     # >= 5,000 messages, ~10 min
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

from art_guidance.ros.env import isolated_ros_env
from common import REPO, use_test_helpers


def run(repeats: int = 900, first_seed: int = 0) -> dict:
    """`repeats` cases from `first_seed` against one node process."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_fuzz_"),
                           100 + (os.getpid() + 37) % 100)
    os.environ.update(ros)
    use_test_helpers()
    from helpers.fuzz_messages import run_campaign
    from helpers.processes import interrupt, process_stats
    from helpers.ros_client import Client

    record_dir = tempfile.mkdtemp(prefix="art_guidance_fuzz_bag_")
    env = {**os.environ, **ros, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    log = open(Path(record_dir) / "node.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "art_guidance.ros.guidance_node",
                             "--ros-args", "-p", "stamp_check:=order",
                             "-p", f"record_dir:={record_dir}/bag"],
                            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    client = Client("fuzz_bench_client")
    try:
        if not client.wait_matched(60.0):
            raise RuntimeError("the guidance node did not match within 60 s")
        rss0 = process_stats(proc.pid)[0]
        t0 = time.perf_counter()
        bar = tqdm(total=int(repeats), desc="fuzz cases")
        counts = run_campaign(client, proc, int(first_seed), int(repeats),
                              progress=lambda c: bar.update(1))
        bar.close()
        wall = time.perf_counter() - t0
        rss1 = process_stats(proc.pid)[0]
    finally:
        client.close()
        interrupt(proc, 60)
        log.close()
    text = (Path(record_dir) / "node.log").read_text()
    return {**counts, "first_seed": int(first_seed), "wall_s": wall,
            "messages_per_s": counts["messages"] / wall, "node_exit_code": proc.returncode,
            "tracebacks": text.count("Traceback"), "rss_start_mb": rss0, "rss_end_mb": rss1}
