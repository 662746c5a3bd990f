"""Recording and reading error paths that the other recorder tests leave out: chunks that fail
each of their checks, files that are empty, not MCAP, cut or garbled in their framing, a
metadata.yaml that is unreadable, older or out of step with the files, payloads that do not
decode, logs that cannot be replayed, and a recorder whose summary, folder or retention write
fails. Every case is reported with what failed and where; none raises out of the reader or the
recorder. The bags are real recordings (one nav fix per solve), damaged byte by byte."""
from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import yaml
import zstandard
from helpers.ros_client import nav_msg
from mcap.opcode import Opcode
from mcap.records import Chunk
from mcap.writer import Writer

from art_guidance.cli import main as cli_main
from art_guidance.errors import ConfigError, InputError
from art_guidance.record import ros2msg
from art_guidance.record.bag_folder import check_cap
from art_guidance.record.bag_metadata import bag_files
from art_guidance.record.loss import describe
from art_guidance.record.mcap_records import (
    MAGIC, BadRecord, ShortRecord, chunk_records, frame, parse,
)
from art_guidance.record.recorder import (
    NAV_TYPE, McapRecorder,
)
from art_guidance.record.reindex import has_summary, repair_bag
from art_guidance.record.replay import advice, read_log, recorded_mode, replay
from art_guidance.record.scan import SUMMARY_NOT_NEEDED, scan_file

STAMP0 = 1_800_000_000_000_000_000
NAV_TOPICS = {"/nav": NAV_TYPE}


def _fix(k: int) -> tuple[list, int]:
    """The messages and log time of solve `k`: one nav fix."""
    stamp = STAMP0 + k * 1_000_000_000
    return [("/nav", nav_msg(stamp, [float(k), 100.0, 0.0, 0.0, 0.0, 0.0]))], stamp


def _bag(tmp_path: Path, n: int = 3, finish: bool = True, name: str = "bag",
         max_bytes: int = 1 << 28, metadata: dict | None = None) -> Path:
    """A bag folder of `n` solves; without `finish` a copy taken between two solves (what a
    kill -9 leaves: no summary, a provisional ending)."""
    live = tmp_path / f"{name}_live"
    rec = McapRecorder(live, metadata, max_bytes, topics=NAV_TOPICS)
    for k in range(n):
        assert rec.record_solve(*_fix(k))
    if not finish:
        shutil.copytree(live, tmp_path / name)
    rec.finish()
    return live if finish else tmp_path / name


def _records(buf: bytes) -> list[tuple[int, int]]:
    """(offset, opcode) of the records from the header to the footer."""
    out, pos = [], len(MAGIC)
    while pos < len(buf) - len(MAGIC):
        opcode, _, end = frame(buf, pos, len(buf))
        out.append((pos, opcode))
        pos = end
    return out


def _chunks(path: Path) -> list[int]:
    return [pos for pos, op in _records(path.read_bytes()) if op == Opcode.CHUNK]


def _patch(path: Path, at: int, data: bytes) -> None:
    buf = bytearray(path.read_bytes())
    buf[at:at + len(data)] = data
    path.write_bytes(bytes(buf))


def _only_file(bag: Path) -> Path:
    (path,) = bag.glob("*.mcap")
    return path


