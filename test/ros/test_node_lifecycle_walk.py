"""The managed guidance node walked through every valid lifecycle transition from every state
while navigation fixes stream in, over real DDS: what a state holds (subscriptions, the worker,
the recorder, the publishers) follows it on every transition, `shutdown` from each of the three
primary states included, and the node lives on, finalized, until SIGINT (exit 0, no traceback).

Three nodes run at once, each in its own namespace, since a finalized node cannot be brought
back: one walks configure, activate, deactivate, cleanup, configure, activate, shutdown (from
active, with the learned model and its proposal worker process), one shuts down from inactive,
one from unconfigured. A thread streams fixes to all three throughout (20 Hz each).

In-process (rclpy, no DDS): a transition whose work raises is logged and answered as an error,
and `on_error` releases everything, so the node is unconfigured and configures again.
"""
from __future__ import annotations

import signal
import subprocess
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from helpers.lifecycle import Lifecycle  # noqa: E402
from helpers.ros_client import Client, nav_msg  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.record.replay import read_log  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)
T = Transition
WALKS = {  # namespace: (node parameters, [(transition, state after it)])
    "walk_full": ([], [
        (T.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE),
        (T.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE),
        (T.TRANSITION_DEACTIVATE, State.PRIMARY_STATE_INACTIVE),
        (T.TRANSITION_CLEANUP, State.PRIMARY_STATE_UNCONFIGURED),
        (T.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE),
        (T.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE),
        (T.TRANSITION_ACTIVE_SHUTDOWN, State.PRIMARY_STATE_FINALIZED)]),
    "walk_inactive": (["model_path:=none"], [
        (T.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE),
        (T.TRANSITION_INACTIVE_SHUTDOWN, State.PRIMARY_STATE_FINALIZED)]),
    "walk_unconfigured": (["model_path:=none"], [
        (T.TRANSITION_UNCONFIGURED_SHUTDOWN, State.PRIMARY_STATE_FINALIZED)]),
}
STREAM_PERIOD_S = 0.05


