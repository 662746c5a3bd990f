"""The checkpoint file's header line, readable without torch.

``ART-GUIDANCE-CHECKPOINT v<version> sha256=<payload sha256> bytes=<payload size>\\n``, then the
payload (`art_guidance.art.checkpoint`). An exported model (`art_guidance.art.onnx_art`) names
the checkpoint it came from by that sha256, which a flight computer without torch can read here.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

from art_guidance.errors import CheckpointError

FORMAT_VERSION = 1
MAGIC = "ART-GUIDANCE-CHECKPOINT"
HEADER_RE = re.compile(rb"^ART-GUIDANCE-CHECKPOINT v(\d+) sha256=([0-9a-f]{64}) bytes=(\d+)\n")
MAX_HEADER = 160


def match_header(path: str | Path, head: bytes) -> re.Match:
    """The header line at the start of `head` (a checkpoint file's first bytes), as a match of
    HEADER_RE: groups version, payload sha256, payload size.

    Raises:
        CheckpointError: no checkpoint header.
    """
    match = HEADER_RE.match(head[:MAX_HEADER])
    if match is None:
        raise CheckpointError(path, f"not an art_guidance checkpoint (no '{MAGIC} v<n> "
                                    "sha256=... bytes=...' header line)")
    return match


def header_sha256(path: str | Path) -> str:
    """The payload sha256 a checkpoint's header announces (the payload is not read).

    Raises:
        CheckpointError: unreadable file or no checkpoint header.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER)
    except OSError as exc:
        raise CheckpointError(path, f"cannot read the checkpoint ({exc.strerror or exc})") from exc
    return match_header(path, head).group(2).decode()


def verified_payload(path: str | Path, expected_sha256: str | None = None) -> tuple[bytes, str]:
    """A checkpoint file's payload bytes and their sha256, checked as far as it can be without
    torch: readable, header, format version, payload length, payload sha256, and
    `expected_sha256` when given (the payload itself is `checkpoint.read_payload`'s).

    Raises:
        CheckpointError: the first check that fails, in words.
    """
    try:
        blob = Path(path).read_bytes()
    except OSError as exc:
        raise CheckpointError(path, f"cannot read the checkpoint ({exc.strerror or exc})") from exc
    match = match_header(path, blob)
    version, digest, size = int(match.group(1)), match.group(2).decode(), int(match.group(3))
    if version != FORMAT_VERSION:
        raise CheckpointError(path, f"unsupported checkpoint format version {version} (this "
                                    f"build reads version {FORMAT_VERSION})")
    data = blob[match.end():]
    if len(data) != size:
        raise CheckpointError(path, f"truncated or padded: the header announces {size} payload "
                                    f"bytes, the file holds {len(data)}")
    actual = hashlib.sha256(data).hexdigest()
    if actual != digest:
        raise CheckpointError(path, f"corrupt: payload sha256 {actual[:16]}... differs from "
                                    f"the header's {digest[:16]}...")
    if expected_sha256 is not None and actual != expected_sha256:
        raise CheckpointError(path, f"not the expected model: sha256 {actual[:16]}..., "
                                    f"expected {expected_sha256[:16]}...")
    return data, actual
