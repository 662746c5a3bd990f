"""The guidance node over real DDS, in its own process: plans, bad input, bursts."""
from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import (  # noqa: E402
    ManeuverPlan, RelativeNavState, ReplanRequest,
)
from helpers.ros_client import Client, nav_msg  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


@pytest.fixture(scope="module")
def node_proc(ros_env, python_exe):
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "solve_deadline_s:=10.0"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    yield proc
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.fixture(scope="module")
def client(node_proc):
    c = Client()
    assert c.wait_matched(60.0), "guidance node did not match within 60 s"
    yield c
    c.close()


def test_plan_arrives_for_nav_state(client, node_proc):
    stamp, decision = client.send_nav(NOMINAL_RTN)
    assert decision == "replanning"
    plan = client.plan_for(stamp, timeout_s=30.0)
    assert plan is not None, "no plan within 30 s"
    assert plan.status in (ManeuverPlan.STATUS_CONVERGED, ManeuverPlan.STATUS_MAX_ITERATIONS)
    n = len(plan.epochs_s)
    assert n == 100 and len(plan.dv_rtn_mps) == 3 * n and len(plan.rtn) == 6 * n
    rtn = np.asarray(plan.rtn).reshape(n, 6)
    assert np.allclose(rtn[0], NOMINAL_RTN, atol=1e-6)
    assert np.allclose(rtn[-1, :3], [0.0, 750.0, 0.0], atol=50.0)  # pre-burn, near +V-bar
    assert plan.cost_mps == pytest.approx(
        np.linalg.norm(np.asarray(plan.dv_rtn_mps).reshape(n, 3), axis=1).sum(), rel=1e-9)
    assert node_proc.poll() is None


def test_unusable_replan_keeps_the_plan_in_force(client, node_proc):
    """A replan that cannot be made safe never replaces the active plan, and says so."""
    stamp, decision = client.send_nav(NOMINAL_RTN + [300.0, 0, 0, 0, 0, 0])  # off the plan
    assert decision == "replanning"
    first = client.plan_for(stamp, timeout_s=30.0)
    assert first is not None and first.status in (ManeuverPlan.STATUS_CONVERGED,
                                                  ManeuverPlan.STATUS_MAX_ITERATIONS)
    assert first.active_plan_id == first.plan_id
    # 300 m from the target, inside the 1 km approach ellipsoid: no burn can make it safe
    inside = np.array([0.0, 300.0, 0.0, 0.0, 0.0, 0.0])
    stamp = time.time_ns()
    client.nav_pub.publish(nav_msg(stamp, inside))
    assert client.decision_for(stamp) == "replanning"
    failed = client.plan_for(stamp, timeout_s=30.0)
    assert failed is not None and failed.status == ManeuverPlan.STATUS_INFEASIBLE
    assert failed.constraint_margin_m < 0.0
    assert failed.active_plan_id == first.plan_id
    assert f"plan {first.plan_id} stays in force" in failed.status_text
    diag = client.wait_for(lambda _, diags: next(
        (v for _, v, n in diags if n == "art_guidance/plan"
         and v.get("plan_id") == failed.plan_id), None), 10.0)
    assert diag["action"] == "kept_active_plan" and diag["active_plan_id"] == first.plan_id
    assert node_proc.poll() is None


def _bad_messages(now: int) -> dict[str, RelativeNavState]:
    nan = NOMINAL_RTN.copy()
    nan[1] = np.nan
    non_psd = np.diag([25.0, 400.0, 25.0, 1e-4, 1e-4, 1e-4])
    non_psd[0, 0] = -5.0
    bad_repr = nav_msg(now + 3, NOMINAL_RTN)
    bad_repr.representation = 7
    chief = np.array(ScenarioConfig().chief_oe)
    chief[1] = 1.2
    eccentric, far = chief.copy(), chief.copy()
    eccentric[1], far[1], far[0] = 0.95, 5.58e-4, 1e12
    bad_nanosec = nav_msg(now + 10, NOMINAL_RTN)
    bad_nanosec.header.stamp.nanosec = 1_500_000_000
    return {
        "empty_frame": nav_msg(now + 7, NOMINAL_RTN, frame_id=""),
        "huge_covariance": nav_msg(now + 8, NOMINAL_RTN, cov=1e300 * np.eye(6)),
        "perigee_inside_earth": nav_msg(now + 9, NOMINAL_RTN, chief_oe=eccentric),
        "semi_major_axis_1e12": nav_msg(now + 11, NOMINAL_RTN, chief_oe=far),
        "nanosec": bad_nanosec,
        "nan": nav_msg(now + 1, nan),
        "non_psd": nav_msg(now + 2, NOMINAL_RTN, cov=non_psd),
        "representation": bad_repr,
        "frame": nav_msg(now + 4, NOMINAL_RTN, frame_id="map"),
        "stale": nav_msg(now - 60_000_000_000, NOMINAL_RTN),
        "future": nav_msg(now + 60_000_000_000, NOMINAL_RTN),
        "absurd": nav_msg(now + 5, np.array([1e9, 0, 0, 0, 0, 0])),
        "hyperbolic_chief": nav_msg(now + 6, NOMINAL_RTN, chief_oe=chief),
    }


