"""A seeded fuzz campaign against the guidance node over real DDS (`helpers.fuzz_messages`):
field-level mutations of RelativeNavState and ReplanRequest in short sequences; every message
answered, the node never stops, and a valid request and fix still get a usable plan after every
case. `art-guidance bench fuzz` runs the same campaign at scale (>= 5,000 messages)."""
from __future__ import annotations

import signal
import subprocess

import pytest

pytest.importorskip("rclpy")
from helpers.fuzz_messages import run_campaign  # noqa: E402
from helpers.processes import interrupt  # noqa: E402
from helpers.ros_client import Client  # noqa: E402

pytestmark = pytest.mark.ros
FIRST_SEED, CASES = 1000, 40  # ~240 messages; a failure names its seed: case(seed) replays it


@pytest.fixture(scope="module")
def node_proc(ros_env, python_exe):
    # stamp_check order: the mode of simulated time, where a future stamp once poisoned the
    # stamp floor; CVX only and no recording keep the solves short
    proc = subprocess.Popen([python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             "-p", "stamp_check:=order", "-p", "model_path:=none",
                             "-p", "record:=false", "-p", "visualization:=false",
                             "-p", "solve_deadline_s:=10.0"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    yield proc
    interrupt(proc, 20)


@pytest.fixture(scope="module")
def client(node_proc):
    c = Client("fuzz_client")
    assert c.wait_matched(60.0), "guidance node did not match within 60 s"
    yield c
    c.close()


def test_fuzzed_messages_never_stop_or_poison_the_node(client, node_proc):
    counts = run_campaign(client, node_proc, FIRST_SEED, CASES)
    assert counts["cases"] == CASES and counts["messages"] >= 150, counts
    assert counts["rejected"] > 0 and counts["replanning"] > 0 and counts["requests"] > 0
    node_proc.send_signal(signal.SIGINT)
    out, _ = node_proc.communicate(timeout=30)
    assert node_proc.returncode == 0, out[-2000:]
    assert "Traceback" not in out, out[-4000:]
