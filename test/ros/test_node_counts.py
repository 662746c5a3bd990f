"""The guidance node's fix counts over real DDS: a dropped fix is told from an unanswered one."""
from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from helpers.processes import stop_cleanly  # noqa: E402
from helpers.ros_client import Client, nav_msg  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)
N_BURST, CHUNK, BAD = 60, 5, {12, 37}  # fixes, sent CHUNK at a time; indices sent with a NaN


def _decisions(client: Client) -> dict[str, dict]:
    """nav stamp -> the values of its "art_guidance/nav" status (every one the client got)."""
    return {v["nav_stamp_ns"]: v for _, v, n in list(client.diags) if n == "art_guidance/nav"}


def test_fix_counts_add_up_under_a_burst(ros_env, python_exe):
    """N fixes sent reliably: every one received and answered; the counts in the nav statuses
    and in "art_guidance/stats" add up (received = rejected + accepted decisions; each replan
    decided is solved or superseded), and a burst supersedes queued replans."""
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "nav_qos_reliability:=reliable", "-p", "record:=false"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    client = Client("counts_client")
    try:
        assert client.wait_matched(20.0)
        stamp, decision = client.send_nav(NOMINAL_RTN)  # discovery done: nothing lost after
        assert decision == "replanning"
        rng = np.random.default_rng(5)
        stamps = []
        for first in range(0, N_BURST, CHUNK):  # within the node's queue depth (10)
            chunk = []
            for k in range(first, first + CHUNK):
                state = NOMINAL_RTN + rng.normal(0.0, 200.0, 6) * [1, 1, 0, 0, 0, 0]
                if k in BAD:
                    state[0] = np.nan
                chunk.append(time.time_ns())
                client.nav_pub.publish(nav_msg(chunk[-1], state))
            stamps += chunk
            assert client.wait_for(lambda _, __: all(
                str(s) in _decisions(client) for s in chunk), 15.0), "a fix was not answered"
        answered = _decisions(client)
        last = answered[str(stamps[-1])]
        received = int(last["fixes_received"])
        assert received == len(answered) >= N_BURST + 1  # none dropped, all answered
        kinds = [v["decision"] for v in answered.values()]
        assert int(last["fixes_rejected"]) == kinds.count("rejected") == len(BAD)
        assert received == kinds.count("rejected") + kinds.count("replanning") \
            + kinds.count("on_plan")
        replans = kinds.count("replanning")

        def settled(_, diags):  # every replan decided is solved or superseded
            for _, v, n in reversed(diags):
                if n == "art_guidance/stats":
                    done = int(v["plans_solved"]) + int(v["replans_superseded"])
                    return v if done == replans else None
            return None
        stats = client.wait_for(settled, 90.0)
        assert stats is not None, [v for _, v, n in client.diags if n == "art_guidance/stats"][-3:]
        assert int(stats["fixes_received"]) == received
        assert int(stats["fixes_rejected"]) == len(BAD)
        assert int(stats["replans_superseded"]) > 0  # a burst replaces queued replans
        assert 0 < int(stats["plans_solved"]) < replans
        assert proc.poll() is None
    finally:
        client.close()
        stop_cleanly(proc)
