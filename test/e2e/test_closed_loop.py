"""End to end: `art-guidance demo` runs the guidance node and the simulator as two processes."""
from __future__ import annotations

import json
import subprocess

import pytest

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import ManeuverPlan  # noqa: E402

from art_guidance.record.recorder import PLAN_TYPE, REQUEST_TYPE  # noqa: E402
from art_guidance.record.replay import read_log, replay  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_demo_reaches_the_waypoint_and_its_log_replays(ros_env, second_ros_env, python_exe,
                                                       tmp_path):
    # on this process's second domain: no other run of the tests uses it (a demo's own default
    # domain comes from its process id, which another demo running at the same time may share)
    out = subprocess.run([python_exe, "-m", "art_guidance.cli", "demo", "--out", str(tmp_path),
                          "--seed", "1", "--timeout", "400",
                          "--domain-id", second_ros_env["ROS_DOMAIN_ID"]],
                         env=ros_env, capture_output=True, text=True, timeout=500)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    run = next(tmp_path.glob("run_*"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["reached"] and summary["miss_m"] < 50.0
    # A late replan may be infeasible (few nodes left, navigation and execution errors); it
    # must then leave the plan in force, which the simulator keeps flying. No replan may fail
    # with no plan in force.
    assert summary["n_plans_received"] >= 1 and summary["n_plans_failed"] == 0
    assert summary["n_replans_kept_active"] <= 3
    assert summary["min_safety_margin_m"] > 0.0
    assert (run / "rendezvous.png").stat().st_size > 10_000
    # the shipped model proposed (its rollouts are replayed below), and the demo compared the
    # delta-v with the same seed flown from CVX warm starts only
    demo = json.loads((run / "demo_summary.json").read_text())
    assert 1 <= demo["n_art_proposed"] <= demo["n_solves"] == summary["n_plans_received"]
    assert 0 <= demo["n_art_accepted"] <= demo["n_art_proposed"]
    assert demo["cvx_only_miss_m"] < 50.0 and demo["cvx_only_total_dv_mps"] > 0.0
    report = replay(run / "mcap")
    assert "sha256 matches" in report["model"]
    assert report["solves"] == summary["n_plans_received"]
    assert report["mismatched"] == 0 and report["matched"] == report["compared"]
    in_force = ""
    log = read_log(run / "mcap")
    assert len(log.of_type(REQUEST_TYPE)) == 1  # one request, however many solves under it
    for plan in log.of_type(PLAN_TYPE):
        # a usable plan is in force unless the end game's cost cap left it out (it then
        # names the plan in force, which its status text says stays)
        if plan.status in (ManeuverPlan.STATUS_CONVERGED, ManeuverPlan.STATUS_MAX_ITERATIONS) \
                and plan.active_plan_id == plan.plan_id:
            in_force = plan.plan_id
        assert plan.active_plan_id == in_force, plan.status_text
