"""`art-guidance export`: a trained ART as one ONNX file that flies without torch.

The file holds the KV-cached decoding step of `kv_cache.CachedDecoder` as an ONNX graph (opset
20 plus ONNX Runtime's `com.microsoft` GroupQueryAttention), the same arithmetic in float32:

    feats (B, n, 17), positions (n,) int64   the new tokens and their rows of the (5 K, d)
                                             embedding-bias table (5 t0 + their positions;
                                             K rows and t0 + positions with one token a step)
    seqlens_k (1,) int32, total_len () int32  p1 - 1 and p1 (p1: tokens fed so far, new included)
    past_k<l>, past_v<l> (1, B H, 5 T, hd)   each layer's key/value cache (updated in place:
                                             bind `present_*` to the same buffer)
    -> control (B, 3 or 4)                   the normalised control (and burn-gate logit) of
                                             the last token, which must be a state token

The batch is folded into the attention heads (ONNX Runtime's CPU kernel takes several new
tokens after a cache only at batch 1): the file's attention nodes carry the heads of one
sample, and the runtime opens one session per batch size B with B times as many
(`onnx_art.OnnxDecoder`). The last layer's projection and MLP run for the last token only.

Everything the flight needs besides the graph is in the model's metadata (`METADATA_KEY`,
one JSON object): the format, the source checkpoint's payload sha256 and file
name, the ArtConfig, the normalisation statistics, the checkpoint's provenance, a sha256 of the
graph's weights and a probe (fixed features and the control torch computed from them), which
`onnx_art.load_exported` checks before the model is used.

Writing is atomic (`files.write_atomic`): a crash leaves the old file or none, never half a
file; an existing file is replaced only with `force`.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from art_guidance.art.checkpoint import TrainedArt
from art_guidance.art.config import FEATURES
from art_guidance.art.onnx_art import (
    FORMAT, FORMAT_VERSION, METADATA_KEY, PROBE_BATCH, PROBE_TOKENS, probe_steps,
    weights_sha256,
)
from art_guidance.errors import InputError, ModelError
from art_guidance.files import write_atomic

OPSET, MS_OPSET, IR_VERSION = 20, 1, 10  # IR 10: what ONNX Runtime 1.30 reads
PROBE_SEED = 20261127
_LAYER_NAMES = ("ln1_w", "ln1_b", "qkv_w", "qkv_b", "proj_w", "proj_b", "ln2_w", "ln2_b",
                "fc_w", "fc_b", "out_w", "out_b")


class _Graph:
    """Collects nodes and float32 weights of the step graph."""

    def __init__(self) -> None:
        from onnx import helper, numpy_helper
        self._helper, self._np = helper, numpy_helper
        self.nodes: list = []
        self.inits: list = []

    def weight(self, name: str, value: object, dtype: type = np.float32) -> str:
        arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
        self.inits.append(self._np.from_array(arr, name))
        return name

    def node(self, op: str, inputs: list[str], output: str | list[str], **attrs) -> str:
        outputs = [output] if isinstance(output, str) else output
        self.nodes.append(self._helper.make_node(op, inputs, outputs, **attrs))
        return outputs[0]


def _numpy(t) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def build_model(art: TrainedArt) -> bytes:
    """The serialised ONNX model of `art`'s decoding step, metadata included.

    Raises:
        ModelError: a config the graph cannot express (head width not a multiple of 8, which
            ONNX Runtime's attention kernel needs).
    """
    import onnx
    from onnx import TensorProto, helper

    cfg, dec = art.config, art.decoder
    d, heads, hd = cfg.width, cfg.n_heads, cfg.head_dim
    if hd % 8:
        raise ModelError(f"cannot export a model with attention heads {hd} wide: ONNX "
                         "Runtime's GroupQueryAttention needs a multiple of 8")
    g = _Graph()
    g.weight("split3", [d, d, d], np.int64)
    g.weight("ax1", [1], np.int64)
    g.weight("ax0", [0], np.int64)
    g.weight("last_start", [-1], np.int64)
    g.weight("last_end", [np.iinfo(np.int64).max], np.int64)
    g.weight("fold", [0, -1], np.int64)          # (n, B, d) -> (n, B d)
    g.weight("unfold", [0, -1, d], np.int64)     # (n, B d) -> (n, B, d)
    eps = float(dec._eps)
    h = g.node("MatMul", ["feats", g.weight("embed", _numpy(dec._embed_t))], "e0")
    bias = g.node("Gather", [g.weight("bias_table", _numpy(dec._bias_table)), "positions"],
                  "bias", axis=0)  # (n, d)
    h = g.node("Add", [h, bias], "e1")
    h = g.node("LayerNormalization", [h, g.weight("ln_e_w", _numpy(dec._ln_e[0])),
                                      g.weight("ln_e_b", _numpy(dec._ln_e[1]))],
               "h0", axis=-1, epsilon=eps)
    last = len(dec._layers) - 1
    for i, layer in enumerate(dec._layers):
        w = {n: g.weight(f"l{i}.{n}", _numpy(t)) for n, t in zip(_LAYER_NAMES, layer)}
        p = f"l{i}."
        x = g.node("LayerNormalization", [h, w["ln1_w"], w["ln1_b"]], p + "x", axis=-1,
                   epsilon=eps)
        qkv = g.node("Add", [g.node("MatMul", [x, w["qkv_w"]], p + "qkv0"), w["qkv_b"]],
                     p + "qkv")
        g.node("Split", [qkv, "split3"], [p + "q", p + "k", p + "v"], axis=-1)
        folded = []
        for t in "qkv":  # (B, n, d) -> (1, n, B d): the batch folded into the heads
            tr = g.node("Transpose", [p + t], p + t + ".t", perm=[1, 0, 2])
            flat = g.node("Reshape", [tr, "fold"], p + t + ".flat")
            folded.append(g.node("Unsqueeze", [flat, "ax0"], p + t + ".f"))
        att = g.node("GroupQueryAttention",
                     folded + [f"past_k{i}", f"past_v{i}", "seqlens_k", "total_len"],
                     [p + "att.f", f"present_k{i}", f"present_v{i}"], domain="com.microsoft",
                     num_heads=heads, kv_num_heads=heads)  # per sample: see `onnx_art`
        att = g.node("Squeeze", [att, "ax0"], p + "att.flat")
        att = g.node("Transpose", [g.node("Reshape", [att, "unfold"], p + "att.u")],
                     p + "att", perm=[1, 0, 2])
        if i == last:  # only the last (state) token's output is read
            att = g.node("Slice", [att, "last_start", "last_end", "ax1"], p + "att.last")
            h = g.node("Slice", [h, "last_start", "last_end", "ax1"], p + "h.last")
        a = g.node("Add", [g.node("MatMul", [att, w["proj_w"]], p + "a0"), w["proj_b"]],
                   p + "a")
        h = g.node("Add", [h, a], p + "h1")
        x = g.node("LayerNormalization", [h, w["ln2_w"], w["ln2_b"]], p + "x2", axis=-1,
                   epsilon=eps)
        f = g.node("Add", [g.node("MatMul", [x, w["fc_w"]], p + "f0"), w["fc_b"]], p + "f1")
        f = g.node("Relu" if cfg.activation == "relu" else "Gelu", [f], p + "f2")
        o = g.node("Add", [g.node("MatMul", [f, w["out_w"]], p + "o0"), w["out_b"]], p + "o")
        h = g.node("Add", [h, o], p + "h2")
    h = g.node("Squeeze", [h, "ax1"], "h.last")
    h = g.node("LayerNormalization", [h, g.weight("ln_f_w", _numpy(dec._ln_f[0])),
                                      g.weight("ln_f_b", _numpy(dec._ln_f[1]))],
               "h.f", axis=-1, epsilon=eps)
    g.node("Add", [g.node("MatMul", [h, g.weight("head_w", _numpy(dec._head_t[1]))], "y0"),
                   g.weight("head_b", _numpy(dec._head_t[0]))], "control")
    n_out = int(dec._head_t[0].shape[0])
    f32 = TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info("feats", f32, ["B", "n", FEATURES]),
              helper.make_tensor_value_info("positions", TensorProto.INT64, ["n"]),
              helper.make_tensor_value_info("seqlens_k", TensorProto.INT32, [1]),
              helper.make_tensor_value_info("total_len", TensorProto.INT32, [])]
    outputs = [helper.make_tensor_value_info("control", f32, ["B", n_out])]
    for i in range(cfg.n_layers):
        for kv in "kv":
            shape = [1, "BH", "T", hd]
            inputs.append(helper.make_tensor_value_info(f"past_{kv}{i}", f32, shape))
            outputs.append(helper.make_tensor_value_info(f"present_{kv}{i}", f32, shape))
    graph = helper.make_graph(g.nodes, "art_decoding_step", inputs, outputs, g.inits)
    model = helper.make_model(graph, ir_version=IR_VERSION, producer_name="art_guidance",
                              opset_imports=[helper.make_opsetid("", OPSET),
                                             helper.make_opsetid("com.microsoft", MS_OPSET)])
    helper.set_model_props(model, {METADATA_KEY: json.dumps(_metadata(art, g.inits))})
    onnx.checker.check_model(model)
    return model.SerializeToString()


def _metadata(art: TrainedArt, inits: list) -> dict:
    """What the flight needs besides the graph (module docstring)."""
    return {"format": FORMAT, "format_version": FORMAT_VERSION,
            "checkpoint_sha256": art.sha256 or "",
            "checkpoint_file": Path(art.path).name if art.path else "",
            "config": art.config.to_dict(), "normalization": art.normalizer.to_json(),
            "meta": json.loads(json.dumps(art.meta)),
            "n_parameters": int(art.model.n_parameters()),
            "weights_sha256": weights_sha256(inits), "probe": _probe(art)}


def _probe(art: TrainedArt) -> dict:
    """Fixed features of PROBE_TOKENS tokens (the last a state token) at the first positions
    of a PROBE_BATCH batch, and the control torch's decoder computes from them."""
    import torch

    rng = np.random.default_rng(PROBE_SEED)
    feats = rng.standard_normal((PROBE_BATCH, PROBE_TOKENS, FEATURES)).astype(np.float32)
    dec = art.decoder
    with torch.inference_mode():
        dec.reset(PROBE_BATCH, probe_steps(art.config), 0)
        out = dec.step(torch.from_numpy(feats).to(dec.dtype), 0).float().numpy()
    return {"feats": feats.tolist(), "control": out.tolist()}


def export(art: TrainedArt, out: str | Path, force: bool = False) -> str:
    """Write `art` as an exported model file at `out`; returns the file's sha256.

    Raises:
        InputError: `out` exists and `force` is not set, or is a directory.
        ModelError: a config the graph cannot express.
    """
    out = Path(out)
    if out.is_dir():
        raise InputError("out", "is a directory; give a file name", str(out))
    if out.exists() and not force:
        raise InputError("out", "exists; pass --force to replace it", str(out))
    blob = build_model(art)
    write_atomic(out, blob)
    return hashlib.sha256(blob).hexdigest()
