"""Walk an MCAP file record by record, check every chunk and keep what is intact.

`scan_file` reads the data section in order. Every chunk is decompressed, its size and CRC
(`uncompressed_crc`, where the writer stored one) are checked and the records inside must parse;
a chunk that fails any of these is damaged. A damaged chunk is named (`Damage`: file, chunk
ordinal, byte offset, what failed), skipped, and reading goes on with the next intact chunk:
from the summary's chunk indexes when the file has a valid summary (its CRC checked), else by
scanning forward for the next plausible chunk record (opcode 0x06, a length that fits in the
file, a record that parses and whose CRC checks out).

A file whose last record runs past its end, with nothing readable after it and no MCAP ending,
was cut short inside a write (a crash): that is a torn end, not damage; the complete chunks
before it are kept. So is a file whose data section is whole but whose ending (footer, closing
magic) is cut or garbled. Damage elsewhere in such a file is still damage.

The messages a damaged chunk held are named, where the file tells, by the Message Index records
written after it (they lie outside the chunk and its CRC): channel and log time of each. Those
read intact elsewhere in the file (a chunk written twice, one copy damaged) are not lost; the
rest are. A damaged stretch that lost nothing (every message it held read intact in another
copy, or a summary that is not used because the data section is read instead) says why in
`Damage.no_loss`; it is named all the same (the file needs a rewrite, the medium a check).

A summary that fails its CRC is not used, nor is the footer's offset to it: the data section is
then read up to the data end record, so a file in which a bad copy wrote a chunk twice (every
offset after it shifted, the footer pointing into data) loses none of the intact chunks after
the bogus offset. A chunk identical to one read before, and a message identical to one read
before (same channel, log time and data), is dropped and named in the notes.

The records themselves are framed, parsed and checked by `record.mcap_records`; this module is
the walk over a file and what it reports (`FileScan`, `Damage`), and `lend_channels` across the
files of a bag.
"""
from __future__ import annotations

import bisect
import hashlib
import mmap
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, DataEnd, Header, Message, Metadata, Schema

from art_guidance.record.mcap_records import (  # noqa: F401 (chunk_records: read from here)
    FRAME_BYTES, MAGIC, OPCODES, BadRecord, ShortRecord, chunk_records, frame, index_times,
    mcap_ending, next_chunk, parse, read_chunk,
)

SUMMARY_NOT_NEEDED = "the data section was read to its data end record instead"
READ_IN_A_COPY = "every message it held was read intact in another copy of the chunk"


@dataclass(frozen=True)
class Damage:
    """A damaged stretch of one file: what was skipped and why.

    `chunk` is the chunk's ordinal in the file (0 = first; from the summary's chunk index when
    the file has one, else counted while reading), None where the damage is not in a chunk.
    `messages` is what the lost chunk(s) held per the file's message index and was read
    nowhere else in the file (None = unknown), `by_topic` the same per topic; `copied` what
    they held that was read intact in another copy of the chunk. `no_loss` says why the
    stretch cost no message ("" = it may have; see the module).
    """

    file: str
    chunk: int | None
    offset: int
    length: int
    reason: str
    messages: int | None = None
    by_topic: dict[str, int] = field(default_factory=dict)
    copied: int = 0
    no_loss: str = ""

    @property
    def lost_data(self) -> bool:
        """Messages may have been lost to this damage (False: see `no_loss`)."""
        return not self.no_loss

    def __str__(self) -> str:
        where = f"chunk {self.chunk}" if self.chunk is not None else "data"
        if self.no_loss:
            held = f"; nothing lost: {self.no_loss}"
        elif self.messages is None:
            held = ""
        else:
            copied = (f" ({self.copied} more it held read intact in another copy)"
                      if self.copied else "")
            held = f"; {self.messages} message(s) lost per the file's message index{copied}"
        return (f"{self.file}: {where} at byte offset {self.offset} ({self.length} bytes "
                f"skipped): {self.reason}{held}")

    def as_dict(self) -> dict:
        """JSON-ready form."""
        return {"file": self.file, "chunk": self.chunk, "offset": self.offset,
                "length": self.length, "reason": self.reason, "messages": self.messages,
                "by_topic": dict(self.by_topic), "copied": self.copied,
                "lost_data": self.lost_data, "no_loss": self.no_loss}


@dataclass
class FileScan:
    """What `scan_file` could read of one file."""

    path: Path
    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    messages: list[Message] = field(default_factory=list)
    chunks: int = 0  # chunks read intact
    damaged: list[Damage] = field(default_factory=list)
    torn: str = ""  # why the file ends before a clean ending ("" = it ends cleanly)
    summary: bool = False  # the file has a valid summary
    notes: list[str] = field(default_factory=list)
    orphans: int = 0  # messages of channels defined nowhere (dropped)


