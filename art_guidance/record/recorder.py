"""Record every solve to MCAP: ROS 2 `cdr` payloads with `ros2msg` schemas (rosbag2 layout).

Payloads are encoded from the embedded schema by mcap_ros2's CDR encoder rather than by
rclpy/Fast-CDR: Fast-CDR pads an empty float64 sequence to 8-byte alignment, which exact-size
readers (rosbags) reject; the schema-driven encoder follows the CDR rule and both read it.

A run writes one folder that is a rosbag2 bag: `metadata.yaml` plus `<name>_<k>.mcap` files,
rotated by size. Topic names and types come from the caller (the node passes its resolved
names); `TOPICS` is the default. Each solve is written as a group of messages (the nav state
that triggered it, the replan request when it changed, a `SolveRecord` with warm starts, SCP
history and timings, and the published `ManeuverPlan`) in a chunk of its own.

Crash safety. A file always ends in a valid MCAP ending: after the last chunk comes a
provisional ending (a Data End record, a Footer without summary and the closing magic). A solve
is first encoded and compressed in memory (mcap's Writer writes into `OffsetStream`, which
reports file offsets, so the chunk indexes of the summary written at finish stay right); then
the new chunk and a new provisional ending go over the old ending in one `os.pwrite` at the
end of the data. The file only grows, so the old ending is intact until that one write; then
the file is fsync'ed and `metadata.yaml` is rewritten atomically. A file is created only once
its first solve is written whole (as a hidden `.<name>_<k>.mcap.part`, renamed when complete).

What a kill -9 can leave: the write itself is the only moment the file has no valid ending
(microseconds per solve, `torn_window_ns`). Linux may end a large write early at a page
boundary when a fatal signal arrives; such a file ends inside the new chunk. `read_log` still
reads every solve before it and `art-guidance bag reindex` repairs it (see `record.reindex`);
the torn solve was never published (a plan is recorded before it is published). A kill between
the write and the rename of `metadata.yaml` leaves `metadata.yaml` one solve behind the data
(that solve was not published either).

Write failures (full disk, unwritable path, file size limit) are logged and counted; they never
raise into the caller. A failed write is undone (the old ending is put back and the file cut
to it), the file is closed there and the next solve starts a new one; a solve counts as
recorded only once the data and `metadata.yaml` that describes it are both written, so
`metadata.yaml` always describes what is on disk (state `write_failed` and the error in
`custom_data` until a solve is recorded again). With `max_total_bytes` the oldest closed files
are deleted at a rotation (see `McapRecorder`). Run metadata (config, versions, model checksum)
goes into an MCAP metadata record.
"""
from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import re
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Iterable

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import CompressionType, Writer

from art_guidance import topics
from art_guidance.errors import ConfigError
from art_guidance.files import fsync_dir
from art_guidance.record.bag_metadata import FileInfo, TopicInfo, write_bag_metadata

try:
    # The encoder mcap_ros2's own Writer uses (see the module docstring for why not Fast-CDR);
    # its public Writer owns the file and cannot write a solve in one write. A private module:
    # setup.py bounds mcap-ros2-support to the tested minor versions.
    from mcap_ros2._dynamic import serialize_dynamic
except ImportError as _exc:  # pragma: no cover - depends on the installed version
    raise ImportError(
        "art_guidance's recorder needs mcap_ros2._dynamic.serialize_dynamic (the CDR encoder "
        "of mcap-ros2-support 0.6); the installed mcap-ros2-support does not have it: install "
        "the version setup.py names (pip install 'mcap-ros2-support>=0.6,<0.7')") from _exc

LOG = logging.getLogger("art_guidance.record.recorder")
SEPARATOR = "=" * 80
MAGIC = b"\x89MCAP0\r\n"
NAV_TYPE = "art_guidance_msgs/msg/RelativeNavState"
REQUEST_TYPE = "art_guidance_msgs/msg/ReplanRequest"
SOLVE_RECORD_TYPE = "art_guidance_msgs/msg/SolveRecord"
PLAN_TYPE = "art_guidance_msgs/msg/ManeuverPlan"
TOPICS = {  # the default mapping (resolved names of a node without namespace or remapping)
    f"/{topics.NAV}": NAV_TYPE,
    f"/{topics.REPLAN_REQUEST}": REQUEST_TYPE,
    f"/{topics.SOLVE_RECORD}": SOLVE_RECORD_TYPE,
    f"/{topics.MANEUVER_PLAN}": PLAN_TYPE,
}
_BUILTIN = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
            "int32", "uint32", "int64", "uint64", "string", "wstring"}


