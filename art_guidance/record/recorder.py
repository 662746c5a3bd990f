"""Record every solve to MCAP: ROS 2 `cdr` payloads with `ros2msg` schemas (rosbag2 layout).

Payloads are encoded from the embedded schema by mcap_ros2's CDR encoder rather than by
rclpy/Fast-CDR: Fast-CDR pads an empty float64 sequence to 8-byte alignment, which exact-size
readers (rosbags) reject; the schema-driven encoder follows the CDR rule and both read it.

A run writes one folder that is a rosbag2 bag: `metadata.yaml` plus `<name>_<k>.mcap` files,
rotated by size. Each solve is written as a group of messages (the nav state that triggered it,
the replan request in force, a `SolveRecord` with warm starts, SCP history and timings, and the
published `ManeuverPlan`), after which the chunk is closed, flushed and fsync'ed: a kill -9 loses
at most the solve being written. Run metadata (config, versions, model checksum) goes into an
MCAP metadata record. Write failures (full disk, unwritable path) are logged and counted; they
never raise into the caller.
"""
from __future__ import annotations

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

from mcap.writer import CompressionType, Writer
# The encoder mcap_ros2's own Writer uses (see the module docstring for why not Fast-CDR); its
# public Writer owns the file and cannot flush and fsync per solve.
from mcap_ros2._dynamic import serialize_dynamic

from art_guidance.files import write_atomic

LOG = logging.getLogger("art_guidance.record.recorder")
SEPARATOR = "=" * 80
TOPICS = {
    "/nav/relative_state": "art_guidance_msgs/msg/RelativeNavState",
    "/guidance/replan_request": "art_guidance_msgs/msg/ReplanRequest",
    "/guidance/solve_record": "art_guidance_msgs/msg/SolveRecord",
    "/guidance/maneuver_plan": "art_guidance_msgs/msg/ManeuverPlan",
}
_BUILTIN = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
            "int32", "uint32", "int64", "uint64", "string", "wstring"}


def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    return [Path(p) / "share" for p in prefixes]


def msg_definition(msg_type: str) -> str:
    """The .msg text of 'pkg/msg/Name' (or 'pkg/Name') from the installed share directories."""
    pkg, name = msg_type.split("/")[0], msg_type.split("/")[-1]
    for share in _share_dirs():
        path = share / pkg / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text(encoding="utf-8")
    raise FileNotFoundError(f"no definition for {msg_type} under {_share_dirs()}")


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


@dataclass
class _File:
    path: Path
    writer: Writer
    stream: object
    channels: dict = field(default_factory=dict)


class McapRecorder:
    """Context-managed MCAP writer for a node run (one bag folder, rotated files)."""

    def __init__(self, directory: str | Path, metadata: dict | None = None,
                 max_bytes: int = 256 * 1024 * 1024, name: str = "guidance") -> None:
        self.directory = Path(directory)
        self.metadata = {k: v if isinstance(v, str) else json.dumps(v)
                         for k, v in (metadata or {}).items()}
        self.max_bytes = int(max_bytes)
        self.name = name
        self.files: list[Path] = []
        self.counts = {topic: 0 for topic in TOPICS}
        self.solves = 0
        self.errors = 0
        self.last_error = ""
        self._file: _File | None = None
        self._encoders = {topic: serialize_dynamic(t, ros2msg_schema(t))[t]
                          for topic, t in TOPICS.items()}
        self._start_ns: int | None = None
        self._end_ns = 0
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
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="art_guidance")
        handle = _File(path, writer, stream)
        for topic, msg_type in TOPICS.items():
            schema_id = writer.register_schema(name=msg_type, encoding="ros2msg",
                                               data=ros2msg_schema(msg_type).encode())
            handle.channels[topic] = writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema_id,
                metadata={"offered_qos_profiles": ""})
        writer.add_metadata("art_guidance", self.metadata)
        writer.flush()
        self.files.append(path)
        return handle

    def _close_file(self) -> None:
        if self._file is not None:
            try:
                self._file.writer.finish()
            finally:
                self._file.stream.close()
                self._file = None

    def finish(self) -> None:
        """Finish the current file and write metadata.yaml. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._close_file()
            self._write_bag_metadata()
        except OSError as exc:
            self._fail(exc)

    # ------------------------------------------------------------------ writing
    def record_solve(self, messages: Iterable[tuple[str, object]], log_time_ns: int) -> bool:
        """Write one solve's (topic, message) pairs, close the chunk and fsync.

        Returns False (and logs) on any write error; never raises.
        """
        if self._closed:
            return False
        try:
            if self._file is None:
                self._file = self._open()
            for topic, msg in messages:
                data = bytes(self._encoders[topic](_plain(msg)))
                self._file.writer.add_message(self._file.channels[topic], log_time_ns,
                                              data, log_time_ns)
                self.counts[topic] += 1
            self._file.writer.flush()
            os.fsync(self._file.stream.fileno())
            self.solves += 1
            self._start_ns = log_time_ns if self._start_ns is None else self._start_ns
            self._end_ns = max(self._end_ns, log_time_ns)
            if self._file.path.stat().st_size >= self.max_bytes:
                self._close_file()
            return True
        except Exception as exc:  # full disk, unwritable path, closed stream ...
            self._fail(exc)
            self._file = None
            return False

    def _fail(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        LOG.error("MCAP recording failed: %s", self.last_error)

    def _write_bag_metadata(self) -> None:
        """rosbag2 metadata.yaml so the folder plays with `ros2 bag play`."""
        if not self.files:
            return
        start = self._start_ns or 0
        topics = "".join(
            f"    - topic_metadata:\n        name: {topic}\n        type: {msg_type}\n"
            f"        serialization_format: cdr\n        offered_qos_profiles: ''\n"
            f"      message_count: {self.counts[topic]}\n"
            for topic, msg_type in TOPICS.items())
        files = "".join(f"    - {p.name}\n" for p in self.files)
        text = (
            "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n"
            f"  relative_file_paths:\n{files}"
            f"  duration:\n    nanoseconds: {max(0, self._end_ns - start)}\n"
            f"  starting_time:\n    nanoseconds_since_epoch: {start}\n"
            f"  message_count: {sum(self.counts.values())}\n"
            f"  topics_with_message_count:\n{topics}"
            "  compression_format: ''\n  compression_mode: ''\n")
        write_atomic(self.directory / "metadata.yaml", text.encode())


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
