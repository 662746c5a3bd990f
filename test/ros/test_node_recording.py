"""The node records every solve: a real kill -9 loses no published plan and leaves a bag that
rosbags opens; SIGTERM finishes; a namespaced node records its resolved topics; each replan
request is recorded once."""
from __future__ import annotations

import json
import signal
import subprocess
import time
from contextlib import contextmanager

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import ManeuverPlan, ReplanRequest  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from helpers.ros_client import Client, nav_msg  # noqa: E402
from helpers.rosbag2_metadata import consistency_problems, metadata_problems  # noqa: E402

from art_guidance.cli import main as cli_main  # noqa: E402
from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.record.recorder import PLAN_TYPE, REQUEST_TYPE  # noqa: E402
from art_guidance.record.replay import read_log, replay, request_stamp_ns  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)
# the tests about the recorder alone plan CVX only: no model, no proposal worker to start (the
# learned path is recorded and replayed in test_node_art.py; the kill -9 here keeps the defaults)
CVX_ONLY = "model_path:=none"


@contextmanager
def _node_with_client(ros_env, python_exe, record_dir, name, namespace="", params=()):
    """A recording guidance node (replanning on every fix; `params`: more of its parameters,
    "name:=value") and a matched client, both in `namespace` when given.

    The client is closed on exit and a node still running is killed; stopping it properly is
    the test's business.
    """
    remap = ["-r", f"__ns:={namespace}"] if namespace else []
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", f"record_dir:={record_dir}",
                             "-p", "replan_sigma_threshold:=1e-9", "-p", "endgame:=none",
                             *[a for p in params for a in ("-p", p)], *remap],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client(name, namespace)
    try:
        assert client.wait_matched(60.0)
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


def _metadata(bag) -> dict:
    doc = yaml.safe_load((bag / "metadata.yaml").read_text())
    assert metadata_problems(doc) == [] and consistency_problems(bag) == []
    return doc["rosbag2_bagfile_information"]


def _rosbags_plans(bag) -> list:
    """Every ManeuverPlan rosbags reads from the bag folder (metadata.yaml and files)."""
    with AnyReader([bag]) as reader:
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                if c.msgtype == PLAN_TYPE]


def test_kill9_keeps_every_published_plan_and_replays(ros_env, python_exe, tmp_path, capsys):
    bag = tmp_path / "bag"
    # a deadline no busy machine reaches: a solve that hit its deadline is not compared
    with _node_with_client(ros_env, python_exe, bag, "recording_client",
                           params=("solve_deadline_s:=120.0",)) as (proc, client):
        published = _plan_ids(client, 4, np.random.default_rng(5))
        # a solve in flight (solves take hundreds of ms): the kill lands between two writes
        client.nav_pub.publish(nav_msg(time.time_ns(), NOMINAL_RTN))
        time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        received = {p.plan_id for _, p in client.plans}
    assert proc.returncode == -signal.SIGKILL
    log = read_log(bag)
    recorded = {plan.plan_id for _, plan in log.solves()}
    assert set(published) <= recorded
    assert received <= recorded  # recorded before published: nothing published is lost
    assert _metadata(bag)["custom_data"]["art_guidance.state"] == "recording"  # it died
    # the crashed folder opens in rosbags as it is: each solve sealed the file and rewrote
    # metadata.yaml
    assert received <= {p.plan_id for p in _rosbags_plans(bag)}
    report = replay(bag)
    assert report["compared"] >= 4 and report["mismatched"] == 0, report
    assert cli_main(["bag", "reindex", str(bag)]) == 0  # adds the missing summary
    assert "rewrote guidance_0.mcap with a summary" in capsys.readouterr().out
    assert _metadata(bag)["custom_data"]["art_guidance.state"] == "reindexed"
    assert {p.plan_id for p in _rosbags_plans(bag)} == recorded


def test_sigterm_finishes_the_bag(ros_env, python_exe, tmp_path):
    with _node_with_client(ros_env, python_exe, tmp_path / "bag", "recording_client2",
                           params=(CVX_ONLY,)) as (
            proc, client):
        ids = _plan_ids(client, 2, np.random.default_rng(6))
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert _metadata(tmp_path / "bag")["custom_data"]["art_guidance.state"] == "finished"
    assert [p.plan_id for p in _rosbags_plans(tmp_path / "bag")] == ids


def test_namespaced_node_records_resolved_topics_and_each_request_once(
        ros_env, python_exe, tmp_path):
    bag, rng = tmp_path / "bag", np.random.default_rng(8)
    with _node_with_client(ros_env, python_exe, bag, "recording_client4", "/chaser",
                           (CVX_ONLY,)) as (
            proc, client):
        before = _plan_ids(client, 1, rng)  # no request yet
        request = ReplanRequest(waypoint="plus_vbar", chance_constrained=True)
        request_ns = time.time_ns()
        request.header.stamp.sec, request.header.stamp.nanosec = divmod(request_ns, 10**9)
        client.req_pub.publish(request)  # replans from the latest fix
        assert client.wait_for(lambda plans, _: len(plans) >= 2, 30.0)
        under = [client.plans[1][1].plan_id] + _plan_ids(client, 3, rng)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert {t["topic_metadata"]["name"] for t in _metadata(bag)["topics_with_message_count"]} \
        == {"/chaser/nav/relative_state", "/chaser/guidance/replan_request",
            "/chaser/guidance/solve_record", "/chaser/guidance/maneuver_plan",
            "/chaser/guidance/viz/plan_path", "/chaser/guidance/viz/plan_markers",
            "/chaser/guidance/viz/deputy", "/chaser/guidance/viz/deputy_pose"}
    assert [p.plan_id for p in _rosbags_plans(bag)] == before + under
    log = read_log(bag)
    assert len(log.of_type(REQUEST_TYPE)) == 1  # four solves under it, one copy
    records = {r.plan_id: r for r, _ in log.solves()}
    assert request_stamp_ns(records[before[0]]) == 0
    assert {request_stamp_ns(records[i]) for i in under} == {request_ns}
    assert {log.request_for(records[i]).waypoint for i in under} == {"plus_vbar"}
    report = replay(bag)
    assert report["solves"] == 5 and report["mismatched"] == 0, report  # a solve slowed
    # past its deadline by a busy machine is skipped, not compared


