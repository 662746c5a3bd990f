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

A record without `metadata_seal` must still have one where its file says that its writer seals
every record (the MCAP header's `library` is `SEALING_LIBRARY`, one character damaged or not:
`writer_seals`; the package version in
`versions` is the same with and without the seal, and files sealed before that header say
"art_guidance") or where another field holds a seal (its key was altered; a seal is known by
its shape, one of its own keys damaged or not): `seal_problems` then
reports the seal as altered, checks the values against a seal found under another key, and
names every field that is not run metadata (`RUN_METADATA_KEYS`).
"""
from __future__ import annotations

import hashlib
import json

SEAL_KEY = "metadata_seal"
SEAL_FORMAT = 1
SEALING_LIBRARY = f"art_guidance (writes {SEAL_KEY})"  # MCAP header `library` of the recorder
SHOWN_CHARS = 72  # a value longer than this is shown cut, with its length
# the fields the node records (`ros.solve_recording`), every version
RUN_METADATA_KEYS = frozenset({"config", "versions", "model_checksum", "model", "parameters",
                               "art_runtime", "art_runtime_checksum"})


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _body_sha256(body: dict) -> str:
    return _sha256(json.dumps(body, sort_keys=True))


def shown(value: str) -> str:
    """`value` quoted for a message, cut to SHOWN_CHARS characters (with its length)."""
    if len(value) <= SHOWN_CHARS:
        return repr(value)
    return f"{value[:SHOWN_CHARS]!r}... ({len(value)} characters)"


def shown_name(name: str) -> str:
    """A field's name for a message: as it is, or quoted and cut as `shown` does where it is
    long or does not print."""
    return name if len(name) <= SHOWN_CHARS and name.isprintable() else shown(name)


def unknown_fields(metadata: dict[str, str]) -> list[str]:
    """The fields of a metadata record that are neither run metadata nor its seal, sorted."""
    return sorted(set(metadata) - RUN_METADATA_KEYS - {SEAL_KEY})


SEAL_FIELDS = frozenset({"format", "fields", "sha256"})


def _reads_as_seal(value: str) -> bool:
    """Whether `value` is a seal by its shape: a JSON object of three keys, at least two of
    them the seal's (one key damaged outside any CRC does not make it something else)."""
    try:
        body = json.loads(value)
    except ValueError:
        return False
    return isinstance(body, dict) and len(body) == 3 and len(set(body) & SEAL_FIELDS) >= 2


def _one_edit(a: str, b: str) -> bool:
    """`a` and `b` differ by at most one character changed, inserted or removed."""
    if abs(len(a) - len(b)) > 1:
        return False
    if len(a) == len(b):
        return sum(x != y for x, y in zip(a, b)) <= 1
    short, long_ = sorted((a, b), key=len)
    i = next((k for k, (x, y) in enumerate(zip(short, long_)) if x != y), len(short))
    return short[i:] == long_[i + 1:]


def writer_seals(library: str | None) -> bool:
    """Whether a file whose MCAP header names `library` was written by a recorder that seals
    every record: `SEALING_LIBRARY`, also with one character damaged (the header lies outside
    every CRC)."""
    return library is not None and _one_edit(str(library), SEALING_LIBRARY)


def seal(metadata: dict[str, str]) -> dict[str, str]:
    """`metadata` (string values, as the record stores them) with its `metadata_seal` over
    every other field."""
    fields = {name: _sha256(value) for name, value in sorted(metadata.items())
              if name != SEAL_KEY}
    body = {"format": SEAL_FORMAT, "fields": fields}
    return {**{k: v for k, v in metadata.items() if k != SEAL_KEY},
            SEAL_KEY: json.dumps({**body, "sha256": _body_sha256(body)}, sort_keys=True)}


def seal_problems(metadata: dict[str, str], writer_seals: bool = False) -> list[str] | None:
    """What in a metadata record does not match its seal ([] = every value does); None when
    the record has no seal and need not have one (recorded before it). Each problem names the
    field and its value. A record without its seal must have one where `writer_seals` (its
    file's writer seals every record) or where another field holds a seal (see the module
    docstring)."""
    if SEAL_KEY not in metadata:
        moved = next((k for k in sorted(metadata) if _reads_as_seal(metadata[k])), None)
        if moved is not None:  # the seal's key was altered: the values are checked all the same
            rest = {k: v for k, v in metadata.items() if k != moved}
            return [f"no {SEAL_KEY}, but {shown_name(moved)} holds a seal: its key was altered "
                    "after recording", *seal_problems({**rest, SEAL_KEY: metadata[moved]})]
        if not writer_seals:
            return None
        return [f"no {SEAL_KEY}, though the file's writer seals every record: removed after "
                "recording", *(f"{shown_name(k)} = {shown(metadata[k])} is not run metadata: "
                               "added after recording" for k in unknown_fields(metadata))]
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
            problems.append(f"{shown_name(name)} is sealed but missing from the record: removed "
                            "after recording")
        elif _sha256(metadata[name]) != digest:
            problems.append(f"{shown_name(name)} = {shown(metadata[name])} does not match its "
                            f"seal (sha256 {_sha256(metadata[name])[:16]}..., sealed "
                            f"{digest[:16]}...): altered after recording")
    for name in sorted(set(metadata) - set(body["fields"]) - {SEAL_KEY}):
        problems.append(f"{shown_name(name)} = {shown(metadata[name])} is not in the seal: added "
                        "after recording")
    return problems
