"""`onnx_wire` against the `onnx` package (the oracle, installed with [train]): the metadata and
the weights it reads from an exported file are the ones onnx parses, and the attention heads it
sets give the very bytes that onnx's own rewrite serialises to. Malformed files are refused."""
from __future__ import annotations

import pytest

from art_guidance.art import onnx_wire
from art_guidance.art.onnx_art import weights_digest, weights_sha256
from art_guidance.art.provider import models_dir

onnx = pytest.importorskip("onnx")
from onnx import helper  # noqa: E402

GQA = "GroupQueryAttention"
EXPORTS = sorted(models_dir().glob("*.onnx"))


def _onnx_rewrite(model, op_type: str, attrs: dict) -> bytes:
    """What onnx_art did with the onnx package: delete the attributes, extend with new ones."""
    copy = onnx.ModelProto()
    copy.CopyFrom(model)
    for node in copy.graph.node:
        if node.op_type == op_type:
            del node.attribute[:]
            node.attribute.extend([helper.make_attribute(k, v) for k, v in attrs.items()])
    return copy.SerializeToString()


@pytest.mark.parametrize("path", EXPORTS, ids=[p.name for p in EXPORTS])
def test_reads_and_rewrites_the_shipped_exports_as_onnx_does(path):
    blob = path.read_bytes()
    model = onnx.load_model_from_string(blob)
    assert onnx_wire.metadata_props(blob) == {p.key: p.value for p in model.metadata_props}
    assert weights_digest(onnx_wire.initializers(blob)) == weights_sha256(
        model.graph.initializer)
    for heads in (1, 3, 24, 200):  # 200: a two-byte varint
        attrs = {"num_heads": heads, "kv_num_heads": heads}
        assert onnx_wire.with_node_attributes(blob, GQA, attrs) == _onnx_rewrite(
            model, GQA, attrs)


def test_a_node_without_attributes_gets_them_in_field_order():
    node = helper.make_node(GQA, ["a"], ["b"], domain="com.microsoft", doc_string="kept")
    other = helper.make_node("Relu", ["b"], ["c"])
    graph = helper.make_graph([node, other], "g", [], [])
    model = helper.make_model(graph)
    attrs = {"num_heads": 7, "kv_num_heads": 7}
    got = onnx_wire.with_node_attributes(model.SerializeToString(), GQA, attrs)
    assert got == _onnx_rewrite(model, GQA, attrs)
    parsed = onnx.load_model_from_string(got)
    assert parsed.graph.node[0].doc_string == "kept" and not parsed.graph.node[1].attribute


def test_malformed_files_are_refused():
    blob = EXPORTS[0].read_bytes()
    for bad in (blob[:len(blob) // 2], blob[:-1], b"not onnx", b"\x0a\xff"):
        with pytest.raises(onnx_wire.WireError):
            onnx_wire.check(bad)
