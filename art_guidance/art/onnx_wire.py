"""The few fields of an ONNX file that the flight reads or rewrites, from the protobuf wire format.

A flight install has ONNX Runtime but not the `onnx` package (an export-time dependency, extra
`[train]`), and ONNX Runtime's Python API can neither list a model's weights nor change a
node's attributes. `onnx_art` needs both: the weights' sha256 (checked against the one recorded
at export) and, per batch size, the GroupQueryAttention nodes' `num_heads` and `kv_num_heads`.
This module reads and rewrites exactly those fields of the serialised `ModelProto` (onnx.proto:
ModelProto.graph = 7, .metadata_props = 14; GraphProto.node = 1, .initializer = 5;
NodeProto.op_type = 4, .attribute = 5; TensorProto.name = 8, .raw_data = 9;
StringStringEntryProto.key = 1, .value = 2; AttributeProto.name = 1, .i = 3, .type = 20) and
leaves every other byte as it is. Protobuf's rules hold: a repeated field is the concatenation
of its occurrences, a singular one is its last, an embedded message given twice is merged.
A truncated or malformed buffer raises `WireError`.
"""
from __future__ import annotations

from typing import Iterator

# field numbers (onnx/onnx.proto)
MODEL_GRAPH, MODEL_METADATA_PROPS = 7, 14
GRAPH_NODE, GRAPH_INITIALIZER = 1, 5
NODE_OP_TYPE, NODE_ATTRIBUTE = 4, 5
TENSOR_NAME, TENSOR_RAW_DATA = 8, 9
ENTRY_KEY, ENTRY_VALUE = 1, 2
ATTRIBUTE_NAME, ATTRIBUTE_I, ATTRIBUTE_TYPE = 1, 3, 20
ATTRIBUTE_TYPE_INT = 2  # AttributeProto.AttributeType.INT

VARINT, FIXED64, LENGTH, FIXED32 = 0, 1, 2, 5  # the wire types ONNX uses (no groups)


class WireError(ValueError):
    """Not a well-formed protobuf message (truncated, an unknown wire type, ...)."""


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    """The varint at `pos` and the position after it."""
    value = shift = 0
    while True:
        if pos >= len(buf):
            raise WireError("truncated varint")
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise WireError("varint longer than 10 bytes")


def fields(buf: bytes | memoryview) -> Iterator[tuple[int, int, int, int, object]]:
    """(number, wire type, start, end, value) of each field of a message, in order: [start,
    end) is the whole field (key included); the value is an int (varint, fixed) or, for a
    length-delimited field, a memoryview of its payload."""
    buf = memoryview(buf)
    pos, size = 0, len(buf)
    while pos < size:
        start = pos
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise WireError(f"field number 0 at byte {start}")
        if wire == VARINT:
            value, pos = _varint(buf, pos)
        elif wire in (FIXED64, FIXED32):
            width = 8 if wire == FIXED64 else 4
            if pos + width > size:
                raise WireError(f"truncated fixed-width field {number}")
            value = int.from_bytes(buf[pos:pos + width], "little")
            pos += width
        elif wire == LENGTH:
            length, pos = _varint(buf, pos)
            if pos + length > size:
                raise WireError(f"field {number} runs {pos + length - size} bytes past the end")
            value = buf[pos:pos + length]
            pos += length
        else:
            raise WireError(f"wire type {wire} of field {number} at byte {start}")
        yield number, wire, start, pos, value


def _messages(buf: bytes | memoryview, number: int) -> list[memoryview]:
    """The payloads of the length-delimited field `number` (every occurrence, in order)."""
    out = []
    for n, wire, _, _, value in fields(buf):
        if n == number:
            if wire != LENGTH:
                raise WireError(f"field {number} is not length-delimited")
            out.append(value)
    return out


def _last(buf: bytes | memoryview, number: int) -> bytes:
    """A singular bytes/string field: its last occurrence (b"" when absent)."""
    found = _messages(buf, number)
    return bytes(found[-1]) if found else b""


