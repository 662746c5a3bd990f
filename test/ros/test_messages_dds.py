"""The custom messages round-trip between two real processes over Fast DDS."""
from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from art_guidance_msgs.msg import (  # noqa: E402
    ManeuverPlan, RelativeNavState, ReplanRequest, SolveRecord,
)

pytestmark = pytest.mark.ros
MATCH_TIMEOUT_S = 10.0
RESEND_PERIOD_S = 1.0


def _sample_messages() -> dict[str, object]:
    rng = np.random.default_rng(7)
    nav = RelativeNavState()
    nav.header.stamp.sec, nav.header.frame_id = 1234, "chief_rtn"
    nav.chief_oe = rng.normal(size=6).tolist()
    nav.representation = RelativeNavState.REPRESENTATION_RTN
    nav.mean = rng.normal(size=6).tolist()
    nav.covariance = np.eye(6).reshape(-1).tolist()
    plan = ManeuverPlan()
    plan.plan_id, plan.status, plan.status_text = "plan-42", ManeuverPlan.STATUS_CONVERGED, "ok"
    plan.epochs_s = np.linspace(0, 100, 5).tolist()
    plan.dv_rtn_mps = rng.normal(size=15).tolist()
    plan.roe_m = rng.normal(size=30).tolist()
    plan.rtn = rng.normal(size=30).tolist()
    plan.cost_mps, plan.warm_start, plan.posthoc = 1.25, "art", ManeuverPlan.POSTHOC_ACCEPTED
    plan.scp_iterations, plan.constraint_margin_m = 3, 12.5
    req = ReplanRequest()
    req.waypoint, req.chance_constrained, req.horizon_orbits = "custom", True, 1.29
    req.target_rtn = [0.0, 750.0, 0.0, 0.0, 0.0, 0.0]
    req.warm_start = "auto"
    rec = SolveRecord()
    rec.plan_id, rec.trigger = "plan-42", "request"
    rec.scp_cost_history_mps = [3.0, 2.5, 2.4]
    rec.request_json = '{"seed": 1}'
    return {"nav": nav, "plan": plan, "replan": req, "record": rec}


def _fields_equal(a: object, b: object) -> bool:
    for name in a.get_fields_and_field_types():
        va, vb = getattr(a, name), getattr(b, name)
        if hasattr(va, "get_fields_and_field_types"):
            if not _fields_equal(va, vb):
                return False
        elif isinstance(va, (str, bool, int, float)):
            if va != vb:
                return False
        elif not np.array_equal(np.asarray(va), np.asarray(vb)):
            return False
    return True


def _spin_until(node: Node, cond, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return cond()


def test_messages_round_trip_between_processes(ros_env, python_exe):
    echo = subprocess.Popen([python_exe, "-m", "helpers.ros_echo"], env=ros_env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node("art_guidance_test_roundtrip")
    try:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        sent = _sample_messages()
        types = {"nav": RelativeNavState, "plan": ManeuverPlan, "replan": ReplanRequest,
                 "record": SolveRecord}
        received: dict[str, object] = {}
        pubs, subs = {}, {}
        for name, msg_type in types.items():
            pubs[name] = node.create_publisher(msg_type, f"echo/{name}_in", qos)
            subs[name] = node.create_subscription(
                msg_type, f"echo/{name}_out",
                lambda msg, n=name: received.__setitem__(n, msg), qos)
        matched = _spin_until(node, lambda: all(
            pubs[n].get_subscription_count() > 0 and subs[n].get_publisher_count() > 0
            for n in types), MATCH_TIMEOUT_S)
        assert matched, "echo process did not match within the discovery timeout"
        # Discovery is per side: this process seeing the echo's writer does not mean the echo's
        # writer has matched this reader yet, and a reliable writer drops what it sends before
        # that. Resend what has not come back (the messages are idempotent) until the timeout.
        end = time.monotonic() + MATCH_TIMEOUT_S
        while len(received) < len(sent) and time.monotonic() < end:
            for name, msg in sent.items():
                if name not in received:
                    pubs[name].publish(msg)
            _spin_until(node, lambda: len(received) == len(sent), RESEND_PERIOD_S)
        assert len(received) == len(sent), received
        for name, msg in sent.items():
            assert _fields_equal(msg, received[name]), name
        assert list(received["plan"].dv_rtn_mps) == list(sent["plan"].dv_rtn_mps)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        echo.send_signal(signal.SIGINT)
        try:
            echo.wait(timeout=10)
        except subprocess.TimeoutExpired:
            echo.kill()
    assert echo.returncode == 0, echo.stdout.read()
