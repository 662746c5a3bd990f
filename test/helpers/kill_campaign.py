"""SIGKILL a recording guidance node at random moments and check the bag it leaves behind.

Each kill starts the node (as `ros2 run` would, replanning on every fix, files rotated small so
that kills also land in file creation and rotation), drives it with a fix every 0.1 s from a
fresh client, waits a random time and sends SIGKILL. The folder is then checked as it is, with
no repair: rosbags opens it (metadata.yaml and files), `read_log` reads it, metadata.yaml is
valid and agrees with the files, no stub or empty `.mcap` is left, and every plan the client
received before the kill is in the bag (a plan is recorded before it is published).

Used by `benchmarks/bench_kill.py` (`art-guidance bench kill`) and `test/ros/test_kill.py`.
"""
from __future__ import annotations

import signal
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import yaml
from art_guidance_msgs.msg import ManeuverPlan
from rosbags.highlevel import AnyReader

from art_guidance.config import ScenarioConfig
from art_guidance.record.recorder import PART_SUFFIX, PLAN_TYPE
from art_guidance.record.replay import read_log
from art_guidance.ros.node_outputs import VIZ_TYPE_NAMES
from helpers.ros_client import Client, nav_msg
from helpers.rosbag2_metadata import consistency_problems, metadata_problems

NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)
FIX_PERIOD_S = 0.1
MAX_BYTES = 100_000  # small files: kills land in file creation and rotation too


def _drive(client: Client, stop: threading.Event, rng: np.random.Generator) -> None:
    while not stop.is_set():
        offset = rng.normal(0.0, 100.0, 6) * [1, 1, 0, 0, 0, 0]
        client.nav_pub.publish(nav_msg(time.time_ns(), NOMINAL_RTN + offset))
        stop.wait(FIX_PERIOD_S)


def kill_once(python_exe: str, env: dict, bag: Path, seed: int, max_delay_s: float,
              name: str) -> dict:
    """One run of the node killed `U(0, max_delay_s)` s after its endpoints matched; the
    check of the folder it left (see `check_bag`)."""
    rng = np.random.default_rng(seed)
    delay_s = float(rng.uniform(0.0, max_delay_s))
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", f"record_dir:={bag}", "-p", "replan_sigma_threshold:=1e-9",
                             "-p", "endgame:=none",
                             "-p", f"record_max_bytes:={MAX_BYTES}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    client, stop = Client(name), threading.Event()
    try:
        if not client.wait_matched(60.0):
            raise RuntimeError("the guidance node did not match within 60 s")
        driver = threading.Thread(target=_drive, args=(client, stop, rng), daemon=True)
        driver.start()
        time.sleep(delay_s)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        stop.set()
        driver.join(timeout=5)
        received = [p.plan_id for _, p in client.plans
                    if p.status != ManeuverPlan.STATUS_REJECTED_INPUT]
    finally:
        stop.set()
        client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    out = {"seed": seed, "delay_s": round(delay_s, 3), "returncode": proc.returncode,
           "published": len(received)}
    out.update(check_bag(bag, received))
    return out


def _one_views_write_behind(per_topic: Counter, info: dict) -> bool:
    """Whether the files hold exactly one visualisation write more than metadata.yaml counts
    (`per_topic`: (topic, type) -> messages read): a published plan's views are written after
    it, and a kill between their data and metadata.yaml leaves it one such write behind, as it
    may leave it one solve behind."""
    counted = Counter({(t["topic_metadata"]["name"], t["topic_metadata"]["type"]):
                       t["message_count"] for t in info["topics_with_message_count"]})
    extra = {key: per_topic[key] - counted[key] for key in per_topic | counted
             if per_topic[key] != counted[key]}
    return bool(extra) and {kind for _, kind in extra} <= set(VIZ_TYPE_NAMES.values()) \
        and set(extra.values()) == {1}


def check_bag(bag: Path, received: list[str]) -> dict:
    """What a crashed folder holds and what is wrong with it (`problems`, empty = none)."""
    problems: list[str] = []
    mcaps = sorted(bag.glob("*.mcap")) if bag.is_dir() else []
    parts = sorted(bag.glob(f".*{PART_SUFFIX}")) if bag.is_dir() else []
    out = {"files": len(mcaps), "part_files": len(parts), "empty_files": 0,
           "metadata": "exact", "recorded": 0}
    out["empty_files"] = sum(1 for p in mcaps if p.stat().st_size == 0)
    if out["empty_files"]:
        problems.append(f"{out['empty_files']} empty .mcap files")
    if not (bag / "metadata.yaml").is_file():
        if mcaps or received:
            problems.append("no metadata.yaml")
        out.update(metadata="none (killed before the first solve was written)",
                   problems=problems)
        return out
    doc = yaml.safe_load((bag / "metadata.yaml").read_text())
    problems += metadata_problems(doc) + consistency_problems(bag)
    info = doc["rosbag2_bagfile_information"]
    try:
        with AnyReader([bag]) as reader:  # the folder as rosbag2 readers open it
            plans = [reader.deserialize(raw, c.msgtype).plan_id
                     for c, _, raw in reader.messages() if c.msgtype == PLAN_TYPE]
            per_topic = Counter((c.topic, c.msgtype) for c, _, _ in reader.messages())
            listed = sum(per_topic.values())
    except Exception as exc:  # a folder rosbags refuses is the failure counted here
        problems.append(f"rosbags: {type(exc).__name__}: {exc}")
        out["problems"] = problems
        return out
    log = read_log(bag)  # every file, listed or not
    in_log = [plan.plan_id for _, plan in log.solves()]
    out["recorded"] = len(in_log)
    if log.truncated:
        problems.append(f"read_log: truncated {log.truncated}")
    meta_plans = sum(t["message_count"] for t in info["topics_with_message_count"]
                     if t["topic_metadata"]["type"] == PLAN_TYPE)
    # solves in listed files beyond the counts + solves in files not listed
    behind = (len(plans) - meta_plans) + (len(in_log) - len(plans))
    if behind == 1 and in_log[-1] not in received:  # killed between data and metadata.yaml
        out["metadata"] = "one solve behind the data"
    elif behind == 0 and _one_views_write_behind(per_topic, info):
        out["metadata"] = "one plan's visualisation behind the data"
    elif behind != 0 or listed != info["message_count"]:
        problems.append(f"metadata.yaml counts {info['message_count']} messages and "
                        f"{meta_plans} plans; rosbags reads {listed} and {len(plans)}, "
                        f"read_log {len(in_log)} plans")
    missing = sorted(set(received) - set(plans))
    if missing:
        problems.append(f"published but not in the bag: {missing}")
    out["problems"] = problems
    return out
