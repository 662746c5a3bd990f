"""The shipped models (`art_guidance/models/`), on scenarios they never saw in training.

Per passive-safety mode (chance-constrained and deterministic) an ROE and an RTN model are
shipped, each trained on the train split of `generate --n N --mode MODE --seed S` (S recorded
in models.json), and beside them the chance-constrained default: the one-token student
distilled from the chance-constrained RTN model (its teacher's dataset, normalisation and
held-out split; its training scenarios are recorded under "distillation"). The defaults: that
student (chance-constrained) and the deterministic ROE model. The held-out scenarios here are
the dataset's own test split (`train_test_split(S, N)`; the training never reads it), drawn
again from their seeds.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from art_guidance.art.provider import (
    DEFAULT_MODELS, TEACHERS, ArtWarmStart, default_model_path, models_dir,
    pinned_sha256, shipped_defaults, shipped_model_with_sha256, shipped_models,
)
from art_guidance.art.rollout import rollout
from art_guidance.cli import main
from art_guidance.config import GuidanceConfig
from art_guidance.errors import CheckpointError
from art_guidance.optim import TransferProblem
from art_guidance.planning import GuidancePipeline
from helpers.shipped import heldout_requests


@pytest.fixture(scope="module")
def provider() -> ArtWarmStart:
    return ArtWarmStart.load()


SHIPPED = sorted(shipped_models())


# Each mode's default, chosen by what is flown on >= 1,000 fresh scenarios per mode
# (benchmarks/analyses/default_models.py; docs/results.md, "Shipped defaults"): the one-token
# students of the RTN (chance-constrained) and ROE (deterministic) teachers.
DEFAULT_REPRESENTATIONS = {"chance": "rtn", "deterministic": "roe"}
DEFAULT_TOKENS_PER_STEP = {"chance": 1, "deterministic": 1}  # the one-token students


def test_shipped_models_are_pinned_and_described(provider):
    assert provider.art.config.representation == DEFAULT_REPRESENTATIONS["chance"]
    assert provider.art.meta["dataset"]["mode"] == "chance"  # the default default
    entries = shipped_models()
    assert {(e["dataset"]["mode"], e["representation"]) for e in entries.values()} == {
        (mode, r) for mode in DEFAULT_MODELS for r in ("roe", "rtn")}
    # models.json says which model is each mode's default, and why
    statement = shipped_defaults()
    assert "default_models.py" in statement["rule"]
    assert {mode: statement[mode]["model"] for mode in DEFAULT_MODELS} == DEFAULT_MODELS
    assert all(len(statement[mode]["why"]) > 100 for mode in DEFAULT_MODELS)
    for mode, name in DEFAULT_MODELS.items():
        assert default_model_path(mode).name == name
        assert (entries[name]["dataset"]["mode"], entries[name]["representation"]) == (
            mode, DEFAULT_REPRESENTATIONS[mode])
        model = ArtWarmStart.load(default_model_path(mode))
        assert model.art.config.tokens_per_step == DEFAULT_TOKENS_PER_STEP[mode]
    # the teachers stay shipped at their paths, with their exports; the student names its own
    for mode in DEFAULT_MODELS:
        student = entries[DEFAULT_MODELS[mode]]
        assert student["distilled_from"] == TEACHERS[mode]
        assert student["teacher_sha256"] == entries[TEACHERS[mode]]["sha256"]
    for name in ("art_small_chance_roe.pt", "art_small_chance_rtn.pt", "art_small_det_roe.pt",
                 "art_small_det_rtn.pt"):
        assert entries[name]["preset"] == "small" and (models_dir() / name).is_file()
        assert pinned_sha256(models_dir() / name) == entries[name]["sha256"]
        onnx = models_dir() / entries[name]["export"]["file"]
        assert onnx == (models_dir() / name).with_suffix(".onnx") and onnx.is_file()
        assert pinned_sha256(onnx) == entries[name]["export"]["sha256"]
    for name in SHIPPED:
        entry = entries[name]
        model = ArtWarmStart.load(models_dir() / name)
        assert model.sha256 == entry["sha256"]
        assert shipped_model_with_sha256(model.sha256) == models_dir() / name
        assert model.art.config.representation == entry["representation"]
        assert model.art.meta["dataset"]["mode"] == entry["dataset"]["mode"]
        assert sum(m["n"] for m in model.art.meta["dataset"]["manifests"]) == (
            entry["dataset"]["n"]) >= 10_000
        assert (models_dir() / name).stat().st_size < 8 * 2**20  # a few MB at most
    # a shipped model that is not the pinned one is refused
    with pytest.raises(CheckpointError, match="not the expected model"):
        ArtWarmStart.load(default_model_path(), expected_sha256="0" * 64)


@pytest.mark.parametrize("name", SHIPPED)
def test_rollouts_are_more_passively_safe_than_cvx(name):
    """On 100 held-out scenarios: the median C(t1) of the rollouts (conditioned on C = 0) is no
    higher than the CVX solutions' (which violate at almost every scenario), and a share of
    them is passively safe throughout (the numbers on fresh scenarios are in
    docs/art_training.md). The median, not the mean: the deterministic ROE model, chosen for
    the warm start it gives, is passively safe in 34 % of these against CVX's 3 %, but its
    unsafe rollouts violate over more nodes (mean 20.4 against 17.4; median 16 against 18)."""
    provider = ArtWarmStart.load(models_dir() / name)
    pipeline = GuidancePipeline(GuidanceConfig.load())
    requests = heldout_requests(100, name)
    transfer = pipeline.transfer(requests[0])
    safety = transfer.safety
    c_cvx, j_cvx = [], []
    for req in requests:
        cvx = TransferProblem.to_target(safety, req.roe0_m, req.target_rtn).cvx()
        c_cvx.append(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0])
        j_cvx.append(cvx.cost_mps)
    res = rollout(provider.art, safety, np.array([r.roe0_m for r in requests]),
                  np.array([r.target_rtn for r in requests]), -np.array(j_cvx), 0.0)
    c_art = res.realised_constraint_to_go[:, 0]
    c_cvx = np.array(c_cvx)
    print(f"\nC(t1) ART mean {c_art.mean():.2f} median {np.median(c_art):.0f} zero "
          f"{np.mean(c_art == 0):.2f}; CVX mean {c_cvx.mean():.2f} median "
          f"{np.median(c_cvx):.0f} zero {np.mean(c_cvx == 0):.2f}")
    assert np.median(c_art) <= np.median(c_cvx)
    assert np.mean(c_art == 0) >= 0.1 > np.mean(c_cvx == 0)


@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_plan_loads_the_default_model_of_its_mode(mode, tmp_path):
    """`plan` without --model rolls out the shipped default of the planned mode."""
    out = tmp_path / "plan.json"
    flags = ["--deterministic"] if mode == "deterministic" else []
    assert main(["plan", "--seed", "4", *flags, "--json", str(out)]) in (0, 1)
    data = json.loads(out.read_text())
    assert data["mode"] == mode
    assert data["model_sha256"] == shipped_models()[DEFAULT_MODELS[mode]]["sha256"]


def test_plan_flies_a_teacher_given_by_path(tmp_path):
    """The teachers stay loadable by path (`--model`, the node's `model_path`): `plan` with the
    chance-constrained teacher rolls it out, not the default student."""
    out = tmp_path / "plan.json"
    teacher = models_dir() / TEACHERS["chance"]
    assert main(["plan", "--seed", "4", "--model", str(teacher), "--json", str(out)]) in (0, 1)
    data = json.loads(out.read_text())
    assert data["model_sha256"] == shipped_models()[TEACHERS["chance"]]["sha256"]
    assert data["model_sha256"] != shipped_models()[DEFAULT_MODELS["chance"]]["sha256"]
