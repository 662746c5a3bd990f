"""One MCAP file of a bag as the recorder writes it: built in memory by mcap's Writer, put on
disk in whole chunks, always ending in a valid MCAP ending (see `record.recorder` for the
crash-safety argument).

The provisional ending (`TAIL`) is a Data End record, a Footer without summary and the closing
magic. mcap's Writer writes into an `OffsetStream`, which keeps the bytes in memory and reports
file offsets, so the chunk indexes of the summary written at the close stay right. A file is
created whole under a hidden `.<name>_<k>.mcap.part` and renamed once its first solve is on disk.
"""
from __future__ import annotations

import errno
import fcntl
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import CompressionType, Writer

from art_guidance.files import fsync_dir
from art_guidance.record.bag_metadata import FileInfo
from art_guidance.record.mcap_records import MAGIC
from art_guidance.record.seal import SEALING_LIBRARY


def provisional_tail() -> bytes:
    """Data End (no CRC), a Footer without summary and the magic: a valid MCAP ending."""
    builder = RecordBuilder()
    DataEnd(0).write(builder)
    Footer(0, 0, 0).write(builder)
    return builder.end() + MAGIC


TAIL = provisional_tail()
PART_SUFFIX = ".part"  # a file being created: `.<name>_<k>.mcap.part`, renamed once whole


class OffsetStream:
    """What mcap's Writer writes into: bytes kept in memory until `take`, and `tell()` the file
    offset the next byte will have (so the Writer's chunk indexes point into the file)."""

    def __init__(self, offset: int = 0) -> None:
        self._offset = offset
        self._buffer = bytearray()

    def write(self, data: bytes) -> int:
        self._buffer += data
        return len(data)

    def tell(self) -> int:
        return self._offset + len(self._buffer)

    def flush(self) -> None:
        """Nothing to do: the bytes stay here until `take`."""

    def take(self) -> bytes:
        """The bytes written since the last take; they belong at the offset `tell()` had then."""
        data = bytes(self._buffer)
        self._offset += len(data)
        self._buffer.clear()
        return data


@dataclass
class OpenFile:
    """The file being written; `fd` is -1 until its first solve is on disk."""

    path: Path
    writer: Writer
    stream: OffsetStream
    channels: dict = field(default_factory=dict)
    fd: int = -1
    data_end: int = 0  # where the next chunk goes (the provisional ending starts here)
    start_ns: int = 0
    end_ns: int = 0
    count: int = 0
    topic_counts: Counter = field(default_factory=Counter)

    def info(self) -> FileInfo:
        return FileInfo(self.path.name, self.start_ns, self.end_ns, self.count)


@dataclass(frozen=True)
class ClosedFile:
    """A file closed at a rotation or after a failure, as retention and metadata.yaml see it."""

    info: FileInfo
    topic_counts: Counter
    size: int  # [bytes]


def start_file(path: Path, schemas: dict[str, str], hashes: dict[str, str],
               topics: dict[str, str], metadata: dict[str, str]) -> OpenFile:
    """A file in memory: header (its library says the run metadata is sealed, `record.seal`),
    schemas ('pkg/msg/Type' -> ros2msg text), one cdr channel per topic (topic -> type, with the
    type's hash) and the run metadata, sealed (nothing on disk)."""
    stream = OffsetStream()
    writer = Writer(stream, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library=SEALING_LIBRARY)
    handle = OpenFile(path, writer, stream)
    schema_ids = {t: writer.register_schema(name=t, encoding="ros2msg", data=text.encode())
                  for t, text in schemas.items()}
    for topic, msg_type in topics.items():
        handle.channels[topic] = writer.register_channel(
            topic=topic, message_encoding="cdr", schema_id=schema_ids[msg_type],
            metadata={"offered_qos_profiles": "", "topic_type_hash": hashes[msg_type]})
    writer.add_metadata("art_guidance", metadata)
    return handle


def pwrite_all(fd: int, data: bytes, offset: int) -> None:
    """`os.pwrite` until all of `data` is at `offset` (a short write is continued; the call that
    cannot go on raises, e.g. ENOSPC or EFBIG)."""
    view, done = memoryview(data), 0
    while done < len(data):
        n = os.pwrite(fd, view[done:], offset + done)
        if n <= 0:
            raise OSError(errno.EIO, f"write returned {n}")
        done += n


def put_back_ending(fd: int, data_end: int) -> None:
    """Cut the file to its data plus a provisional ending and write that ending (after a failed
    or undone write); needs no new disk space."""
    os.ftruncate(fd, data_end + len(TAIL))
    pwrite_all(fd, TAIL, data_end)
    os.fsync(fd)


def create_file(handle: OpenFile, data: bytes) -> None:
    """Put a new file's first bytes on disk: written whole and fsync'ed under a hidden
    name, then renamed, so a failure or a kill never leaves a stub `.mcap`. Sets `handle.fd`
    (the file stays open and locked) or raises with nothing left on disk."""
    directory = handle.path.parent
    directory.mkdir(parents=True, exist_ok=True)
    part = handle.path.with_name(f".{handle.path.name}{PART_SUFFIX}")
    fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
    renamed = False
    try:
        # held while this file is written; `bag reindex` leaves a locked file alone
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        pwrite_all(fd, data, 0)
        os.fsync(fd)
        os.rename(part, handle.path)
        renamed = True
        fsync_dir(directory)
    except BaseException:
        os.close(fd)
        (handle.path if renamed else part).unlink(missing_ok=True)
        raise
    handle.fd = fd
