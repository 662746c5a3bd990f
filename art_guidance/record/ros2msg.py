"""The ROS 2 side of a recording: `ros2msg` schemas of the installed interface types, their
RIHS01 hashes, and the CDR encoder of a message type.

Payloads are encoded from the embedded schema by mcap_ros2's CDR encoder rather than by
rclpy/Fast-CDR: Fast-CDR pads an empty float64 sequence to 8-byte alignment, which exact-size
readers (rosbags) reject; the schema-driven encoder follows the CDR rule and both read it.

Types are found under `<prefix>/share/<pkg>/msg/` of every `AMENT_PREFIX_PATH` entry and of
`sys.prefix` (`.msg` for the definition, `.json` for the hash).
"""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

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

SEPARATOR = "=" * 80
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


def cdr_encoder(msg_type: str, schema: str) -> Callable[[SimpleNamespace], bytes]:
    """The CDR encoder of `msg_type` from its `ros2msg` schema; it takes `plain_message`'s
    namespaces and returns the payload (bytes-like)."""
    return serialize_dynamic(msg_type, schema)[msg_type]


def plain_message(msg: object) -> SimpleNamespace:
    """A ROS message as nested namespaces of Python lists/scalars (what the encoder takes)."""
    out = {}
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if hasattr(value, "get_fields_and_field_types"):
            value = plain_message(value)
        elif isinstance(value, (list, tuple)):
            value = [plain_message(v) if hasattr(v, "get_fields_and_field_types") else v
                     for v in value]
        elif not isinstance(value, (str, bytes, bool, int, float)):
            value = list(value)  # numpy arrays (fixed size) and array.array (sequences)
        out[name] = value
    return SimpleNamespace(**out)
