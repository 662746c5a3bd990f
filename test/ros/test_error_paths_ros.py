"""ROS-side error paths that the other node tests leave out: messages and parameter values the
adapters and parameter specs refuse (naming the field), a model whose proposal carries values
that are not numbers, a managed node whose configure fails (it stays unconfigured, serves its
lifecycle services and configures once the cause is gone), and the simulator stopped by
SIGINT before a guidance node appeared or started with unparsable ROS arguments."""
from __future__ import annotations

import json
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
import rclpy  # noqa: E402
from art_guidance_msgs.msg import RelativeNavState, ReplanRequest  # noqa: E402
from helpers.lifecycle import Lifecycle, start_managed  # noqa: E402
from helpers.processes import stop_cleanly  # noqa: E402
from helpers.ros_client import nav_msg  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402

from art_guidance.config import GuidanceConfig, ScenarioConfig  # noqa: E402
from art_guidance.errors import ConfigError, InputError  # noqa: E402
from art_guidance.planning import (  # noqa: E402
    GuidancePipeline, PlanRequest, WarmStartProposal,
)
from art_guidance.ros.adapters import nav_from_msg, solve_record_msg, target_from_msg  # noqa
from art_guidance.ros.node_status import guard_change_state, transition_name  # noqa: E402
from art_guidance.ros.parameters import SPECS, check_table  # noqa: E402
from art_guidance.sim.closed_loop import WAITING_LINE  # noqa: E402
from art_guidance.config import node_parameter_defaults  # noqa: E402

pytestmark = pytest.mark.ros
SCENARIO = ScenarioConfig()
STAMP = 1_800_000_000_000_000_000


# --------------------------------------------------------------------------- adapters
def test_a_roe_fix_beyond_the_relative_range_is_refused():
    """An ROE mean within its own bound whose RTN position is beyond MAX_RANGE_M."""
    msg = nav_msg(STAMP, [0.0, 4e6, 0.0, 0.0, 0.0, 0.0],
                  representation=RelativeNavState.REPRESENTATION_ROE, frame_id="chief_roe",
                  cov=np.eye(6))
    with pytest.raises(InputError, match="mean: relative range above 500000 m") as exc:
        nav_from_msg(msg)
    assert exc.value.field == "mean"


def test_a_request_with_an_unknown_warm_start_is_refused():
    msg = ReplanRequest(waypoint="plus_vbar", warm_start="transformer")
    with pytest.raises(InputError, match=r"warm_start: must be one of \('', 'auto', 'cvx', "
                       r"'art'\) \(got 'transformer'\)"):
        target_from_msg(msg, SCENARIO.waypoints_rtn)


class _OddNumbers:
    """A model whose proposal is CVX's controls with a reward-to-go it did not compute (None)
    and a constraint-to-go that is not numbers."""

    def propose(self, problem, cvx, **kwargs) -> WarmStartProposal:
        return WarmStartProposal(np.array(cvx.dv_rtn_mps), reward_to_go_mps=None,
                                 constraint_to_go=["n/a"] * problem.horizon.n_nodes,
                                 model_sha256="odd")


def test_a_proposal_with_values_that_are_not_numbers_is_still_recorded():
    """The solve record carries what can be carried: the proposal's controls and checksum,
    empty arrays for the values that are missing or are not numbers."""
    pipeline = GuidancePipeline(GuidanceConfig.load(), provider=_OddNumbers())
    chief = np.array(SCENARIO.chief_oe)
    from art_guidance.dynamics import roe_from_rtn_linear

    result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(
        chief, np.array(SCENARIO.rtn0_nominal)), np.array(SCENARIO.waypoints_rtn["plus_vbar"]),
        warm_start="art"))
    msg = solve_record_msg(result, STAMP, "plan-1", "nav")
    assert msg.model_sha256 == "odd" and len(msg.warm_start_art_dv_rtn_mps) == 3 * len(
        result.epochs_s)
    assert list(msg.art_reward_to_go_mps) == [] and list(msg.art_constraint_to_go) == []


# --------------------------------------------------------------------------- parameters
@pytest.mark.parametrize("name, value, message", [
    ("record_max_bytes", 4096.5, "record_max_bytes must be a whole number, got 4096.5"),
    ("record", "yes", "record must be true or false, got 'yes'"),
    ("record_dir", 3, "record_dir must be a string, got 3"),
])
def test_a_parameter_value_of_the_wrong_kind_is_named(name, value, message):
    with pytest.raises(ConfigError, match=f"^{message}$"):
        SPECS[name].coerce(name, value)


