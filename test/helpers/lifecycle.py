"""The managed guidance node from a test: started in its own process (`start_managed`), and its
change_state / get_state services called from a test client (`Lifecycle`).

Under load Fast DDS may drop a service reply whose writer has not matched the client's reader
yet ("failed to send response (timeout)" in the node's log): the request was served, its answer
never comes. `Lifecycle` asks get_state again (harmless) and judges a change_state whose answer
is lost by the state it left (asking again would request a second transition)."""
from __future__ import annotations

import subprocess
import time

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState

ATTEMPT_S = 10.0  # a reply not back after this long is taken for lost


def call(srv, request, timeout_s: float = 60.0):
    """A service call's result, or None after `timeout_s` (the client's executor spins in its
    own thread)."""
    future = srv.call_async(request)
    end = time.monotonic() + timeout_s
    while not future.done() and time.monotonic() < end:
        time.sleep(0.02)
    return future.result() if future.done() else None


def start_managed(python_exe: str, env: dict, *params: str) -> subprocess.Popen:
    """The managed node in its own process, with `-p` parameters ("name:=value")."""
    args = [arg for param in params for arg in ("-p", param)]
    return subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--managed",
                             "--ros-args", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


class Lifecycle:
    """The managed node's change_state / get_state services, from a test client."""

    def __init__(self, client, wait_s: tuple[float, float] = (20.0, 5.0),
                 node: str = "/guidance_node", timeout_s: float = 60.0) -> None:
        """`wait_s`: how long to wait for change_state, then get_state [s]; `node`: the node's
        full name; `timeout_s`: how long a call may take in all (a configure on a loaded
        machine takes seconds)."""
        self.node, self.timeout_s = node, timeout_s
        self.change = client.node.create_client(ChangeState, f"{node}/change_state")
        self.get = client.node.create_client(GetState, f"{node}/get_state")
        assert self.change.wait_for_service(timeout_sec=wait_s[0]), f"no {self.change.srv_name}"
        assert self.get.wait_for_service(timeout_sec=wait_s[1]), f"no {self.get.srv_name}"

    def state(self) -> int:
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            answer = call(self.get, GetState.Request(), min(ATTEMPT_S, end - time.monotonic()))
            if answer is not None:
                return answer.current_state.id
        raise AssertionError(f"no answer from {self.get.srv_name}")

    def transition(self, tid: int = 0, label: str = "", expected: int | None = None) -> bool:
        """Request a transition (by id or label): its success. A lost answer is judged by the
        state the node is in afterwards: `expected` where given, else any change from the state
        before."""
        before = self.state() if expected is None else None
        answer = call(self.change, ChangeState.Request(transition=Transition(id=tid, label=label)),
                      self.timeout_s)
        if answer is not None:
            return answer.success
        now = self.state()
        return now == expected if expected is not None else now != before
