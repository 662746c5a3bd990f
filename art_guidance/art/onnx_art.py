"""An exported ART flown on ONNX Runtime, without torch (`art-guidance export` writes the file).

`load_exported(path)` reads an exported model (`onnx_export`) and checks it before it is
flown: the file parses as ONNX (its protobuf, `onnx_wire`), its metadata is this format, the
sha256 of its weights is the one recorded at export (a changed weight is refused), the source
checkpoint is the expected one when the caller names it, and ONNX Runtime reproduces the probe
torch computed at export (to `PROBE_TOL`). The result, `ExportedArt`, has what `rollout` reads
of a `TrainedArt` (config, normalizer, meta, decoder) and imports neither torch, nor the `onnx`
package, nor the training code: a flight install has ONNX Runtime only (`onnx_wire` reads the
weights and metadata and sets the attention heads per batch size from the file's bytes).

`OnnxDecoder` is `kv_cache.CachedDecoder` on ONNX Runtime: one session per batch size (the
batch is folded into the attention heads), one thread, no spinning; the key/value caches are
bound as both input and output of every step, so a step writes only its new tokens' keys and
values (no copy of the cache).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from art_guidance.art import onnx_wire
from art_guidance.art.config import FEATURES, ArtConfig, check_steps
from art_guidance.art.normalization import Normalizer
from art_guidance.errors import CheckpointError, ConfigError, ModelError
from art_guidance.extras import installed  # `provider` imports it from here

FORMAT = "art-guidance-onnx-step"
FORMAT_VERSION = 1
METADATA_KEY = "art_guidance"
PROBE_BATCH, PROBE_TOKENS = 2, 4
PROBE_TOL = 1e-4  # largest |difference| of the probe's normalised control, ONNX vs torch [-]
RUNTIMES = ("auto", "torch", "onnx")
ONNX_SUFFIX = ".onnx"


def weights_sha256(initializers: list) -> str:
    """sha256 over a graph's weights (name, then raw bytes, in graph order): `initializers`
    are onnx TensorProtos (at export)."""
    return weights_digest((t.name.encode(), t.raw_data) for t in initializers)


def weights_digest(pairs) -> str:
    """`weights_sha256` of (name, raw_data) byte pairs (`onnx_wire.initializers`)."""
    h = hashlib.sha256()
    for name, raw in pairs:
        h.update(name)
        h.update(raw)
    return h.hexdigest()


class OnnxDecoder:
    """The KV-cached decoding step on ONNX Runtime (see the module docstring).

    Attributes:
        np_dtype: float32, the features' dtype.
    """

    np_dtype = np.dtype(np.float32)

    def __init__(self, model: bytes, config: ArtConfig) -> None:
        """`model`: the serialised ONNX model (its attention nodes carry one sample's heads)."""
        self._model, self._cfg = bytes(model), config
        # batch -> (session, binding, control, capacity, caches): the caches' wrappers keep
        # their numpy buffers alive while the binding points at them
        self._bound: dict[int, tuple] = {}
        self._sess = self._io = self._control = None
        self._t0 = 0

    def _session(self, batch: int):
        """A new session for a batch size: the attention nodes get batch x heads."""
        import onnxruntime as ort

        heads = batch * self._cfg.n_heads
        model = onnx_wire.with_node_attributes(
            self._model, "GroupQueryAttention", {"num_heads": heads, "kv_num_heads": heads})
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        opts.log_severity_level = 3
        return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])

    def reset(self, batch: int, n_steps: int, t0: int) -> None:
        """Start a new batch of rollouts of `n_steps` steps whose first time index is `t0`.

        The session, its binding and the caches of a batch size are kept and reused while
        they hold the tokens (as `CachedDecoder`'s buffers): a step reads only the positions
        written in this rollout (`seqlens_k`), so what earlier rollouts left there is not read.

        Raises:
            ValueError: if the steps do not fit the context (t0 + n_steps > K).
        """
        cfg = self._cfg
        check_steps(cfg, n_steps, t0)
        n_tok = n_steps * cfg.tokens_per_step
        bound = self._bound.get(batch)
        if bound is None or bound[3] < n_tok:
            bound = self._bind(bound[0] if bound else self._session(batch), batch, n_tok)
            self._bound[batch] = bound
        self._sess, self._io, self._control = bound[:3]
        self._t0 = cfg.tokens_per_step * t0

    def _bind(self, sess, batch: int, n_tok: int) -> tuple:
        """A binding of `sess` with its control output and key/value caches for `n_tok`
        tokens, each cache bound as both the past input and the present output."""
        import onnxruntime as ort

        cfg = self._cfg
        io = sess.io_binding()
        control = ort.OrtValue.ortvalue_from_shape_and_type(
            [batch, sess.get_outputs()[0].shape[1]], np.float32)
        io.bind_ortvalue_output("control", control)
        caches = []
        for i in range(cfg.n_layers):
            for kv in "kv":
                cache = ort.OrtValue.ortvalue_from_numpy(
                    np.zeros((1, batch * cfg.n_heads, n_tok, cfg.head_dim), np.float32))
                io.bind_ortvalue_input(f"past_{kv}{i}", cache)
                io.bind_ortvalue_output(f"present_{kv}{i}", cache)
                caches.append(cache)
        return sess, io, control, n_tok, caches

    def step_numpy(self, feats: np.ndarray, p0: int) -> np.ndarray:
        """Feed the tokens at positions p0 .. p0 + n - 1 and predict the control of the last
        (see `CachedDecoder.step`): `feats` (B, n, 17) float32; returns (B, 3) or (B, 4)."""
        n = feats.shape[1]
        p1 = p0 + n
        inputs = (np.ascontiguousarray(feats, np.float32),
                  np.arange(self._t0 + p0, self._t0 + p1, dtype=np.int64),
                  np.array([p1 - 1], np.int32), np.array(p1, np.int32))
        for name, arr in zip(("feats", "positions", "seqlens_k", "total_len"), inputs):
            self._io.bind_cpu_input(name, arr)  # `inputs` keeps the arrays alive for the run
        self._sess.run_with_iobinding(self._io)
        return self._control.numpy().copy()