def _graphs(model: bytes | memoryview) -> list[memoryview]:
    """The graph's occurrences (a singular message given twice is merged: read them all)."""
    return _messages(model, MODEL_GRAPH)


def metadata_props(model: bytes | memoryview) -> dict[str, str]:
    """ModelProto.metadata_props as a dict (a key given twice: its last value)."""
    out = {}
    for entry in _messages(model, MODEL_METADATA_PROPS):
        try:
            key = _last(entry, ENTRY_KEY).decode()
            out[key] = _last(entry, ENTRY_VALUE).decode()
        except UnicodeDecodeError as exc:
            raise WireError(f"metadata that is not UTF-8 ({exc})") from exc
    return out


def initializers(model: bytes | memoryview) -> list[tuple[bytes, bytes]]:
    """(name, raw_data) of every weight of the graph, in graph order (b"" where absent)."""
    return [(_last(t, TENSOR_NAME), _last(t, TENSOR_RAW_DATA))
            for graph in _graphs(model) for t in _messages(graph, GRAPH_INITIALIZER)]


def check(model: bytes | memoryview) -> None:
    """Raise WireError unless the model, its graph, nodes and weights are well-formed."""
    for graph in _graphs(model):
        for number, _, _, _, value in fields(graph):
            if number in (GRAPH_NODE, GRAPH_INITIALIZER):
                for _ in fields(value):
                    pass
    metadata_props(model)


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _encode_varint(number << 3 | wire)


def _length_field(number: int, payload: bytes) -> bytes:
    return _key(number, LENGTH) + _encode_varint(len(payload)) + payload


def int_attribute(name: str, value: int) -> bytes:
    """A serialised AttributeProto of type INT (what onnx.helper.make_attribute(name, value)
    serialises to, for value >= 0)."""
    if value < 0:
        raise ValueError("a negative INT attribute is not needed here")
    return (_length_field(ATTRIBUTE_NAME, name.encode()) + _key(ATTRIBUTE_I, VARINT)
            + _encode_varint(value) + _key(ATTRIBUTE_TYPE, VARINT)
            + _encode_varint(ATTRIBUTE_TYPE_INT))


def _rewrite(buf: memoryview, number: int, edit) -> bytes:
    """`buf` with each occurrence of the message field `number` replaced by `edit(payload)`
    (None: kept as it is); every other field byte for byte."""
    parts, changed = [], False
    for n, wire, start, end, value in fields(buf):
        new = edit(value) if n == number and wire == LENGTH else None
        if new is None:
            parts.append(buf[start:end])
        else:
            parts.append(_length_field(n, new))
            changed = True
    return b"".join(parts) if changed else bytes(buf)


def with_node_attributes(model: bytes, op_type: str, attributes: dict[str, int]) -> bytes:
    """`model` with the attributes of every node of `op_type` replaced by `attributes` (INT
    attributes, in the order given): what deleting a NodeProto's attributes and extending
    them with onnx.helper.make_attribute(...) gives. The new attributes take the place of
    the first old one (field order: before the fields numbered above 5 if there was none)."""
    new_attrs = [_length_field(NODE_ATTRIBUTE, int_attribute(k, v))
                 for k, v in attributes.items()]
    target = op_type.encode()

    def node(payload: memoryview) -> bytes | None:
        if _last(payload, NODE_OP_TYPE) != target:
            return None
        parts, placed = [], False
        for n, _, start, end, _ in fields(payload):
            if n >= NODE_ATTRIBUTE and not placed:
                parts += new_attrs
                placed = True
            if n != NODE_ATTRIBUTE:
                parts.append(payload[start:end])
        if not placed:
            parts += new_attrs
        return b"".join(parts)

    def graph(payload: memoryview) -> bytes:
        return _rewrite(payload, GRAPH_NODE, node)

    return _rewrite(memoryview(model), MODEL_GRAPH, graph)
