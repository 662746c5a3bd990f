"""Repair a bag folder after a crash: rebuild MCAP files without summary, rewrite metadata.yaml.

The recorder seals every file after each solve, so a folder is normally readable after a
kill -9 as it is. A kill inside a write (or a power cut) can leave a file without a valid
ending; other readers (rosbags, rosbag2) then refuse the folder. `reindex_bag` rewrites every
file that lacks a summary from its complete records (a torn chunk at the end is dropped), with
a summary so readers can seek, and then rewrites `metadata.yaml` from the files' summaries.

Each rewrite is atomic: the new file is written next to the old one and fsync'ed, the original
is kept as `<name>.mcap.orig` (a hard link) until the new file has replaced it and the
directory is fsync'ed, then the `.orig` link is removed. A file still locked by a running
recorder is never touched.
"""
from __future__ import annotations

import fcntl
import io
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import yaml
from mcap.reader import make_reader
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from art_guidance.errors import InputError
from art_guidance.files import fsync_dir
from art_guidance.record.bag_metadata import (
    METADATA_FILE, FileInfo, TopicInfo, bag_files, write_bag_metadata,
)
from art_guidance.record.recorder import MAGIC

FOOTER_BYTES = 9 + 20 + len(MAGIC)  # footer record (opcode, length, 8 + 8 + 4) and the magic
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


def _copy_records(src: io.BufferedReader, writer: Writer) -> tuple[int, str]:
    """Copy every complete record of `src` into `writer`; returns (messages, torn reason)."""
    schemas, channels, messages, started = {}, {}, 0, False
    try:
        for record in StreamReader(src).records:
            if isinstance(record, Header):
                writer.start(profile=record.profile, library=record.library)
                started = True
            elif isinstance(record, Schema):
                schemas[record.id] = writer.register_schema(record.name, record.encoding,
                                                            record.data)
            elif isinstance(record, Channel):
                channels[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schemas.get(record.schema_id, 0),
                    dict(record.metadata))
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Message) and record.channel_id in channels:
                writer.add_message(channels[record.channel_id], record.log_time, record.data,
                                   record.publish_time, record.sequence)
                messages += 1
    except Exception as exc:  # the torn end of a crashed file: keep what was complete
        if not started:
            raise InputError("mcap", f"no readable MCAP header ({exc})", str(src.name))
        return messages, f"{type(exc).__name__}: {exc}"
    return messages, ""


def rebuild(path: Path) -> Rebuilt:
    """Rewrite `path` from its complete records, with a summary; atomic (see the module)."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.reindex.tmp")
    orig = path.with_name(path.name + ORIG_SUFFIX)
    try:
        with open(path, "rb") as src, open(tmp, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            messages, torn = _copy_records(src, writer)
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
    return Rebuilt(path, messages, torn)


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
        doc = yaml.safe_load((directory / METADATA_FILE).read_text())
        return dict(doc["rosbag2_bagfile_information"].get("custom_data") or {})
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return {}


def rewrite_metadata(directory: Path) -> Path:
    """metadata.yaml from the summaries of the folder's files (all must have one)."""
    files, topics = [], {}
    for path in bag_files(directory):
        info, file_topics = _summary_info(path)
        files.append(info)
        for key, (count, type_hash) in file_topics.items():
            entry = topics.setdefault(key, [0, type_hash])
            entry[0] += count
    custom = {**_custom_data(directory), "art_guidance.state": "reindexed"}
    return write_bag_metadata(
        directory, files,
        [TopicInfo(name, msg_type, count, type_hash)
         for (name, msg_type), (count, type_hash) in topics.items()], custom)


def reindex_bag(directory: str | Path, say: Callable[[str], None] = print) -> int:
    """Rebuild every file of the bag folder that has no summary, then rewrite metadata.yaml.

    Every change is reported through `say`. Returns the number of files rewritten.

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
    rewritten = 0
    for path in files:
        if has_summary(path):
            continue
        done = rebuild(path)
        rewritten += 1
        end = f"; dropped a torn end ({done.torn})" if done.torn else ""
        say(f"rewrote {path.name} with a summary: {done.messages} messages kept{end}")
    say(f"rewrote {rewrite_metadata(directory)}")
    return rewritten
