"""MCAP recording: independent reader (rosbags), rotation, bag metadata, failures, replay."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.ros_client import nav_msg

from art_guidance.cli import main as cli_main
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.data.stages import sample_scenario
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.record.recorder import TOPICS, McapRecorder, ros2msg_schema
from art_guidance.record.replay import read_log, replay
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg

AnyReader = pytest.importorskip("rosbags.highlevel").AnyReader


@pytest.fixture(scope="module")
def solves():
    """Three real plans with the messages the node records for them."""
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario))
    chief = np.array(scenario.chief_oe)
    out = []
    for seed in range(3):
        s = sample_scenario(scenario, seed)
        result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0),
                                           s.target_rtn, chance_constrained=seed != 1))
        stamp = 1_800_000_000_000_000_000 + seed * 1_000_000_000
        out.append((stamp, [("/nav/relative_state", nav_msg(stamp, s.rtn0)),
                            ("/guidance/solve_record",
                             solve_record_msg(result, stamp, f"plan-{seed}", "test")),
                            ("/guidance/maneuver_plan",
                             plan_to_msg(result, stamp, f"plan-{seed}"))]))
    return pipeline, out


def _record(directory: Path, pipeline, solves, max_bytes=1 << 28) -> McapRecorder:
    with McapRecorder(directory, {"config": pipeline.config_json()}, max_bytes) as rec:
        for stamp, msgs in solves:
            assert rec.record_solve(msgs, stamp)
    return rec


def test_schema_embeds_dependencies():
    text = ros2msg_schema("art_guidance_msgs/msg/ManeuverPlan")
    assert "MSG: std_msgs/Header" in text and "MSG: builtin_interfaces/Time" in text
    assert text.count("=" * 80) == 2


def test_rosbags_reads_every_message_with_embedded_schemas(tmp_path, solves):
    pipeline, data = solves
    rec = _record(tmp_path / "bag", pipeline, data)
    assert rec.solves == 3 and rec.errors == 0
    files = sorted((tmp_path / "bag").glob("*.mcap"))
    assert len(files) == 1
    seen = {}
    with AnyReader(files) as reader:  # raw .mcap, schemas from the file only
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            seen.setdefault(conn.topic, []).append(msg)
    assert {t: len(v) for t, v in seen.items()} == {
        "/nav/relative_state": 3, "/guidance/solve_record": 3, "/guidance/maneuver_plan": 3}
    plan = seen["/guidance/maneuver_plan"][0]
    expected = data[0][1][2][1]
    assert plan.plan_id == expected.plan_id
    np.testing.assert_array_equal(np.asarray(plan.dv_rtn_mps), np.asarray(expected.dv_rtn_mps))
    assert json.loads(seen["/guidance/solve_record"][0].request_json)["chance_constrained"]


def test_rotation_and_rosbag2_metadata(tmp_path, solves):
    pipeline, data = solves
    bag = tmp_path / "bag"
    _record(bag, pipeline, data, max_bytes=20_000)
    files = sorted(bag.glob("*.mcap"))
    assert len(files) >= 2
    meta = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta and "message_count: 9" in meta
    for f in files:
        assert f.name in meta
    with AnyReader([bag]) as reader:  # the folder opens as a rosbag2 bag
        assert sum(1 for _ in reader.messages()) == 9
        assert {c.topic for c in reader.connections} <= set(TOPICS)


def test_replay_matches_and_detects_tampering(tmp_path, solves, capsys):
    pipeline, data = solves
    _record(tmp_path / "good", pipeline, data)
    report = replay(tmp_path / "good")
    assert report["compared"] == 3 and report["matched"] == 3, report
    assert cli_main(["replay", str(tmp_path / "good")]) == 0
    stamp, msgs = data[0]
    tampered = list(msgs)
    plan = type(msgs[2][1])()
    for field in plan.get_fields_and_field_types():
        setattr(plan, field, getattr(msgs[2][1], field))
    dv = np.asarray(plan.dv_rtn_mps)
    dv[0] += 1e-3
    plan.dv_rtn_mps = dv.tolist()
    tampered[2] = ("/guidance/maneuver_plan", plan)
    _record(tmp_path / "bad", pipeline, [(stamp, tampered)])
    assert replay(tmp_path / "bad")["mismatched"] == 1
    assert cli_main(["replay", str(tmp_path / "bad"), "--json", str(tmp_path / "r.json")]) == 1
    assert json.loads((tmp_path / "r.json").read_text())["mismatched"] == 1


def test_unwritable_directory_logs_and_keeps_going(tmp_path, solves):
    pipeline, data = solves
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    rec = McapRecorder(blocker / "bag", {"config": pipeline.config_json()})
    stamp, msgs = data[0]
    assert rec.record_solve(msgs, stamp) is False
    assert rec.record_solve(msgs, stamp) is False
    assert rec.errors == 2 and "Error" in rec.last_error
    rec.finish()
    rec.finish()  # idempotent


def test_truncated_file_keeps_complete_solves(tmp_path, solves):
    pipeline, data = solves
    rec = McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()})
    for stamp, msgs in data:
        rec.record_solve(msgs, stamp)
    path = rec.files[0]
    size = path.stat().st_size
    with open(path, "ab") as fh:  # a torn record after the last complete solve
        fh.write(b"\x05\xff\xff\x00")
    log = read_log(path)
    assert len(log.solves()) == 3
    assert log.truncated and path.stat().st_size == size + 4