# --------------------------------------------------------------------------- records, chunks
def test_each_chunk_check_names_what_failed(tmp_path):
    """A chunk whose compression is unknown, whose size or data is wrong, or that holds a
    record it may not hold, one cut short or one shorter than its fields: a BadRecord saying
    which; so do a field that runs past its record, a string that is not UTF-8 and a frame cut
    before its length."""
    path = _only_file(_bag(tmp_path))
    buf = path.read_bytes()
    _, body, _ = frame(buf, _chunks(path)[0], len(buf))
    chunk = parse(Opcode.CHUNK, body)
    assert isinstance(chunk, Chunk) and chunk.compression == "zstd"
    assert len(chunk_records(chunk)) == 3  # schema, channel, message
    raw = zstandard.ZstdDecompressor().decompress(chunk.data)
    plain = replace(chunk, compression="", data=raw, uncompressed_crc=0)
    assert len(chunk_records(plain)) == 3

    def fails(bad: Chunk, text: str) -> None:
        with pytest.raises(BadRecord, match=re.escape(text)):
            chunk_records(bad)

    def plain_with(data: bytes) -> Chunk:
        return replace(plain, data=data, uncompressed_size=len(data))

    n = chunk.uncompressed_size
    fails(replace(chunk, compression="lz4"), "unsupported chunk compression 'lz4'")
    fails(replace(chunk, uncompressed_size=n + 1), f"{n} bytes uncompressed, the chunk says "
          f"{n + 1}")
    fails(replace(chunk, data=bytes(64)), "zstd decompression failed")
    fails(plain_with(raw + struct.pack("<BQ", Opcode.FOOTER, 20) + bytes(20)),
          "record opcode 0x02 inside the chunk")
    fails(plain_with(raw[:-5]), "inside the chunk: record 0x05 of")
    fails(plain_with(raw + struct.pack("<BQ", Opcode.MESSAGE, 10) + bytes(10)),
          "message record shorter than its fields")
    with pytest.raises(BadRecord, match="a field runs past the end of its record"):
        parse(Opcode.SCHEMA, struct.pack("<HI", 1, 1000) + b"x")
    with pytest.raises(BadRecord, match=r"record 0x01 does not parse \(UnicodeDecodeError"):
        parse(Opcode.HEADER, struct.pack("<I", 2) + b"\xff\xfe" + struct.pack("<I", 0))
    with pytest.raises(ShortRecord, match=re.escape("4 byte(s) left where a record starts")):
        frame(b"\x06\x00\x00\x00", 0, 4)


