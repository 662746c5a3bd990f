"""Append-only, checksummed, resumable dataset storage: `.npz` shards and a JSON-lines manifest.

A dataset directory holds::

    manifest.jsonl     line 1: the header (mode, base seed, N, seed rule, config fingerprint);
                       then one line per committed shard: file, sha256, size, sample indices,
                       small per-shard statistics
    shard-000000.npz   M samples, every array stacked along axis 0 (plain .npz, no pickles)
    split.json         the 90/10 train/test split of the sample indices (from the base seed;
                       a header "test_fraction" changes the share, e.g. 0 for DAgger data)
    summary.json       written at the end of every generate run
    .lock              flock held by the one writer

Commit protocol: a shard is written to a temp file in the directory, fsynced, renamed over its
final name (`os.replace`) and the directory fsynced; only then is its manifest line appended and
fsynced. A shard belongs to the dataset if and only if its manifest line is complete, so a
SIGKILL at any moment leaves at most a temp file, a shard without a manifest line, or a torn
last manifest line without its newline. `DatasetWriter` removes the first two and truncates the
third when it opens the directory again; readers ignore all three.
"""
from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import re
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from art_guidance.errors import ConfigError, DatasetError, InputError
from art_guidance.files import TMP_SUFFIX, write_atomic

FORMAT_VERSION = 1
MANIFEST = "manifest.jsonl"
SPLIT = "split.json"
SUMMARY = "summary.json"
LOCK = ".lock"
TEST_FRACTION = 0.1
SPLIT_STREAM = 0x5E17  # second SeedSequence word: the split never reuses a scenario stream
_SHARD_RE = re.compile(r"^shard-(\d{6,})\.npz$")
# Header fields that must match for a run to resume an existing directory.
RESUME_KEYS = ("format", "mode", "base_seed", "n", "seed_rule", "config_sha256")


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of `data`."""
    return hashlib.sha256(data).hexdigest()


def train_test_split(base_seed: int, n: int, test_fraction: float = TEST_FRACTION
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic 90/10 (or other `test_fraction`) split of the sample indices 0..n-1.

    The test set is the first round(test_fraction n) entries of a permutation drawn from
    SeedSequence([base_seed, SPLIT_STREAM]), sorted; the train set is the rest.

    Returns:
        (train, test): sorted int64 index arrays, disjoint, covering 0..n-1.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(base_seed), SPLIT_STREAM]))
    perm = rng.permutation(int(n))
    n_test = int(round(test_fraction * n))
    return np.sort(perm[n_test:]).astype(np.int64), np.sort(perm[:n_test]).astype(np.int64)


def encode_shard(arrays: dict[str, np.ndarray]) -> bytes:
    """The .npz bytes of `arrays` (every value a numeric or fixed-width string array)."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def read_manifest(root: str | Path) -> tuple[dict, list[dict], int]:
    """Parse `root/manifest.jsonl`.

    Returns:
        header, the shard entries in commit order, and the byte length of the valid part (a
        torn last line without its newline is not part of it).

    Raises:
        DatasetError: missing manifest, a corrupt complete line, a missing header, or shard
            entries that overlap or fall outside 0..n-1.
    """
    path = Path(root) / MANIFEST
    try:
        data = path.read_bytes()
    except FileNotFoundError as exc:
        raise DatasetError(f"{root}: no {MANIFEST}; not a dataset directory") from exc
    valid = data.rfind(b"\n") + 1
    entries = []
    for no, line in enumerate(data[:valid].splitlines(), start=1):
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise DatasetError(f"{path}: line {no} is corrupt ({exc})") from exc
    if not entries or entries[0].get("kind") != "header":
        raise DatasetError(f"{path}: the first line must be the header")
    header, shards = entries[0], entries[1:]
    n = header.get("n")
    seen: set[int] = set()
    for entry in shards:
        idx = entry.get("indices")
        if entry.get("kind") != "shard" or not isinstance(idx, list) \
                or not _SHARD_RE.match(str(entry.get("file"))):
            raise DatasetError(f"{path}: malformed shard entry {str(entry)[:120]}")
        if seen.intersection(idx) or len(set(idx)) != len(idx) \
                or not all(isinstance(i, int) and 0 <= i < n for i in idx):
            raise DatasetError(f"{path}: {entry['file']} holds duplicate or out-of-range "
                               "sample indices")
        seen.update(idx)
    return header, shards, valid


def read_shard(root: str | Path, entry: dict, verify: bool = True) -> dict[str, np.ndarray]:
    """Load one committed shard, checking its sha256 and indices against the manifest entry.

    Raises:
        DatasetError: missing file, checksum mismatch or indices that differ from the manifest.
    """
    path = Path(root) / entry["file"]
    try:
        data = path.read_bytes()
    except FileNotFoundError as exc:
        raise DatasetError(f"{path}: shard listed in the manifest is missing") from exc
    if verify and sha256_bytes(data) != entry["sha256"]:
        raise DatasetError(f"{path}: sha256 mismatch (manifest {entry['sha256'][:16]}..., file "
                           f"{sha256_bytes(data)[:16]}...); the shard or the manifest is corrupt")
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    if not np.array_equal(arrays.get("index"), np.asarray(entry["indices"])):
        raise DatasetError(f"{path}: sample indices differ from the manifest entry")
    return arrays


