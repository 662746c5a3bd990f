"""MCAP recording: independent reader (rosbags), rotation, bag metadata, failures, replay,
crash consistency and repair."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from art_guidance_msgs.msg import ReplanRequest
from helpers.ros_client import nav_msg
from helpers.rosbag2_metadata import consistency_problems, metadata_problems

from art_guidance.cli import main as cli_main
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.errors import ConfigError, InputError
from art_guidance.record.bag_metadata import METADATA_VERSION
from art_guidance.record.recorder import (
    PLAN_TYPE, REQUEST_TYPE, TOPICS, McapRecorder, ros2msg_schema,
)
from art_guidance.record.reindex import has_summary, reindex_bag
from art_guidance.record.replay import read_log, replay
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg

AnyReader = pytest.importorskip("rosbags.highlevel").AnyReader
AnyReaderError = pytest.importorskip("rosbags.highlevel").AnyReaderError


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


def _info(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def _plan_ids(bag: Path) -> list[str]:
    """Plan ids read by rosbags from the bag folder (metadata.yaml + files)."""
    with AnyReader([bag]) as reader:
        return [reader.deserialize(raw, c.msgtype).plan_id for c, _, raw in reader.messages()
                if c.msgtype == PLAN_TYPE]


def _rosbags_v9_metadata(directory: Path) -> dict:
    """metadata.yaml as rosbags writes it in version 9 (one topic with a QoS profile)."""
    from rosbags.interfaces import (
        Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime,
    )
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store, never = get_typestore(Stores.ROS2_JAZZY), QosTime(0, 0)
    qos = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
              never, never, QosLiveliness.AUTOMATIC, never, False)
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store,
                                     offered_qos_profiles=[qos])
        msg = store.types["std_msgs/msg/String"](data="hi")
        writer.write(conn, 42, store.serialize_cdr(msg, "std_msgs/msg/String"))
    return yaml.safe_load((directory / "metadata.yaml").read_text())


def test_metadata_validator_follows_rosbag2(tmp_path):
    """The test's validator refuses what Jazzy refuses and accepts what rosbags writes (v9)."""
    old = yaml.safe_load(
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n"
        "  relative_file_paths: [a.mcap]\n  duration: {nanoseconds: 1}\n"
        "  starting_time: {nanoseconds_since_epoch: 2}\n  message_count: 0\n"
        "  topics_with_message_count: []\n  compression_format: ''\n  compression_mode: ''\n")
    assert metadata_problems(old) == ["info.files: missing"]
    v9 = _rosbags_v9_metadata(tmp_path / "rosbags_bag")
    assert metadata_problems(v9) == []
    v9["rosbag2_bagfile_information"]["topics_with_message_count"][0]["topic_metadata"][
        "offered_qos_profiles"] = ""  # the pre-9 string form
    assert metadata_problems(v9) == [
        "info.topics_with_message_count[0].topic_metadata.offered_qos_profiles: "
        "must be a list from version 9"]


def test_rotation_and_rosbag2_metadata(tmp_path, solves):
    pipeline, data = solves
    bag = tmp_path / "bag"
    _record(bag, pipeline, data, max_bytes=20_000)
    files = sorted(bag.glob("*.mcap"))
    assert len(files) >= 2
    info = _info(bag)
    assert metadata_problems({"rosbag2_bagfile_information": info}) == []
    assert consistency_problems(bag) == []
    assert info["version"] == METADATA_VERSION == 9 and info["message_count"] == 9
    assert sorted(info["relative_file_paths"]) == [f.name for f in files]
    assert info["custom_data"]["art_guidance.state"] == "finished"
    assert all(has_summary(f) for f in files)
    with AnyReader([bag]) as reader:  # the folder opens as a rosbag2 bag
        assert sum(1 for _ in reader.messages()) == 9
        assert {c.topic for c in reader.connections} <= set(TOPICS)
        assert all(c.digest.startswith("RIHS01_") for c in reader.connections)


def test_folder_is_a_valid_bag_after_every_solve(tmp_path, solves):
    """No finish(): what a kill -9 between solves leaves behind opens in rosbags as it is."""
    pipeline, data = solves
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, {"config": pipeline.config_json()}, max_bytes=30_000)
    for k, (stamp, msgs) in enumerate(data, start=1):
        assert rec.record_solve(msgs, stamp)
        info = _info(bag)
        assert metadata_problems({"rosbag2_bagfile_information": info}) == []
        assert consistency_problems(bag) == []
        assert info["message_count"] == 3 * k
        assert info["custom_data"]["art_guidance.state"] == "recording"
        assert _plan_ids(bag) == [f"plan-{i}" for i in range(k)]
    assert not has_summary(rec.files[-1])  # sealed, not finished
    rec.finish()
    assert _plan_ids(bag) == ["plan-0", "plan-1", "plan-2"]


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


