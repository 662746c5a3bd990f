"""MCAP recording: independent reader (rosbags), rotation, bag metadata, failures, replay,
crash consistency and repair."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from art_guidance_msgs.msg import ReplanRequest
from helpers.plans import seed_plans
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
    PLAN_TYPE, REQUEST_TYPE, TAIL, TOPICS, McapRecorder, _plain, check_cap, check_record_dir,
    free_bag_dir, ros2msg_schema,
)
from art_guidance.record.reindex import has_summary, repair_bag
from art_guidance.record.replay import EXIT_UNCOMPARED, read_log, replay
from art_guidance.record.seal import SEALING_LIBRARY
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg

AnyReader = pytest.importorskip("rosbags.highlevel").AnyReader
AnyReaderError = pytest.importorskip("rosbags.highlevel").AnyReaderError


@pytest.fixture(scope="module")
def solves():
    """Three real plans with the messages the node records for them."""
    pipeline, plans = seed_plans(range(3), chance_constrained=lambda seed: seed != 1)
    out = []
    for seed, (s, result) in enumerate(plans):
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
    assert repair_bag(bag, say=lambda _: None).rewritten == []  # nothing left to rebuild


def test_reindex_leaves_a_live_recording_alone(tmp_path, solves, capsys):
    pipeline, data = solves
    with McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()}) as rec:
        assert rec.record_solve(data[0][1], data[0][0])
        before = rec.files[0].read_bytes()
        with pytest.raises(InputError, match="running recorder"):
            repair_bag(tmp_path / "bag")
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


def test_a_new_bag_goes_beside_the_recordings(tmp_path, solves):
    """free_bag_dir (a re-configured node's next bag): the folder while it holds no
    recording, then <folder>_2, _3, ...; none is written into twice."""
    pipeline, msgs = solves
    bag = tmp_path / "bag"
    assert free_bag_dir(bag) == bag  # absent
    bag.mkdir()
    (bag / "metadata.yaml").write_text("{}")  # a bag folder finished without a solve
    assert free_bag_dir(bag) == bag
    for k, name in enumerate(["bag", "bag_2", "bag_3"]):
        target = free_bag_dir(bag)
        assert target == tmp_path / name
        _record(target, pipeline, msgs[k:k + 1])
    assert [len(read_log(tmp_path / n).solves()) for n in ("bag", "bag_2", "bag_3")] == [1, 1, 1]
    assert free_bag_dir(bag) == tmp_path / "bag_4"


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
    assert mismatch["uncompared"] == 2 and mismatch["exit_code"] == EXIT_UNCOMPARED
    assert replay(bag, other, allow_uncompared=True)["exit_code"] == 0
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


# ---------------------------------------------------------------- crash safety and disk trouble
def _plain_writer_bytes(rec: McapRecorder, solves) -> list[bytes]:
    """The same solves written by mcap's plain Writer (flushed after each solve, finished at
    the end): the byte-for-byte oracle of the single-write recorder."""
    import io

    from mcap.writer import CompressionType, Writer

    out = io.BytesIO()
    writer = Writer(out, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library=SEALING_LIBRARY)
    ids = {t: writer.register_schema(name=t, encoding="ros2msg", data=ros2msg_schema(t).encode())
           for t in rec._schemas}
    channels = {topic: writer.register_channel(
        topic=topic, message_encoding="cdr", schema_id=ids[t],
        metadata={"offered_qos_profiles": "", "topic_type_hash": rec._hashes[t]})
        for topic, t in rec.topics.items()}
    writer.add_metadata("art_guidance", rec.metadata)
    prefixes = []
    for stamp, msgs in solves:
        for topic, msg in msgs:
            data = bytes(rec._encoders[topic](_plain(msg)))
            writer.add_message(channels[topic], stamp, data, stamp)
        writer.flush()
        prefixes.append(out.getvalue())
    writer.finish()
    return prefixes + [out.getvalue()]


def test_single_write_files_are_the_plain_writer_bytes(tmp_path, solves):
    """After each solve the file is the plain Writer's bytes plus a provisional ending; after
    finish it is the plain Writer's finished file, byte for byte (summary included)."""
    pipeline, data = solves
    rec = McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()})
    expected = _plain_writer_bytes(rec, data)
    for k, (stamp, msgs) in enumerate(data):
        assert rec.record_solve(msgs, stamp)
        assert rec.files[0].read_bytes() == expected[k] + TAIL
    rec.finish()
    assert rec.files[0].read_bytes() == expected[-1] and has_summary(rec.files[0])
    assert len(rec.torn_window_ns) == len(data) - 1  # the first solve creates the file