class _Walk:
    """State of one `scan_file` pass."""

    def __init__(self, path: Path, buf: bytes) -> None:
        self.scan, self.buf, self.size = FileScan(path), buf, len(buf)
        self.ending = mcap_ending(buf, self.size)
        self.limit = self.size
        self.index: list[ChunkIndex] = []
        self.offsets: list[int] = []
        self.read: set[int] = set()  # offsets of the chunks read intact
        self.counted = 0  # chunk records met (the ordinal without a summary)
        self.pending: list[tuple[Damage, dict[int, list[int]] | None]] = []
        self.chunk_digests: dict[bytes, int] = {}  # chunk body digest -> its first offset
        # header (see `_chunk_key`) of each chunk read intact -> its offset and messages
        self.intact_chunks: dict[tuple[int, int, int, int], tuple[int, int]] = {}
        self.message_keys: set[tuple[int, int, bytes]] = set()  # channel, log time, data
        self.duplicate_messages = 0
        if self.ending is not None:
            self._data_limit()
            self._summary()

    def _data_limit(self) -> None:
        footer_pos, footer = self.ending
        end = footer.summary_start if footer.summary_start else footer_pos
        if len(MAGIC) <= end <= footer_pos:
            self.limit = end

    def _summary(self) -> None:
        footer_pos, footer = self.ending
        start = footer.summary_start
        if not start:
            return
        what = "summary section"
        try:
            if not len(MAGIC) <= start <= footer_pos:
                raise BadRecord(f"the footer points outside the file ({start})")
            if footer.summary_crc:
                crc = zlib.crc32(self.buf[start:footer_pos + FRAME_BYTES + 16])
                if crc != footer.summary_crc:
                    raise BadRecord(f"CRC mismatch (summary_crc {footer.summary_crc:08x}, "
                                    f"computed {crc:08x})")
            pos, index, schemas, channels = start, [], {}, {}
            while pos < footer_pos:
                opcode, body, pos = frame(self.buf, pos, footer_pos)
                if opcode == Opcode.CHUNK_INDEX:
                    index.append(parse(opcode, body))
                elif opcode == Opcode.SCHEMA:
                    schema = parse(opcode, body)
                    schemas[schema.id] = schema
                elif opcode == Opcode.CHANNEL:
                    channel = parse(opcode, body)
                    channels[channel.id] = channel
        except BadRecord as exc:
            self._damage(None, start, footer_pos - start, f"{what}: {exc}; not used",
                         no_loss=SUMMARY_NOT_NEEDED)
            self.limit = footer_pos  # nor its offset: the data end record ends the data
            return
        self.scan.summary = True
        self.index = sorted(index, key=lambda c: c.chunk_start_offset)
        self.offsets = [c.chunk_start_offset for c in self.index]
        self.scan.schemas.update(schemas)
        self.scan.channels.update(channels)

    def _damage(self, chunk: int | None, offset: int, length: int, reason: str,
                times: dict[int, list[int]] | None = None, no_loss: str = "") -> None:
        """Note a damaged stretch; `times`: the log times [ns] per channel id of the messages it
        held, from the message index after it (None: unknown)."""
        self.pending.append((Damage(self.scan.path.name, chunk, offset, length, reason,
                                    no_loss=no_loss), times))

    def _resync(self, pos: int) -> int | None:
        if self.index:
            k = bisect.bisect_right(self.offsets, pos)
            return self.offsets[k] if k < len(self.offsets) else None
        return next_chunk(self.buf, pos + 1, self.limit)

    def _record(self, pos: int) -> int | None:
        """Read the record at `pos`; returns where the next one starts (None: data end)."""
        opcode, body, end = frame(self.buf, pos, self.limit)
        if opcode not in OPCODES:
            raise BadRecord(f"unknown record opcode 0x{opcode:02x}")
        scan = self.scan
        if opcode == Opcode.CHUNK:
            records = read_chunk(body)
            first = self.chunk_digests.setdefault(hashlib.blake2b(body).digest(), pos)
            if first == pos:
                self._keep(records)
                scan.chunks += 1
                key = self._chunk_key(pos)
                if key is not None:
                    self.intact_chunks.setdefault(
                        key, (pos, sum(isinstance(r, Message) for r in records)))
            else:
                scan.notes.append(f"{scan.path.name}: the chunk at byte offset {pos} "
                                  f"duplicates the chunk at byte offset {first}: dropped")
            self.counted += 1
            self.read.add(pos)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            self._keep([parse(opcode, body)])
        elif opcode == Opcode.HEADER:
            scan.header = parse(opcode, body)
        elif opcode == Opcode.METADATA:
            scan.metadata.append(parse(opcode, body))
        elif opcode == Opcode.DATA_END:
            self._data_crc(pos, parse(opcode, body))
            if self.ending is None:
                self.scan.torn = (f"torn end after the data end record (byte offset {end}): "
                                  "no valid footer and closing magic follow it")
            return None
        elif opcode == Opcode.FOOTER:
            return None
        return end

    def _chunk_key(self, pos: int) -> tuple[int, int, int, int] | None:
        """(message start and end time [ns], uncompressed size [bytes], uncompressed CRC) of
        the chunk record at `pos`, from its header; None where there is no chunk record or
        no CRC. A damaged chunk whose header is that of a chunk read intact is a copy of it."""
        if pos < 0 or pos + FRAME_BYTES + 28 > self.size or self.buf[pos] != Opcode.CHUNK:
            return None
        key = struct.unpack_from("<QQQI", self.buf, pos + FRAME_BYTES)
        return key if key[3] else None

    def _keep(self, records: list[object]) -> None:
        for record in records:
            if isinstance(record, Message):
                key = (record.channel_id, record.log_time, bytes(record.data))
                if key in self.message_keys:
                    self.duplicate_messages += 1
                    continue
                self.message_keys.add(key)
                self.scan.messages.append(record)
            elif isinstance(record, Schema):
                self.scan.schemas[record.id] = record
            elif isinstance(record, Channel):
                self.scan.channels[record.id] = record

    def _data_crc(self, pos: int, data_end: DataEnd) -> None:
        if data_end.data_section_crc and not self.pending:
            crc = zlib.crc32(self.buf[:pos])
            if crc != data_end.data_section_crc:
                self._damage(None, 0, pos, f"data section CRC mismatch (data_section_crc "
                             f"{data_end.data_section_crc:08x}, computed {crc:08x}) outside "
                             "the chunks, whose own CRCs check out")

    def _failed(self, pos: int, exc: BadRecord) -> int | None:
        """Name the damage at `pos`; returns where reading goes on (None: it stops)."""
        nxt = self._resync(pos)
        if nxt is None and isinstance(exc, ShortRecord) and self.ending is None:
            self.scan.torn = f"torn end at byte offset {pos}: {exc}"
            return None
        stop = self.limit if nxt is None else nxt
        is_chunk = (pos + FRAME_BYTES <= self.size and self.buf[pos] == Opcode.CHUNK)
        if self.index:
            lost = [k for k, off in enumerate(self.offsets) if pos <= off < stop]
            if not lost:
                self._damage(None, pos, stop - pos, f"{exc} (no chunk in this stretch)")
            for k in lost:
                self._lost_chunk(k, self.offsets[k], pos, stop, exc)
        else:
            chunk = self.counted if is_chunk else None
            self.counted += is_chunk
            times = None
            if is_chunk:
                end = pos + FRAME_BYTES + struct.unpack_from("<Q", self.buf, pos + 1)[0]
                times = index_times(self.buf, end, stop) if end <= stop else None
            self._damage(chunk, pos, stop - pos, str(exc), times)
        return nxt

    def _lost_chunk(self, k: int, offset: int, pos: int, stop: int, exc: BadRecord) -> None:
        entry = self.index[k]
        reason = str(exc) if offset == pos else f"in a damaged stretch ({exc})"
        times = index_times(self.buf, offset + entry.chunk_length, self.limit)
        self._damage(k, offset, entry.chunk_length if offset != pos else stop - pos, reason,
                     times)

    def run(self) -> FileScan:
        pos = len(MAGIC)
        if self.buf[:len(MAGIC)] != MAGIC:
            pos = self._failed(0, BadRecord("no MCAP magic at the start of the file"))
        while pos is not None:
            if pos >= self.limit:
                if self.ending is None:
                    self.scan.torn = (f"torn end at byte offset {pos}: the file ends after a "
                                      "complete record, without an MCAP ending")
                break
            try:
                pos = self._record(pos)
            except BadRecord as exc:
                pos = self._failed(pos, exc)
        self._unread_chunks()
        self._finish()
        return self.scan

    def _unread_chunks(self) -> None:
        """Indexed chunks neither read nor already reported (a skip went past them)."""
        named = {d.offset for d, _ in self.pending}
        for k, entry in enumerate(self.index):
            off = entry.chunk_start_offset
            if off not in self.read and off not in named:
                times = index_times(self.buf, off + entry.chunk_length, self.limit)
                self._damage(k, off, entry.chunk_length, "not reached: the chunk index "
                             "points into a stretch that did not read", times)

    def _finish(self) -> None:
        if self.duplicate_messages:
            self.scan.notes.append(f"{self.scan.path.name}: {self.duplicate_messages} "
                                   "message(s) identical to one read before (same channel, "
                                   "log time and data): dropped")
        read = Counter((m.channel_id, m.log_time) for m in self.scan.messages)
        for damage, times in sorted(self.pending, key=lambda p: p[0].offset):
            copy_of = self.intact_chunks.get(self._chunk_key(damage.offset))
            if copy_of is not None and copy_of[0] != damage.offset:
                damage = replace(damage, messages=0, by_topic={}, copied=copy_of[1],
                                 no_loss=f"a copy of the chunk read intact at byte offset "
                                 f"{copy_of[0]} (the same uncompressed CRC, size and time "
                                 "range)")
            elif times is not None:
                damage = self._held(damage, times, read)
            self.scan.damaged.append(damage)

    def _held(self, damage: Damage, times: dict[int, list[int]], read: Counter) -> Damage:
        """`damage` with what it held (per its message index `times`) split into what was read
        intact elsewhere in the file (same channel and log time: the recorder writes one
        message per topic and solve, at the solve's log time) and what was lost."""
        topics = {cid: ch.topic for cid, ch in self.scan.channels.items()}
        by_topic: dict[str, int] = {}
        copied = 0
        for cid, stamps in times.items():
            held = Counter(stamps)
            found = sum(min(n, read[(cid, t)]) for t, n in held.items())
            copied += found
            if len(stamps) > found:
                topic = topics.get(cid, f"channel {cid}")
                by_topic[topic] = by_topic.get(topic, 0) + len(stamps) - found
        lost = sum(by_topic.values())
        no_loss = damage.no_loss or (READ_IN_A_COPY if copied and not lost else "")
        return replace(damage, messages=lost, by_topic=by_topic, copied=copied, no_loss=no_loss)