class ExportedArt:
    """An exported model ready for rollouts (what `rollout` reads of a `TrainedArt`).

    Attributes:
        runtime: "onnx".
        config, normalizer, meta: as recorded at export.
        path: the file; file_sha256: its sha256.
        sha256: the source checkpoint's payload sha256 (the model's identity, as a
            `TrainedArt`'s).
        checkpoint_file: the source checkpoint's file name.
        n_parameters: the model's parameter count.
        decoder: its `OnnxDecoder`.
    """

    runtime = "onnx"

    def __init__(self, path: Path, blob: bytes, meta: dict) -> None:
        try:
            self.config = ArtConfig.from_dict(dict(meta["config"]))
            self.normalizer = Normalizer.from_dict(meta["normalization"])
        except (KeyError, TypeError, ValueError, ConfigError) as exc:
            raise CheckpointError(path, f"malformed config or normalisation: {exc}") from exc
        self.meta = meta.get("meta") if isinstance(meta.get("meta"), dict) else {}
        self.path = str(path)
        self.file_sha256 = hashlib.sha256(blob).hexdigest()
        self.sha256 = str(meta.get("checkpoint_sha256", ""))
        self.checkpoint_file = str(meta.get("checkpoint_file", ""))
        self.n_parameters = int(meta.get("n_parameters", 0))
        self.decoder = OnnxDecoder(blob, self.config)


def load_exported(path: str | Path, expected_checkpoint_sha256: str | None = None,
                  expected_file_sha256: str | None = None) -> ExportedArt:
    """Read and check an exported model (module docstring).

    Args:
        path: the file `art-guidance export` wrote.
        expected_checkpoint_sha256: the checkpoint it must have been exported from (None: any).
        expected_file_sha256: pin the file itself (e.g. a shipped one; None: not pinned).

    Raises:
        ModelError: ONNX Runtime is not installed.
        CheckpointError: unreadable, not ONNX (corrupt, truncated), not this format, altered
            weights, another checkpoint than expected, a pinned checksum that differs, or a
            probe ONNX Runtime does not reproduce.
    """
    if not installed("onnxruntime"):
        raise ModelError("the ONNX runtime needs the Python package onnxruntime, which is "
                         "not installed (pip install art_guidance brings it)")
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(path, f"cannot read the exported model ({exc.strerror or exc})"
                              ) from exc
    digest = hashlib.sha256(blob).hexdigest()
    if expected_file_sha256 is not None and digest != expected_file_sha256:
        raise CheckpointError(path, f"not the expected file: sha256 {digest[:16]}..., "
                                    f"expected {expected_file_sha256[:16]}...")
    try:
        onnx_wire.check(blob)
        meta = json.loads(onnx_wire.metadata_props(blob)[METADATA_KEY])
    except Exception as exc:  # WireError, KeyError, ValueError: all a refusal
        raise CheckpointError(path, "not an exported art_guidance model (corrupt, truncated "
                                    "or another ONNX file): "
                                    f"{str(exc).splitlines()[0][:200] if str(exc) else exc!r}"
                              ) from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT \
            or meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(path, f"not format {FORMAT} v{FORMAT_VERSION}")
    if weights_digest(onnx_wire.initializers(blob)) != meta.get("weights_sha256"):
        raise CheckpointError(path, "its weights are not those recorded at export (altered "
                                    "after `art-guidance export`)")
    source = str(meta.get("checkpoint_sha256", ""))
    if expected_checkpoint_sha256 is not None and source != expected_checkpoint_sha256:
        raise CheckpointError(path, f"not the expected model: exported from checkpoint "
                                    f"{source[:16] or '?'}..., expected "
                                    f"{expected_checkpoint_sha256[:16]}...")
    art = ExportedArt(path, blob, meta)
    _check_probe(path, art, meta.get("probe"))
    return art


def _check_probe(path: Path, art: ExportedArt, probe: object) -> None:
    """Run the probe recorded at export; refuse a runtime that does not reproduce it."""
    try:
        feats = np.asarray(probe["feats"], np.float32)
        expected = np.asarray(probe["control"], np.float64)
        ok = feats.shape == (PROBE_BATCH, PROBE_TOKENS, FEATURES) \
            and expected.shape[0] == PROBE_BATCH
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        raise CheckpointError(path, "no valid probe in its metadata")
    dec = art.decoder
    try:
        dec.reset(PROBE_BATCH, probe_steps(art.config), 0)
        got = dec.step_numpy(feats, 0)
    except Exception as exc:  # the graph does not run here: a refusal, not a crash
        raise CheckpointError(path, f"ONNX Runtime cannot run it: "
                                    f"{str(exc).splitlines()[0][:200]}") from exc
    err = float(np.max(np.abs(got - expected))) if got.shape == expected.shape else np.inf
    if not err <= PROBE_TOL:
        raise CheckpointError(path, f"ONNX Runtime does not reproduce the export's probe "
                                    f"(largest difference {err:.3g} > {PROBE_TOL:g})")


def probe_steps(config: ArtConfig) -> int:
    """Steps whose tokens hold the probe's PROBE_TOKENS tokens."""
    return -(-PROBE_TOKENS // config.tokens_per_step)


def exported_path(checkpoint: str | Path) -> Path:
    """Where the exported file of a checkpoint lies by convention: beside it, `.onnx`."""
    return Path(checkpoint).with_suffix(ONNX_SUFFIX)
