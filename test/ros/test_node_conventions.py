"""ROS 2 conventions of the guidance node over real DDS: parameters, QoS, statuses, shutdown."""
from __future__ import annotations

import math
import signal
import subprocess
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState  # noqa: E402
from helpers.ros_client import Client, nav_msg  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from art_guidance import topics  # noqa: E402
from art_guidance.config import ScenarioConfig  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


@pytest.fixture(scope="module")
def node_proc(ros_env, python_exe):
    # a whole number for a double parameter, as `ros2 run ... -p max_nav_age_s:=5` passes it
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "max_nav_age_s:=5", "-p", "record:=false",
                             "-p", "solve_deadline_s:=10", "-p", "model_path:=none"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def client(node_proc):
    c = Client("conventions_client")
    assert c.wait_matched(60.0), "guidance node did not match within 60 s"
    params = AsyncParameterClient(c.node, "guidance_node")
    assert params.wait_for_services(timeout_sec=10.0)
    c.params = params
    yield c
    c.close()


def _result(future, timeout_s: float = 10.0):
    end = time.monotonic() + timeout_s
    while not future.done() and time.monotonic() < end:
        time.sleep(0.02)
    assert future.done(), "parameter service did not answer"
    return future.result()


def test_whole_number_for_a_double_and_descriptors(client):
    value = _result(client.params.get_parameters(["max_nav_age_s"])).values[0]
    # kept as given (dynamic typing); the node reads it as 5.0 s (see the next test)
    assert (value.type, value.integer_value) == (ParameterType.PARAMETER_INTEGER, 5)
    described = _result(client.params.describe_parameters(
        ["max_nav_age_s", "record", "stamp_check"])).descriptors
    by_name = {d.name: d for d in described}
    assert "[s]" in by_name["max_nav_age_s"].description
    assert not by_name["max_nav_age_s"].read_only and by_name["record"].read_only
    assert by_name["stamp_check"].additional_constraints == "one of: wallclock, order, off"


def test_runtime_changes_apply_and_invalid_ones_are_refused(client):
    old = time.time_ns() - 8_000_000_000  # 8 s old: stale under max_nav_age_s = 5
    client.nav_pub.publish(nav_msg(old, NOMINAL_RTN))
    assert client.decision_for(old) == "rejected"
    results = _result(client.params.set_parameters(
        [Parameter("max_nav_age_s", Parameter.Type.INTEGER, 20)])).results
    assert results[0].successful
    old = time.time_ns() - 8_000_000_000
    client.nav_pub.publish(nav_msg(old, NOMINAL_RTN))
    assert client.decision_for(old) == "replanning"  # the new limit is in force
    bad = _result(client.params.set_parameters(
        [Parameter("stamp_check", Parameter.Type.STRING, "bogus")])).results[0]
    assert not bad.successful and "stamp_check must be one of" in bad.reason
    frozen = _result(client.params.set_parameters(
        [Parameter("record", Parameter.Type.BOOL, True)])).results[0]
    assert not frozen.successful and "read-only" in frozen.reason
    values = _result(client.params.get_parameters(["stamp_check", "max_nav_age_s"])).values
    assert values[0].string_value == "wallclock" and values[1].integer_value == 20


def test_a_replan_window_is_set_at_run_time_and_bad_ones_are_refused(client):
    for name, kind, value, reason in [
            ("replan_window_nodes", Parameter.Type.INTEGER, 1, "must be 0 (the whole"),
            ("replan_window_nodes", Parameter.Type.INTEGER, 100, "in [2, 99]"),
            ("terminal_target", Parameter.Type.STRING, "waypoint", "must be one of")]:
        bad = _result(client.params.set_parameters([Parameter(name, kind, value)])).results[0]
        assert not bad.successful and reason in bad.reason, bad.reason
    ok = _result(client.params.set_parameters(
        [Parameter("replan_window_nodes", Parameter.Type.INTEGER, 20),
         Parameter("terminal_target", Parameter.Type.STRING, "cvx")])).results
    assert all(r.successful for r in ok)
    try:
        # far off the plan in force (if any): replanned
        stamp, _ = client.send_nav(NOMINAL_RTN + np.array([400.0, -900.0, 0, 0, 0, 0]))
        plan = client.plan_for(stamp, timeout_s=30.0)
        assert plan is not None and plan.status == ManeuverPlan.STATUS_CONVERGED, plan
        assert "window of 20 of 99 nodes to a CVX target" in plan.warm_start_reason
        assert len(plan.epochs_s) == 100  # to the waypoint: the window, then CVX's burns
    finally:
        assert _result(client.params.set_parameters(
            [Parameter("replan_window_nodes", Parameter.Type.INTEGER, 0)])).results[0].successful