def test_bad_messages_are_rejected_and_node_keeps_serving(client, node_proc):
    now = time.time_ns()
    bad = list(_bad_messages(now).items())
    for first in range(0, len(bad), 6):  # bursts within the node's nav queue (depth 10)
        chunk = bad[first:first + 6]
        for _, msg in chunk:
            client.nav_pub.publish(msg)
        for name, msg in chunk:
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            assert client.decision_for(stamp) == "rejected", name
            status = client.plan_for(stamp, timeout_s=5.0)
            assert status is not None and status.status == ManeuverPlan.STATUS_REJECTED_INPUT, \
                name
            assert status.status_text, name
    good = time.time_ns()
    client.nav_pub.publish(nav_msg(good, NOMINAL_RTN + [50.0, 0, 0, 0, 0, 0]))
    assert client.decision_for(good) in ("replanning", "on_plan")
    assert node_proc.poll() is None


def test_fuzzed_fatal_sequences_are_refused_and_change_nothing(client, node_proc):
    """Two sequences fuzzing found fatal: a request with a horizon below 0.01 orbits, and an
    RTN fix with a finite but huge radial component followed by a valid request."""
    def request_diag(since: float):
        return client.wait_for(lambda _, diags: next(
            (v for t, v, n in diags if n == "art_guidance/replan_request" and t >= since),
            None), 10.0)

    since = time.monotonic()
    client.req_pub.publish(ReplanRequest(waypoint="plus_vbar", chance_constrained=True,
                                         horizon_orbits=0.005))
    diag = request_diag(since)
    assert diag is not None and "horizon_orbits" in diag.get("reason", ""), diag
    since = time.monotonic()
    client.req_pub.publish(ReplanRequest(waypoint="custom", chance_constrained=True,
                                         target_rtn=[0.0, 750.0, 0.0, 1e9, 0.0, 0.0]))
    diag = request_diag(since)
    assert diag is not None and "target speed" in diag.get("reason", ""), diag
    huge = time.time_ns()
    client.nav_pub.publish(nav_msg(huge, [1e308, 0, 0, 0, 0, 0]))
    assert client.decision_for(huge) == "rejected"
    since = time.monotonic()
    client.req_pub.publish(ReplanRequest(waypoint="plus_vbar", chance_constrained=True))
    diag = request_diag(since)
    assert diag is not None and diag.get("waypoint") == "plus_vbar", diag
    stamp, decision = client.send_nav(NOMINAL_RTN)
    assert decision == "replanning"
    assert client.plan_for(stamp, timeout_s=30.0) is not None
    assert node_proc.poll() is None


