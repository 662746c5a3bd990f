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

The messages a damaged chunk held are counted, where the file tells, from the Message Index
records written after it (they lie outside the chunk and its CRC).
"""
from __future__ import annotations

import bisect
import io
import mmap
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, MessageIndex, Metadata, Schema,
)

MAGIC = b"\x89MCAP0\r\n"
FRAME_BYTES = 9  # opcode (1) and record length (8)
FOOTER_BYTES = FRAME_BYTES + 20
DATA_END_BYTES = FRAME_BYTES + 4
_OPCODES = frozenset(int(op) for op in Opcode)
_IN_CHUNK = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)
_COMPRESSIONS = ("", "zstd")
_READERS = {
    Opcode.HEADER: Header.read, Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read,
    Opcode.METADATA: Metadata.read, Opcode.CHUNK: Chunk.read, Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read, Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


class _Bad(Exception):
    """A record that does not parse or does not check out."""


class _Short(_Bad):
    """A record that runs past the end of the file (a torn end when nothing follows it)."""


@dataclass(frozen=True)
class Damage:
    """A damaged stretch of one file: what was skipped and why.

    `chunk` is the chunk's ordinal in the file (0 = first; from the summary's chunk index when
    the file has one, else counted while reading), None where the damage is not in a chunk.
    `messages` is what the lost chunk(s) held per the file's message index (None = unknown),
    `by_topic` the same per topic.
    """

    file: str
    chunk: int | None
    offset: int
    length: int
    reason: str
    messages: int | None = None
    by_topic: dict[str, int] = field(default_factory=dict)

    def __str__(self) -> str:
        where = f"chunk {self.chunk}" if self.chunk is not None else "data"
        held = ("" if self.messages is None else
                f"; {self.messages} message(s) lost per the file's message index")
        return (f"{self.file}: {where} at byte offset {self.offset} ({self.length} bytes "
                f"skipped): {self.reason}{held}")

    def as_dict(self) -> dict:
        """JSON-ready form."""
        return {"file": self.file, "chunk": self.chunk, "offset": self.offset,
                "length": self.length, "reason": self.reason, "messages": self.messages,
                "by_topic": dict(self.by_topic)}


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


class _Exact(io.BytesIO):
    """A record body: reading past its end is an error, not a short read."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and size > 0 and len(data) < size:
            raise _Bad("a field runs past the end of its record")
        return data


def _frame(buf: bytes, pos: int, limit: int) -> tuple[int, bytes, int]:
    """(opcode, body, end) of the record at `pos`, which must end by `limit`."""
    if pos + FRAME_BYTES > limit:
        raise _Short(f"{limit - pos} byte(s) left where a record starts")
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    end = pos + FRAME_BYTES + length
    if end > limit:
        raise _Short(f"record 0x{opcode:02x} of {length} bytes runs past the end "
                     f"({limit - pos - FRAME_BYTES} bytes left)")
    return opcode, buf[pos + FRAME_BYTES:end], end


def _parse(opcode: int, body: bytes) -> object:
    """The record of `opcode` from its body (extra bytes at its end are allowed padding)."""
    stream = ReadDataStream(_Exact(body))
    try:
        if opcode == Opcode.MESSAGE:
            if len(body) < 22:
                raise _Bad("message record shorter than its fields")
            return Message.read(stream, len(body))
        return _READERS[opcode](stream)
    except _Bad:
        raise
    except Exception as exc:  # struct, UnicodeDecodeError, mcap's EndOfFile ...
        raise _Bad(f"record 0x{opcode:02x} does not parse ({type(exc).__name__}: {exc})")


