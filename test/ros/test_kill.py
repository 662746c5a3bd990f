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


def test_metadata_one_visualisation_write_behind_is_told_from_a_loss():
    """A kill after a plan's views reach the file and before metadata.yaml is rewritten leaves
    metadata.yaml one views write behind: accepted; any other difference is not."""
    from collections import Counter

    from art_guidance.record.recorder import PLAN_TYPE
    from art_guidance.ros.node_outputs import VIZ_TYPE_NAMES
    from helpers.kill_campaign import _one_views_write_behind

    views = sorted(VIZ_TYPE_NAMES.items())
    plans = ("guidance/plan", PLAN_TYPE)
    info = {"topics_with_message_count": [
        {"topic_metadata": {"name": name, "type": kind}, "message_count": n}
        for (name, kind), n in [(plans, 13)] + [(v, 12) for v in views]]}
    on_disk = Counter({plans: 13, **{v: 13 for v in views}})
    assert _one_views_write_behind(on_disk, info)
    assert not _one_views_write_behind(Counter({plans: 13, **{v: 12 for v in views}}), info)
    assert not _one_views_write_behind(on_disk | Counter({plans: 14}), info)
    assert not _one_views_write_behind(on_disk | Counter({views[0]: 14}), info)