def scan_file(path: str | Path) -> FileScan:
    """Every intact record of an MCAP file, and what is damaged or torn (see the module)."""
    path = Path(path)
    with open(path, "rb") as fh:
        if path.stat().st_size == 0:
            return FileScan(path, torn="torn end at byte offset 0: the file is empty")
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            return _Walk(path, buf).run()


def _retopic(damage: Damage, channels: dict[int, Channel]) -> Damage:
    """`damage` with its "channel <id>" counts put under the topics `channels` now name."""
    names = {f"channel {cid}": ch.topic for cid, ch in channels.items()}
    by_topic: dict[str, int] = {}
    for topic, n in damage.by_topic.items():
        by_topic[names.get(topic, topic)] = by_topic.get(names.get(topic, topic), 0) + n
    return replace(damage, by_topic=by_topic)


def lend_channels(scans: list[FileScan]) -> None:
    """Give a file whose channel definitions were lost (they are written once, in its first
    chunk) those of another file of the same bag: the recorder writes the same schemas and
    channels, with the same ids, to every file. Messages of channels defined nowhere are
    dropped and counted in `orphans`."""
    for scan in scans:
        missing = {m.channel_id for m in scan.messages} - set(scan.channels)
        for cid in sorted(missing):
            donor = next((s for s in scans if cid in s.channels and s is not scan), None)
            if donor is None:
                continue
            channel = donor.channels[cid]
            scan.channels[cid] = channel
            if channel.schema_id in donor.schemas:
                scan.schemas.setdefault(channel.schema_id, donor.schemas[channel.schema_id])
            scan.notes.append(f"{scan.path.name}: channel {cid} ({channel.topic}) was defined in "
                              f"a lost chunk; its definition is taken from {donor.path.name}")
        if missing:
            scan.damaged = [_retopic(d, scan.channels) for d in scan.damaged]
        known = [m for m in scan.messages if m.channel_id in scan.channels]
        scan.orphans = len(scan.messages) - len(known)
        if scan.orphans:
            unknown = Counter(f"channel {m.channel_id}" for m in scan.messages
                              if m.channel_id not in scan.channels)
            scan.damaged.append(Damage(scan.path.name, None, -1, 0, f"{scan.orphans} intact "
                                       "message(s) of channels defined only in a lost chunk "
                                       "cannot be decoded", scan.orphans, dict(unknown)))
        scan.messages = known