def read_split(root: str | Path, header: dict) -> np.ndarray:
    """(n,) bool, True for test samples; split.json is checked against the seed rule."""
    train, test = train_test_split(header["base_seed"], header["n"], _test_fraction(header))
    path = Path(root) / SPLIT
    if path.exists():
        stored = json.loads(path.read_text(encoding="utf-8"))
        if stored.get("test") != test.tolist() or stored.get("train") != train.tolist():
            raise DatasetError(f"{path}: does not match the split of base seed "
                               f"{header['base_seed']} and n = {header['n']}")
    is_test = np.zeros(header["n"], dtype=bool)
    is_test[test] = True
    return is_test


def complete_shards(root: str | Path) -> Iterator[dict[str, np.ndarray]]:
    """The shards of a complete dataset, one at a time (memory: one shard), each with
    "is_test" (M,) bool added from the split.

    Raises:
        DatasetError: an incomplete or corrupt dataset.
    """
    head, shards, _ = read_manifest(root)
    if sum(len(e["indices"]) for e in shards) != head["n"]:
        raise DatasetError(f"{root}: incomplete dataset; re-run its generate command first")
    is_test = read_split(root, head)
    for entry in shards:
        arrays = read_shard(root, entry)
        yield dict(arrays, is_test=is_test[arrays["index"]])


