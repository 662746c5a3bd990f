"""The managed (lifecycle) guidance node over real DDS: plans only when configured and active."""
from __future__ import annotations

import contextlib
import signal
import subprocess
from typing import Iterator

import numpy as np
import pytest

pytest.importorskip("rclpy")
from helpers.lifecycle import Lifecycle, start_managed  # noqa: E402
from helpers.processes import stop_cleanly, stop_kernel_filler  # noqa: E402
from helpers.ros_client import Client  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.record.replay import read_log  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


@contextlib.contextmanager
def _running(proc: subprocess.Popen) -> Iterator[Client]:
    """A test client beside the node process; a failure inside carries the node's output."""
    client = Client("lifecycle_client")
    try:
        yield client
    except BaseException as exc:
        client.close()
        proc.kill()
        raise AssertionError(f"node output:\n{proc.communicate(timeout=30)[0]}") from exc
    client.close()


def _stop(proc: subprocess.Popen) -> str:
    """SIGINT the node; its output (asserted: exit 0, no traceback)."""
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    return out


def test_transitions_gate_planning(ros_env, python_exe, tmp_path):
    proc = start_managed(python_exe, ros_env, f"record_dir:={tmp_path / 'bag'}")
    client = Client("lifecycle_client")
    try:
        node = Lifecycle(client, wait_s=(60.0, 20.0))
        state, transition = node.state, node.transition

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
        stop_cleanly(proc)


def test_invalid_transitions_are_refused_and_node_keeps_serving(ros_env, python_exe):
    """A transition the state does not offer is answered success=False (rclpy's own handler
    raises out of spin): unknown ids, labels and transitions after shutdown included."""
    proc = start_managed(python_exe, ros_env, "record:=false")
    with _running(proc) as client:
        node = Lifecycle(client)
        assert not node.transition(Transition.TRANSITION_DEACTIVATE)  # while unconfigured
        assert not node.transition(99)  # no such transition
        assert not node.transition(label="activate")  # by label, while unconfigured
        assert node.state() == State.PRIMARY_STATE_UNCONFIGURED and proc.poll() is None
        assert node.transition(Transition.TRANSITION_CONFIGURE)
        assert not node.transition(Transition.TRANSITION_CONFIGURE)  # already configured
        assert node.transition(label="activate")
        assert node.state() == State.PRIMARY_STATE_ACTIVE
        assert client.wait_matched(20.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning" and client.plan_for(stamp, 30.0) is not None
        assert node.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
        assert node.state() == State.PRIMARY_STATE_FINALIZED
        for tid in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_CLEANUP, 99):
            assert not node.transition(tid), tid  # nothing after shutdown
        assert node.state() == State.PRIMARY_STATE_FINALIZED and proc.poll() is None
    out = _stop(proc)
    assert ("lifecycle transition deactivate (id 4) refused: not valid in state "
            "'unconfigured'") in out, out
    assert "callback_error (id 99) refused" in out and "'finalized'" in out, out


def test_configure_after_cleanup_records_a_new_bag_beside_the_first(ros_env, python_exe,
                                                                    tmp_path):
    """configure -> cleanup -> configure with an explicit record_dir that now holds a bag: the
    second configuration records to <record_dir>_2 (the first bag is never written again),
    and says so in the log and on /diagnostics."""
    bag, bag2 = tmp_path / "bag", tmp_path / "bag_2"
    proc = start_managed(python_exe, ros_env, f"record_dir:={bag}")
    plans = []
    with _running(proc) as client:
        node = Lifecycle(client)
        for k, where in enumerate((bag, bag2)):
            assert node.transition(Transition.TRANSITION_CONFIGURE), where
            assert node.transition(Transition.TRANSITION_ACTIVATE), where
            assert client.wait_matched(20.0)
            stamp, decision = client.send_nav(NOMINAL_RTN + [0.0, 300.0 * k, 0, 0, 0, 0])
            plan = client.plan_for(stamp, 30.0)
            assert decision == "replanning" and plan is not None, where
            plans.append(plan)
            diag = client.wait_for(lambda _, diags: next(
                (v for _, v, n in diags if n == "art_guidance/plan"
                 and v.get("nav_stamp_ns") == str(stamp)), None), 10.0)
            assert diag is not None and diag["record_dir"] == str(where), diag
            assert node.transition(Transition.TRANSITION_DEACTIVATE), where
            assert node.transition(Transition.TRANSITION_CLEANUP), where
            assert node.state() == State.PRIMARY_STATE_UNCONFIGURED
    out = _stop(proc)
    assert f"recording every solve to {bag2} (a new bag: {bag} holds" in out, out
    for where, plan in zip((bag, bag2), plans):
        log = read_log(where)
        solves = log.solves()
        assert [p.plan_id for _, p in solves] == [plan.plan_id], where
        assert list(solves[0][1].dv_rtn_mps) == pytest.approx(list(plan.dv_rtn_mps), abs=0.0)
        assert not log.data_lost and not log.truncated, where
        assert not any(log.unmatched().values()), where
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "bag_2"]


def test_configure_on_a_cold_kernel_cache_does_not_wait_for_the_compile(
        ros_env, python_exe, tmp_path):
    """A cold kernel cache (a fresh install, a cache in RAM at every boot): configure returns
    while a background process compiles the kernels (it held the transition for 12-46 s, past a
    lifecycle manager's timeout); the node plans on the numpy path meanwhile and says so."""
    env = {**ros_env, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    proc = start_managed(python_exe, env, "record:=false")
    with _running(proc) as client:
        node = Lifecycle(client)
        assert node.transition(Transition.TRANSITION_CONFIGURE)
        assert node.transition(Transition.TRANSITION_ACTIVATE)
        assert client.wait_matched(60.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning" and client.plan_for(stamp, 60.0) is not None
    out = _stop(proc)
    configured = out.index("guidance_node planning")
    assert out.index("numerics: numpy while the kernels compile in the background") < configured
    ready = out.find("kernels ready in")
    assert ready == -1 or ready > configured, out  # never inside configure
    # the background compile, not waited for (unless it finished before the node stopped)
    stop_kernel_filler(tmp_path / "numba", wait_s=30.0 if ready == -1 else 0.0)
