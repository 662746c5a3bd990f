"""The bag folder of a run: where it goes by default, the check that it can be written at
start, and how large it may grow (retention under `max_total_bytes`).

Retention: when a file is closed at a rotation, the oldest closed files are deleted until the
closed files plus a full new file (`max_bytes`) fit under the cap; the file being written is
never deleted. The cap is at least `MIN_CAP_FILES` * `max_bytes` (a closed file exceeds
`max_bytes` by up to one solve and its summary, so one closed file always stays).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from art_guidance.errors import ConfigError
from art_guidance.files import fsync_dir
from art_guidance.record.mcap_file import ClosedFile

MIN_CAP_FILES = 3      # max_total_bytes >= this many max_bytes


def default_log_dir() -> Path:
    """<ROS_HOME or ~/.ros>/art_guidance_logs/<UTC timestamp>_<pid>."""
    home = Path(os.environ.get("ROS_HOME", Path.home() / ".ros"))
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return home / "art_guidance_logs" / f"{stamp}_{os.getpid()}"


def holds_recording(directory: str | Path) -> bool:
    """The folder holds MCAP files (finished, torn or partial): a bag never overwritten."""
    directory = Path(directory)
    return directory.is_dir() and any(directory.glob("*.mcap*"))


def free_bag_dir(directory: str | Path) -> Path:
    """`directory` if it holds no recording, else the first of `<directory>_2`, `_3`, ...
    that holds none: where a re-configured node's next bag goes, beside the ones before."""
    directory = Path(directory)
    k = 1
    candidate = directory
    while holds_recording(candidate):
        k += 1
        candidate = directory.with_name(f"{directory.name}_{k}")
    return candidate


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


def take_over_cap(closed: list[ClosedFile], max_bytes: int,
                  max_total_bytes: int) -> list[ClosedFile]:
    """Take the oldest files out of `closed` (in place, oldest first) until the rest plus a
    full new file of `max_bytes` fit under `max_total_bytes` [bytes]; returns those taken.
    The newest closed file is never taken: where one solve and a summary exceed `max_bytes`
    (small files), the bag then exceeds the cap by that much rather than hold nothing."""
    dropped = []
    while len(closed) > 1 and sum(f.size for f in closed) + max_bytes > max_total_bytes:
        dropped.append(closed.pop(0))
    return dropped


def delete_files(directory: Path, dropped: list[ClosedFile]) -> None:
    """Delete the files retention took (once metadata.yaml no longer lists them)."""
    for gone in dropped:
        (directory / gone.info.path).unlink(missing_ok=True)
    fsync_dir(directory)
