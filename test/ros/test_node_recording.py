"""The node records every solve: a real kill -9 loses no published plan; SIGTERM finishes."""
from __future__ import annotations

import signal
import subprocess
import time
from contextlib import contextmanager

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rosbags.highlevel import AnyReader  # noqa: E402
from helpers.ros_client import Client, nav_msg  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.record.replay import read_log, replay  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


@contextmanager
def _node_with_client(ros_env, python_exe, record_dir, name):
    """A recording guidance node (replanning on every fix) and a matched client.

    The client is closed on exit and a node still running is killed; stopping it properly is
    the test's business.
    """
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", f"record_dir:={record_dir}",
                             "-p", "replan_sigma_threshold:=1e-9"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client(name)
    try:
        assert client.wait_matched(20.0)
        yield proc, client
    finally:
        client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def _plan_ids(client, n, rng):
    ids = []
    for _ in range(n):
        offset = rng.normal(0.0, 100.0, 6) * [1, 1, 0, 0, 0, 0]
        stamp, _ = client.send_nav(NOMINAL_RTN + offset)
        plan = client.plan_for(stamp, timeout_s=30.0)
        assert plan is not None
        ids.append(plan.plan_id)
    return ids


def test_kill9_keeps_every_published_plan_and_replays(ros_env, python_exe, tmp_path):
    with _node_with_client(ros_env, python_exe, tmp_path / "bag", "recording_client") as (
            proc, client):
        published = _plan_ids(client, 4, np.random.default_rng(5))
        client.nav_pub.publish(nav_msg(time.time_ns(), NOMINAL_RTN))  # a solve in flight
        time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        received = {p.plan_id for _, p in client.plans}
    log = read_log(tmp_path / "bag")
    recorded = {plan.plan_id for _, plan in log.solves()}
    assert set(published) <= recorded
    assert received <= recorded  # recorded before published: nothing published is lost
    assert not (tmp_path / "bag" / "metadata.yaml").exists()  # it really died
    report = replay(tmp_path / "bag")
    assert report["compared"] >= 4 and report["mismatched"] == 0, report


def test_sigterm_finishes_the_bag(ros_env, python_exe, tmp_path):
    with _node_with_client(ros_env, python_exe, tmp_path / "bag", "recording_client2") as (
            proc, client):
        ids = _plan_ids(client, 2, np.random.default_rng(6))
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    with AnyReader([tmp_path / "bag"]) as reader:
        plans = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                 if c.topic == "/guidance/maneuver_plan"]
    assert [p.plan_id for p in plans] == ids


def test_unwritable_log_directory_does_not_stop_guidance(ros_env, python_exe):
    with _node_with_client(ros_env, python_exe, "/proc/art_guidance_cannot_write_here",
                           "recording_client3") as (proc, client):
        ids = _plan_ids(client, 2, np.random.default_rng(7))
        assert len(ids) == 2  # plans still arrive
        errors = client.wait_for(lambda _, diags: [v for _, v, n in diags
                                                   if n == "art_guidance/recorder"], 10.0)
        assert errors, "no recorder error on /diagnostics"
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 0
