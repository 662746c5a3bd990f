"""Distillation: the student's training sequences are exactly what the teacher saw and did, and
a distilled checkpoint is a model like any other (loads, proposes, exports)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from art_guidance.art.distill import distill, features, teacher_sequences
from art_guidance.art.onnx_art import load_exported
from art_guidance.art.onnx_export import export
from art_guidance.art.provider import TEACHERS, ArtWarmStart, models_dir
from art_guidance.art.rollout import GATE_LOGIT_THRESHOLD, build_safety
from art_guidance.errors import InputError
from art_guidance.optim import TransferProblem
from art_guidance.planning import PlanRequest

SEEDS = [9_000_000, 9_000_001]
# the chance-constrained teacher (the RTN model the shipped default student was distilled from),
# by its path: the default itself is a student now
TEACHER = models_dir() / TEACHERS["chance"]


@pytest.fixture(scope="module")
def teacher() -> ArtWarmStart:
    return ArtWarmStart.load(TEACHER, runtime="torch")


def test_teacher_forcing_on_the_sequences_gives_the_teachers_controls(teacher):
    """The teacher's own model, fed its sequences as training batches (`features`), predicts
    at every step the control it applied there: the student learns from what the teacher saw,
    normalised as it saw it."""
    data = teacher_sequences(str(TEACHER), SEEDS)
    assert data["reward"].shape == (8 * len(SEEDS), 100) and data["dv_rtn_mps"].shape[-1] == 3
    batch = features(teacher, data)
    model = teacher.art.model
    with torch.no_grad():
        pred, _ = model(batch["goal"].to(torch.float32), batch["reward"], batch["constraint"],
                        batch["state"], batch["control"], batch["timestep"])
    pred = pred.double().numpy()
    norm = teacher.art.normalizer
    t = batch["timestep"].numpy()
    u = norm.denormalize("control", pred[..., :3], t)
    u[pred[..., 3] <= GATE_LOGIT_THRESHOLD] = 0.0
    assert np.abs(u - data["dv_rtn_mps"]).max() < 1e-4  # float32 attention, another order


def test_a_distilled_student_loads_proposes_and_exports(tmp_path, teacher):
    out = tmp_path / "student.pt"
    summary = distill(TEACHER, out, scenarios=3, epochs=2, workers=1, threads=1, progress=False)
    assert summary["sequences"] == 8 * summary["scenarios"] and summary["best_epoch"] >= 1
    assert (tmp_path / "student.pt.sequences.npz").is_file()
    student = ArtWarmStart.load(out, runtime="torch")
    meta = student.art.meta["distillation"]
    assert meta["teacher_sha256"] == teacher.sha256 and len(meta["history_epoch_train_val"]) == 2
    assert student.art.config.width == 64 and student.art.config.n_layers == 2
    assert student.art.meta["dataset"]["mode"] == "chance"  # the teacher's horizon and mode
    safety = build_safety(student.art)
    chief = safety.horizon.chief_oe[0]
    roe0 = np.array([0.0, -600.0, 0.0, 300.0, 0.0, 300.0])
    request = PlanRequest(chief, roe0, np.array([0.0, -100.0, 0.0, 0.0, 0.0, 0.0]))
    problem = TransferProblem.to_target(safety, roe0, request.target_rtn)
    proposal = student.propose(problem, problem.cvx())
    assert np.all(np.isfinite(proposal.dv_rtn_mps))
    export(student.art, tmp_path / "student.onnx")
    exported = load_exported(tmp_path / "student.onnx", student.sha256)
    assert exported.n_parameters == student.art.n_parameters
    with pytest.raises(InputError, match="never overwritten"):
        distill(TEACHER, out, scenarios=3, epochs=1, workers=1, progress=False)
