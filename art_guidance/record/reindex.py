"""Repair a bag folder: rebuild torn, damaged or unsummarised MCAP files, rewrite metadata.yaml.

The recorder seals every file after each solve, so a folder is normally readable after a
kill -9 as it is. A kill inside a write (or a power cut) can leave a file without a valid
ending, and failing storage or a bad copy can damage a chunk; other readers (rosbags, rosbag2)
then refuse the folder. `repair_bag` reads every file with `record.scan` (each chunk's CRC
checked, also in files that have a summary) and rewrites every file that is torn, damaged or
lacks a summary from its intact chunks, with a summary so readers can seek. It names what it
kept and what it could not recover (file, chunk, byte offset, messages lost where the file's
message index or metadata.yaml tells), then rewrites `metadata.yaml` from the files' summaries,
noting the repair in its custom_data. Damage that cost no message (a summary that fails its CRC
and is not needed, a damaged copy of a chunk read intact: `Damage.no_loss`) is named and
dropped but is no data loss (`Repair.data_lost`).

Each rewrite is atomic: the new file is written next to the old one and fsync'ed, the original
is kept as `<name>.mcap.orig` (a hard link) until the new file has replaced it and the
directory is fsync'ed, then the `.orig` link is removed. A file still locked by a running
recorder is never touched.
"""
from __future__ import annotations

import fcntl
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from art_guidance.errors import InputError
from art_guidance.files import fsync_dir, load_yaml
from art_guidance.record.bag_metadata import (
    METADATA_FILE, FileInfo, TopicInfo, bag_files, write_bag_metadata,
)
from art_guidance.record.loss import account, describe
from art_guidance.record.mcap_records import FOOTER_BYTES as FOOTER_RECORD_BYTES
from art_guidance.record.mcap_records import MAGIC
from art_guidance.record.scan import Damage, FileScan, lend_channels, scan_file

FOOTER_BYTES = FOOTER_RECORD_BYTES + len(MAGIC)  # the footer record and the closing magic
ORIG_SUFFIX = ".orig"


def has_summary(path: Path) -> bool:
    """True when the file ends in a footer that points to a summary section."""
    size = path.stat().st_size
    if size < 8 + FOOTER_BYTES:
        return False
    with open(path, "rb") as fh:
        fh.seek(size - FOOTER_BYTES)
        tail = fh.read()
    opcode, length, summary_start = struct.unpack_from("<BQQ", tail)
    return (tail.endswith(MAGIC) and opcode == 0x02 and length == 20
            and 0 < summary_start < size - FOOTER_BYTES)


def is_locked(path: Path) -> bool:
    """True while a running recorder holds the file's lock (released when it dies)."""
    with open(path, "rb") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    return False


@dataclass(frozen=True)
class Rebuilt:
    """What `rebuild` kept of one file."""

    path: Path
    messages: int
    torn: str  # why reading stopped before a clean end ("" = the file ended cleanly)
    damaged: tuple[Damage, ...] = ()  # what could not be recovered


def _write(scan: FileScan, writer: Writer) -> int:
    """Write what `scan` kept through `writer`; returns the number of messages."""
    header = scan.header
    writer.start(profile=header.profile if header else "ros2",
                 library=header.library if header else "art_guidance reindex")
    schemas = {sid: writer.register_schema(s.name, s.encoding, s.data)
               for sid, s in sorted(scan.schemas.items())}
    channels = {cid: writer.register_channel(c.topic, c.message_encoding,
                                             schemas.get(c.schema_id, 0), dict(c.metadata))
                for cid, c in sorted(scan.channels.items())}
    for record in scan.metadata:
        writer.add_metadata(record.name, dict(record.metadata))
    for msg in scan.messages:
        writer.add_message(channels[msg.channel_id], msg.log_time, msg.data, msg.publish_time,
                           msg.sequence)
    return len(scan.messages)


def rebuild(path: Path, scan: FileScan | None = None) -> Rebuilt:
    """Rewrite `path` from its intact chunks (`scan`, read now when not given), with a summary;
    atomic (see the module)."""
    scan = scan_file(path) if scan is None else scan
    tmp = path.with_name(f"{path.name}.{os.getpid()}.reindex.tmp")
    orig = path.with_name(path.name + ORIG_SUFFIX)
    try:
        with open(tmp, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            messages = _write(scan, writer)
            writer.finish()
            out.flush()
            os.fsync(out.fileno())
        orig.unlink(missing_ok=True)
        os.link(path, orig)
        os.replace(tmp, path)
        fsync_dir(path.parent)
        orig.unlink()
        fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)
    return Rebuilt(path, messages, scan.torn, tuple(scan.damaged))


def _summary_info(path: Path) -> tuple[FileInfo, dict[tuple[str, str], list]]:
    """FileInfo and {(topic, type): [count, type hash]} from a file's summary."""
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    stats = summary.statistics
    counts = stats.channel_message_counts if stats else {}
    topics = {}
    for cid, channel in summary.channels.items():
        schema = summary.schemas.get(channel.schema_id)
        key = (channel.topic, schema.name if schema else "")
        entry = topics.setdefault(key, [0, channel.metadata.get("topic_type_hash", "")])
        entry[0] += counts.get(cid, 0)
    count = stats.message_count if stats else 0
    start = stats.message_start_time if count else 0
    end = stats.message_end_time if count else 0
    return FileInfo(path.name, start, end, count), topics