def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    return [Path(p) / "share" for p in prefixes]


def _interface_file(msg_type: str, suffix: str) -> Path | None:
    pkg, name = msg_type.split("/")[0], msg_type.split("/")[-1]
    for share in _share_dirs():
        path = share / pkg / "msg" / f"{name}{suffix}"
        if path.is_file():
            return path
    return None


def msg_definition(msg_type: str) -> str:
    """The .msg text of 'pkg/msg/Name' (or 'pkg/Name') from the installed share directories."""
    path = _interface_file(msg_type, ".msg")
    if path is None:
        raise FileNotFoundError(f"no definition for {msg_type} under {_share_dirs()}")
    return path.read_text(encoding="utf-8")


def type_description_hash(msg_type: str) -> str:
    """The installed type's RIHS01 hash (what rosbag2 records per topic); '' if not found."""
    path = _interface_file(msg_type, ".json")
    if path is None:
        return ""
    try:
        hashes = json.loads(path.read_text(encoding="utf-8"))["type_hashes"]
        return next(h["hash_string"] for h in hashes if h["type_name"] == msg_type)
    except (ValueError, KeyError, StopIteration):
        return ""


def _dependencies(text: str, pkg: str) -> list[str]:
    deps = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or "=" in line:  # blank, comment or constant
            continue
        ftype = re.sub(r"\[.*\]$", "", line.split()[0])
        ftype = re.sub(r"<=\d+$", "", ftype)
        if ftype in _BUILTIN or ftype.startswith(("string<", "wstring<")):
            continue
        deps.append(ftype if "/" in ftype else f"{pkg}/{ftype}")
    return deps


def ros2msg_schema(msg_type: str) -> str:
    """rosbag2-style schema: the .msg text with every dependency appended after a separator."""
    pkg = msg_type.split("/")[0]
    text = msg_definition(msg_type)
    parts, seen = [text], set()
    queue = _dependencies(text, pkg)
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_text = msg_definition(dep)
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{dep_text}")
        queue.extend(_dependencies(dep_text, dep.split("/")[0]))
    return "\n".join(p.rstrip("\n") for p in parts) + "\n"


def provisional_tail() -> bytes:
    """Data End (no CRC), a Footer without summary and the magic: a valid MCAP ending."""
    builder = RecordBuilder()
    DataEnd(0).write(builder)
    Footer(0, 0, 0).write(builder)
    return builder.end() + MAGIC


TAIL = provisional_tail()
PART_SUFFIX = ".part"  # a file being created: `.<name>_<k>.mcap.part`, renamed once whole
TORN_SAMPLES = 4096    # the last solves whose write time `torn_window_ns` keeps
MIN_CAP_FILES = 3      # max_total_bytes >= this many max_bytes (see McapRecorder)


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


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    """`os.pwrite` until all of `data` is at `offset` (a short write is continued; the call that
    cannot go on raises, e.g. ENOSPC or EFBIG)."""
    view, done = memoryview(data), 0
    while done < len(data):
        n = os.pwrite(fd, view[done:], offset + done)
        if n <= 0:
            raise OSError(errno.EIO, f"write returned {n}")
        done += n


def _put_back_ending(fd: int, data_end: int) -> None:
    """Cut the file to its data plus a provisional ending and write that ending (after a failed
    or undone write); needs no new disk space."""
    os.ftruncate(fd, data_end + len(TAIL))
    _pwrite_all(fd, TAIL, data_end)
    os.fsync(fd)


def check_record_dir(directory: str | Path) -> Path:
    """Create the bag folder if needed and check that files can be created in it.

    Returns the folder. Raises:
        ConfigError: naming the path and why it cannot be used (a regular file in the way, no
            write permission, a read-only file system, ...).
    """
    directory = Path(directory)
    for path in (directory, *directory.parents):
        if path.exists():
            if not path.is_dir():
                raise ConfigError(f"record_dir {directory} cannot be used: {path} is a file, "
                                  "not a folder")
            break
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write_probe.{os.getpid()}"
        try:
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            try:
                os.write(fd, b"\0")
            finally:
                os.close(fd)
        finally:
            probe.unlink(missing_ok=True)
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise ConfigError(f"record_dir {directory} cannot be used: files cannot be created in "
                          f"it ({why})") from exc
    return directory


@dataclass
class _File:
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
class _ClosedFile:
    info: FileInfo
    topic_counts: Counter
    size: int  # [bytes]


