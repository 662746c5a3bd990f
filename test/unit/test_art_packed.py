"""One packed token a step (`ArtConfig.tokens_per_step` = 1): the machinery of the layout.

Untrained models with fixed seeds: the packed token sees what the paper's state token sees
(the previous control, not this step's), the KV-cached decoder equals the full-context forward
pass, the speculative rollout equals one step at a time, the checkpoint round trip keeps the
layout, and the exported file on ONNX Runtime reproduces torch. Tolerances in m/s.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.art_models import deterministic_setup, untrained_art

from art_guidance.art import ArtModel, preset
from art_guidance.art.checkpoint import load, model_payload, save
from art_guidance.art.config import ArtConfig
from art_guidance.art.rollout import rollout
from art_guidance.errors import ConfigError

torch.set_num_threads(1)
CACHE_TOL_MPS = 1e-7  # float32 cached vs full-context arithmetic
ONNX_TOL_MPS = 1e-5   # float32 ONNX Runtime vs torch


@pytest.fixture(scope="module")
def setup():
    return deterministic_setup(3, 3)


@pytest.fixture(scope="module")
def packed():
    return untrained_art("slim1", seed=4)


def test_the_layout_is_validated_and_the_paper_layout_stays_the_default():
    assert ArtConfig().tokens_per_step == 5 and preset("slim1")[0].tokens_per_step == 1
    for bad in (2, 0, True, "1"):
        with pytest.raises(ConfigError, match="tokens_per_step"):
            preset("tiny", tokens_per_step=bad)
    old = ArtConfig().to_dict()
    del old["tokens_per_step"]  # a checkpoint written before the field existed
    assert ArtConfig.from_dict(old).tokens_per_step == 5


def test_a_step_sees_the_previous_control_and_not_its_own():
    """Changing u(t_i) changes the control predicted at i + 1 and after, never at i or
    before (causality with the control carried by the next step's token)."""
    torch.manual_seed(0)
    model = ArtModel(preset("tiny", tokens_per_step=1)[0]).eval()
    b, t = 2, 12
    args = [torch.randn(b, t, 6), torch.randn(b, t), torch.randn(b, t), torch.randn(b, t, 6)]
    ctrl = torch.randn(b, t, 3)
    time = torch.arange(t).expand(b, t) + 88
    with torch.no_grad():
        u0, _ = model(*args, ctrl, time)
        ctrl[:, 5] += 1.0
        u1, _ = model(*args, ctrl, time)
    assert torch.equal(u0[:, :6], u1[:, :6])
    assert (u0[:, 6:] - u1[:, 6:]).abs().amax(dim=(0, 2)).min() > 1e-6


@pytest.mark.parametrize("start", [0, 40])
def test_cache_equals_recompute_and_speculation_equals_one_step_at_a_time(setup, packed,
                                                                          start):
    safety, x0, target = setup
    x = x0 if start == 0 else safety.horizon.propagate_nonlinear(
        x0[0], np.zeros((100, 3)))[start][None].repeat(3, 0)
    cached = rollout(packed, safety, x, target, -0.25, start_node=start)
    full = rollout(packed, safety, x, target, -0.25, start_node=start, use_cache=False)
    step = rollout(packed, safety, x, target, -0.25, start_node=start, speculate=False)
    assert np.abs(cached.dv_rtn_mps - full.dv_rtn_mps).max() <= CACHE_TOL_MPS
    assert np.array_equal(cached.dv_rtn_mps, step.dv_rtn_mps)
    assert np.array_equal(cached.violation, step.violation)
    assert np.abs(cached.dv_rtn_mps).max() > 0  # an untrained model still burns


def test_the_layout_survives_a_checkpoint_and_an_export(setup, packed, tmp_path):
    pytest.importorskip("onnxruntime")
    from art_guidance.art.onnx_art import load_exported
    from art_guidance.art.onnx_export import export

    safety, x0, target = setup
    save(tmp_path / "m.pt", model_payload(packed.model, packed.normalizer, {}))
    again = load(tmp_path / "m.pt")
    assert again.config == packed.config and again.config.tokens_per_step == 1
    export(again, tmp_path / "m.onnx")
    onnx_art = load_exported(tmp_path / "m.onnx", expected_checkpoint_sha256=again.sha256)
    assert onnx_art.config.tokens_per_step == 1
    ref = rollout(again, safety, x0, target, -0.25)
    got = rollout(onnx_art, safety, x0, target, -0.25)
    tail = rollout(onnx_art, safety, x0[:1].repeat(3, 0), target, -0.1, start_node=70)
    tail_ref = rollout(again, safety, x0[:1].repeat(3, 0), target, -0.1, start_node=70)
    assert np.abs(got.dv_rtn_mps - ref.dv_rtn_mps).max() <= ONNX_TOL_MPS
    assert np.array_equal(got.violation, ref.violation)
    assert np.abs(tail.dv_rtn_mps - tail_ref.dv_rtn_mps).max() <= ONNX_TOL_MPS


SLIM_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "slim"
MODELS_DIR = Path(__file__).resolve().parents[2] / "art_guidance" / "models"
SLIM1 = {"art_slim1_chance_rtn.pt": "chance", "art_slim1_det_roe.pt": "deterministic",
         "art_slim1e40_chance_rtn.pt": "chance"}  # committed student -> its mode
# where each is: the 40-epoch one is the shipped chance-constrained default (its provenance in
# models.json, "file_sha256" the file's checksum), the others stay in benchmarks/results/slim
SLIM1_DIR = {name: MODELS_DIR if name == "art_slim1e40_chance_rtn.pt" else SLIM_DIR
             for name in SLIM1}


def _student_provenance(name: str) -> tuple[Path, str, str]:
    """(path, file sha256, export sha256) of a committed one-token student."""
    import json

    if SLIM1_DIR[name] == MODELS_DIR:
        entry = json.loads((MODELS_DIR / "models.json").read_text())[name]
        return MODELS_DIR / name, entry["file_sha256"], entry["export"]["sha256"]
    prov = json.loads((SLIM_DIR / "provenance.json").read_text())[name]
    return SLIM_DIR / name, prov["sha256"], prov["export"]["sha256"]


STUDENT_DV_TOL_MPS = 1e-3  # as test_onnx_runtime's DV_TOL_MPS


@pytest.mark.parametrize("name", sorted(SLIM1))
def test_the_committed_students_are_packed_and_fly_alike_on_both_runtimes(name):
    """The distilled one-token students in benchmarks/results/slim: the files of their
    provenance, one token a step, and the learned step (sweep, C update, judging, check) on
    ONNX Runtime as on torch on held-out scenarios of their teacher's dataset."""
    pytest.importorskip("onnxruntime")
    import hashlib

    from helpers.shipped import heldout_requests, runtimes_agree

    from art_guidance.art.provider import TEACHERS, ArtWarmStart

    path, file_sha, export_sha = _student_provenance(name)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == file_sha
    onnx_sha = hashlib.sha256(path.with_suffix(".onnx").read_bytes()).hexdigest()
    assert onnx_sha == export_sha
    torch_p = ArtWarmStart.load(path, runtime="torch")
    onnx_p = ArtWarmStart.load(path, runtime="onnx")
    assert torch_p.art.config.tokens_per_step == onnx_p.art.config.tokens_per_step == 1
    assert onnx_p.sha256 == torch_p.sha256  # the checkpoint payload the export names
    requests = heldout_requests(6, TEACHERS[SLIM1[name]])
    assert runtimes_agree(torch_p, onnx_p, requests, STUDENT_DV_TOL_MPS) >= 4


def test_a_student_is_never_evaluated_on_the_scenarios_it_was_distilled_on():
    """The committed students' teacher rolled out scenario seeds 9,000,000..9,002,499: the
    scenarios of dataset seeds 8 (its last indices) and 9 (`scenarios.SEED_RULE`). A student
    counts as trained on both, so `evaluate --split all` refuses datasets of those seeds for
    it (their scenarios are not held out) and takes those of seed 10 and on."""
    from art_guidance.eval.inputs import DatasetInfo, model_info
    from art_guidance.scenarios import sample_seed

    assert 9_000_000 <= sample_seed(9, 0) <= 9_002_499  # dataset seed 9 starts inside
    for name in SLIM1:
        info = model_info(SLIM1_DIR[name] / name)
        for base, seen in ((8, True), (9, True), (10, False), (11, False)):
            assert info.saw(DatasetInfo("d", "sha", info.mode, 1000, base)) is seen, (name, base)