def test_torn_write_keeps_complete_solves_and_reindex_repairs(tmp_path, solves, capsys):
    """A kill inside the third solve's write: readers keep two solves, `bag reindex` repairs."""
    pipeline, data = solves
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, {"config": pipeline.config_json()})
    for stamp, msgs in data[:2]:
        assert rec.record_solve(msgs, stamp)
    path = rec.files[0]
    two_solves = path.read_bytes()
    # metadata.yaml is rewritten only once a solve is sealed: a kill inside the third write
    # leaves the one of two solves, so nothing it counts is lost
    metadata = (bag / "metadata.yaml").read_bytes()
    assert rec.record_solve(data[2][1], data[2][0])
    torn = path.read_bytes()[:len(two_solves) + 100]  # half of the third chunk, no ending
    rec.finish()  # releases the file lock; then the crashed state is put back
    path.write_bytes(torn)
    (bag / "metadata.yaml").write_bytes(metadata)
    log = read_log(bag)
    assert [r.plan_id for r, _ in log.solves()] == ["plan-0", "plan-1"] and log.truncated
    with pytest.raises(AnyReaderError, match="end magic"):
        _plan_ids(bag)  # rosbags needs a valid file ending
    assert cli_main(["replay", str(bag)]) == 0  # replays as it is, and says how to repair
    assert "2/2 matched" in (out := capsys.readouterr().out) and "bag reindex" in out
    assert "torn end" in out and "lost: nothing" in out and "DAMAGED" not in out
    assert path.read_bytes() == torn  # reading and replaying never modify the folder
    assert cli_main(["bag", "reindex", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "rewrote guidance_0.mcap" in out and "6 messages kept" in out
    assert "metadata.yaml" in out
    assert _plan_ids(bag) == ["plan-0", "plan-1"] and has_summary(path)
    assert metadata_problems(yaml.safe_load((bag / "metadata.yaml").read_text())) == []
    assert consistency_problems(bag) == [] and _info(bag)["message_count"] == 6
    assert sorted(p.name for p in bag.iterdir()) == ["guidance_0.mcap", "metadata.yaml"]
    assert reindex_bag(bag, say=lambda _: None) == 0  # nothing left to rebuild


def test_reindex_leaves_a_live_recording_alone(tmp_path, solves, capsys):
    pipeline, data = solves
    with McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()}) as rec:
        assert rec.record_solve(data[0][1], data[0][0])
        before = rec.files[0].read_bytes()
        with pytest.raises(InputError, match="running recorder"):
            reindex_bag(tmp_path / "bag")
        assert cli_main(["bag", "reindex", str(tmp_path / "bag")]) == 2
        assert rec.files[0].read_bytes() == before
    assert capsys.readouterr().out == ""


def test_resolved_topics_and_the_request_link(tmp_path, solves):
    """Topics as the node resolved them (a namespace); replay finds messages by type; the
    request is recorded once and every solve under it links to it by stamp."""
    pipeline, data = solves
    topics = {f"/chaser{t}": msg_type for t, msg_type in TOPICS.items()}
    request = ReplanRequest(waypoint="plus_vbar")
    request.header.stamp.sec = 1_700_000_000
    rec = McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()}, topics=topics)
    for k, (stamp, msgs) in enumerate(data):
        msgs = [(f"/chaser{t}", m) for t, m in msgs]
        msgs[1][1].request_stamp.sec = 1_700_000_000 if k else 0
        if k == 1:
            msgs.insert(1, ("/chaser/guidance/replan_request", request))
        assert rec.record_solve(msgs, stamp)
    rec.finish()
    for _, msgs in data:  # the fixture is shared
        msgs[1][1].request_stamp.sec = 0
    with AnyReader([tmp_path / "bag"]) as reader:
        assert {c.topic for c in reader.connections} == set(topics)
    log = read_log(tmp_path / "bag")
    assert len(log.of_type(REQUEST_TYPE)) == 1
    requests = [log.request_for(r) for r, _ in log.solves()]
    assert requests[0] is None and requests[1] is requests[2] is log.of_type(REQUEST_TYPE)[0]
    report = replay(tmp_path / "bag")
    assert report["matched"] == 3
    assert report["per_solve"][2]["request_stamp_ns"] == 1_700_000_000 * 10**9


