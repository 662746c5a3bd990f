"""A model's files, read without torch: the shipped models and the checksums
`models/models.json` pins (`pinned_sha256`), the checkpoint beside an exported file
(`checkpoint_beside`) and a checkpoint file checked whole (`checkpoint_problem`).

`provider.ArtWarmStart.load` reads them (and `provider` re-exports the models.json readers).
"""
from __future__ import annotations

import json
from pathlib import Path

from art_guidance.art.checkpoint_header import verified_payload
from art_guidance.errors import CheckpointError

DEFAULTS_KEY = "defaults"  # models.json: the default per mode and why (not a model entry)
CHECKPOINT_SUFFIX = ".pt"  # a checkpoint's file; its exported file lies beside it (.onnx)


def models_dir() -> Path:
    """The packaged model directory (`art_guidance/models`)."""
    return Path(__file__).resolve().parent.parent / "models"


def shipped_model_with_sha256(sha256: str) -> Path | None:
    """The shipped model whose pinned checksum is `sha256` (None: no shipped model has it)."""
    for name, entry in shipped_models().items():
        if isinstance(entry, dict) and entry.get("sha256") == sha256:
            return models_dir() / name
    return None


def _models_json() -> dict:
    """`models/models.json` as a dict ({} if missing or unreadable)."""
    path = models_dir() / "models.json"
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return {}


def shipped_models() -> dict[str, dict]:
    """`models/models.json`: file name -> {"sha256", provenance} of every shipped model (its
    "defaults" statement left out: `shipped_defaults`)."""
    return {name: entry for name, entry in _models_json().items()
            if name != DEFAULTS_KEY and isinstance(entry, dict) and "sha256" in entry}


def shipped_defaults() -> dict:
    """What models.json says of the defaults: {"rule": ..., mode: {"model", "why"}}."""
    defaults = _models_json().get(DEFAULTS_KEY)
    return dict(defaults) if isinstance(defaults, dict) else {}


def pinned_sha256(path: str | Path) -> str | None:
    """The checksum a shipped model must have (None for a file that is not a shipped model):
    a checkpoint's payload sha256, or an exported file's sha256 (its checkpoint's entry in
    models.json lists it under "export")."""
    path = Path(path).resolve()
    if path.parent != models_dir():
        return None
    for name, entry in shipped_models().items():
        if not isinstance(entry, dict):
            continue
        if name == path.name:
            return entry.get("sha256")
        export = entry.get("export")
        if isinstance(export, dict) and export.get("file") == path.name:
            return export.get("sha256")
    return None


def checkpoint_beside(exported: str | Path) -> Path:
    """Where the checkpoint of an exported file lies by convention: beside it, `.pt` (the
    inverse of `onnx_art.exported_path`)."""
    return Path(exported).with_suffix(CHECKPOINT_SUFFIX)


def checkpoint_problem(path: str | Path, expected_sha256: str | None = None) -> str | None:
    """Why a checkpoint file would be refused before its payload is unpickled, or None where it
    passes: `checkpoint_header.verified_payload`, the checks `checkpoint.read_payload` makes of
    the file before torch reads it (a file that passes may still hold a payload torch
    refuses)."""
    try:
        verified_payload(path, expected_sha256)
    except CheckpointError as exc:
        return exc.reason
    return None
