"""The node's RViz2/Foxglove topics over real DDS, a late subscriber, and the same messages in
the bag (read back by rosbags)."""
from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from pathlib import Path as FilePath

import numpy as np
import pytest

pytest.importorskip("rclpy")
import rclpy  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from nav_msgs.msg import Path  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402
from helpers.ros_client import Client  # noqa: E402

from art_guidance import topics  # noqa: E402
from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.plan_view import DRIFT_SAMPLES  # noqa: E402
from art_guidance.record.render import render_bag  # noqa: E402
from art_guidance.ros import visualization as viz  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ROOT = FilePath(__file__).resolve().parents[2]
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
TOPICS = {topics.PLAN_PATH: Path, topics.PLAN_MARKERS: MarkerArray,
          topics.DEPUTY_MARKERS: MarkerArray, topics.DEPUTY_POSE: PoseWithCovarianceStamped}


class LateListener:
    """Subscribes to the visualisation topics (transient local) after the plan exists."""

    def __init__(self) -> None:
        self.node = rclpy.create_node("art_guidance_viz_listener")
        self.got: dict[str, object] = {}
        self._cv = threading.Condition()
        for topic, msg_type in TOPICS.items():
            self.node.create_subscription(msg_type, topic, self._keep(topic), LATCHED)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def _keep(self, topic):
        def callback(msg):
            with self._cv:
                self.got[topic] = msg
                self._cv.notify_all()
        return callback

    def wait_all(self, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        with self._cv:
            while len(self.got) < len(TOPICS) and time.monotonic() < end:
                self._cv.wait(0.2)
            return len(self.got) == len(TOPICS)

    def close(self) -> None:
        self.executor.shutdown()
        self._thread.join(timeout=5)
        self.node.destroy_node()


def _stamp(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _check_plan_messages(path: Path, markers: MarkerArray, plan, stamp: int) -> None:
    n = len(plan.epochs_s)
    assert path.header.frame_id == "chief_rtn" and _stamp(path.header) == stamp
    assert len(path.poses) == n
    rtn = np.asarray(plan.rtn).reshape(n, 6)
    pos = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                    for p in path.poses])
    np.testing.assert_allclose(pos, rtn[:, :3], atol=1e-9)
    assert _stamp(path.poses[-1].header) == stamp + int(round(plan.epochs_s[-1] * 1e9))
    ms = markers.markers
    assert ms[0].action == Marker.DELETEALL
    assert all(m.header.frame_id == "chief_rtn" for m in ms)
    by_ns = {}
    for m in ms[1:]:
        by_ns.setdefault(m.ns, []).append(m)
    assert len(by_ns["approach_ellipsoid"]) == 1 and len(by_ns["keep_out_zone"]) == 1
    ae = by_ns["approach_ellipsoid"][0]
    assert ae.type == Marker.SPHERE and ae.scale.x == pytest.approx(2000.0)
    assert by_ns["keep_out_zone"][0].scale.y == pytest.approx(400.0)
    drift = by_ns["drift"]
    assert len(drift) == n and {m.id for m in drift} == set(range(n))
    assert all(m.type == Marker.LINE_STRIP and len(m.points) == DRIFT_SAMPLES for m in drift)
    # a converged plan: every margin >= 0, so no drift is drawn red
    assert plan.constraint_margin_m >= 0
    assert all(m.color.g > m.color.r or m.color.r < 1.0 for m in drift)
    dv = np.linalg.norm(np.asarray(plan.dv_rtn_mps).reshape(n, 3), axis=1)
    assert len(by_ns["burns"]) == int((dv >= viz.BURN_MIN_MPS).sum()) >= 1
    assert by_ns["status"][0].text.startswith(plan.plan_id)


