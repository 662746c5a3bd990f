"""Randomised rendezvous transfers (paper Table I ranges), drawn from integer seeds.

Datasets, the simulator, `art-guidance plan`, the benchmarks and the tests draw their
scenarios here, so one seed names one transfer everywhere.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.config import ScenarioConfig

SEED_STRIDE = 1_000_003
SEED_RULE = f"seed_i = base_seed * {SEED_STRIDE} + i"


@dataclass(frozen=True)
class ScenarioSample:
    """One randomised transfer: initial RTN state and a terminal waypoint."""

    seed: int
    rtn0: np.ndarray       # (6,) initial relative RTN state [m, m/s]
    waypoint: str          # name of the waypoint in the scenario config
    target_rtn: np.ndarray  # (6,) terminal RTN state [m, m/s]


def sample_scenario(scenario: ScenarioConfig, seed: int) -> ScenarioSample:
    """Uniform initial state around the nominal one and a uniformly chosen waypoint."""
    rng = np.random.default_rng(int(seed))
    half = np.asarray(scenario.rtn0_half_width)
    rtn0 = np.asarray(scenario.rtn0_nominal) + rng.uniform(-1.0, 1.0, 6) * half
    names = sorted(scenario.waypoints_rtn)
    name = names[int(rng.integers(len(names)))]
    return ScenarioSample(int(seed), rtn0, name, np.asarray(scenario.waypoints_rtn[name]))


def sample_seed(base_seed: int, index: int) -> int:
    """Scenario seed of sample `index` of a dataset started with `base_seed` (SEED_RULE).

    With index < SEED_STRIDE the seeds of different base seeds never collide.
    """
    return int(base_seed) * SEED_STRIDE + int(index)