def test_false_chunk_starts_are_passed_over(tmp_path):
    """A killed recording (no summary) whose second chunk was overwritten: a length past the
    end, then three bytes 0x06 that only look like chunk records (a name longer than a
    compression name, a data length that disagrees with the record's, a CRC that fails). The
    scan for the next chunk passes over them to the third chunk; the second is named, with
    its loss counted against metadata.yaml."""
    bag = _bag(tmp_path, finish=False)
    path = _only_file(bag)
    second, third = _chunks(path)[1:]
    header = struct.pack("<QQQI", STAMP0, STAMP0, 0, 0)
    stretch = bytearray(third - second)
    stretch[0:9] = struct.pack("<BQ", Opcode.CHUNK, 10**9)  # runs past the end of the file
    stretch[20:20 + 41] = struct.pack("<BQ", Opcode.CHUNK, 100) + header + struct.pack("<I", 200)
    stretch[70:70 + 53] = (struct.pack("<BQ", Opcode.CHUNK, 60) + header
                           + struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", 5))
    crc_fails = struct.pack("<QQQI", STAMP0, STAMP0, 0, 1234) + struct.pack("<I", 0) \
        + struct.pack("<Q", 0)
    stretch[130:130 + 49] = struct.pack("<BQ", Opcode.CHUNK, len(crc_fails)) + crc_fails
    assert stretch.count(Opcode.CHUNK) == 4
    _patch(path, second, bytes(stretch))
    log = read_log(bag)
    assert [t for _, _, t in log.messages] == [STAMP0, STAMP0 + 2 * 10**9]
    (damage,) = log.damaged
    assert (damage.chunk, damage.offset, damage.length) == (1, second, third - second)
    assert "runs past the end" in damage.reason and damage.messages is None
    assert log.lost["messages"] == 1 and log.lost["by_topic"] == {"/nav": 1}
    assert log.truncated == []


# --------------------------------------------------------------------------- whole files
def test_an_empty_file_and_a_file_that_is_not_mcap(tmp_path):
    """An empty file is a torn end; a file without the MCAP magic is damage from byte 0 with
    nothing found after it. Outside a bag folder the advice is to put the file in one."""
    empty, text = tmp_path / "empty.mcap", tmp_path / "notes.mcap"
    empty.write_bytes(b"")
    text.write_text("not a recording\n" * 10)
    log = read_log(empty)
    assert log.truncated == ["empty.mcap: torn end at byte offset 0: the file is empty"]
    assert log.messages == [] and log.lost["source"] == "message index"
    assert describe(log.lost) == "lost: nothing found (no metadata.yaml to count against)"
    assert any("a folder of its own" in line for line in advice(empty, log))
    scan = scan_file(text)
    (damage,) = scan.damaged
    assert (damage.offset, damage.length) == (0, text.stat().st_size)
    assert damage.reason == "no MCAP magic at the start of the file"
    assert scan.messages == [] and scan.chunks == 0


def test_a_footer_pointing_outside_the_file(tmp_path):
    """The summary is not used (named, nothing lost): every chunk is read from the data
    section."""
    path = _only_file(_bag(tmp_path))
    size = path.stat().st_size
    footer = size - len(MAGIC) - 29
    _patch(path, footer + 9, struct.pack("<Q", 10 * size))
    scan = scan_file(path)
    assert len(scan.messages) == 3 and not scan.summary and not scan.torn
    (damage,) = scan.damaged
    assert damage.reason == (f"summary section: the footer points outside the file "
                             f"({10 * size}); not used")
    assert damage.no_loss == SUMMARY_NOT_NEEDED and not damage.lost_data
    assert not read_log(path.parent).data_lost


def test_an_unknown_record_in_the_data_section(tmp_path):
    """A chunk whose opcode became one MCAP does not know: named by its ordinal (from the
    summary), skipped, its message counted as lost; the chunk after it is read."""
    bag = _bag(tmp_path)
    path = _only_file(bag)
    second = _chunks(path)[1]
    _patch(path, second, bytes([0x7F]))
    log = read_log(bag)
    assert len(log.messages) == 2
    (damage,) = log.damaged
    assert (damage.chunk, damage.offset) == (1, second)
    assert damage.reason == "unknown record opcode 0x7f" and damage.messages == 1
    assert log.lost["messages"] == 1 and "lost: 1 message(s)" in describe(log.lost)


def test_an_early_data_end_record(tmp_path):
    """A chunk read as a data end record: its CRC field does not match the data section before
    it (named), reading stops there, and the chunks the summary indexes after it are named
    as not reached, each with its lost message."""
    bag = _bag(tmp_path)
    path = _only_file(bag)
    second, third = _chunks(path)[1:]
    _patch(path, second, bytes([Opcode.DATA_END]))
    log = read_log(bag)
    assert len(log.messages) == 1
    crc, second_lost, third_lost = sorted(log.damaged, key=lambda d: d.offset)
    assert crc.reason.startswith("data section CRC mismatch (data_section_crc ")
    assert [(d.chunk, d.offset, d.messages) for d in (second_lost, third_lost)] == [
        (1, second, 1), (2, third, 1)]
    assert all(d.reason.startswith("not reached: the chunk index points into a stretch")
               for d in (second_lost, third_lost))
    assert log.lost["messages"] == 2


def test_damage_outside_the_chunks(tmp_path):
    """The run metadata record (between the header and the first chunk) garbled in a finished
    file: named as damage in no chunk, every chunk read; the run metadata is gone with it."""
    bag = _bag(tmp_path, metadata={"config": {"a": 1}})
    path = _only_file(bag)
    (metadata,) = [pos for pos, op in _records(path.read_bytes()) if op == Opcode.METADATA]
    _patch(path, metadata, bytes([0x7F]))
    log = read_log(bag)
    assert len(log.messages) == 3 and log.metadata == {}
    (damage,) = log.damaged
    assert (damage.chunk, damage.offset) == (None, metadata)
    assert damage.reason == "unknown record opcode 0x7f (no chunk in this stretch)"
    assert damage.length == _chunks(path)[0] - metadata


def test_a_damaged_chunk_whose_message_index_is_garbled_too(tmp_path):
    """A killed recording whose second chunk fails its CRC and whose message index after it
    does not parse: what the chunk held is unknown to the file, and metadata.yaml counts the
    loss."""
    bag = _bag(tmp_path, finish=False)
    path = _only_file(bag)
    buf = path.read_bytes()
    second = _chunks(path)[1]
    _, _, end = frame(buf, second, len(buf))
    assert buf[end] == Opcode.MESSAGE_INDEX
    _patch(path, end - 20, bytes(8))  # inside the chunk's compressed data
    _patch(path, end + 9 + 2, struct.pack("<I", 10**6))  # the index's records run past it
    log = read_log(bag)
    assert len(log.messages) == 2
    (damage,) = log.damaged
    assert (damage.chunk, damage.offset, damage.messages) == (1, second, None)
    assert log.lost["messages"] == 1 and log.lost["by_topic"] == {"/nav": 1}


@pytest.mark.parametrize("cut", ["ending", "footer"])
def test_torn_ends_of_a_killed_recording(tmp_path, cut):
    """A killed recording cut right after its last chunk (its provisional ending gone), or
    whose footer record is garbled before the closing magic: a torn end, every message read,
    nothing lost."""
    bag = _bag(tmp_path, finish=False)
    path = _only_file(bag)
    buf = path.read_bytes()
    data_end = max(pos for pos, op in _records(buf) if op == Opcode.DATA_END)
    if cut == "ending":
        path.write_bytes(buf[:data_end])
        expected = (f"torn end at byte offset {data_end}: the file ends after a complete "
                    "record, without an MCAP ending")
    else:
        _patch(path, len(buf) - len(MAGIC) - 29, bytes([0x00]))
        expected = (f"torn end after the data end record (byte offset {data_end + 13}): no "
                    "valid footer and closing magic follow it")
    log = read_log(bag)
    assert log.truncated == [f"{path.name}: {expected}"]
    assert len(log.messages) == 3 and log.damaged == [] and not log.lost["messages"]


def test_channels_defined_only_in_a_lost_chunk(tmp_path):
    """A killed recording of one file whose first chunk (the one with the schema and channel
    definitions) is damaged: the messages of the intact chunks after it cannot be decoded and
    are reported as such, beside the damaged chunk. The loss is every message once: 3, as
    metadata.yaml counts them per topic, and 3 without metadata.yaml, under the channel id
    (its topic is known nowhere)."""
    bag = _bag(tmp_path, finish=False)
    path = _only_file(bag)
    first = _chunks(path)[0]
    _patch(path, first + 9 + 60, bytes(40))  # inside the compressed data
    log = read_log(bag)
    assert log.messages == []
    chunk, orphans = log.damaged
    assert (chunk.chunk, chunk.offset, chunk.messages) == (0, first, 1)
    assert orphans.reason == ("2 intact message(s) of channels defined only in a lost chunk "
                              "cannot be decoded") and orphans.messages == 2
    assert orphans.by_topic == {"channel 1": 2}
    assert log.lost["messages"] == 3 and log.lost["by_topic"] == {"/nav": 3}
    (bag / "metadata.yaml").unlink()
    lost = read_log(bag).lost
    assert lost["messages"] == 3 and lost["by_topic"] == {"channel 1": 3}
    assert describe(lost) == "lost: 3 message(s), 0 solve(s) (3 unknown) (per message index)"


def test_a_message_read_twice_is_kept_once(tmp_path):
    """Two chunks holding the same message (channel, log time, data), as a bad copy leaves
    them: it is kept once and the duplicate is named."""
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, topics={"/nav": NAV_TYPE, "/nav_copy": NAV_TYPE})
    msgs, stamp = _fix(0)
    assert rec.record_solve(msgs, stamp)
    assert rec.record_solve(msgs + [("/nav_copy", msgs[0][1])], stamp)
    rec.finish()
    scan = scan_file(_only_file(bag))
    assert len(scan.messages) == 2 and scan.chunks == 2
    assert scan.notes == ["guidance_0.mcap: 1 message(s) identical to one read before (same "
                          "channel, log time and data): dropped"]