def test_visualisation_topics_over_dds_and_in_the_bag(ros_env, python_exe, tmp_path):
    bag = tmp_path / "bag"
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", f"record_dir:={bag}", "-p", "model_path:=none"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client("art_guidance_viz_client")
    listener = None
    try:
        assert client.wait_matched(60.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning"
        plan = client.plan_for(stamp, timeout_s=60.0)
        assert plan is not None and plan.status == plan.STATUS_CONVERGED
        time.sleep(0.5)
        listener = LateListener()  # joins after the plan was published
        assert listener.wait_all(20.0), sorted(listener.got)
        got = listener.got
        _check_plan_messages(got[topics.PLAN_PATH], got[topics.PLAN_MARKERS], plan, stamp)
        deputy = got[topics.DEPUTY_MARKERS]
        assert [m.ns for m in deputy.markers] == ["deputy", "deputy_3sigma"]
        pose = got[topics.DEPUTY_POSE]
        assert pose.header.frame_id == "chief_rtn" and _stamp(pose.header) == stamp
        p = pose.pose.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], NOMINAL_RTN[:3], rtol=0.01, atol=20.0)
        cov = np.asarray(pose.pose.covariance).reshape(6, 6)[:3, :3]
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    finally:
        if listener is not None:
            listener.close()
        client.close()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    with AnyReader([bag]) as reader:
        counts, last, log_ns = {}, {}, {}
        for conn, t_ns, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            last[conn.topic] = reader.deserialize(raw, conn.msgtype)
            log_ns.setdefault(conn.topic, []).append(t_ns)
    # the plan is recorded and published first; its views are drawn, published and recorded
    # after it, in a write of their own
    plan_ns = sorted(log_ns["/guidance/maneuver_plan"])
    for topic in TOPICS:
        assert all(v > p for v, p in zip(sorted(log_ns[f"/{topic}"]), plan_ns)), topic
    # one plan per answered fix: send_nav resends when the node's answer is late (a loaded
    # machine), and a resent fix can be planned for too; every plan carries its views
    n_plans = counts["/guidance/maneuver_plan"]
    assert 1 <= n_plans <= 2
    for topic in TOPICS:
        assert counts[f"/{topic}"] == n_plans, topic
    recorded = last[f"/{topics.PLAN_MARKERS}"]
    assert len([m for m in recorded.markers if m.ns == "drift"]) == len(plan.epochs_s)
    assert recorded.markers[0].header.frame_id == "chief_rtn"
    # the layout's picture drawn from the bag (`art-guidance bag render`)
    counts = render_bag(bag, tmp_path / "bag.png")
    assert counts["plans"] == n_plans and counts["drift"] == len(plan.epochs_s)
    assert counts["deputy_fixes"] == n_plans and counts["burns"] >= 1
    assert (tmp_path / "bag.png").read_bytes()[:4] == b"\x89PNG"


def _leaves(node) -> list[str]:
    return [node] if isinstance(node, str) else _leaves(node["first"]) + _leaves(node["second"])


def test_foxglove_layout_shows_only_published_topics():
    """config/foxglove_layout.json: a 3D panel in chief_rtn on the visualisation topics, plots
    of fields ManeuverPlan has, the status text; its layout tree holds exactly its panels."""
    from art_guidance_msgs.msg import ManeuverPlan

    layout = json.loads((ROOT / "config" / "foxglove_layout.json").read_text())
    panels = layout["configById"]
    assert sorted(_leaves(layout["layout"])) == sorted(panels)
    three_d = [v for k, v in panels.items() if k.startswith("3D!")]
    assert len(three_d) == 1 and three_d[0]["followTf"] == "chief_rtn"
    published = {f"/{t}" for t in (*TOPICS, topics.TRUTH_PATH)}
    assert set(three_d[0]["topics"]) <= published
    assert {f"/{t}" for t in TOPICS} <= set(three_d[0]["topics"])
    fields = set(ManeuverPlan.get_fields_and_field_types())
    paths = [p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]]
    paths += [v["topicPath"] for k, v in panels.items() if k.startswith("RawMessages!")]
    assert len(paths) == 3
    for path in paths:
        topic, field = path.split(".", 1)
        assert topic == "/guidance/maneuver_plan" and field in fields


def test_visualisation_off_creates_no_topics(ros_env, python_exe, tmp_path):
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "record:=false", "-p", "model_path:=none",
                             "-p", "visualization:=false"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client("art_guidance_viz_off_client")
    try:
        assert client.wait_matched(60.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert client.plan_for(stamp, timeout_s=60.0) is not None
        names = {n for n, _ in client.node.get_topic_names_and_types()}
        assert "/guidance/maneuver_plan" in names
        assert not any(n.startswith("/guidance/viz") for n in names)
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
