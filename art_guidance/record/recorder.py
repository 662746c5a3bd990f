"""Record every solve to MCAP: ROS 2 `cdr` payloads with `ros2msg` schemas (rosbag2 layout).

Schemas, hashes and the CDR encoder come from `record.ros2msg`, the file primitives from
`record.mcap_file`, the folder checks and retention from `record.bag_folder`.

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
the write and the rename of `metadata.yaml` leaves `metadata.yaml` one write behind the data:
one solve (not published either) or one published plan's visualisation messages (written after
the plan goes out).

Write failures (full disk, unwritable path, file size limit) are logged and counted; they never
raise into the caller. A failed write is undone (the old ending is put back and the file cut
to it), the file is closed there and the next solve starts a new one; a solve counts as
recorded only once the data and `metadata.yaml` that describes it are both written, so
`metadata.yaml` always describes what is on disk (state `write_failed` and the error in
`custom_data` until a solve is recorded again). With `max_total_bytes` the oldest closed files
are deleted at a rotation (see `McapRecorder` and `record.bag_folder`). Run metadata (config,
versions, model checksum) goes into an MCAP metadata record, sealed (`record.seal`: a sha256 of
every value, which replay checks).
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections import Counter, deque
from pathlib import Path
from typing import Iterable

from art_guidance import topics
from art_guidance.errors import ConfigError
from art_guidance.files import fsync_dir
# MIN_CAP_FILES, check_record_dir, default_log_dir, MAGIC and PART_SUFFIX are imported from here
from art_guidance.record.bag_folder import (  # noqa: F401
    MIN_CAP_FILES, check_cap, check_record_dir, default_log_dir, delete_files, free_bag_dir,
    holds_recording, take_over_cap,
)
from art_guidance.record.bag_metadata import TopicInfo, write_bag_metadata
from art_guidance.record.mcap_file import (  # noqa: F401
    MAGIC, PART_SUFFIX, TAIL, ClosedFile, OpenFile, create_file, put_back_ending, pwrite_all,
    start_file,
)
from art_guidance.record.ros2msg import (
    cdr_encoder, plain_message as _plain, ros2msg_schema, type_description_hash,
)
from art_guidance.record.seal import seal

LOG = logging.getLogger("art_guidance.record.recorder")
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
TORN_SAMPLES = 4096    # the last solves whose write time `torn_window_ns` keeps


class McapRecorder:
    """Context-managed MCAP writer for a node run (one bag folder, rotated files).

    Args:
        directory: the bag folder (created on the first solve).
        metadata: run metadata (values that are not strings are stored as JSON), recorded
            with its `metadata_seal` (`record.seal`).
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
        if holds_recording(self.directory):
            raise ConfigError(f"{self.directory} already holds a recording; choose another "
                              "record_dir (or move that one away): a bag is never overwritten")
        self.max_bytes = int(max_bytes)
        self.max_total_bytes = int(max_total_bytes)
        check_cap(self.max_total_bytes, self.max_bytes)
        self.metadata = seal({k: v if isinstance(v, str) else json.dumps(v)
                              for k, v in (metadata or {}).items()})
        self.name = name
        self.topics = dict(topics or TOPICS)
        self.files: list[Path] = []  # every file created, in order (deleted ones included)
        self.solves = 0
        self.errors = 0
        self.last_error = ""
        self.dropped_files = 0
        self.dropped_messages = 0
        self.torn_window_ns: deque[int] = deque(maxlen=TORN_SAMPLES)  # per solve: the write
        self._file: OpenFile | None = None
        self._closed_files: list[ClosedFile] = []
        self._schemas = {t: ros2msg_schema(t) for t in set(self.topics.values())}
        self._hashes = {t: type_description_hash(t) for t in self._schemas}
        self._encoders = {topic: cdr_encoder(t, self._schemas[t])
                          for topic, t in self.topics.items()}
        self._closed = False

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.finish()

    def _new_file(self) -> OpenFile:
        """The next file in memory: header, schemas, channels and run metadata (not on disk)."""
        return start_file(self.directory / f"{self.name}_{len(self.files)}.mcap",
                          self._schemas, self._hashes, self.topics, self.metadata)

    def _append(self, handle: OpenFile, data: bytes) -> None:
        """Write `data` (whole chunks) and a provisional ending over the old ending: one write
        (the torn window), then fsync."""
        if handle.fd < 0:
            create_file(handle, data + TAIL)
            self.files.append(handle.path)
        else:
            start = time.perf_counter_ns()
            pwrite_all(handle.fd, data + TAIL, handle.data_end)
            self.torn_window_ns.append(time.perf_counter_ns() - start)
            os.fsync(handle.fd)
        handle.data_end += len(data)

    def _drop_file(self, handle: OpenFile, keep_end: int) -> None:
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
                put_back_ending(handle.fd, keep_end)
        except OSError as exc:  # already failing: the first error is the one reported
            LOG.error("could not restore the ending of %s (`art-guidance bag reindex` repairs "
                      "it): %s", handle.path, exc)
        finally:
            os.close(handle.fd)
            handle.fd = -1
        if keep_end:
            self._closed_files.append(ClosedFile(handle.info(), Counter(handle.topic_counts),
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
            pwrite_all(handle.fd, data, handle.data_end)
            os.fsync(handle.fd)
            size = handle.data_end + len(data)
        except Exception as exc:
            self._fail(exc)
            try:
                put_back_ending(handle.fd, handle.data_end)
            except OSError as again:
                LOG.error("could not restore the ending of %s: %s", handle.path, again)
        finally:
            os.close(handle.fd)
            handle.fd = -1
        self._closed_files.append(ClosedFile(handle.info(), Counter(handle.topic_counts), size))

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
    def record_solve(self, messages: Iterable[tuple[str, object]], log_time_ns: int,
                     solve: bool = True) -> bool:
        """Write one solve's (topic, message) pairs in a chunk of their own with one write over
        the file's ending, fsync, then rewrite metadata.yaml (see the module docstring).
        `solve` False: messages that follow a solve already written (its visualisation), not
        counted as a solve.

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
        undo = self._count(handle, [topic for topic, _ in encoded], log_time_ns, solve)
        try:
            self._write_bag_metadata("recording")
        except Exception as exc:  # the data without its metadata.yaml is undone
            undo()
            return self._failed(exc, handle, 0 if created else keep_end)
        if handle.data_end + len(TAIL) >= self.max_bytes:
            self._close_file()
            self._apply_cap()
        return True

    def _failed(self, exc: Exception, handle: OpenFile | None, keep_end: int | None) -> bool:
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

    def _count(self, handle: OpenFile, topics: list[str], log_time_ns: int, solve: bool):
        """Count written messages (and a solve); returns the function that takes them back."""
        before = (handle.start_ns, handle.end_ns, handle.count, self.solves)
        for topic in topics:
            handle.topic_counts[topic] += 1
        handle.start_ns = min(handle.start_ns, log_time_ns) if handle.count else log_time_ns
        handle.end_ns = max(handle.end_ns, log_time_ns)
        handle.count += len(topics)
        self.solves += int(solve)

        def undo() -> None:
            handle.start_ns, handle.end_ns, handle.count, self.solves = before
            for topic in topics:
                handle.topic_counts[topic] -= 1
        return undo

    def _apply_cap(self) -> None:
        """The retention rule of `max_total_bytes` (see the class docstring)."""
        if not self.max_total_bytes:
            return
        dropped = take_over_cap(self._closed_files, self.max_bytes, self.max_total_bytes)
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
        delete_files(self.directory, dropped)
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