# --------------------------------------------------------------------------- metadata.yaml
@pytest.mark.parametrize("text", ["rosbag2_bagfile_information: [unclosed",
                                  "something_else: {}\n"])
def test_an_unreadable_metadata_yaml(tmp_path, text):
    """The loss is then known from the damaged chunks only, and the report says why."""
    bag = _bag(tmp_path)
    (bag / "metadata.yaml").write_text(text)
    log = read_log(bag)
    assert len(log.messages) == 3 and log.lost["source"] == "message index"
    assert re.fullmatch(r"metadata\.yaml unreadable \((ParserError|KeyError): .*\): the loss "
                        "is known only from the damaged chunks", log.lost["metadata"], re.S)


def test_files_missing_from_or_unknown_to_metadata_yaml(tmp_path):
    """A rotated bag: a file metadata.yaml lists that is gone is lost (named, with its count,
    and `bag reindex` advised); a file it does not list yet is said to lag."""
    bag = _bag(tmp_path, n=8, max_bytes=1800)
    files = bag_files(bag)
    assert len(files) >= 3
    counts = {f["path"]: f["message_count"] for f in yaml.safe_load(
        (bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["files"]}
    gone = files[1].name
    files[1].unlink()
    shutil.copy(files[0], bag / "guidance_99.mcap")
    log = read_log(bag)
    assert log.lost["files"] == {gone: counts[gone]}
    assert f"{gone} is listed in metadata.yaml ({counts[gone]} messages) but missing" \
        in log.lost["notes"]
    assert (f"guidance_99.mcap is not in metadata.yaml yet ({counts[files[0].name]} messages "
            "read): it lags the data") in log.lost["notes"]
    assert any("bag reindex" in line for line in advice(bag, log))


def test_intact_files_with_fewer_messages_than_an_older_metadata_yaml(tmp_path):
    """metadata.yaml without per-file counts (only relative_file_paths, as older rosbag2
    writes it) over a file replaced by a shorter intact one: the loss is counted per topic,
    and no repair is advised, since none would help."""
    bag = _bag(tmp_path, n=3)
    shorter = _bag(tmp_path, n=2, name="shorter")
    shutil.copy(_only_file(shorter), bag / "guidance_0.mcap")
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    del meta["rosbag2_bagfile_information"]["files"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    log = read_log(bag)
    assert len(log.messages) == 2 and log.lost["messages"] == 1 and log.lost["files"] == {}
    assert advice(bag, log) == [
        "the files are intact but hold fewer messages than metadata.yaml counts: files were "
        "cut or replaced after recording; no repair brings them back"]


def test_loss_unknown_without_metadata_yaml_or_message_index(tmp_path):
    """A killed recording without metadata.yaml whose second chunk's length field is garbled
    (its message index lies beyond the garbled end): what it held is unknown, and said so."""
    bag = _bag(tmp_path, finish=False)
    (bag / "metadata.yaml").unlink()
    path = _only_file(bag)
    second = _chunks(path)[1]
    _patch(path, second + 1, struct.pack("<Q", 10**9))
    log = read_log(bag)
    assert len(log.messages) == 2 and log.damaged[0].messages is None
    assert log.lost["messages"] is None and log.data_lost
    assert describe(log.lost) == ("lost: unknown (no metadata.yaml and a damaged chunk without "
                                  "a message index)")


# --------------------------------------------------------------------------- decoding, replay
def test_undecodable_payloads_and_foreign_channels(tmp_path):
    """An intact chunk with a payload that is not the CDR its schema says: that message is
    damage (named with topic and log time) and the others are read; a channel that is not
    CDR (JSON here) is not ours and is left alone."""
    path = tmp_path / "mixed.mcap"
    schema = ros2msg.ros2msg_schema(NAV_TYPE)
    encode = ros2msg.cdr_encoder(NAV_TYPE, schema)
    msgs, stamp = _fix(0)
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start("ros2", "test")
        nav = writer.register_channel("/nav", "cdr", writer.register_schema(
            NAV_TYPE, "ros2msg", schema.encode()))
        note = writer.register_channel("/note", "json", writer.register_schema(
            "Note", "jsonschema", b"{}"))
        writer.add_message(nav, stamp, bytes(encode(ros2msg.plain_message(msgs[0][1]))), stamp)
        writer.add_message(nav, stamp + 1, b"\x00\x01\x00\x00\x05", stamp + 1)
        writer.add_message(note, stamp, b'{"a": 1}', stamp)
        writer.finish()
    log = read_log(path)
    assert [(topic, t) for topic, _, t in log.messages] == [("/nav", stamp)]
    (damage,) = log.damaged
    assert damage.reason.startswith(f"a message on /nav (log time {stamp + 1}) does not "
                                    "decode: ")
    assert damage.by_topic == {"/nav": 1} and log.lost["messages"] == 1


def test_missing_logs_are_input_errors(tmp_path, capsys):
    (tmp_path / "empty_bag").mkdir()
    for path, why in ((tmp_path / "nothing", "no such file"),
                      (tmp_path / "empty_bag", "no .mcap files in the directory")):
        assert cli_main(["replay", str(path)]) == 2
        err = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
        assert err == {"error": "InputError", "message": f"log: {why} (got {str(path)!r})"}


@pytest.mark.parametrize("metadata, why", [
    ({}, "log: no art_guidance configuration in the MCAP metadata"),
    ({"config": [1, 2]}, "config: the recorded configuration is not a JSON object"),
])
def test_a_log_without_a_usable_configuration_is_not_replayed(tmp_path, metadata, why):
    bag = _bag(tmp_path, n=1, metadata=metadata)
    with pytest.raises(InputError, match=re.escape(why)):
        replay(bag)


def test_an_unreadable_recorded_request_counts_as_chance_constrained(tmp_path):
    """`recorded_mode` reads every solve's request; one that is not JSON is judged when it is
    replayed and, for choosing the default model, counts as chance-constrained."""
    from art_guidance_msgs.msg import ManeuverPlan, SolveRecord

    def bag_of(name: str, requests: list[str]) -> Path:
        rec = McapRecorder(tmp_path / name)
        for k, request_json in enumerate(requests):
            record, plan = SolveRecord(), ManeuverPlan()
            record.plan_id = plan.plan_id = f"plan-{k}"
            record.request_json = request_json
            assert rec.record_solve([("/guidance/solve_record", record),
                                     ("/guidance/maneuver_plan", plan)], STAMP0 + k)
        rec.finish()
        return rec.directory

    deterministic = '{"chance_constrained": false}'
    assert recorded_mode(read_log(bag_of("one", [deterministic]))) == "deterministic"
    log = read_log(bag_of("two", [deterministic, "{not json"]))
    assert len(log.solves()) == 2 and recorded_mode(log) == "chance"


def test_a_solve_that_hit_its_deadline_is_not_compared(tmp_path):
    """A recorded plan that timed out in flight cannot be reproduced (replays are not
    time-boxed): it is listed as such, not compared and not a mismatch."""
    from art_guidance_msgs.msg import ManeuverPlan, SolveRecord

    from art_guidance.config import GuidanceConfig
    from art_guidance.planning import GuidancePipeline
    from art_guidance.record.replay import DEADLINE_HIT, EXIT_OK

    config = GuidancePipeline(GuidanceConfig.load()).config_json()
    rec = McapRecorder(tmp_path / "bag", {"config": config})
    record, plan = SolveRecord(), ManeuverPlan()
    record.plan_id = plan.plan_id = "plan-1"
    plan.status_text = "TIMEOUT: the plan's deadline (solve_deadline_s) passed"
    assert rec.record_solve([("/guidance/solve_record", record),
                             ("/guidance/maneuver_plan", plan)], STAMP0)
    rec.finish()
    report = replay(tmp_path / "bag")
    (row,) = report["per_solve"]
    assert row["match"] is None and row["reason"] == DEADLINE_HIT and row["status"] == "TIMEOUT"
    assert (report["compared"], report["deadline_hit"]) == (0, 1)
    assert report["exit_code"] == EXIT_OK


def test_a_file_whose_seal_was_removed(tmp_path):
    """A bag whose first file's run metadata has no seal while the other file's has one: the
    seal was removed after recording, an alteration named with the file."""
    from art_guidance.record.seal import SEAL_KEY

    bag = _bag(tmp_path, n=6, max_bytes=1800, metadata={"config": {"a": 1}})
    first, second = bag_files(bag)[:2]
    sealed = read_log(second).metadata
    assert SEAL_KEY in sealed
    msgs, stamp = _fix(0)
    schema = ros2msg.ros2msg_schema(NAV_TYPE)
    with open(first, "wb") as fh:  # the same run metadata, written without its seal
        writer = Writer(fh)
        writer.start("ros2", "another writer")
        writer.add_metadata("art_guidance", {k: v for k, v in sealed.items() if k != SEAL_KEY})
        nav = writer.register_channel("/nav", "cdr", writer.register_schema(
            NAV_TYPE, "ros2msg", schema.encode()))
        writer.add_message(nav, stamp, bytes(ros2msg.cdr_encoder(NAV_TYPE, schema)(
            ros2msg.plain_message(msgs[0][1]))), stamp)
        writer.finish()
    state, problems = read_log(bag).metadata_check()
    assert state == "altered"
    assert (f"{first.name}: no {SEAL_KEY}, where the other files have one: removed after "
            "recording") in problems


def test_a_log_without_visualisation_is_not_rendered(tmp_path, capsys):
    bag = _bag(tmp_path, n=1)
    assert cli_main(["bag", "render", str(bag), "--png", str(tmp_path / "bag.png")]) == 2
    err = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert err["error"] == "InputError" and "recorded with visualization:=false?" \
        in err["message"]
    assert not (tmp_path / "bag.png").exists()


# --------------------------------------------------------------------------- the recorder
_SUMMARY_EFBIG_CHILD = """
import json, os, resource, signal, sys
from helpers.ros_client import nav_msg
from art_guidance.record.recorder import NAV_TYPE, McapRecorder
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
rec = McapRecorder(sys.argv[1], topics={"/nav": NAV_TYPE}, max_bytes=1 << 20)
ok = [rec.record_solve([("/nav", nav_msg(10**18 + k, [float(k), 100.0, 0, 0, 0, 0]))],
                       10**18 + k) for k in range(40)]
size = rec.files[0].stat().st_size
_, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (size, hard))  # the summary no longer fits
rec.finish()
resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))  # what the process writes at exit
print(json.dumps({"ok": sum(ok), "errors": rec.errors, "error": rec.last_error,
                  "size": size, "after": rec.files[0].stat().st_size}))
"""


def test_a_summary_that_does_not_fit_under_the_file_size_limit(tmp_path):
    """A real EFBIG (RLIMIT_FSIZE lowered to the file's size, SIGXFSZ ignored) when `finish`
    writes the summary: reported, the provisional ending put back (the file as it was), and
    metadata.yaml finished with the error; every solve reads back, and `bag reindex` adds
    the summary."""
    bag = tmp_path / "bag"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    out = subprocess.run([sys.executable, "-c", _SUMMARY_EFBIG_CHILD, str(bag)], env=env,
                         capture_output=True, text=True, timeout=60, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["ok"] == 40 and result["errors"] == 1, result
    assert "File too large" in result["error"] and result["after"] == result["size"]
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["custom_data"]
    assert custom["art_guidance.state"] == "finished"
    assert "File too large" in custom["art_guidance.last_error"]
    path = _only_file(bag)
    assert not has_summary(path)
    log = read_log(bag)
    assert len(log.messages) == 40 and not log.data_lost and log.truncated == []
    repair_bag(bag)
    assert has_summary(path) and len(read_log(bag).messages) == 40


def test_a_bag_folder_swapped_for_a_file_before_finish(tmp_path):
    """`finish` cannot write metadata.yaml where the folder was: reported, never raised, and
    the file in its place is left as it is."""
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, topics=NAV_TOPICS)
    assert rec.record_solve(*_fix(0))
    shutil.rmtree(bag)
    bag.write_text("not a folder")
    rec.finish()
    assert rec.errors == 1 and rec.last_error.startswith(("FileExistsError",
                                                          "NotADirectoryError"))
    assert bag.read_text() == "not a folder"
    assert rec.record_solve(*_fix(1)) is False  # finished


def test_a_tight_cap_keeps_the_newest_closed_file(tmp_path):
    """Files so small that one solve and its summary exceed `max_bytes`: a closed file is more
    than the cap leaves beside a new file, yet the newest closed file stays at every rotation
    (the bag exceeds the cap by that much); only older files are deleted."""
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, topics=NAV_TOPICS, max_bytes=2500, max_total_bytes=7500)
    for k in range(20):
        assert rec.record_solve(*_fix(k))
        assert list(bag.glob("*.mcap")), f"no file left after solve {k}"
    rec.finish()
    assert rec.dropped_files > 0 and rec.errors == 0
    newest = bag_files(bag)[-1]
    log = read_log(bag)
    assert not log.data_lost and log.messages[-1][2] == STAMP0 + 19 * 10**9
    assert len(log.messages) == 20 - rec.dropped_messages
    assert newest.name == rec.files[-1].name


def test_retention_waits_when_metadata_yaml_cannot_be_written(tmp_path, monkeypatch):
    """With a cap, the oldest files are dropped only after metadata.yaml that no longer lists
    them is written. When that write fails the files are kept (the error reported) and the
    next rotation drops them."""
    import art_guidance.record.recorder as recorder_module

    real_write, real_cap = recorder_module.write_bag_metadata, McapRecorder._apply_cap
    failing = {"on": False, "failed": 0}

    def write(directory, files, topics, custom):
        if failing["on"] and failing["failed"] == 0:
            failing["failed"] += 1
            raise OSError(28, "No space left on device")
        return real_write(directory, files, topics, custom)

    def cap(self):
        failing["on"] = True
        try:
            real_cap(self)
        finally:
            failing["on"] = False

    monkeypatch.setattr(recorder_module, "write_bag_metadata", write)
    monkeypatch.setattr(McapRecorder, "_apply_cap", cap)
    bag = tmp_path / "bag"
    rec = McapRecorder(bag, topics=NAV_TOPICS, max_bytes=2500, max_total_bytes=7500)
    kept_at_failure = None
    for k in range(60):
        assert rec.record_solve(*_fix(k))
        if failing["failed"] and kept_at_failure is None:
            kept_at_failure = len(list(bag.glob("*.mcap")))
            assert rec.errors == 1 and "No space left" in rec.last_error
            assert rec.dropped_files == 0
    rec.finish()
    monkeypatch.undo()
    assert kept_at_failure is not None and rec.dropped_files > 0
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == sorted(
        (p.name for p in bag.glob("*.mcap")), key=lambda n: (len(n), n))
    log = read_log(bag)
    assert not log.data_lost and "retention cap dropped" in log.lost["metadata"]


def test_message_types_that_are_not_installed(tmp_path, monkeypatch):
    """A topic of a type with no installed definition is refused when the recorder is made,
    naming the type; a type description hash that is missing or does not read is left
    empty (rosbag2 allows that)."""
    with pytest.raises(FileNotFoundError, match="no definition for no_such_pkg/msg/Nothing"):
        McapRecorder(tmp_path / "bag", topics={"/x": "no_such_pkg/msg/Nothing"})
    assert not (tmp_path / "bag").exists()
    assert ros2msg.type_description_hash("no_such_pkg/msg/Nothing") == ""
    share = tmp_path / "prefix" / "share" / "broken_msgs" / "msg"
    share.mkdir(parents=True)
    (share / "Thing.msg").write_text("float64 x\n")
    (share / "Thing.json").write_text("{\"type_hashes\": [")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "prefix"))
    assert ros2msg.msg_definition("broken_msgs/msg/Thing") == "float64 x\n"
    assert ros2msg.type_description_hash("broken_msgs/msg/Thing") == ""
    (share / "Thing.json").write_text(json.dumps({"type_hashes": [
        {"type_name": "broken_msgs/msg/Other", "hash_string": "RIHS01_00"}]}))
    assert ros2msg.type_description_hash("broken_msgs/msg/Thing") == ""


def test_a_negative_cap_is_refused():
    with pytest.raises(ConfigError, match="record_max_total_bytes must be >= 0, got -1"):
        check_cap(-1, 4096)
