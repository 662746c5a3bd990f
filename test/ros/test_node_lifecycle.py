"""The managed (lifecycle) guidance node over real DDS: plans only when configured and active."""
from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from helpers.ros_client import Client  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


def _call(client, srv, request, timeout_s: float = 60.0):
    future = srv.call_async(request)
    end = time.monotonic() + timeout_s
    while not future.done() and time.monotonic() < end:
        time.sleep(0.02)
    assert future.done(), f"no answer from {srv.srv_name}"
    return future.result()


def test_transitions_gate_planning(ros_env, python_exe, tmp_path):
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--managed",
                             "--ros-args", "-p", f"record_dir:={tmp_path / 'bag'}"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client("lifecycle_client")
    try:
        change = client.node.create_client(ChangeState, "/guidance_node/change_state")
        get = client.node.create_client(GetState, "/guidance_node/get_state")
        assert change.wait_for_service(timeout_sec=60.0) and get.wait_for_service(20.0)

        def state() -> int:
            return _call(client, get, GetState.Request()).current_state.id

        def transition(tid: int) -> bool:
            return _call(client, change, ChangeState.Request(
                transition=Transition(id=tid))).success

        assert state() == State.PRIMARY_STATE_UNCONFIGURED
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert state() == State.PRIMARY_STATE_INACTIVE
        assert not (tmp_path / "bag").exists() or not list((tmp_path / "bag").glob("*.mcap"))
        assert transition(Transition.TRANSITION_ACTIVATE)
        assert client.wait_matched(60.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning" and client.plan_for(stamp, 30.0) is not None

        assert transition(Transition.TRANSITION_DEACTIVATE)
        assert state() == State.PRIMARY_STATE_INACTIVE
        stamp, decision = client.send_nav(NOMINAL_RTN, attempts=2, wait_s=1.0, first_wait_s=1.0)
        assert decision is None  # inactive: not subscribed, nothing planned

        assert transition(Transition.TRANSITION_ACTIVATE)  # and back
        stamp, decision = client.send_nav(NOMINAL_RTN + [0.0, 500.0, 0, 0, 0, 0])
        assert decision == "replanning" and client.plan_for(stamp, 30.0) is not None

        assert transition(Transition.TRANSITION_DEACTIVATE)
        assert transition(Transition.TRANSITION_CLEANUP)
        assert state() == State.PRIMARY_STATE_UNCONFIGURED
        assert (tmp_path / "bag" / "metadata.yaml").is_file()  # recording finished on cleanup
        assert transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
        assert state() == State.PRIMARY_STATE_FINALIZED
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
