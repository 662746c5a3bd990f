"""A few random SIGKILLs of a recording guidance node (`art-guidance bench kill` runs many):
each folder opens as it is with rosbags and read_log, metadata.yaml agrees with the files and
every plan published before the kill is in the bag."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")
from helpers.kill_campaign import kill_once  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_random_kills_leave_readable_consistent_bags(ros_env, python_exe, tmp_path):
    for seed in (0, 1, 2):
        result = kill_once(python_exe, ros_env, tmp_path / f"bag_{seed}", seed, 4.0,
                           f"kill_client_{seed}")
        assert result["returncode"] == -9
        assert result["problems"] == [], result
