"""The managed guidance node from a test: started in its own process (`start_managed`), and its
change_state / get_state services called from a test client (`Lifecycle`)."""
from __future__ import annotations

import subprocess
import time

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState


def call(srv, request, timeout_s: float = 60.0):
    """A service call's result, waited for up to `timeout_s` (the client's executor spins in
    its own thread)."""
    future = srv.call_async(request)
    end = time.monotonic() + timeout_s
    while not future.done() and time.monotonic() < end:
        time.sleep(0.02)
    assert future.done(), f"no answer from {srv.srv_name}"
    return future.result()


def start_managed(python_exe: str, env: dict, *params: str) -> subprocess.Popen:
    """The managed node in its own process, with `-p` parameters ("name:=value")."""
    args = [arg for param in params for arg in ("-p", param)]
    return subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--managed",
                             "--ros-args", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


class Lifecycle:
    """The managed node's change_state / get_state services, from a test client."""

    def __init__(self, client, wait_s: tuple[float, float] = (20.0, 5.0)) -> None:
        """`wait_s`: how long to wait for change_state, then get_state [s]."""
        self.change = client.node.create_client(ChangeState, "/guidance_node/change_state")
        self.get = client.node.create_client(GetState, "/guidance_node/get_state")
        assert self.change.wait_for_service(timeout_sec=wait_s[0])
        assert self.get.wait_for_service(timeout_sec=wait_s[1])

    def state(self) -> int:
        return call(self.get, GetState.Request()).current_state.id

    def transition(self, tid: int = 0, label: str = "") -> bool:
        return call(self.change, ChangeState.Request(
            transition=Transition(id=tid, label=label))).success