class McapRecorder:
    """Context-managed MCAP writer for a node run (one bag folder, rotated files).

    Args:
        directory: the bag folder (created on the first solve).
        metadata: run metadata (values that are not strings are stored as JSON).
        max_bytes: a file is closed and a new one started once it reaches this size [bytes].
        name: file name stem, files are `<name>_<k>.mcap`.
        topics: resolved topic name -> 'pkg/msg/Type' of everything `record_solve` may get;
            `TOPICS` when None.
        max_total_bytes: cap on the size of the bag's files [bytes]; 0 = unbounded. Retention:
            when a file is closed at a rotation, the oldest closed files are deleted until the
            closed files plus a full new file (`max_bytes`) fit under the cap; the file being
            written is never deleted. `metadata.yaml` is rewritten without them first (files,
            counts, start time; `custom_data` counts the dropped files and messages), then they
            are deleted. At least `MIN_CAP_FILES` * `max_bytes` (a closed file exceeds
            `max_bytes` by up to one solve and its summary, so one closed file always stays).

    Raises:
        ConfigError: if `directory` already holds a recording (a bag is never overwritten) or
            the cap is below its minimum.
    """

    def __init__(self, directory: str | Path, metadata: dict | None = None,
                 max_bytes: int = 256 * 1024 * 1024, name: str = "guidance",
                 topics: dict[str, str] | None = None, max_total_bytes: int = 0) -> None:
        self.directory = Path(directory)
        if self.directory.is_dir() and any(self.directory.glob("*.mcap*")):
            raise ConfigError(f"{self.directory} already holds a recording; choose another "
                              "record_dir (or move that one away): a bag is never overwritten")
        self.max_bytes = int(max_bytes)
        self.max_total_bytes = int(max_total_bytes)
        check_cap(self.max_total_bytes, self.max_bytes)
        self.metadata = {k: v if isinstance(v, str) else json.dumps(v)
                         for k, v in (metadata or {}).items()}
        self.name = name
        self.topics = dict(topics or TOPICS)
        self.files: list[Path] = []  # every file created, in order (deleted ones included)
        self.solves = 0
        self.errors = 0
        self.last_error = ""
        self.dropped_files = 0
        self.dropped_messages = 0
        self.torn_window_ns: deque[int] = deque(maxlen=TORN_SAMPLES)  # per solve: the write
        self._file: _File | None = None
        self._closed_files: list[_ClosedFile] = []
        self._schemas = {t: ros2msg_schema(t) for t in set(self.topics.values())}
        self._hashes = {t: type_description_hash(t) for t in self._schemas}
        self._encoders = {topic: serialize_dynamic(t, self._schemas[t])[t]
                          for topic, t in self.topics.items()}
        self._closed = False

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.finish()

    def _new_file(self) -> _File:
        """A file in memory: header, schemas, channels and run metadata (nothing on disk)."""
        stream = OffsetStream()
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="art_guidance")
        handle = _File(self.directory / f"{self.name}_{len(self.files)}.mcap", writer, stream)
        schema_ids = {t: writer.register_schema(name=t, encoding="ros2msg", data=text.encode())
                      for t, text in self._schemas.items()}
        for topic, msg_type in self.topics.items():
            handle.channels[topic] = writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema_ids[msg_type],
                metadata={"offered_qos_profiles": "", "topic_type_hash": self._hashes[msg_type]})
        writer.add_metadata("art_guidance", self.metadata)
        return handle

    def _create(self, handle: _File, data: bytes) -> None:
        """Put a new file's first bytes on disk: written whole and fsync'ed under a hidden
        name, then renamed, so a failure or a kill never leaves a stub `.mcap`."""
        self.directory.mkdir(parents=True, exist_ok=True)
        part = handle.path.with_name(f".{handle.path.name}{PART_SUFFIX}")
        fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
        renamed = False
        try:
            # held while this file is written; `bag reindex` leaves a locked file alone
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            _pwrite_all(fd, data, 0)
            os.fsync(fd)
            os.rename(part, handle.path)
            renamed = True
            fsync_dir(self.directory)
        except BaseException:
            os.close(fd)
            (handle.path if renamed else part).unlink(missing_ok=True)
            raise
        handle.fd = fd
        self.files.append(handle.path)

    def _append(self, handle: _File, data: bytes) -> None:
        """Write `data` (whole chunks) and a provisional ending over the old ending: one write
        (the torn window), then fsync."""
        if handle.fd < 0:
            self._create(handle, data + TAIL)
        else:
            start = time.perf_counter_ns()
            _pwrite_all(handle.fd, data + TAIL, handle.data_end)
            self.torn_window_ns.append(time.perf_counter_ns() - start)
            os.fsync(handle.fd)
        handle.data_end += len(data)

    def _drop_file(self, handle: _File, keep_end: int) -> None:
        """Close a file after a failed or undone write, cut back to `keep_end` (0: the file
        was created by that write and is removed). Its writer holds the failed chunk in its
        indexes, so the file keeps a provisional ending (no summary; `bag reindex` adds one)."""
        if self._file is handle:
            self._file = None
        if handle.fd < 0:
            return
        try:
            if keep_end == 0:
                handle.path.unlink(missing_ok=True)
                self.files.remove(handle.path)
                fsync_dir(self.directory)
            else:
                handle.data_end = keep_end
                _put_back_ending(handle.fd, keep_end)
        except OSError as exc:  # already failing: the first error is the one reported
            LOG.error("could not restore the ending of %s (`art-guidance bag reindex` repairs "
                      "it): %s", handle.path, exc)
        finally:
            os.close(handle.fd)
            handle.fd = -1
        if keep_end:
            self._closed_files.append(_ClosedFile(handle.info(), Counter(handle.topic_counts),
                                                  keep_end + len(TAIL)))

    def _close_file(self) -> None:
        """Close the current file with its summary (one write over the provisional ending)."""
        handle, self._file = self._file, None
        if handle is None or handle.fd < 0:
            return
        size = handle.data_end + len(TAIL)
        try:
            handle.writer.finish()
            data = handle.stream.take()
            _pwrite_all(handle.fd, data, handle.data_end)
            os.fsync(handle.fd)
            size = handle.data_end + len(data)
        except Exception as exc:
            self._fail(exc)
            try:
                _put_back_ending(handle.fd, handle.data_end)
            except OSError as again:
                LOG.error("could not restore the ending of %s: %s", handle.path, again)
        finally:
            os.close(handle.fd)
            handle.fd = -1
        self._closed_files.append(_ClosedFile(handle.info(), Counter(handle.topic_counts), size))

    def finish(self) -> None:
        """Finish the current file and write the final metadata.yaml. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._close_file()
            self._write_bag_metadata("finished")
        except Exception as exc:  # never raises into the caller
            self._fail(exc)

    # ------------------------------------------------------------------ writing
    def record_solve(self, messages: Iterable[tuple[str, object]], log_time_ns: int) -> bool:
        """Write one solve's (topic, message) pairs in a chunk of their own with one write over
        the file's ending, fsync, then rewrite metadata.yaml (see the module docstring).

        Returns False (and logs) on any error, with the folder as it was; never raises.
        """
        if self._closed:
            return False
        handle = None
        try:
            encoded = [(topic, bytes(self._encoders[topic](_plain(msg))))
                       for topic, msg in messages]
            handle = self._file = self._file or self._new_file()
            created, keep_end = handle.fd < 0, handle.data_end
            for topic, data in encoded:
                handle.writer.add_message(handle.channels[topic], log_time_ns, data,
                                          log_time_ns)
            handle.writer.flush()  # the chunk, compressed, into memory
            self._append(handle, handle.stream.take())
        except Exception as exc:  # full disk, unwritable path, size limit, bad message ...
            return self._failed(exc, handle, None if handle is None else handle.data_end)
        undo = self._count(handle, [topic for topic, _ in encoded], log_time_ns)
        try:
            self._write_bag_metadata("recording")
        except Exception as exc:  # the data without its metadata.yaml is undone
            undo()
            return self._failed(exc, handle, 0 if created else keep_end)
        if handle.data_end + len(TAIL) >= self.max_bytes:
            self._close_file()
            self._apply_cap()
        return True

    def _failed(self, exc: Exception, handle: _File | None, keep_end: int | None) -> bool:
        """Report a failed solve, close the file at its last whole solve (keep_end None: the
        file was not touched) and say so in metadata.yaml when it can be written."""
        self._fail(exc)
        if handle is not None and keep_end is not None:
            self._drop_file(handle, keep_end)
        try:
            self._write_bag_metadata("write_failed")
        except Exception:  # already failing: the first error is the one reported
            pass
        return False

    def _count(self, handle: _File, topics: list[str], log_time_ns: int):
        """Count a written solve; returns the function that takes it back."""
        before = (handle.start_ns, handle.end_ns, handle.count, self.solves)
        for topic in topics:
            handle.topic_counts[topic] += 1
        handle.start_ns = min(handle.start_ns, log_time_ns) if handle.count else log_time_ns
        handle.end_ns = max(handle.end_ns, log_time_ns)
        handle.count += len(topics)
        self.solves += 1

        def undo() -> None:
            handle.start_ns, handle.end_ns, handle.count, self.solves = before
            for topic in topics:
                handle.topic_counts[topic] -= 1
        return undo

    def _apply_cap(self) -> None:
        """The retention rule of `max_total_bytes` (see the class docstring)."""
        if not self.max_total_bytes:
            return
        dropped = []
        while self._closed_files and (sum(f.size for f in self._closed_files) + self.max_bytes
                                      > self.max_total_bytes):
            dropped.append(self._closed_files.pop(0))
        if not dropped:
            return
        for gone in dropped:
            self.dropped_messages += gone.info.message_count
        self.dropped_files += len(dropped)
        try:
            self._write_bag_metadata("recording")  # first: it never lists a deleted file
        except Exception as exc:  # keep them; the next rotation tries again
            self._fail(exc)
            self._closed_files[:0] = dropped
            for gone in dropped:
                self.dropped_messages -= gone.info.message_count
            self.dropped_files -= len(dropped)
            return
        for gone in dropped:
            (self.directory / gone.info.path).unlink(missing_ok=True)
        fsync_dir(self.directory)
        LOG.info("recording cap %d bytes: deleted %s", self.max_total_bytes,
                 ", ".join(f.info.path for f in dropped))

    @property
    def counts(self) -> dict[str, int]:
        """Messages per topic in the bag's files: the closed ones kept and the current one."""
        total: Counter = Counter()
        for closed in self._closed_files:
            total.update(closed.topic_counts)
        if self._file is not None:
            total.update(self._file.topic_counts)
        return {topic: total[topic] for topic in self.topics}

    def _fail(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        LOG.error("MCAP recording failed: %s", self.last_error)

    def _write_bag_metadata(self, state: str) -> None:
        """rosbag2 metadata.yaml describing what is on disk (see `bag_metadata`)."""
        files = [f.info for f in self._closed_files]
        if self._file is not None and self._file.fd >= 0:
            files.append(self._file.info())
        if not files and not self.errors:
            return
        counts = self.counts
        topics = [TopicInfo(topic, t, counts[topic], self._hashes[t])
                  for topic, t in self.topics.items()]
        custom = {"art_guidance.writer": "McapRecorder", "art_guidance.state": state}
        if self.errors:
            custom.update({"art_guidance.write_errors": self.errors,
                           "art_guidance.last_error": self.last_error})
        if self.max_total_bytes:
            custom.update({"art_guidance.max_total_bytes": self.max_total_bytes,
                           "art_guidance.dropped_files": self.dropped_files,
                           "art_guidance.dropped_messages": self.dropped_messages})
        write_bag_metadata(self.directory, files, topics, custom)


def check_cap(max_total_bytes: int, max_bytes: int) -> None:
    """Raises ConfigError unless the cap is 0 (none) or at least `MIN_CAP_FILES` files."""
    if max_total_bytes < 0:
        raise ConfigError(f"record_max_total_bytes must be >= 0, got {max_total_bytes}")
    if max_total_bytes and max_total_bytes < MIN_CAP_FILES * max_bytes:
        raise ConfigError(
            f"record_max_total_bytes must be 0 (no cap) or >= {MIN_CAP_FILES} * "
            f"record_max_bytes = {MIN_CAP_FILES * max_bytes}, got {max_total_bytes}: a closed "
            "file exceeds record_max_bytes by up to one solve, and at least one closed file "
            "is kept beside the one being written")


def _plain(msg: object) -> SimpleNamespace:
    """A ROS message as nested namespaces of Python lists/scalars (what the encoder takes)."""
    out = {}
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if hasattr(value, "get_fields_and_field_types"):
            value = _plain(value)
        elif isinstance(value, (list, tuple)):
            value = [_plain(v) if hasattr(v, "get_fields_and_field_types") else v for v in value]
        elif not isinstance(value, (str, bytes, bool, int, float)):
            value = list(value)  # numpy arrays (fixed size) and array.array (sequences)
        out[name] = value
    return SimpleNamespace(**out)


def default_log_dir() -> Path:
    """<ROS_HOME or ~/.ros>/art_guidance_logs/<UTC timestamp>_<pid>."""
    home = Path(os.environ.get("ROS_HOME", Path.home() / ".ros"))
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return home / "art_guidance_logs" / f"{stamp}_{os.getpid()}"
