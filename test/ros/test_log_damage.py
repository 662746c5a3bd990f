"""Damaged and cut recordings: every chunk's CRC is checked, damage is named and skipped, the
intact chunks after it are read, the loss is counted against metadata.yaml, `replay` and
`bag reindex` exit non-zero when data was lost (and only then: a chunk written twice, one copy
damaged, loses nothing), and a repaired folder opens in rosbags."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers.plans import seed_plans
from helpers.ros_client import nav_msg
from mcap.reader import make_reader

from art_guidance.cli import main as cli_main
from art_guidance.record.recorder import PLAN_TYPE, SOLVE_RECORD_TYPE, McapRecorder
from art_guidance.record.reindex import has_summary, repair_bag
from art_guidance.record.replay import EXIT_LOST, EXIT_OK, read_log, replay
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg

AnyReader = pytest.importorskip("rosbags.highlevel").AnyReader
N_SOLVES = 15
# rotating at this size, a bag of N_SOLVES solves spans three files of five solves (one chunk a
# solve): the replays in these tests re-solve every solve read, so the bags are no longer
FILE_BYTES = 85_000
STAMP0 = 1_800_000_000_000_000_000


@pytest.fixture(scope="module")
def results():
    """Three real plans; the bags repeat them under new plan ids."""
    return seed_plans(range(3))


def _solve(results, k: int, parts=("nav", "record", "plan")) -> tuple[int, list]:
    s, result = results[1][k % 3]
    stamp = STAMP0 + k * 1_000_000_000
    msgs = {"nav": ("/nav/relative_state", nav_msg(stamp, s.rtn0)),
            "record": ("/guidance/solve_record",
                       solve_record_msg(result, stamp, f"plan-{k}", "test")),
            "plan": ("/guidance/maneuver_plan", plan_to_msg(result, stamp, f"plan-{k}"))}
    return stamp, [msgs[p] for p in parts]


def _bag(tmp_path: Path, results, n: int = N_SOLVES, finish: bool = True,
         max_bytes: int = 1 << 28, name: str = "bag") -> Path:
    """A recorded bag folder; without `finish` a copy of what a kill -9 between two solves
    leaves (no summary in the last file; the copy holds no recorder lock)."""
    live = tmp_path / f"{name}_live"
    rec = McapRecorder(live, {"config": results[0].config_json()}, max_bytes)
    for k in range(n):
        assert rec.record_solve(*reversed(_solve(results, k)))
    if finish:
        rec.finish()
        return live
    shutil.copytree(live, tmp_path / name)
    rec.finish()
    return tmp_path / name


def _flip(path: Path, at: int, n: int = 200, seed: int = 0) -> None:
    """XOR `n` bytes from offset `at` with nonzero random bytes (fixed seed)."""
    data = bytearray(path.read_bytes())
    noise = np.random.default_rng(seed).integers(1, 256, n, dtype=np.uint8)
    data[at:at + n] = (np.frombuffer(bytes(data[at:at + n]), np.uint8) ^ noise).tobytes()
    path.write_bytes(bytes(data))


def _summary(path: Path):
    with open(path, "rb") as fh:
        return make_reader(fh).get_summary()


def _chunk_at(path: Path, offset: int) -> tuple[int, int]:
    """(ordinal, start offset) of the chunk holding byte `offset`, from the summary of the
    intact file (mcap's reader)."""
    indexes = sorted(_summary(path).chunk_indexes, key=lambda c: c.chunk_start_offset)
    for k, index in enumerate(indexes):
        if index.chunk_start_offset <= offset < index.chunk_start_offset + index.chunk_length:
            return k, index.chunk_start_offset
    raise AssertionError(f"no chunk holds byte {offset}")


def _plan_ids(log) -> list[int]:
    return sorted(int(plan.plan_id.split("-")[1]) for _, plan in log.solves())


def _rosbags_plan_ids(bag: Path) -> list[str]:
    with AnyReader([bag]) as reader:
        return [reader.deserialize(raw, c.msgtype).plan_id for c, _, raw in reader.messages()
                if c.msgtype == PLAN_TYPE]


def _info(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def test_flipped_bytes_in_a_rotated_bag_are_named_skipped_counted_and_repaired(
        tmp_path, results, capsys):
    """200 flipped bytes in the middle of a finished 15-solve bag of three files: the solves
    before and after the damage are read (the damaged chunk is named by the summary's chunk
    index), one solve is lost, replay exits 3; reindex rebuilds the file, rosbags opens it."""
    bag = _bag(tmp_path, results, max_bytes=FILE_BYTES)
    files = sorted(bag.glob("*.mcap"), key=lambda p: p.name)
    assert len(files) == 3 and all(has_summary(f) for f in files)
    middle = files[1]
    at = middle.stat().st_size // 2
    ordinal, start = _chunk_at(middle, at)
    kept = _summary(middle).statistics.message_count - 3
    _flip(middle, at)
    log = read_log(bag)
    ids = _plan_ids(log)
    assert len(ids) == N_SOLVES - 1 and ids[0] == 0 and ids[-1] == N_SOLVES - 1
    lost_id = sorted(set(range(N_SOLVES)) - set(ids))[0]
    assert 5 <= lost_id < 10  # in the middle file; solves after it in that file are read
    assert [(d.file, d.chunk, d.offset, d.messages) for d in log.damaged] == [
        (middle.name, ordinal, start, 3)]
    assert log.truncated == []
    assert log.lost["messages"] == 3 and log.lost["solves"] == 1
    assert log.lost["by_type"] == {SOLVE_RECORD_TYPE: 1, PLAN_TYPE: 1,
                                   "art_guidance_msgs/msg/RelativeNavState": 1}
    assert log.lost["files"] == {middle.name: 3}
    report_path = tmp_path / "report.json"
    assert cli_main(["replay", str(bag), "--json", str(report_path)]) == EXIT_LOST
    out = capsys.readouterr().out
    assert f"{N_SOLVES - 1}/{N_SOLVES - 1} matched" in out
    assert f"DAMAGED: {middle.name} chunk {ordinal} at byte offset {start}" in out
    assert "lost: 3 message(s), 1 solve(s)" in out and "bag reindex" in out
    report = json.loads(report_path.read_text())
    assert report["exit_code"] == EXIT_LOST and report["mismatched"] == 0
    assert report["damaged"][0]["chunk"] == ordinal and report["lost"]["solves"] == 1

    assert cli_main(["bag", "reindex", str(bag)]) == EXIT_LOST
    out = capsys.readouterr().out
    assert f"rewrote {middle.name} with a summary: {kept} messages kept" in out
    assert f"could not recover: {middle.name}: chunk {ordinal}" in out
    assert "lost: 3 message(s), 1 solve(s)" in out
    assert sorted(p.name for p in bag.iterdir()) == [f.name for f in files] + ["metadata.yaml"]
    plan_ids = _rosbags_plan_ids(bag)  # rosbags checks chunk CRCs: it refused the damage
    assert len(plan_ids) == N_SOLVES - 1 and f"plan-{lost_id}" not in plan_ids
    with open(middle, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary().statistics.message_count == kept
        assert sum(1 for _ in reader.iter_messages()) == kept
    info = _info(bag)
    assert info["message_count"] == 3 * (N_SOLVES - 1)
    assert info["custom_data"]["art_guidance.state"] == "reindexed"
    assert info["custom_data"]["art_guidance.lost_messages"] == "3"
    assert middle.name in info["custom_data"]["art_guidance.repair"]
    repaired = read_log(bag)
    assert repaired.damaged == [] and repaired.lost["messages"] == 0
    assert "rewritten by a repair" in repaired.lost["notes"][0]
    assert repair_bag(bag, say=lambda _: None).rewritten == []  # nothing left to repair


def test_flipped_bytes_without_summary_resynchronise_on_the_next_chunk(tmp_path, results):
    """A killed recording (no summary): after the damaged chunk, reading resynchronises by
    scanning for the next chunk record that checks out; the message index after the damaged
    chunk counts its messages."""
    bag = _bag(tmp_path, results, finish=False)
    path = bag / "guidance_0.mcap"
    assert not has_summary(path)
    finished = _bag(tmp_path, results, name="finished")  # same layout, with a summary
    at = path.stat().st_size // 2
    ordinal, start = _chunk_at(finished / "guidance_0.mcap", at)
    _flip(path, at, seed=1)
    log = read_log(bag)
    ids = _plan_ids(log)
    assert len(ids) == N_SOLVES - 1 and ids[-1] == N_SOLVES - 1
    assert [(d.chunk, d.offset, d.messages) for d in log.damaged] == [(ordinal, start, 3)]
    assert log.lost["messages"] == 3 and log.lost["solves"] == 1
    (bag / "metadata.yaml").unlink()  # no metadata: the message index is all there is
    log = read_log(bag)
    assert log.lost["messages"] == 3 and log.lost["source"] == "message index"
    assert "no metadata.yaml" in log.lost["metadata"]
    repair = repair_bag(bag, say=lambda _: None)
    assert repair.data_lost and repair.rewritten == ["guidance_0.mcap"]
    assert len(_rosbags_plan_ids(bag)) == N_SOLVES - 1


def test_a_lost_first_chunk_borrows_the_channels_of_another_file(tmp_path, results):
    """The first chunk of an unsummarised file holds its schemas and channels: when it is
    damaged, the rest of the file is decoded with another file's (the recorder writes the same
    ones to every file), and the loss is counted under the right topics."""
    bag = _bag(tmp_path, results, finish=False, max_bytes=FILE_BYTES)
    twin = _bag(tmp_path, results, max_bytes=FILE_BYTES, name="twin")
    last = sorted(bag.glob("*.mcap"), key=lambda p: p.name)[-1]
    assert not has_summary(last)
    first = min(c.chunk_start_offset for c in _summary(twin / last.name).chunk_indexes)
    _flip(last, first + 100, n=50)
    log = read_log(bag)
    assert len(log.solves()) == N_SOLVES - 1
    assert [(d.file, d.chunk, d.offset) for d in log.damaged] == [(last.name, 0, first)]
    assert any("taken from guidance_0.mcap" in note for note in log.notes)
    assert log.lost["by_topic"] == {"/nav/relative_state": 1, "/guidance/solve_record": 1,
                                    "/guidance/maneuver_plan": 1}
    assert repair_bag(bag, say=lambda _: None).lost["messages"] == 3
    assert len(_rosbags_plan_ids(bag)) == N_SOLVES - 1


def test_truncated_at_half_reports_the_loss_against_metadata(tmp_path, results, capsys):
    """A file cut at half: the complete chunks before the cut are read and the cut is a torn
    end, not damage; metadata.yaml counted 15 solves, so those after the cut are reported lost,
    and replay and reindex exit 3."""
    bag = _bag(tmp_path, results, finish=False)
    path = bag / "guidance_0.mcap"
    path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
    log = read_log(bag)
    kept = len(log.solves())
    assert 0 < kept < N_SOLVES and log.truncated and log.damaged == []
    assert log.lost["solves"] == N_SOLVES - kept and log.lost["messages"] == 3 * (N_SOLVES - kept)
    report = replay(bag)
    assert report["matched"] == kept and report["exit_code"] == EXIT_LOST
    assert report["lost"]["by_type"][SOLVE_RECORD_TYPE] == N_SOLVES - kept
    assert cli_main(["bag", "reindex", str(bag)]) == EXIT_LOST
    out = capsys.readouterr().out
    assert "dropped a torn end" in out and f"{N_SOLVES - kept} solve(s)" in out
    assert len(_rosbags_plan_ids(bag)) == kept and _info(bag)["message_count"] == 3 * kept


def test_metadata_lagging_by_a_solve_is_no_loss(tmp_path, results):
    """A kill between a solve's write and the metadata.yaml rewrite: more is read than
    metadata.yaml counts; that is reported as a lag, not a loss."""
    bag = _bag(tmp_path, results, n=3, finish=False)
    info = yaml.safe_load((bag / "metadata.yaml").read_text())
    for topic in info["rosbag2_bagfile_information"]["topics_with_message_count"]:
        topic["message_count"] -= 1
    info["rosbag2_bagfile_information"]["files"][0]["message_count"] -= 3
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    log = read_log(bag)
    assert log.lost["messages"] == 0 and not log.data_lost
    assert any("lags the data" in note for note in log.lost["notes"])


def test_unmatched_records_and_plans_are_reported(tmp_path, results, capsys):
    bag = tmp_path / "bag"
    with McapRecorder(bag, {"config": results[0].config_json()}) as rec:
        for k, parts in enumerate((("nav", "record", "plan"), ("nav", "record"),
                                   ("nav", "plan"))):
            stamp, msgs = _solve(results, k, parts)
            assert rec.record_solve(msgs, stamp)
    log = read_log(bag)
    assert log.unmatched() == {"records_without_plan": ["plan-1"],
                               "plans_without_record": ["plan-2"]}
    assert log.damaged == [] and log.lost["messages"] == 0 and log.data_lost
    assert cli_main(["replay", str(bag)]) == EXIT_LOST
    out = capsys.readouterr().out
    assert "1/1 matched" in out
    assert "unmatched: 1 records without plan: plan-1" in out
    assert "unmatched: 1 plans without record: plan-2" in out


def test_a_clean_bag_exits_0_with_nothing_reported(tmp_path, results, capsys):
    bag = _bag(tmp_path, results, n=3)
    assert cli_main(["replay", str(bag), "--json", str(tmp_path / "r.json")]) == EXIT_OK
    out = capsys.readouterr().out
    assert "3/3 matched" in out
    for word in ("DAMAGED", "torn", "unmatched", "note:", "advice:"):
        assert word not in out, out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["damaged"] == [] and report["truncated"] == [] and report["advice"] == []
    assert report["lost"]["messages"] == 0 and report["lost"]["notes"] == []
    assert cli_main(["bag", "reindex", str(bag)]) == EXIT_OK
    assert "0 file(s) rewritten" in capsys.readouterr().out


def _duplicate_chunk(path: Path, k: int) -> tuple[int, int]:
    """Write chunk `k` of a file twice (what a bad copy or sync tool does): its bytes again
    right after it. Returns (its start offset, its length)."""
    index = sorted(_summary(path).chunk_indexes, key=lambda c: c.chunk_start_offset)[k]
    start, length = index.chunk_start_offset, index.chunk_length
    data = path.read_bytes()
    path.write_bytes(data[:start + length] + data[start:start + length] + data[start + length:])
    return start, length


def test_a_chunk_written_twice_loses_nothing_and_the_copy_is_dropped(tmp_path, results, capsys):
    """The footer's summary offset then points into data and the summary fails its CRC: the
    rest of the file is scanned (no intact chunk after the bogus offset is dropped), the
    second copy is dropped and named, and `bag reindex` rewrites the file with every solve
    once. The unused summary is no data loss: reindex exits 0 and records no loss."""
    bag = _bag(tmp_path, results)
    path = bag / "guidance_0.mcap"
    n_chunks = len(_summary(path).chunk_indexes)
    start, length = _duplicate_chunk(path, n_chunks // 3)
    log = read_log(bag)
    assert _plan_ids(log) == list(range(N_SOLVES))
    assert any(f"duplicates the chunk at byte offset {start}" in n for n in log.notes), log.notes
    assert [d.reason.split(":")[0] for d in log.damaged] == ["summary section"]
    assert not log.damaged[0].lost_data and "data end record" in log.damaged[0].no_loss
    assert log.lost["messages"] == 0 and not log.data_lost, log.lost
    assert cli_main(["bag", "reindex", str(bag)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "duplicates the chunk" in out and "lost: nothing" in out, out
    assert "could not recover" not in out and "dropped: guidance_0.mcap: data at" in out, out
    custom = _info(bag)["custom_data"]
    assert custom["art_guidance.lost_messages"] == "0"
    assert "1 damaged stretch(es) that lost nothing dropped" in custom["art_guidance.repair"]
    assert _info(bag)["message_count"] == 3 * N_SOLVES
    ids = _rosbags_plan_ids(bag)
    assert sorted(int(i.split("-")[1]) for i in ids) == list(range(N_SOLVES))
    assert read_log(bag).damaged == [] and _plan_ids(read_log(bag)) == list(range(N_SOLVES))


@pytest.mark.parametrize("damage", ["copy", "original", "copy_header", "another_chunk"])
def test_a_damaged_copy_of_a_chunk_read_intact_loses_nothing(tmp_path, results, capsys, damage):
    """A chunk written twice, one copy damaged (its data; or the original's; or the copy's
    header too, so only its message index tells what it held): every solve is read once, the
    damaged copy is named but nothing is lost, `bag reindex` exits 0 and records no loss.
    Damage to a chunk that has no copy is still lost and exits 3."""
    n = 12
    bag = _bag(tmp_path, results, n=n)
    path = bag / "guidance_0.mcap"
    chunks = sorted(_summary(path).chunk_indexes, key=lambda c: c.chunk_start_offset)
    other = chunks[len(chunks) // 6]
    start, length = _duplicate_chunk(path, len(chunks) // 3)
    if damage == "another_chunk":  # before the copy: its offset did not move
        _flip(path, other.chunk_start_offset + other.chunk_length // 2, n=20)
    else:
        at = start + (length if damage.startswith("copy") else 0)
        _flip(path, at + length // 2, n=20, seed=2)
        if damage == "copy_header":
            _flip(path, at + 9, n=8, seed=3)  # message_start_time: no longer the original's
    log = read_log(bag)
    lossy = [d for d in log.damaged if d.lost_data]
    if damage == "another_chunk":
        assert len(log.solves()) == n - 1 and log.data_lost
        assert [(d.offset, d.messages) for d in lossy] == [(other.chunk_start_offset, 3)]
        assert log.lost["messages"] == 3 and log.lost["solves"] == 1
        assert replay(bag)["exit_code"] == EXIT_LOST
        assert cli_main(["bag", "reindex", str(bag)]) == EXIT_LOST
        assert "lost: 3 message(s), 1 solve(s)" in capsys.readouterr().out
        assert _info(bag)["custom_data"]["art_guidance.lost_messages"] == "3"
        return
    assert _plan_ids(log) == list(range(n)) and lossy == [], log.damaged
    chunk = [d for d in log.damaged if d.chunk is not None]
    assert [(d.offset, d.messages, d.copied) for d in chunk] == [
        (start + (length if damage.startswith("copy") else 0), 0, 3)]
    # identified by its header (the same CRC as the intact copy), else by its message index
    assert ("read intact in another copy" if damage == "copy_header" else
            "the same uncompressed CRC, size and time range") in chunk[0].no_loss, chunk
    assert log.lost["messages"] == 0 and log.lost["by_topic"] == {} and not log.data_lost
    if damage == "copy":
        assert cli_main(["replay", str(bag)]) == EXIT_OK
        out = capsys.readouterr().out
        assert f"{n}/{n} matched" in out and "damaged, nothing lost (a copy of the chunk" in out
    assert cli_main(["bag", "reindex", str(bag)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "lost: nothing" in out and "could not recover" not in out, out
    info = _info(bag)
    assert info["custom_data"]["art_guidance.lost_messages"] == "0"
    assert "2 damaged stretch(es) that lost nothing" in info["custom_data"]["art_guidance.repair"]
    assert info["message_count"] == 3 * n
    repaired = read_log(bag)
    assert repaired.damaged == [] and _plan_ids(repaired) == list(range(n))
    assert repaired.metadata_check() == ("sealed", [])  # the rewrite keeps the seal
