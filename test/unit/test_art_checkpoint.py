"""Checkpoint files: round trip, and refusal (with the file and the reason) of every bad file."""
from __future__ import annotations

import hashlib
import io
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from art_guidance.art import checkpoint
from art_guidance.art.config import preset
from art_guidance.art.model import ArtModel
from art_guidance.art.normalization import Normalizer
from art_guidance.errors import CheckpointError, GuidanceError

torch.set_num_threads(1)


def _normalizer() -> Normalizer:
    rng = np.random.default_rng(0)
    arrays = {"goal": rng.normal(size=(5, 6)), "reward": rng.normal(size=(5, 10)),
              "constraint": rng.integers(0, 3, (5, 10)), "state": rng.normal(size=(5, 10, 6)),
              "control": rng.normal(size=(5, 10, 3))}
    return Normalizer.fit(arrays)


@pytest.fixture()
def saved(tmp_path) -> tuple[Path, ArtModel, Normalizer]:
    torch.manual_seed(0)
    model = ArtModel(preset("tiny", "rtn")[0])
    norm = _normalizer()
    path = tmp_path / "model.pt"
    checkpoint.save(path, checkpoint.model_payload(model, norm, {"training": {"command": "x"}}))
    return path, model, norm


def _refused(path: Path, match: str, **kw) -> CheckpointError:
    with pytest.raises(CheckpointError, match=match) as info:
        checkpoint.load(path, **kw)
    assert info.value.path == str(path) and str(path) in str(info.value)
    assert isinstance(info.value, GuidanceError)
    return info.value


def test_round_trip_keeps_weights_config_normalisation_and_meta(saved):
    path, model, norm = saved
    art = checkpoint.load(path)
    assert art.config == model.cfg and art.config.representation == "rtn"
    assert all(torch.equal(a, b) for a, b in zip(art.model.state_dict().values(),
                                                 model.state_dict().values()))
    for m in norm.mean:
        assert np.array_equal(art.normalizer.mean[m], norm.mean[m])
        assert np.array_equal(art.normalizer.std[m], norm.std[m])
    assert art.meta == {"training": {"command": "x"}} and not art.model.training
    assert checkpoint.load(path, expected_sha256=art.sha256).sha256 == art.sha256


def test_a_flipped_byte_is_refused_as_corrupt(saved):
    path = saved[0]
    blob = bytearray(path.read_bytes())
    blob[len(blob) // 2] ^= 0x01
    path.write_bytes(bytes(blob))
    _refused(path, "corrupt: payload sha256")


def test_a_truncated_file_is_refused(saved):
    path = saved[0]
    path.write_bytes(path.read_bytes()[:-100])
    _refused(path, "truncated")
    path.write_bytes(b"")
    _refused(path, "not an art_guidance checkpoint")


def test_missing_file_wrong_version_and_pinned_checksum(saved, tmp_path):
    path = saved[0]
    _refused(tmp_path / "absent.pt", "cannot read")
    _refused(path, "not the expected model", expected_sha256="0" * 64)
    head, body = path.read_bytes().split(b"\n", 1)
    path.write_bytes(head.replace(b" v1 ", b" v2 ") + b"\n" + body)
    _refused(path, "unsupported checkpoint format version 2")


def test_wrong_shapes_and_bad_values_are_refused(saved, tmp_path):
    path, model, norm = saved
    payload = checkpoint.model_payload(model, norm, {})
    payload["config"] = dict(payload["config"], width=64)  # weights are 32 wide
    checkpoint.save(path, payload)
    _refused(path, r"weight .* has shape \(32, 6\), the config needs \(64, 6\)")
    payload = checkpoint.model_payload(model, norm, {})
    payload["state_dict"]["head_state.bias"] = torch.full((6,), float("nan"))
    checkpoint.save(path, payload)
    _refused(path, "head_state.bias holds NaN")
    payload = checkpoint.model_payload(model, norm, {})
    del payload["state_dict"]["ln_f.weight"]
    checkpoint.save(path, payload)
    _refused(path, r"missing \['ln_f.weight'\]")
    payload = checkpoint.model_payload(model, norm, {})
    payload["format_version"] = 7
    checkpoint.save(path, payload)
    _refused(path, "payload format version 7")
    payload = checkpoint.model_payload(model, norm, {})
    payload["config"]["activation"] = "tanh"
    checkpoint.save(path, payload)
    _refused(path, "malformed config")


class _Exploit:
    """Unpickling this calls os.system: a weights-only loader must never run it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_pickled_callable_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "executed"
    buf = io.BytesIO()
    torch.save({"format_version": 1, "config": _Exploit(marker)}, buf, pickle_protocol=2)
    path = tmp_path / "evil.pt"
    # a valid header with the right checksum: only the weights-only loader stands in the way
    data = buf.getvalue()
    header = f"{checkpoint.MAGIC} v1 sha256={hashlib.sha256(data).hexdigest()} bytes={len(data)}"
    path.write_bytes(header.encode() + b"\n" + data)
    _refused(path, "refused: the payload is not weights-only")
    assert not marker.exists()
    raw = tmp_path / "raw.pkl"  # a plain pickle, no header: refused before unpickling
    raw.write_bytes(pickle.dumps(_Exploit(marker)))
    _refused(raw, "not an art_guidance checkpoint")
    assert not marker.exists()


def test_meta_must_be_plain_data():
    model = ArtModel(preset("tiny")[0])
    with pytest.raises(TypeError):
        checkpoint.model_payload(model, _normalizer(), {"x": np.float32(1.0)})
