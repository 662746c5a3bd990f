"""The seal of a recording's run metadata: a sha256 of every value in the MCAP metadata record.

The recorder writes the run metadata (the configuration, the model's and the runtime's
checksums, the runtime, the node's parameters, the package versions) into the `art_guidance`
metadata record of every file. That record lies outside every chunk, so outside any CRC, and
replay trusts what it says: the model checksum picks the model a log is replayed with. `seal`
adds `metadata_seal` to it: JSON {"format", "fields": {name: sha256 of the value as stored},
"sha256": of the format and fields}. `seal_problems` names every value that no longer matches
its seal (field and value), every field added or removed since, and a seal that is itself
damaged. A recording from before the seal has no `metadata_seal` and is reported as unsealed
(its configuration is still sealed by its own `record_sha256`).
"""
from __future__ import annotations

import hashlib
import json

SEAL_KEY = "metadata_seal"
SEAL_FORMAT = 1
SHOWN_CHARS = 72  # a value longer than this is shown cut, with its length


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _body_sha256(body: dict) -> str:
    return _sha256(json.dumps(body, sort_keys=True))


def shown(value: str) -> str:
    """`value` quoted for a message, cut to SHOWN_CHARS characters (with its length)."""
    if len(value) <= SHOWN_CHARS:
        return repr(value)
    return f"{value[:SHOWN_CHARS]!r}... ({len(value)} characters)"


def seal(metadata: dict[str, str]) -> dict[str, str]:
    """`metadata` (string values, as the record stores them) with its `metadata_seal` over
    every other field."""
    fields = {name: _sha256(value) for name, value in sorted(metadata.items())
              if name != SEAL_KEY}
    body = {"format": SEAL_FORMAT, "fields": fields}
    return {**{k: v for k, v in metadata.items() if k != SEAL_KEY},
            SEAL_KEY: json.dumps({**body, "sha256": _body_sha256(body)}, sort_keys=True)}


def seal_problems(metadata: dict[str, str]) -> list[str] | None:
    """What in a metadata record does not match its seal ([] = every value does); None when
    the record has no seal (recorded before it). Each problem names the field and its value."""
    if SEAL_KEY not in metadata:
        return None
    try:
        sealed = json.loads(metadata[SEAL_KEY])
        body = {"format": sealed["format"], "fields": dict(sealed["fields"])}
        own = sealed["sha256"]
    except (ValueError, KeyError, TypeError) as exc:
        return [f"{SEAL_KEY} = {shown(metadata[SEAL_KEY])} does not read ({type(exc).__name__}:"
                f" {exc}): the seal was altered and no value can be checked"]
    if own != _body_sha256(body) or body["format"] != SEAL_FORMAT:
        return [f"{SEAL_KEY} does not match its own sha256 {str(own)[:16]}... (format "
                f"{body['format']!r}): the seal was altered and no value can be checked"]
    problems = []
    for name, digest in sorted(body["fields"].items()):
        if name not in metadata:
            problems.append(f"{name} is sealed but missing from the record: removed after "
                            "recording")
        elif _sha256(metadata[name]) != digest:
            problems.append(f"{name} = {shown(metadata[name])} does not match its seal "
                            f"(sha256 {_sha256(metadata[name])[:16]}..., sealed "
                            f"{digest[:16]}...): altered after recording")
    for name in sorted(set(metadata) - set(body["fields"]) - {SEAL_KEY}):
        problems.append(f"{name} = {shown(metadata[name])} is not in the seal: added after "
                        "recording")
    return problems