def test_a_write_cut_at_any_page_boundary_loses_only_that_solve(tmp_path, solves):
    """Linux may end a large write early at a page boundary on SIGKILL: for every such cut of
    the third solve's write, read_log keeps the first two solves and `bag reindex` repairs."""
    pipeline, data = solves
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, {"config": pipeline.config_json()})
    for stamp, msgs in data[:2]:
        assert rec.record_solve(msgs, stamp)
    path, start = rec.files[0], rec._file.data_end
    before, metadata = path.read_bytes(), (bag / "metadata.yaml").read_bytes()
    assert rec.record_solve(data[2][1], data[2][0])
    after = path.read_bytes()
    rec.finish()
    page = 4096
    cuts = [start] + list(range((start // page + 1) * page, len(after), page))
    assert len(cuts) >= 3
    for cut in cuts:
        torn = after[:cut] + before[cut:]
        path.write_bytes(torn)
        (bag / "metadata.yaml").write_bytes(metadata)
        for p in bag.glob("*.orig"):
            p.unlink()
        ids = [r.plan_id for r, _ in read_log(bag).solves()]
        assert ids[:2] == ["plan-0", "plan-1"] and len(ids) <= 3, cut
        repair_bag(bag, say=lambda _: None)
        assert _plan_ids(bag)[:2] == ["plan-0", "plan-1"], cut
        assert consistency_problems(bag) == []


def _no_stubs(bag: Path) -> None:
    assert not list(bag.glob(".*.part")) and all(p.stat().st_size > 0 for p in bag.glob("*.mcap"))


def _full_disk_after(monkeypatch, n_bytes: int) -> list[int]:
    """os.pwrite and os.write write `n_bytes` more bytes, then fail with ENOSPC (a short write
    first, as on a filling disk); rewriting bytes inside a file still works, as on a full
    ext4 disk. Returns the budget cell (set [0] to reset)."""
    import errno
    import os as os_module

    budget = [n_bytes]
    real_pwrite, real_write = os_module.pwrite, os_module.write

    def limited(real):
        def call(fd, data, *args):
            if args and args[0] + len(data) <= os_module.fstat(fd).st_size:
                return real(fd, data, *args)  # over allocated blocks: needs no space
            if budget[0] <= 0:
                raise OSError(errno.ENOSPC, "No space left on device")
            n = real(fd, bytes(data)[:budget[0]], *args)
            budget[0] -= n
            return n
        return call
    monkeypatch.setattr(os_module, "pwrite", limited(real_pwrite))
    monkeypatch.setattr(os_module, "write", limited(real_write))
    return budget


def test_full_disk_keeps_the_folder_consistent(tmp_path, solves, monkeypatch):
    """ENOSPC in the middle of the third solve's write: the solve is reported, the file is cut
    back to two whole solves with a valid ending, metadata.yaml says so; once space is back the
    next solve goes to a new file and finish gives a state 'finished' bag."""
    pipeline, data = solves
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, {"config": pipeline.config_json()})
    for stamp, msgs in data[:2]:
        assert rec.record_solve(msgs, stamp)
    budget = _full_disk_after(monkeypatch, 5000)  # part of the chunk, then a full disk
    assert rec.record_solve(data[2][1], data[2][0]) is False
    assert "No space left" in rec.last_error and rec.errors == 1
    monkeypatch.undo()
    _no_stubs(bag)
    assert _plan_ids(bag) == ["plan-0", "plan-1"]  # as it is, with rosbags
    info = _info(bag)
    assert info["custom_data"]["art_guidance.state"] == "write_failed"
    assert "No space left" in info["custom_data"]["art_guidance.last_error"]
    assert consistency_problems(bag) == [] and info["message_count"] == 6
    budget[0] = 0
    assert rec.record_solve(data[2][1], data[2][0])  # space again: a new file
    assert [p.name for p in rec.files] == ["guidance_0.mcap", "guidance_1.mcap"]
    rec.finish()
    info = _info(bag)
    assert info["custom_data"]["art_guidance.state"] == "finished"
    assert info["custom_data"]["art_guidance.write_errors"] == "1"
    assert consistency_problems(bag) == [] and info["message_count"] == 9
    assert _plan_ids(bag) == ["plan-0", "plan-1", "plan-2"]
    assert [r.plan_id for r, _ in read_log(bag).solves()] == ["plan-0", "plan-1", "plan-2"]


def test_a_full_disk_from_the_start_leaves_no_file(tmp_path, solves, monkeypatch):
    pipeline, data = solves
    bag = tmp_path / "bag"
    bag.mkdir()
    rec = McapRecorder(bag, {"config": pipeline.config_json()})
    _full_disk_after(monkeypatch, 3000)
    assert rec.record_solve(data[0][1], data[0][0]) is False
    assert rec.record_solve(data[1][1], data[1][0]) is False
    rec.finish()
    monkeypatch.undo()
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml"] and rec.files == []
    info = _info(bag)  # says what happened: no file, two errors
    assert info["relative_file_paths"] == [] and info["message_count"] == 0
    assert info["custom_data"]["art_guidance.write_errors"] == "2"


def test_a_failed_metadata_write_undoes_the_solve(tmp_path, solves, monkeypatch):
    """metadata.yaml never lags the data: when it cannot be written the solve's data is
    taken back (here the second solve, then the first solve of a new file)."""
    import art_guidance.record.recorder as recorder_module

    pipeline, data = solves
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, {"config": pipeline.config_json()})
    assert rec.record_solve(data[0][1], data[0][0])
    one_solve = rec.files[0].read_bytes()
    real = recorder_module.write_bag_metadata

    def unwritable(directory, files, topics, custom):
        if custom["art_guidance.state"] == "recording":
            raise OSError(28, "No space left on device")
        return real(directory, files, topics, custom)
    monkeypatch.setattr(recorder_module, "write_bag_metadata", unwritable)
    assert rec.record_solve(data[1][1], data[1][0]) is False
    assert rec.files[0].read_bytes() == one_solve  # taken back
    info = _info(bag)
    assert info["custom_data"]["art_guidance.state"] == "write_failed"
    assert "No space left" in info["custom_data"]["art_guidance.last_error"]
    assert consistency_problems(bag) == [] and info["message_count"] == 3
    assert rec.record_solve(data[1][1], data[1][0]) is False  # a new file, removed again
    assert [p.name for p in bag.glob("*.mcap")] == ["guidance_0.mcap"]
    monkeypatch.undo()
    assert rec.record_solve(data[2][1], data[2][0])
    rec.finish()
    assert _plan_ids(bag) == ["plan-0", "plan-2"] and consistency_problems(bag) == []
    _no_stubs(bag)


_FSIZE_CHILD = """
import json, resource, signal, sys
from pathlib import Path
from helpers.ros_client import nav_msg
from art_guidance.record.recorder import NAV_TYPE, McapRecorder
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))
rec = McapRecorder(sys.argv[1], topics={"/nav": NAV_TYPE}, max_bytes=1 << 20)
ok = [rec.record_solve([("/nav", nav_msg(10**18 + k, [float(k)] * 6))], 10**18 + k)
      for k in range(300)]
rec.finish()
print(json.dumps({"ok": sum(ok), "failed": len(ok) - sum(ok), "error": rec.last_error}))
"""


def test_file_size_limit_in_a_real_process(tmp_path):
    """A real EFBIG (RLIMIT_FSIZE, SIGXFSZ ignored) in a child process: every solve past the
    limit is reported, no stub file, and the folder opens as it is with a finished summary."""
    import os
    import subprocess
    import sys

    bag = tmp_path / "bag"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    out = subprocess.run([sys.executable, "-c", _FSIZE_CHILD, str(bag)], env=env,
                         capture_output=True, text=True, timeout=60, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["ok"] > 10 and result["failed"] > 0 and "File too large" in result["error"]
    _no_stubs(bag)
    info = _info(bag)
    assert consistency_problems(bag) == [] and metadata_problems(
        {"rosbag2_bagfile_information": info}) == []
    with AnyReader([bag]) as reader:
        assert sum(1 for _ in reader.messages()) == info["message_count"] == result["ok"]
    assert len(read_log(bag).messages) == result["ok"]


def test_recording_cap_deletes_the_oldest_closed_files(tmp_path, solves):
    pipeline, data = solves
    bag = tmp_path / "bag"
    repeated = [(stamp + 10**9 * 3 * k, msgs) for k in range(4) for stamp, msgs in data]
    with pytest.raises(ConfigError, match="record_max_total_bytes must be 0"):
        McapRecorder(bag, max_bytes=20_000, max_total_bytes=59_999)
    rec = McapRecorder(bag, {"config": pipeline.config_json()}, max_bytes=20_000,
                       max_total_bytes=60_000)
    sizes = []
    for stamp, msgs in repeated:
        assert rec.record_solve(msgs, stamp)
        sizes.append(sum(p.stat().st_size for p in bag.glob("*.mcap")))
        assert consistency_problems(bag) == []
    rec.finish()
    info = _info(bag)
    on_disk = [p.name for p in sorted(bag.glob("*.mcap"), key=lambda p: len(p.name))]
    assert info["relative_file_paths"] == on_disk and on_disk[0] != "guidance_0.mcap"
    assert max(sizes) <= 60_000 + 20_000  # the cap plus one solve and a summary
    custom = info["custom_data"]
    kept = info["message_count"]
    assert int(custom["art_guidance.dropped_messages"]) + kept == 3 * len(repeated)
    assert int(custom["art_guidance.dropped_files"]) == len(rec.files) - len(on_disk)
    with AnyReader([bag]) as reader:
        stamps = [t for _, t, _ in reader.messages()]
    assert len(stamps) == kept and min(stamps) == info["starting_time"][
        "nanoseconds_since_epoch"]
    assert metadata_problems({"rosbag2_bagfile_information": info}) == []
    log = read_log(bag)  # files dropped by the retention rule are not reported as lost
    assert not log.data_lost and len(log.solves()) == kept // 3, (log.lost, log.notes)
    assert "retention cap dropped" in log.lost["metadata"], log.lost


def test_record_dir_is_checked_at_start_up(tmp_path):
    import os

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ConfigError, match=f"{blocker} is a file, not a folder"):
        check_record_dir(blocker / "bag")
    with pytest.raises(ConfigError, match="cannot be used: files cannot be created"):
        check_record_dir("/proc/art_guidance_bag")
    assert check_record_dir(tmp_path / "a" / "bag").is_dir()
    assert list((tmp_path / "a" / "bag").iterdir()) == []  # the probe is gone
    if os.geteuid() != 0:  # root writes to a read-only folder: the /proc case stands in
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(ConfigError, match="Permission denied"):
            check_record_dir(ro / "bag")
    with pytest.raises(ConfigError, match=">= 3 \\* record_max_bytes"):
        check_cap(10, 4096)
