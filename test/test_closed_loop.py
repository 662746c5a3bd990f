"""End to end: `art-guidance demo` runs the guidance node and the simulator as two processes."""
from __future__ import annotations

import json
import subprocess

import pytest

from art_guidance.replay import replay

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_demo_reaches_the_waypoint_and_its_log_replays(ros_env, python_exe, tmp_path):
    out = subprocess.run([python_exe, "-m", "art_guidance.cli", "demo", "--out", str(tmp_path),
                          "--seed", "1", "--timeout", "400"],
                         env=ros_env, capture_output=True, text=True, timeout=500)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    run = next(tmp_path.glob("run_*"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["reached"] and summary["miss_m"] < 50.0
    assert summary["n_plans_received"] >= 1 and summary["n_plans_failed"] == 0
    assert summary["min_safety_margin_m"] > 0.0
    assert (run / "rendezvous.png").stat().st_size > 10_000
    report = replay(run / "mcap")
    assert report["solves"] == summary["n_plans_received"]
    assert report["mismatched"] == 0 and report["matched"] == report["compared"]