def test_an_existing_recording_is_never_overwritten(tmp_path, solves):
    pipeline, msgs = solves
    _record(tmp_path / "bag", pipeline, msgs[:1])
    before = {p.name: p.read_bytes() for p in (tmp_path / "bag").iterdir()}
    with pytest.raises(ConfigError, match="already holds a recording"):
        McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()})
    assert {p.name: p.read_bytes() for p in (tmp_path / "bag").iterdir()} == before


def test_replay_of_an_art_warm_started_log(tmp_path):
    """Solves planned with a learned warm start replay with the same model: the rollout (to
    1e-6 m/s), the post hoc decision, the warm start kept and the plan match. Given another
    model, the log is reported as recorded with a different model, not as a mismatch."""
    from helpers.art_models import write_untrained_checkpoint

    from art_guidance.art.provider import ArtWarmStart

    model, other = tmp_path / "model.pt", tmp_path / "other.pt"
    sha = write_untrained_checkpoint(model, seed=0)
    write_untrained_checkpoint(other, seed=1)
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load(), provider=ArtWarmStart.load(model))
    chief = np.array(scenario.chief_oe)
    data = []
    for seed, warm_start in ((7, "art"), (8, "auto"), (9, "cvx")):
        s = sample_scenario(scenario, seed)
        result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0),
                                           s.target_rtn, warm_start=warm_start))
        assert (result.proposal is None) == (warm_start == "cvx")
        stamp = 1_800_000_000_000_000_000 + seed * 1_000_000_000
        data.append((stamp, [("/guidance/solve_record",
                              solve_record_msg(result, stamp, f"plan-{seed}", "test")),
                             ("/guidance/maneuver_plan",
                              plan_to_msg(result, stamp, f"plan-{seed}"))]))
    bag = tmp_path / "bag"
    with McapRecorder(bag, {"config": pipeline.config_json(), "model_checksum": sha}) as rec:
        for stamp, msgs in data:
            assert rec.record_solve(msgs, stamp)
    record = read_log(bag).of_type("art_guidance_msgs/msg/SolveRecord")[0]
    assert record.model_sha256 == sha and len(record.art_reward_to_go_mps) == 100
    assert record.warm_start == "art" and record.posthoc in (1, 2)
    report = replay(bag, model)
    assert report["compared"] == 3 and report["matched"] == 3, report
    assert "sha256 matches" in report["model"]
    art_rows = [r for r in report["per_solve"] if "rollout_max_abs_diff_mps" in r]
    assert len(art_rows) == 2 and all(r["rollout_max_abs_diff_mps"] <= 1e-6 for r in art_rows)
    mismatch = replay(bag, other)
    assert "replayed with other.pt" in mismatch["model"] and mismatch["mismatched"] == 0
    assert mismatch["compared"] == 1  # the CVX-requested solve only
    assert {r["reason"] for r in mismatch["per_solve"] if r["match"] is None} == {
        "recorded with a different model"}


@pytest.mark.parametrize("chance", [False, True])
def test_replay_of_an_unknown_model_falls_back_to_the_default_of_the_log_mode(tmp_path, chance):
    """A log whose model checksum no shipped model has, replayed without --model, is replayed
    with the shipped default of its own passive-safety mode (deterministic logs with the
    deterministic default), and the mismatch is reported."""
    from helpers.art_models import write_untrained_checkpoint

    from art_guidance.art.provider import DEFAULT_MODELS
    from art_guidance.record.replay import recorded_mode

    sha = write_untrained_checkpoint(tmp_path / "unknown.pt", seed=3)
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load())
    chief = np.array(scenario.chief_oe)
    s = sample_scenario(scenario, 5)
    result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
                                       chance_constrained=chance, warm_start="cvx"))
    stamp = 1_800_000_000_000_000_000
    bag = tmp_path / "bag"
    with McapRecorder(bag, {"config": pipeline.config_json(), "model_checksum": sha}) as rec:
        assert rec.record_solve([
            ("/guidance/solve_record", solve_record_msg(result, stamp, "plan-5", "test")),
            ("/guidance/maneuver_plan", plan_to_msg(result, stamp, "plan-5"))], stamp)
    mode = "chance" if chance else "deterministic"
    assert recorded_mode(read_log(bag)) == mode
    report = replay(bag)
    assert f"replayed with {DEFAULT_MODELS[mode]}" in report["model"], report["model"]
    assert report["compared"] == 1 and report["matched"] == 1, report
