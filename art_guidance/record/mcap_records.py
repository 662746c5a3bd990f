"""Reading MCAP records defensively: the framing (opcode, length) of a record, its parse, the
checks of a chunk (decompression, size, CRC, the records inside) and the search for the next
plausible chunk record after a damaged stretch. `record.scan` walks a file with these.

Every failure is a `BadRecord` (a `ShortRecord` when the record runs past the end of what is
read), never an exception of the mcap library; offsets and lengths are in bytes.
"""
from __future__ import annotations

import io
import struct
import zlib

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, MessageIndex, Metadata, Schema,
)

MAGIC = b"\x89MCAP0\r\n"
FRAME_BYTES = 9  # opcode (1) and record length (8)
FOOTER_BYTES = FRAME_BYTES + 20
OPCODES = frozenset(int(op) for op in Opcode)
_IN_CHUNK = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)
_READERS = {
    Opcode.HEADER: Header.read, Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read,
    Opcode.METADATA: Metadata.read, Opcode.CHUNK: Chunk.read, Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read, Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


class BadRecord(Exception):
    """A record that does not parse or does not check out."""


class ShortRecord(BadRecord):
    """A record that runs past the end of the file (a torn end when nothing follows it)."""


class _Exact(io.BytesIO):
    """A record body: reading past its end is an error, not a short read."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and size > 0 and len(data) < size:
            raise BadRecord("a field runs past the end of its record")
        return data


def frame(buf: bytes, pos: int, limit: int) -> tuple[int, bytes, int]:
    """(opcode, body, end) of the record at `pos`, which must end by `limit`."""
    if pos + FRAME_BYTES > limit:
        raise ShortRecord(f"{limit - pos} byte(s) left where a record starts")
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    end = pos + FRAME_BYTES + length
    if end > limit:
        raise ShortRecord(f"record 0x{opcode:02x} of {length} bytes runs past the end "
                          f"({limit - pos - FRAME_BYTES} bytes left)")
    return opcode, buf[pos + FRAME_BYTES:end], end


def parse(opcode: int, body: bytes) -> object:
    """The record of `opcode` from its body (extra bytes at its end are allowed padding)."""
    stream = ReadDataStream(_Exact(body))
    try:
        if opcode == Opcode.MESSAGE:
            if len(body) < 22:
                raise BadRecord("message record shorter than its fields")
            return Message.read(stream, len(body))
        return _READERS[opcode](stream)
    except BadRecord:
        raise
    except Exception as exc:  # struct, UnicodeDecodeError, mcap's EndOfFile ...
        raise BadRecord(f"record 0x{opcode:02x} does not parse ({type(exc).__name__}: {exc})")


def chunk_records(chunk: Chunk) -> list[object]:
    """The Schema, Channel and Message records inside a chunk, every check passed.

    Raises:
        BadRecord: decompression failed, the size or CRC does not match, or a record inside does
            not parse.
    """
    if chunk.compression == "zstd":
        try:
            data = zstandard.ZstdDecompressor().decompress(
                chunk.data, max_output_size=chunk.uncompressed_size)
        except zstandard.ZstdError as exc:
            raise BadRecord(f"zstd decompression failed ({exc})")
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise BadRecord(f"unsupported chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise BadRecord(f"{len(data)} bytes uncompressed, the chunk says "
                        f"{chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise BadRecord(f"CRC mismatch (uncompressed_crc {chunk.uncompressed_crc:08x}, computed "
                        f"{zlib.crc32(data):08x})")
    records, pos = [], 0
    while pos < len(data):
        try:
            opcode, body, pos = frame(data, pos, len(data))
        except ShortRecord as exc:
            raise BadRecord(f"inside the chunk: {exc}")
        if opcode not in _IN_CHUNK:
            raise BadRecord(f"record opcode 0x{opcode:02x} inside the chunk")
        records.append(parse(opcode, body))
    return records


def read_chunk(body: bytes) -> list[object]:
    chunk = parse(Opcode.CHUNK, body)
    return chunk_records(chunk)


def plausible_chunk(buf: bytes, pos: int, limit: int) -> bool:
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
        read_chunk(buf[head:head + length])
    except BadRecord:
        return False
    return True


def next_chunk(buf: bytes, start: int, limit: int) -> int | None:
    """Offset of the next plausible chunk record at or after `start` (None: there is none)."""
    pos = start
    while True:
        pos = buf.find(b"\x06", pos, limit)
        if pos < 0:
            return None
        if plausible_chunk(buf, pos, limit):
            return pos
        pos += 1


def mcap_ending(buf: bytes, size: int) -> tuple[int, Footer] | None:
    """(footer offset, footer) when the file ends in a footer and the closing magic."""
    if size < 2 * len(MAGIC) + FOOTER_BYTES or buf[size - len(MAGIC):size] != MAGIC:
        return None
    pos = size - len(MAGIC) - FOOTER_BYTES
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    if opcode != Opcode.FOOTER or length != 20:
        return None
    start, offsets, crc = struct.unpack_from("<QQI", buf, pos + FRAME_BYTES)
    return pos, Footer(start, offsets, crc)


def index_times(buf: bytes, pos: int, limit: int) -> dict[int, list[int]] | None:
    """Log times [ns] of the messages per channel id in the Message Index records from `pos`
    (None: none there). A chunk's index lies outside it and its CRC: it names what a damaged
    chunk held."""
    times: dict[int, list[int]] = {}
    try:
        while pos < limit:
            opcode, body, end = frame(buf, pos, limit)
            if opcode != Opcode.MESSAGE_INDEX:
                break
            index = parse(opcode, body)
            times.setdefault(index.channel_id, []).extend(t for t, _ in index.records)
            pos = end
    except BadRecord:
        pass
    return times or None