def test_windowed_solves_are_recorded_with_their_window_and_replay(
        ros_env, python_exe, tmp_path):
    bag = tmp_path / "bag"
    window = ("replan_window_nodes:=20", "terminal_target:=art", "visualization:=false")
    with _node_with_client(ros_env, python_exe, bag, "recording_client_window",
                           params=window) as (proc, client):
        ids = _plan_ids(client, 3, np.random.default_rng(9))
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    records = {r.plan_id: r for r, _ in read_log(bag).solves()}
    assert set(ids) <= set(records)
    for plan_id in ids:
        window = json.loads(records[plan_id].window_json)
        assert window["window_nodes"] == 20 and window["end_node"] == 20
        assert window["target_source"] in ("art", "cvx") and window["reason"]
        assert json.loads(records[plan_id].request_json)["window_nodes"] == 20
    report = replay(bag)
    assert report["compared"] >= 3 and report["mismatched"] == 0, report
    assert all(r["window_match"] for r in report["per_solve"] if r["match"] is not None)


def test_a_window_too_short_for_the_planner_leaves_a_plan_in_force(
        ros_env, python_exe, tmp_path):
    """replan_window_nodes 2 with a request of 0.3 orbits: the window would span 0.006 orbits,
    below the planner's 0.01 (it was SOLVER_ERROR and no plan in force, fix after fix). The
    whole remainder is planned, the plan says why, and it is in force; at 0.01 orbits the node
    plans as without a window (its status that of window 0, never a SOLVER_ERROR for the
    window). The bag replays."""
    bag = tmp_path / "bag"
    params = ("replan_window_nodes:=2", "visualization:=false")
    with _node_with_client(ros_env, python_exe, bag, "recording_client_short_window",
                           params=params) as (proc, client):
        statuses = {}
        for orbits in (0.3, 0.01):
            since = time.monotonic()
            client.req_pub.publish(ReplanRequest(waypoint="plus_vbar", chance_constrained=True,
                                                 horizon_orbits=orbits))
            assert client.wait_for(lambda _, diags: any(
                n == "art_guidance/replan_request" and t >= since for t, _, n in diags), 15.0)
            stamp, _ = client.send_nav(NOMINAL_RTN)
            plan = client.plan_for(stamp, timeout_s=60.0)
            assert plan is not None, orbits
            statuses[orbits] = plan
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert statuses[0.3].status == ManeuverPlan.STATUS_CONVERGED, statuses[0.3].status_text
    assert statuses[0.3].plan_id and "in force" not in statuses[0.3].status_text
    assert statuses[0.01].status != ManeuverPlan.STATUS_SOLVER_ERROR, statuses[0.01].status_text
    records = [r for r, _ in read_log(bag).solves()]
    reasons = [json.loads(r.window_json)["reason"] for r in records]
    assert len(reasons) >= 2 and all("below the planner's 0.01" in r for r in reasons), reasons
    report = replay(bag)
    assert report["mismatched"] == 0, report


@pytest.mark.parametrize("where", ["under_a_file", "proc"])
def test_an_unusable_record_dir_is_refused_at_start_up(ros_env, python_exe, tmp_path, where):
    """A record_dir under a regular file, or where no file can be created (/proc stands in for
    a read-only folder: the tests may run as root, whom chmod does not stop), stops the node at
    start-up with a message naming the path and why, before the node loads its model or starts
    its proposal worker."""
    (tmp_path / "file").write_text("in the way")
    record_dir = (tmp_path / "file" / "bag" if where == "under_a_file"
                  else "/proc/art_guidance_cannot_write_here")
    out = subprocess.run([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                          "-p", f"record_dir:={record_dir}"], env=ros_env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    why = "is a file, not a folder" if where == "under_a_file" else "files cannot be created"
    assert f"record_dir {record_dir} cannot be used" in out.stderr and why in out.stderr
    assert "worker process" not in out.stdout + out.stderr


def test_a_record_dir_lost_mid_run_does_not_stop_guidance(ros_env, python_exe, tmp_path):
    """The bag folder replaced by a regular file mid-run: plans keep coming, each failed solve
    is reported on /diagnostics, and the folder as it was (moved away) stays consistent: no
    stub file, metadata.yaml describes exactly the solves recorded before."""
    bag, moved = tmp_path / "bag", tmp_path / "moved"
    with _node_with_client(ros_env, python_exe, bag, "recording_client3",
                           params=(CVX_ONLY,)) as (proc, client):
        before = _plan_ids(client, 2, np.random.default_rng(7))
        bag.rename(moved)
        bag.write_text("in the way")
        after = _plan_ids(client, 2, np.random.default_rng(8))
        assert len(after) == 2  # plans still arrive
        errors = client.wait_for(lambda _, diags: [v for _, v, n in diags
                                                   if n == "art_guidance/recorder"], 10.0)
        assert errors, "no recorder error on /diagnostics"
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 0
    assert [p.plan_id for p in _rosbags_plans(moved)] == before
    assert _metadata(moved)["message_count"] == len(read_log(moved).messages)
    assert [p.name for p in moved.iterdir() if p.suffix != ".yaml"] == ["guidance_0.mcap"]
