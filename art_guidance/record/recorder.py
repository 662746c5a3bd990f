"""Record every solve to MCAP: ROS 2 `cdr` payloads with `ros2msg` schemas (rosbag2 layout).

Payloads are encoded from the embedded schema by mcap_ros2's CDR encoder rather than by
rclpy/Fast-CDR: Fast-CDR pads an empty float64 sequence to 8-byte alignment, which exact-size
readers (rosbags) reject; the schema-driven encoder follows the CDR rule and both read it.

A run writes one folder that is a rosbag2 bag: `metadata.yaml` plus `<name>_<k>.mcap` files,
rotated by size. Topic names and types come from the caller (the node passes its resolved
names); `TOPICS` is the default. Each solve is written as a group of messages (the nav state
that triggered it, the replan request when it changed, a `SolveRecord` with warm starts, SCP
history and timings, and the published `ManeuverPlan`), after which the chunk is closed and the
file is sealed: a Data End record, a Footer without summary and the closing magic are written
after the chunk, flushed and fsync'ed, and overwritten by the next solve. Then `metadata.yaml`
is rewritten atomically. A kill -9 outside the few milliseconds of a write therefore leaves a
folder that rosbag2 readers open as it is; a file torn inside a write is repaired by
`art-guidance bag reindex` (see `record.reindex`). Run metadata (config, versions, model
checksum) goes into an MCAP metadata record. Write failures (full disk, unwritable path) are
logged and counted; they never raise into the caller.
"""
from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Iterable

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import CompressionType, Writer
# The encoder mcap_ros2's own Writer uses (see the module docstring for why not Fast-CDR); its
# public Writer owns the file and cannot flush and fsync per solve.
from mcap_ros2._dynamic import serialize_dynamic

from art_guidance import topics
from art_guidance.errors import ConfigError
from art_guidance.record.bag_metadata import FileInfo, TopicInfo, write_bag_metadata

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


@dataclass
class _File:
    path: Path
    writer: Writer
    stream: object
    channels: dict = field(default_factory=dict)
    data_end: int = 0  # where the next chunk goes (the provisional ending starts here)
    start_ns: int = 0
    end_ns: int = 0
    count: int = 0

    def info(self) -> FileInfo:
        return FileInfo(self.path.name, self.start_ns, self.end_ns, self.count)


class McapRecorder:
    """Context-managed MCAP writer for a node run (one bag folder, rotated files).

    Args:
        directory: the bag folder (created on the first solve).
        metadata: run metadata (values that are not strings are stored as JSON).
        max_bytes: a file is closed and a new one started once it reaches this size [bytes].
        name: file name stem, files are `<name>_<k>.mcap`.
        topics: resolved topic name -> 'pkg/msg/Type' of everything `record_solve` may get;
            `TOPICS` when None.

    Raises:
        ConfigError: if `directory` already holds a recording (a bag is never overwritten).
    """

    def __init__(self, directory: str | Path, metadata: dict | None = None,
                 max_bytes: int = 256 * 1024 * 1024, name: str = "guidance",
                 topics: dict[str, str] | None = None) -> None:
        self.directory = Path(directory)
        if self.directory.is_dir() and any(self.directory.glob("*.mcap*")):
            raise ConfigError(f"{self.directory} already holds a recording; choose another "
                              "record_dir (or move that one away): a bag is never overwritten")
        self.metadata = {k: v if isinstance(v, str) else json.dumps(v)
                         for k, v in (metadata or {}).items()}
        self.max_bytes = int(max_bytes)
        self.name = name
        self.topics = dict(topics or TOPICS)
        self.files: list[Path] = []
        self.counts = {topic: 0 for topic in self.topics}
        self.solves = 0
        self.errors = 0
        self.last_error = ""
        self._file: _File | None = None
        self._closed_files: list[FileInfo] = []
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

    def _open(self) -> _File:
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"{self.name}_{len(self.files)}.mcap"
        stream = open(path, "wb")
        # held while this file is written; `bag reindex` leaves a locked file alone
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="art_guidance")
        handle = _File(path, writer, stream)
        schema_ids = {t: writer.register_schema(name=t, encoding="ros2msg", data=text.encode())
                      for t, text in self._schemas.items()}
        for topic, msg_type in self.topics.items():
            handle.channels[topic] = writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema_ids[msg_type],
                metadata={"offered_qos_profiles": "", "topic_type_hash": self._hashes[msg_type]})
        writer.add_metadata("art_guidance", self.metadata)
        writer.flush()
        handle.data_end = stream.tell()
        self.files.append(path)
        return handle

    @staticmethod
    def _seal(handle: _File) -> None:
        """Append a provisional MCAP ending after the last chunk and fsync; the next write
        starts at `data_end`, over that ending."""
        handle.data_end = handle.stream.tell()
        handle.stream.write(provisional_tail())
        handle.stream.flush()
        os.fsync(handle.stream.fileno())

    def _close_file(self, summary: bool = True) -> None:
        """Close the current file with its summary, or (after a failed write) cut it back to
        the last sealed solve. A file that cannot be closed whole stays out of metadata.yaml
        (`bag reindex` repairs it)."""
        handle, self._file = self._file, None
        if handle is None:
            return
        try:
            handle.stream.seek(handle.data_end)
            handle.stream.truncate()
            if summary:
                handle.writer.finish()
            else:
                handle.stream.write(provisional_tail())
            handle.stream.flush()
            os.fsync(handle.stream.fileno())
            self._closed_files.append(handle.info())
        finally:
            handle.stream.close()

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
        """Write one solve's (topic, message) pairs, close the chunk, seal the file and fsync,
        then rewrite metadata.yaml.

        Returns False (and logs) on any write error; never raises.
        """
        if self._closed:
            return False
        try:
            if self._file is None:
                self._file = self._open()
            handle = self._file
            handle.stream.seek(handle.data_end)
            handle.stream.truncate()  # drop the provisional ending of the previous solve
            written = []
            for topic, msg in messages:
                data = bytes(self._encoders[topic](_plain(msg)))
                handle.writer.add_message(handle.channels[topic], log_time_ns, data,
                                          log_time_ns)
                written.append(topic)
            handle.writer.flush()
            self._seal(handle)
            self._count(handle, written, log_time_ns)
            if handle.path.stat().st_size >= self.max_bytes:
                self._close_file()
            self._write_bag_metadata("recording")
            return True
        except Exception as exc:  # full disk, unwritable path, closed stream ...
            self._fail(exc)
            try:  # best effort: keep the file's sealed solves; the next solve starts a new file
                self._close_file(summary=False)
            except Exception:  # already failing: the first error is the one reported
                pass
            return False

    def _count(self, handle: _File, topics: list[str], log_time_ns: int) -> None:
        for topic in topics:
            self.counts[topic] += 1
        handle.start_ns = min(handle.start_ns, log_time_ns) if handle.count else log_time_ns
        handle.end_ns = max(handle.end_ns, log_time_ns)
        handle.count += len(topics)
        self.solves += 1

    def _fail(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        LOG.error("MCAP recording failed: %s", self.last_error)

    def _write_bag_metadata(self, state: str) -> None:
        """rosbag2 metadata.yaml describing what is on disk (see `bag_metadata`)."""
        files = self._closed_files + ([self._file.info()] if self._file is not None else [])
        if not files:
            return
        topics = [TopicInfo(topic, t, self.counts[topic], self._hashes[t])
                  for topic, t in self.topics.items()]
        write_bag_metadata(self.directory, files, topics,
                           {"art_guidance.writer": "McapRecorder",
                            "art_guidance.state": state})


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