class Walked:
    """One managed node process in namespace `ns`, its test client and lifecycle services."""

    def __init__(self, ns: str, python_exe: str, env: dict, params: list[str],
                 record_dir: str, index: int) -> None:
        args = [a for p in [*params, f"record_dir:={record_dir}", "solve_deadline_s:=10.0"]
                for a in ("-p", p)]
        self.ns, self.index, self.record_dir = ns, index, record_dir
        self.proc = subprocess.Popen(
            [python_exe, "-m", "art_guidance.ros.guidance_node", "--managed", "--ros-args",
             "-r", f"__ns:=/{ns}", *args], env=env, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True)
        self.client = Client(f"{ns}_client", namespace=f"/{ns}")
        self.lifecycle: Lifecycle | None = None  # its services, found at the first call
        self.sent: list[tuple[float, int]] = []  # (monotonic time, stamp) of streamed fixes
        self.lock = threading.Lock()

    def _services(self) -> Lifecycle:
        if self.lifecycle is None:
            self.lifecycle = Lifecycle(self.client, wait_s=(60.0, 60.0),
                                       node=f"/{self.ns}/guidance_node")
        return self.lifecycle

    def state(self) -> int:
        return self._services().state()

    def transition(self, tid: int, expected: int) -> bool:
        """Request a transition; a lost reply is judged by the state it left."""
        return self._services().transition(tid, expected=expected)

    def stream_one(self) -> None:
        stamp = (time.time_ns() // 10) * 10 + self.index  # unique across the three streams
        with self.lock:
            self.sent.append((time.monotonic(), stamp))
        self.client.nav_pub.publish(nav_msg(stamp, NOMINAL_RTN))

    def answered_after(self, t0: float, timeout_s: float) -> int:
        """How many of the fixes streamed after monotonic time `t0` got an
        "art_guidance/nav" status, waiting up to `timeout_s` for the first."""
        def count(_, diags):
            with self.lock:
                wanted = {str(s) for t, s in self.sent if t > t0}
            return sum(1 for _, v, name in diags
                       if name == "art_guidance/nav" and v.get("nav_stamp_ns") in wanted)
        return self.client.wait_for(count, timeout_s) or 0


def _walk(node: Walked, steps: list[tuple[int, int]]) -> None:
    assert node.state() == State.PRIMARY_STATE_UNCONFIGURED
    for tid, expected in steps:
        assert node.transition(tid, expected), (node.ns, tid)
        t_done = time.monotonic()
        assert node.state() == expected, (node.ns, tid)
        assert node.proc.poll() is None, (node.ns, tid)
        if expected == State.PRIMARY_STATE_ACTIVE:
            assert node.answered_after(t_done, 30.0) > 0, f"{node.ns}: active, no fix answered"
            # a plan published is a solve recorded: each configuration's bag holds one (on a
            # loaded machine the first plan can take longer than the fix's answer)
            assert node.client.wait_for(lambda plans, _: any(t > t_done for t, _ in plans),
                                        60.0), f"{node.ns}: active, no plan"
        else:  # fixes keep streaming into a node that must not take them (nor die of them)
            time.sleep(1.0)
            assert node.answered_after(t_done + 0.5, 0.0) == 0, (node.ns, tid)
    time.sleep(1.0)  # finalized under traffic
    assert node.proc.poll() is None and node.state() == State.PRIMARY_STATE_FINALIZED


def test_every_valid_transition_from_every_state_under_streaming_fixes(ros_env, python_exe,
                                                                       tmp_path):
    nodes = [Walked(ns, python_exe, ros_env, params, str(tmp_path / ns), k)
             for k, (ns, (params, _)) in enumerate(WALKS.items())]
    streaming = threading.Event()

    def stream() -> None:
        while not streaming.wait(STREAM_PERIOD_S):
            for node in nodes:
                node.stream_one()

    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    outputs = {}
    try:
        walkers = {}
        failures: dict[str, BaseException] = {}

        def run(node: Walked) -> None:
            try:
                _walk(node, WALKS[node.ns][1])
            except BaseException as exc:  # reported below with the node's output
                failures[node.ns] = exc

        for node in nodes:
            walkers[node.ns] = threading.Thread(target=run, args=(node,))
            walkers[node.ns].start()
        for thread in walkers.values():
            thread.join(timeout=300)
        streaming.set()
        streamer.join(timeout=5)
        for node in nodes:
            node.proc.send_signal(signal.SIGINT)
            outputs[node.ns] = node.proc.communicate(timeout=60)[0]
        for node in nodes:
            out = outputs[node.ns]
            assert not failures.get(node.ns), f"{failures[node.ns]!r}\n{out}"
            assert node.proc.returncode == 0, f"{node.ns}:\n{out}"
            assert "Traceback" not in out, f"{node.ns}:\n{out}"
            assert not any("lifecycle" in line and "failed" in line
                           for line in out.splitlines()), f"{node.ns}:\n{out}"
    finally:
        streaming.set()
        for node in nodes:
            if node.proc.poll() is None:
                node.proc.kill()
                node.proc.communicate(timeout=30)
        for i, node in enumerate(nodes):
            node.client.close(shutdown=i == len(nodes) - 1)
    # both configurations of the full walk recorded, and finished (the second by shutdown)
    full = tmp_path / "walk_full"
    for where in (full, tmp_path / "walk_full_2"):
        log = read_log(where)
        assert log.solves() and not log.data_lost and not log.truncated, where


def test_a_transition_that_raises_returns_the_node_to_unconfigured(monkeypatch, tmp_path):
    """rclpy swallows an exception of an on_* callback; the node logs it, answers ERROR and
    `on_error` releases what the failed transition had built."""
    import rclpy
    from rclpy.lifecycle import TransitionCallbackReturn

    from art_guidance.ros.guidance_node import ManagedGuidanceNode

    context = rclpy.Context()  # its own: the test clients of this process keep theirs
    rclpy.init(args=["n", "--ros-args", "-r", "__ns:=/raising", "-p", "model_path:=none",
                     "-p", f"record_dir:={tmp_path / 'bag'}"], context=context)
    node = ManagedGuidanceNode(context=context)
    try:
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        with monkeypatch.context() as patch:
            def boom() -> None:
                raise RuntimeError("injected")
            patch.setattr(node, "_start_worker", boom)
            assert node.trigger_activate() == TransitionCallbackReturn.ERROR
        assert node._state_machine.current_state[0] == State.PRIMARY_STATE_UNCONFIGURED
        assert node.nav_sub is None and node.core is None and node.out is None
        assert node.recording is None and node.pipeline is None and node._worker is None
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert node.nav_sub is not None and node.core is not None
        assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
        assert node.nav_sub is None and node.core is None
    finally:
        node.shutdown_worker()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