def test_a_parameter_table_out_of_step_with_the_specs_is_refused():
    """config/guidance_node.yaml and the specs are checked against each other at start-up: a
    parameter in one and not the other is named."""
    defaults = node_parameter_defaults()
    check_table(defaults)
    del defaults["record"]
    with pytest.raises(ConfigError, match=r"guidance_node.yaml and the parameter specs "
                       r"differ: \['record'\]"):
        check_table(defaults)
    with pytest.raises(ConfigError, match=r"differ: \['no_such_parameter', 'record'\]"):
        check_table({**defaults, "no_such_parameter": 1})


def test_lifecycle_helpers_outside_a_lifecycle_node():
    """An unknown transition id has a name ("unknown"); a node without lifecycle services is
    left as it is by the change_state guard."""
    assert transition_name(Transition.TRANSITION_CONFIGURE) == "configure"
    assert transition_name(250) == "unknown"
    if not rclpy.ok():
        rclpy.init()
    node = rclpy.create_node("plain_node_for_the_guard")
    try:
        guard_change_state(node)
        assert getattr(node, "_service_change_state", None) is None
    finally:
        node.destroy_node()


# --------------------------------------------------------------------------- processes
def test_a_managed_node_whose_configure_fails_stays_unconfigured(ros_env, python_exe,
                                                                 tmp_path):
    """record_dir is a file: configure fails (success False, the cause logged), the node is
    unconfigured with nothing held and keeps serving its lifecycle services; once the file is
    gone, configure succeeds. SIGINT then ends it cleanly."""
    from helpers.ros_client import Client

    blocker = tmp_path / "bag"
    blocker.write_text("not a folder")
    proc = start_managed(python_exe, ros_env, f"record_dir:={blocker}")
    client = Client("configure_failure_client")
    try:
        node = Lifecycle(client, wait_s=(60.0, 20.0))
        state = node.state

        def configure() -> bool:
            return node.transition(Transition.TRANSITION_CONFIGURE)

        assert not configure()
        assert state() == State.PRIMARY_STATE_UNCONFIGURED
        assert not configure()  # the cause is still there
        blocker.unlink()
        assert configure() and state() == State.PRIMARY_STATE_INACTIVE
        assert blocker.is_dir()  # the bag folder, created by the configure that succeeded
    except BaseException:
        proc.kill()
        raise
    finally:
        client.close()
    out = stop_cleanly(proc)
    assert out.count(f"configure failed: record_dir {blocker} cannot be used: {blocker} is a "
                     "file, not a folder") == 2, out


def test_the_simulator_stopped_before_a_guidance_node_appears(ros_env, python_exe, tmp_path):
    """SIGINT while the simulator waits for a guidance node: the ROS context shuts down, the
    run ends as "shutdown" with its partial summary (stdout and summary_path) and picture,
    exit 1."""
    png, summary = tmp_path / "run.png", tmp_path / "run.json"
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.sim_node", "--ros-args",
                             "-p", "step_timeout_s:=120.0", "-p", f"png_path:={png}",
                             "-p", f"summary_path:={summary}"], env=ros_env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # the run under way: its first log line (a stop while it is set up ends without a run)
    err_lines: list[str] = []

    def read_stderr() -> None:
        for line in proc.stderr:
            err_lines.append(line)

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    end = time.monotonic() + 60.0
    while not any(WAITING_LINE in line for line in err_lines) and time.monotonic() < end:
        assert proc.poll() is None, "".join(err_lines)
        time.sleep(0.1)
    assert any(WAITING_LINE in line for line in err_lines), "the simulator never started its run"
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    reader.join(timeout=10)
    out, err = proc.stdout.read(), "".join(err_lines)
    assert proc.returncode == 1, err
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert lines, (out, err)  # the summary line
    result = json.loads(lines[-1])
    assert result["outcome"] in ("shutdown", "interrupted") and result["reached"] is False
    assert json.loads(summary.read_text()) == result
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Traceback" not in err, err


def test_the_simulator_with_unparsable_ros_arguments_exits_2(ros_env, python_exe):
    out = subprocess.run([python_exe, "-m", "art_guidance.ros.sim_node", "--ros-args", "-p",
                          "seed:="], env=ros_env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    error = json.loads(out.stderr.strip().splitlines()[-1])
    assert error["error"] == "RCLError" and error["message"], error
    assert "Traceback" not in out.stderr
