"""Benchmark: SIGKILL a recording guidance node at random moments; the bag must survive as it is.

`repeats` kills (`test/helpers/kill_campaign.py`): each starts the node as `ros2 run` would
(replanning on every fix, files rotated at 100 kB), drives it with a fix every 0.1 s, kills it
`U(0, 8)` s after its endpoints matched (seeded: kill k uses seed `first_seed + k`) and checks
the folder with no repair: rosbags and `read_log` open it, metadata.yaml is valid and agrees
with the files (or is one unpublished solve behind, when the kill fell between the data write
and its rename), no stub or empty `.mcap`, and every plan published before the kill is in it.
Also measures the torn window in-process: the time of the one write per solve during which
the file has no valid ending, over `TORN_SOLVES` solves of a real plan's messages.

    art-guidance bench kill --repeats 50 --first-seed 0 \\
        --json benchmarks/results/recording/kill_50.json
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from art_guidance.ros.env import isolated_ros_env
from common import REPO, use_test_helpers

MAX_DELAY_S = 8.0
TORN_SOLVES = 500


def torn_window(solves: int = TORN_SOLVES) -> dict:
    """Median / p99 / max of the per-solve write window [ms] and the bytes per solve."""
    from art_guidance.config import GuidanceConfig, ScenarioConfig
    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.planning import GuidancePipeline, PlanRequest
    from art_guidance.record.recorder import McapRecorder
    from art_guidance.ros.adapters import plan_to_msg, solve_record_msg
    from art_guidance.scenarios import sample_scenario

    use_test_helpers()
    from helpers.ros_client import nav_msg
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario))
    chief, s = np.array(scenario.chief_oe), sample_scenario(scenario, 0)
    result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn))
    stamp = time.time_ns()
    msgs = [("/nav/relative_state", nav_msg(stamp, s.rtn0)),
            ("/guidance/solve_record", solve_record_msg(result, stamp, "plan-0", "bench")),
            ("/guidance/maneuver_plan", plan_to_msg(result, stamp, "plan-0"))]
    with tempfile.TemporaryDirectory(prefix="art_guidance_torn_") as tmp:
        with McapRecorder(Path(tmp) / "bag", {"config": pipeline.config_json()}) as rec:
            for k in range(solves):
                rec.record_solve(msgs, stamp + k)
            window_ms = np.array(rec.torn_window_ns) / 1e6
        size = sum(p.stat().st_size for p in (Path(tmp) / "bag").glob("*.mcap"))
    return {"torn_window_median_ms": float(np.median(window_ms)),
            "torn_window_p99_ms": float(np.quantile(window_ms, 0.99)),
            "torn_window_max_ms": float(window_ms.max()), "torn_window_solves": solves,
            "torn_window_bytes_per_solve": size / solves}


def run(repeats: int = 50, first_seed: int = 0) -> dict:
    """`repeats` kills from seed `first_seed`, then the torn window."""
    ros = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_kill_"),
                           100 + (os.getpid() + 53) % 100)
    os.environ.update(ros)
    use_test_helpers()
    from helpers.kill_campaign import kill_once

    env = {**os.environ, **ros, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    root = Path(tempfile.mkdtemp(prefix="art_guidance_kill_bags_"))
    kills, t0 = [], time.perf_counter()
    for k in range(int(repeats)):
        seed = int(first_seed) + k
        kill = kill_once(sys.executable, env, root / f"bag_{seed}", seed, MAX_DELAY_S,
                         f"kill_bench_client_{seed}")
        kills.append(kill)
        print(f"  kill {k + 1}/{repeats}: {kill}", flush=True)
    failed = [k for k in kills if k["problems"]]
    report = {
        "kills": len(kills), "first_seed": int(first_seed), "max_delay_s": MAX_DELAY_S,
        "folders_ok": len(kills) - len(failed),
        "metadata_exact": sum(k["metadata"] == "exact" for k in kills),
        "metadata_one_solve_behind": sum(k["metadata"].startswith("one solve") for k in kills),
        "killed_before_first_solve": sum(k["metadata"].startswith("none") for k in kills),
        "part_files_left": sum(k["part_files"] for k in kills),
        "empty_mcap_files": sum(k["empty_files"] for k in kills),
        "plans_published": sum(k["published"] for k in kills),
        "solves_recorded": sum(k["recorded"] for k in kills),
        "files": sum(k["files"] for k in kills),
        "campaign_s": time.perf_counter() - t0,
        "failures": failed,
    }
    report.update(torn_window())
    report["per_kill"] = kills
    return report