def chunk_records(chunk: Chunk) -> list[object]:
    """The Schema, Channel and Message records inside a chunk, every check passed.

    Raises:
        _Bad: decompression failed, the size or CRC does not match, or a record inside does
            not parse.
    """
    if chunk.compression == "zstd":
        try:
            data = zstandard.ZstdDecompressor().decompress(
                chunk.data, max_output_size=chunk.uncompressed_size)
        except zstandard.ZstdError as exc:
            raise _Bad(f"zstd decompression failed ({exc})")
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise _Bad(f"unsupported chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise _Bad(f"{len(data)} bytes uncompressed, the chunk says {chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise _Bad(f"CRC mismatch (uncompressed_crc {chunk.uncompressed_crc:08x}, computed "
                   f"{zlib.crc32(data):08x})")
    records, pos = [], 0
    while pos < len(data):
        try:
            opcode, body, pos = _frame(data, pos, len(data))
        except _Short as exc:
            raise _Bad(f"inside the chunk: {exc}")
        if opcode not in _IN_CHUNK:
            raise _Bad(f"record opcode 0x{opcode:02x} inside the chunk")
        records.append(_parse(opcode, body))
    return records


def _read_chunk(body: bytes) -> list[object]:
    chunk = _parse(Opcode.CHUNK, body)
    return chunk_records(chunk)


def _plausible_chunk(buf: bytes, pos: int, limit: int) -> bool:
    """A chunk record starts at `pos`: its length fits, its header agrees with its length,
    and it reads with every check passed."""
    head = pos + FRAME_BYTES
    if head + 32 > limit:
        return False
    length = struct.unpack_from("<Q", buf, pos + 1)[0]
    (name_len,) = struct.unpack_from("<I", buf, head + 28)
    if head + length > limit or name_len > 8 or head + 32 + name_len + 8 > limit:
        return False
    (data_len,) = struct.unpack_from("<Q", buf, head + 32 + name_len)
    if 32 + name_len + 8 + data_len != length:
        return False
    try:
        _read_chunk(buf[head:head + length])
    except _Bad:
        return False
    return True


def _next_chunk(buf: bytes, start: int, limit: int) -> int | None:
    """Offset of the next plausible chunk record at or after `start` (None: there is none)."""
    pos = start
    while True:
        pos = buf.find(b"\x06", pos, limit)
        if pos < 0:
            return None
        if _plausible_chunk(buf, pos, limit):
            return pos
        pos += 1


def _ending(buf: bytes, size: int) -> tuple[int, Footer] | None:
    """(footer offset, footer) when the file ends in a footer and the closing magic."""
    if size < 2 * len(MAGIC) + FOOTER_BYTES or buf[size - len(MAGIC):size] != MAGIC:
        return None
    pos = size - len(MAGIC) - FOOTER_BYTES
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    if opcode != Opcode.FOOTER or length != 20:
        return None
    start, offsets, crc = struct.unpack_from("<QQI", buf, pos + FRAME_BYTES)
    return pos, Footer(start, offsets, crc)


def _index_counts(buf: bytes, pos: int, limit: int) -> dict[int, int] | None:
    """Messages per channel id in the Message Index records from `pos` (None: none there)."""
    counts: dict[int, int] = {}
    try:
        while pos < limit:
            opcode, body, end = _frame(buf, pos, limit)
            if opcode != Opcode.MESSAGE_INDEX:
                break
            index = _parse(opcode, body)
            counts[index.channel_id] = counts.get(index.channel_id, 0) + len(index.records)
            pos = end
    except _Bad:
        pass
    return counts or None


class _Walk:
    """State of one `scan_file` pass."""

    def __init__(self, path: Path, buf: bytes) -> None:
        self.scan, self.buf, self.size = FileScan(path), buf, len(buf)
        self.ending = _ending(buf, self.size)
        self.limit = self.size
        self.index: list[ChunkIndex] = []
        self.offsets: list[int] = []
        self.read: set[int] = set()  # offsets of the chunks read intact
        self.counted = 0  # chunk records met (the ordinal without a summary)
        self.pending: list[tuple[Damage, dict[int, int] | None]] = []
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
                raise _Bad(f"the footer points outside the file ({start})")
            if footer.summary_crc:
                crc = zlib.crc32(self.buf[start:footer_pos + FRAME_BYTES + 16])
                if crc != footer.summary_crc:
                    raise _Bad(f"CRC mismatch (summary_crc {footer.summary_crc:08x}, "
                               f"computed {crc:08x})")
            pos, index, schemas, channels = start, [], {}, {}
            while pos < footer_pos:
                opcode, body, pos = _frame(self.buf, pos, footer_pos)
                if opcode == Opcode.CHUNK_INDEX:
                    index.append(_parse(opcode, body))
                elif opcode == Opcode.SCHEMA:
                    schema = _parse(opcode, body)
                    schemas[schema.id] = schema
                elif opcode == Opcode.CHANNEL:
                    channel = _parse(opcode, body)
                    channels[channel.id] = channel
        except _Bad as exc:
            self._damage(None, start, footer_pos - start, f"{what}: {exc}; not used")
            return
        self.scan.summary = True
        self.index = sorted(index, key=lambda c: c.chunk_start_offset)
        self.offsets = [c.chunk_start_offset for c in self.index]
        self.scan.schemas.update(schemas)
        self.scan.channels.update(channels)

    def _damage(self, chunk: int | None, offset: int, length: int, reason: str,
                counts: dict[int, int] | None = None) -> None:
        self.pending.append((Damage(self.scan.path.name, chunk, offset, length, reason),
                             counts))

    def _resync(self, pos: int) -> int | None:
        if self.index:
            k = bisect.bisect_right(self.offsets, pos)
            return self.offsets[k] if k < len(self.offsets) else None
        return _next_chunk(self.buf, pos + 1, self.limit)

    def _record(self, pos: int) -> int | None:
        """Read the record at `pos`; returns where the next one starts (None: data end)."""
        opcode, body, end = _frame(self.buf, pos, self.limit)
        if opcode not in _OPCODES:
            raise _Bad(f"unknown record opcode 0x{opcode:02x}")
        scan = self.scan
        if opcode == Opcode.CHUNK:
            self._keep(_read_chunk(body))
            self.counted += 1
            scan.chunks += 1
            self.read.add(pos)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            self._keep([_parse(opcode, body)])
        elif opcode == Opcode.HEADER:
            scan.header = _parse(opcode, body)
        elif opcode == Opcode.METADATA:
            scan.metadata.append(_parse(opcode, body))
        elif opcode == Opcode.DATA_END:
            self._data_crc(pos, _parse(opcode, body))
            if self.ending is None:
                self.scan.torn = (f"torn end after the data end record (byte offset {end}): "
                                  "no valid footer and closing magic follow it")
            return None
        elif opcode == Opcode.FOOTER:
            return None
        return end

    def _keep(self, records: list[object]) -> None:
        for record in records:
            if isinstance(record, Message):
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

    def _failed(self, pos: int, exc: _Bad) -> int | None:
        """Name the damage at `pos`; returns where reading goes on (None: it stops)."""
        nxt = self._resync(pos)
        if nxt is None and isinstance(exc, _Short) and self.ending is None:
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
            counts = None
            if is_chunk:
                end = pos + FRAME_BYTES + struct.unpack_from("<Q", self.buf, pos + 1)[0]
                counts = _index_counts(self.buf, end, stop) if end <= stop else None
            self._damage(chunk, pos, stop - pos, str(exc), counts)
        return nxt

    def _lost_chunk(self, k: int, offset: int, pos: int, stop: int, exc: _Bad) -> None:
        entry = self.index[k]
        reason = str(exc) if offset == pos else f"in a damaged stretch ({exc})"
        counts = _index_counts(self.buf, offset + entry.chunk_length, self.limit)
        self._damage(k, offset, entry.chunk_length if offset != pos else stop - pos, reason,
                     counts)

    def run(self) -> FileScan:
        pos = len(MAGIC)
        if self.buf[:len(MAGIC)] != MAGIC:
            pos = self._failed(0, _Bad("no MCAP magic at the start of the file"))
        while pos is not None:
            if pos >= self.limit:
                if self.ending is None:
                    self.scan.torn = (f"torn end at byte offset {pos}: the file ends after a "
                                      "complete record, without an MCAP ending")
                break
            try:
                pos = self._record(pos)
            except _Bad as exc:
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
                counts = _index_counts(self.buf, off + entry.chunk_length, self.limit)
                self._damage(k, off, entry.chunk_length, "not reached: the chunk index "
                             "points into a stretch that did not read", counts)

    def _finish(self) -> None:
        topics = {cid: ch.topic for cid, ch in self.scan.channels.items()}
        for damage, counts in sorted(self.pending, key=lambda p: p[0].offset):
            if counts is not None:
                by_topic: dict[str, int] = {}
                for cid, n in counts.items():
                    topic = topics.get(cid, f"channel {cid}")
                    by_topic[topic] = by_topic.get(topic, 0) + n
                damage = Damage(damage.file, damage.chunk, damage.offset, damage.length,
                                damage.reason, sum(counts.values()), by_topic)
            self.scan.damaged.append(damage)


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
    return Damage(damage.file, damage.chunk, damage.offset, damage.length, damage.reason,
                  damage.messages, by_topic)


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
            scan.damaged.append(Damage(scan.path.name, None, -1, 0, f"{scan.orphans} intact "
                                       "message(s) of channels defined only in a lost chunk "
                                       "cannot be decoded", scan.orphans))
        scan.messages = known
