"""The `auto` warm start with the shipped default models against the CVX warm start, on
held-out scenarios of each mode (end-to-end: CVX, rollout, post hoc check, SCVx* from both)."""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from helpers.shipped import heldout_requests

FLOOR_MPS = 0.010  # the paper's post hoc floor: auto never worse than CVX by more than this


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_auto_is_never_worse_than_cvx_warm_start_on_heldout_scenarios(mode):
    """50 held-out scenarios per mode, with the mode's default model: the `auto` plan (ART if
    accepted post hoc, retried from CVX if its SCP does not converge) costs at most 10 mm/s
    more than the CVX-warm-started plan, and is feasible whenever that one is."""
    config = GuidanceConfig.load()
    auto = GuidancePipeline(config, provider=ArtWarmStart.load(default_model_path(mode)))
    cvx_only = GuidancePipeline(config)
    rows = []
    for req in heldout_requests(50, DEFAULT_MODELS[mode]):
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