def _custom_data(directory: Path) -> dict[str, str]:
    """The previous metadata.yaml's custom_data (empty when missing or unreadable)."""
    try:
        doc = load_yaml((directory / METADATA_FILE).read_text())
        return dict(doc["rosbag2_bagfile_information"].get("custom_data") or {})
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return {}


def rewrite_metadata(directory: Path, notes: dict[str, str] | None = None) -> Path:
    """metadata.yaml from the summaries of the folder's files (all must have one); `notes`
    go into its custom_data."""
    files, topics = [], {}
    for path in bag_files(directory):
        info, file_topics = _summary_info(path)
        files.append(info)
        for key, (count, type_hash) in file_topics.items():
            entry = topics.setdefault(key, [0, type_hash])
            entry[0] += count
    custom = {**_custom_data(directory), "art_guidance.state": "reindexed", **(notes or {})}
    return write_bag_metadata(
        directory, files,
        [TopicInfo(name, msg_type, count, type_hash)
         for (name, msg_type), (count, type_hash) in topics.items()], custom)


@dataclass
class Repair:
    """What `repair_bag` did and found."""

    rewritten: list[str] = field(default_factory=list)
    damaged: list[Damage] = field(default_factory=list)
    torn: list[str] = field(default_factory=list)
    lost: dict = field(default_factory=dict)  # `record.loss.account` against the old metadata

    @property
    def data_lost(self) -> bool:
        """Damage that may have cost messages, or fewer messages on disk than the old
        metadata.yaml counted (damage that lost nothing, `Damage.no_loss`, is no loss)."""
        return bool(any(d.lost_data for d in self.damaged)
                    or self.lost.get("messages") is None or self.lost.get("messages"))


def _say_rebuilt(done: Rebuilt, say: Callable[[str], None]) -> None:
    end = f"; dropped a torn end ({done.torn})" if done.torn else ""
    say(f"rewrote {done.path.name} with a summary: {done.messages} messages kept{end}")
    for damage in done.damaged:
        say(f"  {'could not recover' if damage.lost_data else 'dropped'}: {damage}")


def _repair_notes(repair: Repair) -> dict[str, str]:
    if not repair.rewritten:
        return {}
    what = [f"rebuilt {', '.join(repair.rewritten)}"]
    lossy = sum(d.lost_data for d in repair.damaged)
    if lossy:
        what.append(f"{lossy} damaged stretch(es) dropped")
    if len(repair.damaged) > lossy:
        what.append(f"{len(repair.damaged) - lossy} damaged stretch(es) that lost nothing "
                    "dropped (an unused summary, a damaged copy of an intact chunk)")
    if repair.torn:
        what.append(f"{len(repair.torn)} torn end(s) dropped")
    return {"art_guidance.repair": "; ".join(what),
            "art_guidance.lost_messages": str(repair.lost.get("messages"))}


def repair_bag(directory: str | Path, say: Callable[[str], None] = print) -> Repair:
    """Rebuild every file of the bag folder that is torn, damaged or has no summary, then
    rewrite metadata.yaml; every change and every loss is reported through `say`.

    Raises:
        InputError: not a folder of MCAP files, or a recorder is still writing to it.
    """
    directory = Path(directory)
    files = bag_files(directory) if directory.is_dir() else []
    if not files:
        raise InputError("bag", "not a folder with .mcap files", str(directory))
    locked = [p.name for p in files if is_locked(p)]
    if locked:
        raise InputError("bag", "a running recorder is writing to this bag", locked)
    scans = [scan_file(path) for path in files]
    lend_channels(scans)
    repair, read_topics, read_files, types = Repair(), {}, {}, {}
    for scan in scans:
        for note in scan.notes:
            say(note)
        repair.damaged += scan.damaged
        if scan.torn:
            repair.torn.append(f"{scan.path.name}: {scan.torn}")
        topics = {cid: c.topic for cid, c in scan.channels.items()}
        types.update({c.topic: scan.schemas[c.schema_id].name
                      for c in scan.channels.values() if c.schema_id in scan.schemas})
        for msg in scan.messages:
            read_topics[topics[msg.channel_id]] = read_topics.get(topics[msg.channel_id], 0) + 1
        read_files[scan.path.name] = len(scan.messages)
        if scan.damaged or scan.torn or not scan.summary:
            _say_rebuilt(rebuild(scan.path, scan), say)
            repair.rewritten.append(scan.path.name)
        scan.messages = []
    repair.lost = account(directory, read_topics, read_files, types, repair.damaged)
    if repair.data_lost or repair.lost["files"] or repair.damaged or repair.torn:
        say(describe(repair.lost))
    if repair.lost["source"] != METADATA_FILE:
        say(f"note: {repair.lost['metadata']}")
    for note in repair.lost["notes"]:
        say(f"note: {note}")
    say(f"rewrote {rewrite_metadata(directory, _repair_notes(repair))}")
    return repair