@pytest.mark.slow
def test_burst_keeps_node_responsive_and_plans_newest(client, node_proc):
    rss_before = _rss_kb(node_proc.pid)
    rng = np.random.default_rng(3)
    stamps = []
    for _ in range(200):
        stamp = time.time_ns()
        state = NOMINAL_RTN + rng.normal(0.0, 200.0, 6) * [1, 1, 0, 0, 0, 0]
        client.nav_pub.publish(nav_msg(stamp, state))
        stamps.append(stamp)
        time.sleep(0.01)
    answered = client.wait_for(lambda _, diags: sum(
        1 for _, v, n in diags if n == "art_guidance/nav"
        and v.get("nav_stamp_ns") in {str(s) for s in stamps}) == len(stamps), 30.0)
    assert answered, "not every nav message got a decision"
    last_plan = client.plan_for(stamps[-1], timeout_s=30.0)
    assert last_plan is not None, "no plan for the newest state"
    assert last_plan.status in (ManeuverPlan.STATUS_CONVERGED,
                                ManeuverPlan.STATUS_MAX_ITERATIONS)
    plans_in_burst = [p for _, p in client.plans
                      if p.header.stamp.sec * 1_000_000_000 + p.header.stamp.nanosec
                      in set(stamps)]
    assert len(plans_in_burst) < 100, "queued requests were not superseded"
    assert _rss_kb(node_proc.pid) - rss_before < 200_000  # < 200 MB growth
    assert node_proc.poll() is None


def test_params_file_is_honoured(second_ros_env, python_exe, tmp_path):
    """--params-file with the packaged layout; a changed waypoint reaches the plan."""
    from art_guidance.config import default_config_dir

    text = (default_config_dir() / "guidance_node.yaml").read_text()
    params = tmp_path / "params.yaml"
    params.write_text(text.replace("default_waypoint: plus_vbar", "default_waypoint: minus_rbar")
                      .replace("record: true", "record: false"))
    env = second_ros_env  # a node apart from the module's
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "--params-file", str(params)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out = subprocess.run([python_exe, "-c", _PLAN_ONCE], env=env, capture_output=True,
                             text=True, timeout=90)
        assert out.returncode == 0, out.stdout + out.stderr
        final = np.asarray(json.loads(out.stdout.strip().splitlines()[-1]))
        assert np.allclose(final[:3], [-750.0, 0.0, 0.0], atol=60.0)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


_PLAN_ONCE = """
import json, time, numpy as np
from helpers.ros_client import Client
from art_guidance.config import ScenarioConfig
c = Client('params_probe')
assert c.wait_matched(60.0)
stamp, _ = c.send_nav(np.array(ScenarioConfig().rtn0_nominal))
plan = c.plan_for(stamp, 60.0)
print(json.dumps(np.asarray(plan.rtn).reshape(-1, 6)[-1].tolist()))
c.close()
"""


def test_bad_parameter_refuses_to_start(ros_env, python_exe):
    out = subprocess.run([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                          "-p", "stamp_check:=sometimes"], env=ros_env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2
    assert "stamp_check" in out.stderr


@pytest.mark.parametrize("form, value, reason", [
    ("plain", "numerics:=7", "numerics must be a string (one of: compiled, numpy), got 7 "
     "(an integer)"),
    ("plain", "replan_window_nodes:=abc", "replan_window_nodes must be an integer (>= 0), got "
     "'abc' (a string)"),
    ("plain", "terminal_target:=7", "terminal_target must be a string"),
    ("plain", "stamp_check:=off", "stamp_check must be a string (one of: wallclock, order, "
     "off), got False (a boolean); YAML reads an unquoted"),
    ("managed", "art_context:=maybe", "art_context must be a boolean (true or false), got "
     "'maybe' (a string)"),
])
def test_a_wrongly_typed_parameter_refuses_to_start(ros_env, python_exe, form, value, reason):
    """A start-up value of another type than the parameter's (which rclpy refuses at
    declaration) is refused as an invalid value is: one line naming the parameter, the type it
    must have and the value given, exit 2, no traceback; the managed node (through
    `art-guidance node --managed`) alike."""
    entry = (["-m", "art_guidance.ros.guidance_node"] if form == "plain"
             else ["-m", "art_guidance.cli", "node", "--managed"])
    out = subprocess.run([python_exe, *entry, "--ros-args", "-p", value], env=ros_env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stdout + out.stderr
    assert "Traceback" not in out.stdout + out.stderr, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"guidance_node: {reason}"), out.stderr


def test_a_long_refused_value_is_cut(ros_env, python_exe):
    """A 100,000-character value is refused with a short reason: the value cut, with its
    length."""
    out = subprocess.run([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                          "-p", f"terminal_target:={'x' * 100_000}"], env=ros_env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr[-2000:]
    assert len(out.stderr) < 300 and "(100000 characters)" in out.stderr, out.stderr[-2000:]
    assert out.stderr.startswith("guidance_node: terminal_target must be one of")
