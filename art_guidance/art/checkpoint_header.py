"""The checkpoint file's header line, readable without torch.

``ART-GUIDANCE-CHECKPOINT v<version> sha256=<payload sha256> bytes=<payload size>\\n``, then the
payload (`art_guidance.art.checkpoint`). An exported model (`art_guidance.art.onnx_art`) names
the checkpoint it came from by that sha256, which a flight computer without torch can read here.
"""
from __future__ import annotations

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
