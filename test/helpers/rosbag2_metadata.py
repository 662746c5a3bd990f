"""What ROS 2 Jazzy's rosbag2 requires of metadata.yaml, per declared version.

Transcribed from rosbag2_storage (Jazzy): `include/rosbag2_storage/yaml.hpp` (BagMetadata,
TopicInformation, TopicMetadata and FileInformation decoders) and `src/rosbag2_storage/qos.cpp`
(QoS profile decoder). A key the decoder reads with `node[key].as<T>()` is required once the
declared version reaches the one that introduced it; a missing key or a wrong type makes
`ros2 bag info` / `ros2 bag play` fail. Jazzy writes version 9 and reads 1 to 9.
"""
from __future__ import annotations

from pathlib import Path

import yaml

JAZZY_VERSION = 9
_TIME = {"sec": int, "nsec": int}
_QOS_V9 = {"history": (int, str), "reliability": str, "durability": str, "liveliness": str,
           "deadline": _TIME, "lifespan": _TIME, "liveliness_lease_duration": _TIME,
           "avoid_ros_namespace_conventions": bool}


def _check(node: object, spec: dict, where: str, problems: list[str]) -> None:
    """Every key of `spec` present in `node` with the type (or nested spec) given."""
    if not isinstance(node, dict):
        problems.append(f"{where}: expected a map, got {type(node).__name__}")
        return
    for key, kind in spec.items():
        if key not in node:
            problems.append(f"{where}.{key}: missing")
        elif isinstance(kind, dict):
            _check(node[key], kind, f"{where}.{key}", problems)
        elif not isinstance(node[key], kind) or (kind is int and isinstance(node[key], bool)):
            problems.append(f"{where}.{key}: {node[key]!r} is not {kind}")
        elif kind is int and node[key] < 0:  # read as uint64
            problems.append(f"{where}.{key}: negative")


def _qos_problems(profiles: object, version: int, where: str) -> list[str]:
    problems: list[str] = []
    if version < 9:  # a YAML string (empty = none), parsed by to_rclcpp_qos_vector
        if not isinstance(profiles, str):
            problems.append(f"{where}: must be a string before version 9")
        return problems
    if not isinstance(profiles, list):
        return [f"{where}: must be a list from version 9"]
    for k, qos in enumerate(profiles):
        spec = dict(_QOS_V9)
        if isinstance(qos, dict) and qos.get("history") in ("keep_last", 1):
            spec["depth"] = int
        _check(qos, spec, f"{where}[{k}]", problems)
    return problems


def _topic_problems(entry: object, version: int, where: str) -> list[str]:
    problems: list[str] = []
    _check(entry, {"message_count": int, "topic_metadata": {
        "name": str, "type": str, "serialization_format": str}}, where, problems)
    meta = entry.get("topic_metadata") if isinstance(entry, dict) else None
    if not isinstance(meta, dict):
        return problems
    if version >= 4:
        if "offered_qos_profiles" not in meta:
            problems.append(f"{where}.topic_metadata.offered_qos_profiles: missing")
        else:
            problems += _qos_problems(meta["offered_qos_profiles"], version,
                                      f"{where}.topic_metadata.offered_qos_profiles")
    if version >= 7:
        _check(meta, {"type_description_hash": str}, f"{where}.topic_metadata", problems)
    return problems


def metadata_problems(doc: object) -> list[str]:
    """Everything Jazzy's rosbag2 would refuse in a parsed metadata.yaml ([] = accepted)."""
    problems: list[str] = []
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        return ["rosbag2_bagfile_information: missing"]
    version = info.get("version")
    if not isinstance(version, int) or not 1 <= version <= JAZZY_VERSION:
        return [f"version: {version!r} is not one Jazzy reads (1..{JAZZY_VERSION})"]
    spec = {"storage_identifier": str, "duration": {"nanoseconds": int},
            "starting_time": {"nanoseconds_since_epoch": int}, "message_count": int,
            "topics_with_message_count": list, "relative_file_paths": list}
    if version >= 3:
        spec.update(compression_format=str, compression_mode=str)
    if version >= 5:
        spec["files"] = list
    if version >= 8:
        spec["ros_distro"] = str
    _check(info, spec, "info", problems)
    custom = info.get("custom_data", "missing")
    if version >= 6 and not (custom is None or isinstance(custom, dict)):
        problems.append("info.custom_data: missing or not a map (null allowed)")
    for k, entry in enumerate(info.get("topics_with_message_count") or []):
        problems += _topic_problems(entry, version, f"info.topics_with_message_count[{k}]")
    for k, entry in enumerate((info.get("files") or []) if version >= 5 else []):
        _check(entry, {"path": str, "starting_time": {"nanoseconds_since_epoch": int},
                       "duration": {"nanoseconds": int}, "message_count": int},
               f"info.files[{k}]", problems)
    return problems


def consistency_problems(directory: Path) -> list[str]:
    """Counts and file lists of a bag folder's metadata.yaml agree with each other and disk."""
    info = yaml.safe_load((directory / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    files, problems = info["files"], []
    if [f["path"] for f in files] != info["relative_file_paths"]:
        problems.append("files[].path differs from relative_file_paths")
    problems += [f"{p} listed but not on disk" for p in info["relative_file_paths"]
                 if not (directory / p).is_file()]
    total = info["message_count"]
    if sum(f["message_count"] for f in files) != total:
        problems.append("files[].message_count does not add up to message_count")
    if sum(t["message_count"] for t in info["topics_with_message_count"]) != total:
        problems.append("topic message counts do not add up to message_count")
    return problems
