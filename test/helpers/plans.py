"""Real plans of the paper scenario for tests that record or replay them."""
from __future__ import annotations

from typing import Callable

import numpy as np

from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.scenarios import sample_scenario


def seed_plans(seeds: range, chance_constrained: Callable[[int], bool] = lambda seed: True
               ) -> tuple[GuidancePipeline, list[tuple[object, object]]]:
    """The CVX-warm-started pipeline and (scenario, PlanResult) of `sample_scenario` seeds."""
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario))
    chief = np.array(scenario.chief_oe)
    out = []
    for seed in seeds:
        s = sample_scenario(scenario, seed)
        out.append((s, pipeline.plan(PlanRequest(
            chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
            chance_constrained=chance_constrained(seed)))))
    return pipeline, out
