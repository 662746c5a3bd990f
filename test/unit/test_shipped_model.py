"""The shipped models (`art_guidance/models/`), on scenarios they never saw in training.

The models (the ROE default and the RTN one) were trained on the train split of `generate --n
20000 --mode chance --seed 0` (scenario seeds 0..19999). The held-out scenarios here are that
dataset's own test split (`train_test_split(0, 20000)`; the training never reads it), drawn
again from their seeds.
"""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.art.provider import (
    ArtWarmStart, default_model_path, models_dir, shipped_models,
)
from art_guidance.art.rollout import rollout
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.data.stages import sample_scenario
from art_guidance.data.storage import train_test_split
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import CheckpointError
from art_guidance.optim import solve_cvx
from art_guidance.planning import GuidancePipeline, PlanRequest

FLOOR_MPS = 0.010  # the paper's post hoc floor: auto never worse than CVX by more than this


@pytest.fixture(scope="module")
def provider() -> ArtWarmStart:
    return ArtWarmStart.load()


def _heldout(n: int) -> list[PlanRequest]:
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    _, test = train_test_split(0, 20_000)
    out = []
    for seed in test[:n]:
        s = sample_scenario(scenario, int(seed))
        out.append(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn))
    return out


SHIPPED = sorted(shipped_models())


def test_shipped_models_are_pinned_and_described(provider):
    assert provider.art.config.representation == "roe"  # the default
    assert {shipped_models()[name]["representation"] for name in SHIPPED} == {"roe", "rtn"}
    for name in SHIPPED:
        entry = shipped_models()[name]
        model = ArtWarmStart.load(models_dir() / name)
        assert model.sha256 == entry["sha256"]
        assert model.art.config.representation == entry["representation"]
        assert model.art.meta["dataset"]["mode"] == "chance"
        assert sum(m["n"] for m in model.art.meta["dataset"]["manifests"]) >= 20_000
        assert (models_dir() / name).stat().st_size < 8 * 2**20  # a few MB at most
    # a shipped model that is not the pinned one is refused
    with pytest.raises(CheckpointError, match="not the expected model"):
        ArtWarmStart.load(default_model_path(), expected_sha256="0" * 64)


@pytest.mark.parametrize("name", SHIPPED)
def test_rollouts_are_more_passively_safe_than_cvx(name):
    """On 100 held-out scenarios: C(t1) of the rollouts (conditioned on C = 0) is below the CVX
    solutions' (which violate at almost every scenario), and a share of them is passively safe
    throughout (the numbers on all 2,000 held-out scenarios are in the README)."""
    provider = ArtWarmStart.load(models_dir() / name)
    pipeline = GuidancePipeline(GuidanceConfig.load())
    requests = _heldout(100)
    horizon, safety = pipeline._setup(requests[0])
    c_cvx, j_cvx = [], []
    for req in requests:
        roe_f = np.linalg.solve(horizon.psi[-1], req.target_rtn)
        cvx = solve_cvx(horizon, req.roe0_m, roe_f)
        c_cvx.append(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0])
        j_cvx.append(cvx.cost_mps)
    res = rollout(provider.art, safety, np.array([r.roe0_m for r in requests]),
                  np.array([r.target_rtn for r in requests]), -np.array(j_cvx), 0.0)
    c_art = res.realised_constraint_to_go[:, 0]
    c_cvx = np.array(c_cvx)
    print(f"\nC(t1) ART mean {c_art.mean():.2f} median {np.median(c_art):.0f} zero "
          f"{np.mean(c_art == 0):.2f}; CVX mean {c_cvx.mean():.2f} median "
          f"{np.median(c_cvx):.0f} zero {np.mean(c_cvx == 0):.2f}")
    assert c_art.mean() < c_cvx.mean()
    assert np.mean(c_art == 0) >= 0.1 > np.mean(c_cvx == 0)


@pytest.mark.slow
def test_auto_is_never_worse_than_cvx_warm_start_on_heldout_scenarios(provider):
    """50 held-out chance-constrained scenarios: the `auto` plan (ART if accepted post hoc,
    retried from CVX if its SCP does not converge) costs at most 10 mm/s more than the
    CVX-warm-started plan, and is feasible whenever that one is."""
    config = GuidanceConfig.load()
    auto = GuidancePipeline(config, provider=provider)
    cvx_only = GuidancePipeline(config)
    rows = []
    for req in _heldout(50):
        a, c = auto.plan(req), cvx_only.plan(req)
        rows.append((a.cost_mps - c.cost_mps, a.scp.feasible, c.scp.feasible,
                     a.warm_start == "art", a.scp.iterations, c.scp.iterations))
        if c.scp.feasible:
            assert a.scp.feasible, a.warm_start_reason
            assert a.cost_mps <= c.cost_mps + FLOOR_MPS, a.warm_start_reason
    d = np.array([r[0] for r in rows if r[1] and r[2]])
    accepted = np.array([r[3] for r in rows])
    print(f"\nauto - cvx cost [mm/s] over {d.size} feasible pairs: min {1e3 * d.min():.2f} "
          f"p5 {1e3 * np.percentile(d, 5):.2f} median {1e3 * np.median(d):.2f} "
          f"p95 {1e3 * np.percentile(d, 95):.2f} max {1e3 * d.max():.2f}; ART accepted "
          f"{accepted.sum()}/{accepted.size}; iterations auto {np.mean([r[4] for r in rows]):.1f}"
          f" cvx {np.mean([r[5] for r in rows]):.1f}")
