"""Checkpoint files: a checksummed header line, then a weights-only `torch.save` payload.

File layout::

    ART-GUIDANCE-CHECKPOINT v1 sha256=<64 hex> bytes=<payload length>\\n
    <payload: torch.save of plain data (dict, list, str, int, float, bool, None) and tensors>

Reading checks, in order: the magic and the format version of the header, the payload length
(a truncated file), its sha256 (a corrupt or tampered file; optionally against a pinned value),
then `torch.load(weights_only=True)`, which refuses any pickled callable without running it,
and finally the config, the normalisation and every weight's name and shape against the model
the config builds. Every refusal raises `CheckpointError` naming the file and the reason.
Writes are atomic (`files.write_atomic`).
"""
from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import torch

from art_guidance.art.checkpoint_header import (
    FORMAT_VERSION, MAGIC, match_header, verified_payload,
)
from art_guidance.art.config import ArtConfig
from art_guidance.art.kv_cache import CachedDecoder
from art_guidance.art.model import ArtModel
from art_guidance.art.normalization import Normalizer
from art_guidance.errors import CheckpointError, ConfigError
from art_guidance.files import write_atomic


class TrainedArt:
    """A trained model ready for rollouts: weights, config, normalisation and provenance.

    Its KV-cached decoder holds one cache: run one rollout at a time per TrainedArt (load one
    per thread for concurrent rollouts).

    Attributes:
        model: the ArtModel in eval mode.
        config: its ArtConfig.
        normalizer: the training split's normalisation statistics.
        meta: provenance (dataset manifests and scenario, training command and history).
        path: the file it was loaded from (None if built in memory).
        sha256: sha256 of the checkpoint payload (None if built in memory).
        runtime: "torch" (an exported model flies on "onnx": `onnx_art.ExportedArt`).
    """

    runtime = "torch"

    def __init__(self, model: ArtModel, normalizer: Normalizer, meta: dict | None = None,
                 path: str | None = None, sha256: str | None = None) -> None:
        self.model = model.eval()
        self.config = model.cfg
        self.normalizer = normalizer
        self.meta = meta or {}
        self.path = path
        self.sha256 = sha256
        self._decoder: CachedDecoder | None = None

    @property
    def n_parameters(self) -> int:
        """The model's parameter count."""
        return self.model.n_parameters()

    @property
    def decoder(self) -> CachedDecoder:
        """The KV-cached decoder (weights packed on first use)."""
        if self._decoder is None:
            self._decoder = CachedDecoder(self.model)
        return self._decoder


def encode(payload: dict[str, Any]) -> bytes:
    """The bytes of a checkpoint file holding `payload` (plain data and tensors only)."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    data = buf.getvalue()
    digest = hashlib.sha256(data).hexdigest()
    return f"{MAGIC} v{FORMAT_VERSION} sha256={digest} bytes={len(data)}\n".encode() + data


def save(path: str | Path, payload: dict[str, Any]) -> str:
    """Atomically write `payload` as a checkpoint file; returns the payload's sha256."""
    blob = encode(payload)
    write_atomic(path, blob)
    return match_header(path, blob).group(2).decode()


def read_payload(path: str | Path, expected_sha256: str | None = None
                 ) -> tuple[dict[str, Any], str]:
    """Read and verify a checkpoint file; returns (payload, payload sha256).

    Raises:
        CheckpointError: missing file, bad header, wrong version, truncated, checksum
            mismatch (or not the pinned `expected_sha256`), or a payload that is not plain
            data and tensors.
    """
    data, actual = verified_payload(path, expected_sha256)
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # UnpicklingError, RuntimeError, zip errors: all a refusal
        raise CheckpointError(path, "refused: the payload is not weights-only data (it may "
                                    f"hold pickled code, which is never run): "
                                    f"{str(exc).splitlines()[0][:200]}") from exc
    if not isinstance(payload, dict):
        raise CheckpointError(path, f"payload is a {type(payload).__name__}, expected a dict")
    return payload, actual


def model_payload(model: ArtModel, normalizer: Normalizer, meta: dict,
                  state_dict: dict[str, torch.Tensor] | None = None) -> dict[str, Any]:
    """The payload of an inference checkpoint (weights default to the model's own).

    Raises:
        TypeError: if `meta` is not plain JSON-like data (it is stored as such).
    """
    weights = model.state_dict() if state_dict is None else state_dict
    return {"format_version": FORMAT_VERSION, "kind": "model",
            "config": model.cfg.to_dict(), "normalization": normalizer.to_dict(),
            "state_dict": {k: v.detach().cpu().clone() for k, v in weights.items()},
            "meta": json.loads(json.dumps(meta))}


def load(path: str | Path, device: str | torch.device = "cpu",
         expected_sha256: str | None = None) -> TrainedArt:
    """Load an inference checkpoint into a `TrainedArt` (model in eval mode on `device`).

    Args:
        path: checkpoint file written by `art-guidance train`.
        device: where the weights go.
        expected_sha256: pin the payload's sha256 (e.g. of the shipped default model).

    Raises:
        CheckpointError: see `read_payload`, plus a wrong format version inside the payload,
            a malformed config or normalisation, and missing, unexpected, mis-shaped or
            non-finite weights.
    """
    payload, digest = read_payload(path, expected_sha256)
    model, normalizer = build(path, payload)
    meta = payload.get("meta") if isinstance(payload.get("meta"), dict) else {}
    return TrainedArt(model.to(device), normalizer, meta, str(path), digest)


def build(path: str | Path, payload: dict[str, Any]) -> tuple[ArtModel, Normalizer]:
    """Validate a payload's config, normalisation and weights and build the model.

    Raises:
        CheckpointError: on any inconsistency (see `load`).
    """
    if payload.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(path, f"payload format version {payload.get('format_version')!r}"
                                    f" is not {FORMAT_VERSION}")
    try:
        cfg = ArtConfig.from_dict(dict(payload["config"]))
        normalizer = Normalizer.from_dict(payload["normalization"])
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise CheckpointError(path, f"malformed config or normalisation: {exc}") from exc
    weights = payload.get("state_dict")
    if not isinstance(weights, dict):
        raise CheckpointError(path, "no state_dict")
    model = ArtModel(cfg)
    _check_weights(path, model.state_dict(), weights)
    model.load_state_dict(weights, strict=True)
    return model.eval(), normalizer


def _check_weights(path: str | Path, expected: dict[str, torch.Tensor],
                   weights: dict[str, Any]) -> None:
    missing = sorted(set(expected) - set(weights))
    unexpected = sorted(set(weights) - set(expected))
    if missing or unexpected:
        raise CheckpointError(path, f"weights do not match the config: missing {missing[:5]}, "
                                    f"unexpected {unexpected[:5]}")
    for name, ref in expected.items():
        w = weights[name]
        if not isinstance(w, torch.Tensor) or tuple(w.shape) != tuple(ref.shape):
            shape = tuple(w.shape) if isinstance(w, torch.Tensor) else type(w).__name__
            raise CheckpointError(path, f"weight {name} has shape {shape}, the config needs "
                                        f"{tuple(ref.shape)}")
        if not torch.isfinite(w).all():
            raise CheckpointError(path, f"weight {name} holds NaN or infinite values")