def load_dataset(root: str | Path, verify: bool = True,
                 require_complete: bool = True) -> dict[str, np.ndarray]:
    """Load a dataset directory into stacked arrays sorted by sample index.

    Args:
        root: dataset directory written by `art-guidance generate`.
        verify: check every shard's sha256 against the manifest.
        require_complete: raise unless all n samples are present.

    Returns:
        {name: array with a leading sample axis (M, ...)} as written by the generator (see
        `art_guidance.data.stages.generate_chunk`), plus "is_test" (M,) bool from the split.

    Raises:
        DatasetError: checksum or index mismatch, missing shard, or (when required) an
            incomplete dataset.
    """
    header, shards, _ = read_manifest(root)
    parts = [read_shard(root, entry, verify) for entry in shards]
    if not parts:
        if require_complete and header["n"] > 0:
            raise DatasetError(f"{root}: no committed shards (0 of {header['n']} samples)")
        return {}
    keys = set(parts[0])
    if any(set(p) != keys for p in parts):
        raise DatasetError(f"{root}: shards hold different array names")
    out = {k: np.concatenate([p[k] for p in parts]) for k in sorted(keys)}
    order = np.argsort(out["index"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    if require_complete and not np.array_equal(out["index"], np.arange(header["n"])):
        raise DatasetError(f"{root}: incomplete, {out['index'].size} of {header['n']} samples; "
                           "re-run the same generate command to resume")
    out["is_test"] = read_split(root, header)[out["index"]]
    return out


class DatasetWriter:
    """The single writer of a dataset directory (create or resume), used as a context manager.

    Opening takes an exclusive lock, creates the header or checks it against `header`, verifies
    the committed shards, and removes what an interrupted run left behind (temp files, shards
    without a manifest line, a torn last manifest line).
    """

    def __init__(self, root: str | Path, header: dict[str, Any], verify: bool = True) -> None:
        """Open (create or resume) `root` for `header`.

        Raises:
            InputError: unwritable directory, a directory that is not a dataset, another
                writer holding the lock, or a header (mode, seed, n) that does not match.
            ConfigError: the configuration fingerprint differs from the stored one.
            DatasetError: the existing data is corrupt.
        """
        self.root = Path(root)
        self._lock_fd = self._open_locked()
        try:
            self._open(dict(header, kind="header", format=FORMAT_VERSION), verify)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ opening
    def _open_locked(self) -> int:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.root / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError("--out", f"cannot create or write the dataset directory ({exc})",
                             str(self.root)) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            raise InputError("--out", "another generate run is writing this directory",
                             str(self.root)) from exc
        return fd

    def _open(self, header: dict, verify: bool) -> None:
        manifest = self.root / MANIFEST
        if not manifest.exists():
            self._check_empty()
            self._cleanup(set())
            write_atomic(self.root / SPLIT, _split_json(header))
            write_atomic(manifest, (json.dumps(header, sort_keys=True) + "\n").encode())
        stored, shards, valid = read_manifest(self.root)
        _check_resume(stored, header)
        if valid != manifest.stat().st_size:
            os.truncate(manifest, valid)  # torn last line of a killed run
        for entry in shards:
            path = self.root / entry["file"]
            if not path.is_file() or path.stat().st_size != entry["bytes"]:
                raise DatasetError(f"{path}: missing or of the wrong size for its manifest entry")
            if verify:
                read_shard(self.root, entry)
        self.header = stored
        self.shards = shards
        self._done = {i for e in shards for i in e["indices"]}
        if not (self.root / SPLIT).exists():
            write_atomic(self.root / SPLIT, _split_json(stored))
        read_split(self.root, stored)
        self._cleanup({e["file"] for e in shards})
        self._next = 1 + max((int(_SHARD_RE.match(e["file"]).group(1)) for e in shards),
                             default=-1)

    def _check_empty(self) -> None:
        ours = {LOCK, SPLIT, SUMMARY}
        foreign = [p.name for p in self.root.iterdir()
                   if p.name not in ours and not p.name.endswith(TMP_SUFFIX)
                   and not _SHARD_RE.match(p.name)]
        if foreign:
            raise InputError("--out", f"exists, is not empty and has no {MANIFEST} "
                             f"(holds {sorted(foreign)[:5]})", str(self.root))

    def _cleanup(self, committed: set[str]) -> None:
        """Remove temp files and shard files that no manifest line commits."""
        for p in self.root.iterdir():
            stale_shard = _SHARD_RE.match(p.name) and p.name not in committed
            if p.name.endswith(TMP_SUFFIX) or stale_shard:
                p.unlink()

    # ------------------------------------------------------------------ writing
    @property
    def done_indices(self) -> np.ndarray:
        """Sorted indices of the committed samples."""
        return np.array(sorted(self._done), dtype=np.int64)

    def write_shard(self, arrays: dict[str, np.ndarray], stats: dict | None = None) -> str:
        """Commit one shard: atomic .npz write, then its manifest line (fsynced).

        Args:
            arrays: stacked per-sample arrays; must include "index" (M,) int.
            stats: small JSON-ready per-shard statistics stored in the manifest line.

        Returns:
            The shard's file name.
        """
        indices = [int(i) for i in np.asarray(arrays["index"]).reshape(-1)]
        if self._done.intersection(indices) or len(set(indices)) != len(indices):
            raise DatasetError(f"{self.root}: refusing to write duplicate sample indices")
        name = f"shard-{self._next:06d}.npz"
        data = encode_shard(arrays)
        write_atomic(self.root / name, data)
        entry = {"kind": "shard", "file": name, "sha256": sha256_bytes(data),
                 "bytes": len(data), "indices": indices, "stats": stats or {}}
        with open(self.root / MANIFEST, "ab") as fh:
            fh.write((json.dumps(entry, sort_keys=True) + "\n").encode())
            fh.flush()
            os.fsync(fh.fileno())
        self.shards.append(entry)
        self._done.update(indices)
        self._next += 1
        return name

    def write_json(self, name: str, data: dict) -> None:
        """Atomically write `name` (e.g. summary.json) in the dataset directory."""
        write_atomic(self.root / name, json.dumps(data, indent=1, sort_keys=True).encode())

    def close(self) -> None:
        """Release the lock (idempotent)."""
        if self._lock_fd is not None:
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _test_fraction(header: dict) -> float:
    """The header's test share (TEST_FRACTION unless it says otherwise)."""
    return float(header.get("test_fraction", TEST_FRACTION))


def _split_json(header: dict) -> bytes:
    fraction = _test_fraction(header)
    train, test = train_test_split(header["base_seed"], header["n"], fraction)
    data = {"base_seed": header["base_seed"], "n": header["n"], "test_fraction": fraction,
            "rule": f"test = sorted(first round({fraction:g} n) of default_rng(SeedSequence(["
                    f"base_seed, {SPLIT_STREAM:#x}])).permutation(n))",
            "train": train.tolist(), "test": test.tolist()}
    return json.dumps(data).encode()


_OPTION_OF = {"mode": "--mode", "base_seed": "--seed", "n": "--n"}


def _check_resume(stored: dict, wanted: dict) -> None:
    for key in RESUME_KEYS:
        if stored.get(key) == wanted.get(key):
            continue
        msg = (f"the directory holds a dataset with {key} = {stored.get(key)!r}; this run asks "
               f"for {wanted.get(key)!r}. Re-run with the same options or use a new --out")
        if key in _OPTION_OF:
            raise InputError(_OPTION_OF[key], msg)
        if key == "config_sha256":
            raise ConfigError("configuration (scenario/uncertainty/scp YAML) changed since the "
                              f"dataset was started: {msg}")
        raise DatasetError(f"incompatible dataset directory: {msg}")


def aggregate_stats(entries: Iterable[dict]) -> dict[str, float]:
    """Sum the numeric per-shard statistics of manifest entries key by key."""
    total: dict[str, float] = {}
    for entry in entries:
        for key, value in entry.get("stats", {}).items():
            total[key] = total.get(key, 0) + value
    return total
