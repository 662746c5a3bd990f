"""rosbag2 `metadata.yaml` for a folder of MCAP files, in the version ROS 2 Jazzy writes (9).

What Jazzy's rosbag2_storage reads (`yaml.hpp` / `qos.cpp`), by the version declared:

- always: `version`, `storage_identifier`, `duration.nanoseconds`,
  `starting_time.nanoseconds_since_epoch`, `message_count`, `relative_file_paths` and
  `topics_with_message_count` (each `message_count` and `topic_metadata` with `name`, `type`,
  `serialization_format`);
- from 3: `compression_format`, `compression_mode`;
- from 4: `topic_metadata.offered_qos_profiles` (a YAML string up to 8, a YAML list from 9);
- from 5: `files`, each `path`, `starting_time.nanoseconds_since_epoch`,
  `duration.nanoseconds`, `message_count`;
- from 6: `custom_data` (string to string map); from 7: `topic_metadata.type_description_hash`;
- from 8: `ros_distro`; 9: QoS profiles as a list with policy names (`reliable`, ...).

Empty `offered_qos_profiles` means "not recorded": `ros2 bag play` then offers its default
profile (reliable, volatile, keep last 10).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from art_guidance.files import dump_yaml, write_atomic

METADATA_VERSION = 9
METADATA_FILE = "metadata.yaml"


def bag_files(directory: str | Path) -> list[Path]:
    """The folder's MCAP files in recording order (`<name>_<k>.mcap`, k ascending)."""
    return sorted(Path(directory).glob("*.mcap"), key=lambda p: (len(p.name), p.name))


@dataclass(frozen=True)
class FileInfo:
    """One storage file of the bag: its name, time span [ns] and message count."""

    path: str
    start_ns: int
    end_ns: int
    message_count: int


@dataclass(frozen=True)
class TopicInfo:
    """One recorded topic: resolved name, 'pkg/msg/Type', message count, RIHS01 hash or ''."""

    name: str
    msg_type: str
    message_count: int
    type_hash: str = ""


def _time(start_ns: int, end_ns: int) -> dict:
    return {"starting_time": {"nanoseconds_since_epoch": int(start_ns)},
            "duration": {"nanoseconds": max(0, int(end_ns) - int(start_ns))}}


def bag_metadata(files: list[FileInfo], topics: list[TopicInfo],
                 custom_data: dict[str, str] | None = None) -> dict:
    """The `metadata.yaml` document (version `METADATA_VERSION`) describing `files`."""
    counted = [f for f in files if f.message_count]
    start = min((f.start_ns for f in counted), default=0)
    end = max((f.end_ns for f in counted), default=0)
    info = {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        **_time(start, end),
        "message_count": sum(f.message_count for f in files),
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.name, "type": t.msg_type,
                                "serialization_format": "cdr", "offered_qos_profiles": [],
                                "type_description_hash": t.type_hash},
             "message_count": t.message_count}
            for t in topics],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [f.path for f in files],
        "files": [{"path": f.path, **_time(f.start_ns, f.end_ns),
                   "message_count": f.message_count} for f in files],
        "custom_data": {str(k): str(v) for k, v in (custom_data or {}).items()},
        "ros_distro": os.environ.get("ROS_DISTRO", "jazzy"),
    }
    return {"rosbag2_bagfile_information": info}


def write_bag_metadata(directory: str | Path, files: list[FileInfo], topics: list[TopicInfo],
                       custom_data: dict[str, str] | None = None) -> Path:
    """Write `<directory>/metadata.yaml` atomically; returns its path."""
    path = Path(directory) / METADATA_FILE
    text = dump_yaml(bag_metadata(files, topics, custom_data))
    write_atomic(path, text.encode())
    return path
