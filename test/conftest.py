"""Shared fixtures: an isolated ROS 2 environment per session (own domain, logs, discovery)."""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

from art_guidance.ros.env import isolated_ros_env

TEST_ROOT = Path(__file__).resolve().parent  # on sys.path via setup.cfg `pythonpath`


def _ros_env() -> dict[str, str]:
    # Own domain per session so concurrent runs on one machine do not cross-talk.
    env = isolated_ros_env(tempfile.mkdtemp(prefix="art_guidance_ros_"),
                           100 + os.getpid() % 100)
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    return env


ROS_ENV = _ros_env()
os.environ.update(ROS_ENV)


@pytest.fixture(scope="session")
def ros_env() -> dict[str, str]:
    """Environment for child processes that must share this session's DDS domain."""
    env = dict(os.environ)
    env.update(ROS_ENV)
    env["PYTHONUNBUFFERED"] = "1"
    # child processes import the test helpers as `helpers.<module>` too
    env["PYTHONPATH"] = os.pathsep.join([str(TEST_ROOT), env.get("PYTHONPATH", "")])
    return env


@pytest.fixture(scope="module")
def horizon():
    """The paper scenario's horizon (Table I chief orbit, 1.29 orbits, 100 nodes)."""
    import numpy as np

    from art_guidance.config import ScenarioConfig
    from art_guidance.dynamics import Horizon, time_grid_s

    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    return Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))


@pytest.fixture(scope="session")
def python_exe() -> str:
    """The interpreter running the tests (the project venv)."""
    return sys.executable
