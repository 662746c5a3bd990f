"""The oracle: the rollout machinery driven by the planner's own controls judges them as the
planner did.

A perfect model would emit the dataset's controls. Driven through the rollout's propagation,
R and C updates and post hoc metrics (`art.rollout.replay`, `eval.scoring.score_oracle`),
they must reproduce the dataset's states, its constraint-to-go labels C(t_1) and its
E_R = (J - J_CVX) / J_CVX; otherwise even a perfect model is rejected by the post hoc check.
The scenarios come from a seed no shipped model was trained on.
"""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.eval.scoring import score_oracle, heldout_scenarios
from art_guidance.art.rollout import replay
from art_guidance.config import GuidanceConfig
from art_guidance.data.generate import generate
from art_guidance.data.storage import load_dataset
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.planning.learned import posthoc_check
from art_guidance.safety import PassiveSafety

N_SAMPLES, SEED = 24, 424242  # a seed no shipped model's dataset uses


@pytest.fixture(scope="module")
def plans(tmp_path_factory):
    out = tmp_path_factory.mktemp("oracle") / "chance"
    generate(out, N_SAMPLES, "chance", base_seed=SEED, workers=2, shard_size=4,
             progress=False, log=lambda _: None)
    data = load_dataset(out)
    held = heldout_scenarios(data, ("dv_rtn_mps", "roe_m", "cost_mps", "constraint_to_go",
                                    "feasible"), split="all")
    ok = held["feasible"]
    config = GuidanceConfig.load()
    sc = config.scenario
    chief = np.array(sc.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
    return {k: v[ok] for k, v in held.items()}, PassiveSafety(horizon, sc, config.uncertainty)


def test_replayed_plans_reproduce_their_states_and_labels(plans):
    held, safety = plans
    res = replay(safety, held["roe0_m"], held["dv_rtn_mps"], -held["cvx_cost_mps"], 0.0)
    # same propagation as the planner: the states agree to round-off (tolerance 1e-6 m)
    assert np.max(np.abs(res.roe_m - held["roe_m"])) < 1e-6
    # same C update: every C(t_i) label is reproduced exactly
    assert np.array_equal(res.realised_constraint_to_go, held["constraint_to_go"])
    # the planner's plans are passively safe: most have C(t_1) = 0 (>= 95 % on 1,000)
    assert np.mean(res.realised_constraint_to_go[:, 0] == 0) >= 0.9
    assert np.allclose(res.cost_mps, held["cost_mps"], rtol=1e-12, atol=1e-12)


def test_oracle_metrics_equal_the_datasets(plans):
    held, safety = plans
    ev = score_oracle(safety, held["roe0_m"], held["dv_rtn_mps"], held["cvx_cost_mps"],
                      held["cvx_constraint_to_go0"])
    e_r = (held["cost_mps"] - held["cvx_cost_mps"]) / held["cvx_cost_mps"]
    assert np.allclose(ev.e_r, e_r, rtol=0, atol=1e-12)
    assert np.array_equal(ev.c_art, held["constraint_to_go"][:, 0])
    # the pipeline's post hoc check (propagating the controls itself) agrees, plan by plan
    for i in range(held["roe0_m"].shape[0]):
        roe = safety.horizon.propagate_nonlinear(held["roe0_m"][i], held["dv_rtn_mps"][i])
        ph = posthoc_check(held["dv_rtn_mps"][i], roe, held["cvx_cost_mps"][i], safety,
                           GuidanceConfig.load().planning.posthoc)
        assert ph.e_c == held["constraint_to_go"][i, 0]
        assert ph.accepted == bool(ev.accepted[i])


def test_the_linear_model_would_misjudge_the_plans(plans):
    """Why the oracle matters: propagated with the convex problem's linear model, the same
    controls drift tens of metres from the plan (a tolerance that keeps the test meaningful)."""
    held, safety = plans
    lin = np.stack([safety.horizon.propagate(x0, dv)
                    for x0, dv in zip(held["roe0_m"], held["dv_rtn_mps"])])
    assert np.median(np.abs(lin - held["roe_m"]).max(axis=(1, 2))) > 5.0
