"""The simulator process against a stand-in guidance node over real DDS (separate processes).

`test/helpers/fake_guidance.py` implements the protocol trivially (a hand-made 3-node plan, or
GuidancePipeline plans over the remaining horizon every 10 fixes); the simulator runs as
`python -m art_guidance.ros.sim_node` with ROS parameters.
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess

import numpy as np
import pytest

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import ManeuverPlan  # noqa: E402

from art_guidance.errors import InputError  # noqa: E402
from art_guidance.optim import ScpStatus  # noqa: E402
from art_guidance.ros.adapters import MSG_STATUS, link_plan_from_msg  # noqa: E402
from art_guidance.cli.sim import add_parser as add_sim_parser, sim_argv  # noqa: E402
from art_guidance.sim.closed_loop import (  # noqa: E402
    SIM_EPOCH0_NS, exit_code, parse_plan, sim_stamp_ns, sim_time_s,
)

pytestmark = pytest.mark.ros
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# A run takes a few seconds on a quiet 2-core machine; a stalled loop fails by this timeout (no
# budget on the run's own time: it depends on the machine and on what shares its cores).
RUN_TIMEOUT_S = 180.0
SUMMARY_KEYS = {"miss_m", "velocity_error_mps", "total_dv_mps", "min_safety_margin_m",
                "n_replans", "n_burns", "final_t_s", "outcome", "reached", "waypoint"}


def _fake(ros_env, python_exe, *args: str) -> subprocess.Popen:
    proc = subprocess.Popen([python_exe, "-m", "helpers.fake_guidance", *args], env=ros_env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc


def _stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=30)  # DDS teardown is slow on a busy machine
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


def _run_sim(ros_env, python_exe, tmp_path, params: dict[str, str],
             timeout_s: float = RUN_TIMEOUT_S):
    png, summary = tmp_path / "run.png", tmp_path / "summary.json"
    argv = [python_exe, "-m", "art_guidance.ros.sim_node", "--ros-args",
            "-p", f"png_path:={png}", "-p", f"summary_path:={summary}"]
    for name, value in params.items():
        argv += ["-p", f"{name}:={value}"]
    out = subprocess.run(argv, env=ros_env, capture_output=True, text=True, timeout=timeout_s)
    return out, png, summary


def _summary_line(stdout: str) -> dict:
    lines = [ln for ln in stdout.strip().splitlines() if ln.startswith("{")]
    assert lines, stdout
    return json.loads(lines[-1])


def test_sim_flies_a_handmade_plan(ros_env, python_exe, tmp_path):
    """V-bar hold at +750 m; the fake answers the first fix with a 3-node plan (0, 300, 600 s,
    three 1 mm/s burns) and says on_plan afterwards. Measured: ~3 s wall, miss ~1 m."""
    fake = _fake(ros_env, python_exe, "--mode", "handmade")
    try:
        out, png, summary_path = _run_sim(
            ros_env, python_exe, tmp_path, {"rtn0": "[0.0, 750.0, 0.0, 0.0, 0.0, 0.0]"})
    finally:
        fake_out = _stop(fake)
    assert out.returncode == 0, out.stderr + fake_out
    s = _summary_line(out.stdout)
    assert SUMMARY_KEYS <= set(s)
    assert s == json.loads(summary_path.read_text())
    assert s["outcome"] == "final_epoch" and s["reached"] is True
    assert s["n_replans"] == 1 and s["n_plans_received"] == 1 and s["n_burns"] == 3
    assert s["n_steps"] == 3 and s["n_replanning"] == 1 and s["n_on_plan"] == 2
    assert s["final_t_s"] == pytest.approx(600.0, abs=1e-6)
    assert s["miss_m"] < 10.0
    assert s["commanded_dv_mps"] == pytest.approx(3e-3, rel=1e-9)
    assert abs(s["total_dv_mps"] - 3e-3) < 3e-3  # Gates errors: sigma 0.3 mm/s per axis
    assert s["min_safety_margin_m"] < 0  # a 750 m hold is inside the 1000 m approach ellipsoid
    assert png.read_bytes()[:8] == PNG_MAGIC
    assert fake.returncode == 0, fake_out


def test_lost_first_fix_is_sent_again(ros_env, python_exe, tmp_path):
    """The fake ignores the first fix (lost after discovery): the simulator re-sends request
    and fix after 2 s and the run completes as usual. Measured: ~5 s wall."""
    fake = _fake(ros_env, python_exe, "--mode", "handmade", "--drop-first", "1")
    try:
        out, _, _ = _run_sim(
            ros_env, python_exe, tmp_path, {"rtn0": "[0.0, 750.0, 0.0, 0.0, 0.0, 0.0]",
                                            "errors": "false"})
    finally:
        fake_out = _stop(fake)
    assert out.returncode == 0, out.stderr + fake_out
    assert "sending request and fix again" in out.stderr
    s = _summary_line(out.stdout)
    assert s["outcome"] == "final_epoch" and s["n_steps"] == 3 and s["n_replans"] == 1
    assert s["total_dv_mps"] == pytest.approx(3e-3, rel=1e-12)  # errors off: as commanded


@pytest.mark.slow
def test_closed_loop_reaches_the_waypoint(ros_env, python_exe, tmp_path):
    """Seed 0 (Table I start, +V-bar), chance-constrained plans from GuidancePipeline every
    10 fixes over the remaining horizon, navigation and Gates errors on. 100 nodes.
    Measured: miss 6.8 m, 1.97 m/s, min passive-safety margin 117 m, ~4 s loop, ~7 s wall."""
    fake = _fake(ros_env, python_exe, "--mode", "pipeline", "--replan-every", "10")
    try:
        out, png, _ = _run_sim(ros_env, python_exe, tmp_path, {"seed": "0"})
    finally:
        fake_out = _stop(fake)
    assert out.returncode == 0, out.stderr + fake_out
    s = _summary_line(out.stdout)
    assert s["outcome"] == "final_epoch" and s["reached"]
    assert s["n_burns"] == 100 and s["n_replans"] == 10 and s["n_plans_failed"] == 0
    assert s["miss_m"] < 50.0
    assert 1.0 < s["total_dv_mps"] < 4.0
    assert s["min_safety_margin_m"] is not None and np.isfinite(s["min_safety_margin_m"])
    assert s["final_t_s"] == pytest.approx(1.29 * 5509.0, rel=0.01)
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_loss_fault_over_dds_reports_the_post_fault_drift(ros_env, python_exe, tmp_path):
    """`-p fault:=loss -p fault_node:=30`: the simulator stops burning at node 30, drifts the
    truth for one orbit and reports the closest approach to the approach ellipsoid (in force
    before node 55); exit 0 because the drift stays outside."""
    fake = _fake(ros_env, python_exe, "--mode", "pipeline", "--replan-every", "10")
    try:
        out, png, summary_path = _run_sim(ros_env, python_exe, tmp_path,
                                          {"seed": "0", "fault": "loss", "fault_node": "30"})
    finally:
        fake_out = _stop(fake)
    assert out.returncode == 0, out.stderr + fake_out
    s = _summary_line(out.stdout)
    f = s["fault"]
    assert s["outcome"] == "fault_loss" and s["n_burns"] == 30 and not s["reached"]
    assert f["kind"] == "loss" and f["node"] == 30 and f["hit"] and f["n_checked"] == 1
    assert f["zone"] == "approach_ellipsoid" and f["entered"] is False
    assert f["min_margin_m"] > 0 and f["t_fault_s"] <= f["t_closest_s"]
    assert f["t_closest_s"] <= f["t_fault_s"] + 5600.0
    assert json.loads(summary_path.read_text())["fault"] == f
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_sim_without_guidance_gives_up_and_reports(ros_env, python_exe, tmp_path):
    """No guidance node: exit 1 after the discovery timeout, still a summary and a PNG.

    The argument vector comes from the `art-guidance sim` parser (YAML-quoted values).
    """
    parser = argparse.ArgumentParser()
    add_sim_parser(parser.add_subparsers())
    png, summary = tmp_path / "none.png", tmp_path / "none.json"
    args = parser.parse_args(["sim", "--waypoint", "minus_vbar", "--seed", "4",
                              "--deterministic", "--png", str(png), "--summary-json",
                              str(summary), "--step-timeout", "2"])
    argv = [python_exe, "-m", "art_guidance.ros.sim_node", *sim_argv(args)[1:]]
    out = subprocess.run(argv, env=ros_env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out.stderr
    s = _summary_line(out.stdout)
    assert s["outcome"] in ("no_guidance", "timeout_decision")  # a stale peer may linger
    assert s["reached"] is False and s["n_burns"] == 0
    assert s["waypoint"] == "minus_vbar" and s["seed"] == 4
    assert s["chance_constrained"] is False
    assert json.loads(summary.read_text()) == s
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_bad_parameter_exits_2(ros_env, python_exe, tmp_path):
    out, png, _ = _run_sim(ros_env, python_exe, tmp_path, {"waypoint": "nowhere"})
    assert out.returncode == 2
    err = json.loads(out.stderr.strip().splitlines()[-1])
    assert err["error"] == "InputError" and "waypoint" in err["message"]
    assert not png.exists()


# --------------------------------------------------------------------------- pure helpers
def test_plan_parsing_and_exit_code():
    msg = ManeuverPlan()
    stamp = sim_stamp_ns(120.5)
    assert stamp == SIM_EPOCH0_NS + 120_500_000_000
    assert sim_time_s(stamp) == pytest.approx(120.5, abs=1e-9)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
    msg.epochs_s = [0.0, 60.0, 120.0]
    msg.dv_rtn_mps = [0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, -0.1, 0.0]
    plan = parse_plan(link_plan_from_msg(msg))
    assert np.allclose(plan.epochs_s, [120.5, 180.5, 240.5]) and plan.rtn is None
    assert plan.index_at(121.2) == 0 and plan.index_at(150.0) is None
    assert plan.next_epoch_after(120.5) == 180.5 and plan.next_epoch_after(240.5) is None
    assert plan.dv_rtn_mps.shape == (3, 3)
    msg.dv_rtn_mps = msg.dv_rtn_mps[:-1]
    with pytest.raises(InputError):
        parse_plan(link_plan_from_msg(msg))
    msg.dv_rtn_mps = [0.0] * 9
    msg.epochs_s = [0.0, 60.0, 60.0]
    with pytest.raises(InputError):
        parse_plan(link_plan_from_msg(msg))
    assert exit_code("final_epoch", 10.0, 50.0) == 0
    assert exit_code("final_epoch", 60.0, 50.0) == 1
    assert exit_code("max_steps", 1.0, 50.0) == 1


def test_status_mapping_is_one_to_one():
    assert set(MSG_STATUS) == set(ScpStatus)
    values = set(MSG_STATUS.values())
    assert len(values) == len(ScpStatus)
    assert ManeuverPlan.STATUS_REJECTED_INPUT not in values
    msg = ManeuverPlan()
    for status, value in MSG_STATUS.items():
        msg.status = value
        assert link_plan_from_msg(msg).status is status
    msg.status = ManeuverPlan.STATUS_REJECTED_INPUT
    assert link_plan_from_msg(msg).rejection
    msg.status = 200  # from a newer guidance: never flown
    assert link_plan_from_msg(msg).status is ScpStatus.SOLVER_ERROR


def test_cli_options_map_to_ros_parameters():
    parser = argparse.ArgumentParser()
    add_sim_parser(parser.add_subparsers())
    args = parser.parse_args(["sim", "--waypoint", "plus_rbar", "--seed", "7", "--png",
                              "a b/p.png", "--step-timeout", "5", "--fault", "missed",
                              "--fault-node", "7", "--ros-args", "-p", "errors:=false"])
    argv = sim_argv(args)
    assert argv[:2] == ["art_guidance_sim", "--ros-args"]
    pairs = dict(a.split(":=", 1) for a in argv[2:] if ":=" in a)
    assert pairs["waypoint"] == '"plus_rbar"' and pairs["seed"] == "7"
    assert pairs["chance_constrained"] == "true" and pairs["png_path"] == '"a b/p.png"'
    assert pairs["step_timeout_s"] == "5.0" and pairs["errors"] == "false"
    assert pairs["fault"] == '"missed"' and pairs["fault_node"] == "7"
    assert argv.count("--ros-args") == 1
    assert args.func.__module__ == "art_guidance.cli.sim"