def test_wrongly_typed_and_long_values_are_refused_at_run_time(client, node_proc):
    """`ros2 param set` of a value of another type than the parameter's is refused (by rclpy,
    before the node's validation: the reason names the type expected and the type given), a
    100,000-character value with a short reason (the value cut, with its length); nothing
    changes and the node keeps serving."""
    names = ["terminal_target", "replan_window_nodes", "art_context", "stamp_check"]
    before = _result(client.params.get_parameters(names)).values
    for name, kind, value, expected in [
            ("terminal_target", Parameter.Type.INTEGER, 7, "STRING"),
            ("replan_window_nodes", Parameter.Type.STRING, "abc", "INTEGER"),
            ("art_context", Parameter.Type.STRING, "maybe", "BOOL"),
            ("stamp_check", Parameter.Type.BOOL, False, "STRING")]:
        bad = _result(client.params.set_parameters([Parameter(name, kind, value)])).results[0]
        assert not bad.successful and "Wrong parameter type" in bad.reason, bad.reason
        assert f"expected 'Type.{expected}'" in bad.reason, bad.reason
    long = _result(client.params.set_parameters(
        [Parameter("terminal_target", Parameter.Type.STRING, "x" * 100_000)])).results[0]
    assert not long.successful and len(long.reason) < 300, len(long.reason)
    assert long.reason.startswith("terminal_target must be one of: art, cvx, carry, got 'xxx")
    assert long.reason.endswith("... (100000 characters)"), long.reason
    assert node_proc.poll() is None
    assert _result(client.params.get_parameters(names)).values == before
    ok = _result(client.params.set_parameters(
        [Parameter("terminal_target", Parameter.Type.STRING, "cvx")])).results[0]
    assert ok.successful, ok.reason


def test_plans_say_what_they_are(client):
    assert ManeuverPlan().status == ManeuverPlan.STATUS_UNKNOWN  # unset never reads as success
    stamp, decision = client.send_nav(NOMINAL_RTN + [0.0, 400.0, 0, 0, 0, 0])
    plan = client.plan_for(stamp, timeout_s=30.0)
    assert plan is not None and plan.status != ManeuverPlan.STATUS_UNKNOWN
    assert plan.posthoc == ManeuverPlan.POSTHOC_NOT_RUN and math.isnan(plan.posthoc_e_r)
    # from CVX (no model), or, where the fix lands on the plan in force's node grid, from that
    # plan (replan_warm_start carry): the reason says which
    assert plan.warm_start in ("cvx", "carried"), plan.warm_start
    assert ("no learned model" if plan.warm_start == "cvx" else "carried plan-") \
        in plan.warm_start_reason, plan.warm_start_reason
    assert "m/s after" in plan.status_text or "replan not usable" in plan.status_text
    nan = NOMINAL_RTN.copy()
    nan[0] = np.nan
    stamps = [time.time_ns() + k for k in (1, 2)]
    for s in stamps:
        client.nav_pub.publish(nav_msg(s, nan))
    rejections = [client.plan_for(s, timeout_s=10.0) for s in stamps]
    assert all(r.status == ManeuverPlan.STATUS_REJECTED_INPUT for r in rejections)
    assert rejections[0].plan_id != rejections[1].plan_id  # every answer has its own id
    assert "np." not in rejections[0].status_text and "nan" in rejections[0].status_text


def test_best_effort_publisher_is_served(client):
    """A filter publishing with the sensor-data QoS (BEST_EFFORT) still gets plans."""
    pub = client.node.create_publisher(RelativeNavState, topics.NAV,
                                       QoSProfile(depth=10,
                                                  reliability=ReliabilityPolicy.BEST_EFFORT))
    try:
        for _ in range(10):
            stamp = time.time_ns()
            pub.publish(nav_msg(stamp, NOMINAL_RTN + [0.0, -300.0, 0, 0, 0, 0]))
            if client.decision_for(stamp, 2.0) is not None:
                break
        assert client.decision_for(stamp, 1.0) == "replanning"
        assert client.plan_for(stamp, timeout_s=30.0) is not None
    finally:
        client.node.destroy_publisher(pub)


def test_sigint_shuts_down_without_errors(client, node_proc):
    """Also with a solve under way: it finishes quietly after the context is gone."""
    stamp = time.time_ns()
    client.nav_pub.publish(nav_msg(stamp, NOMINAL_RTN + [0.0, 900.0, 0, 0, 0, 0]))
    assert client.decision_for(stamp) == "replanning"
    node_proc.send_signal(signal.SIGINT)
    out, _ = node_proc.communicate(timeout=30)
    assert node_proc.returncode == 0, out
    assert "Failed to publish" not in out and "Traceback" not in out, out
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in out
    # the refusal of a 100,000-character value is logged as short as it is answered
    assert max(len(line) for line in out.splitlines()) < 1000
