"""A thruster loss in the flown closed loop, against the test helpers' own two-body + J2 truth.

Navigation and actuation errors on, CVX warm starts, seed 0. The fault node is chosen from the
guidance's own model: the node after the one whose post-burn drift passes closest to the
ellipsoid in force (`run_safety_model`, the planner's linear drift of the realised post-burn
states). Chance-constrained, that drift must stay outside in truth; deterministic (no
uncertainty margin, the drift planned tangent to the ellipsoid) the same run enters it, which
the check must report: it can fail. Both verdicts and margins are confirmed by integrating the
post-fault state with `helpers.orbit_truth` (its own acceleration, frame and sampling).

Measured: chance-constrained node 54, margin +64.7 m; deterministic node 54, -47.2 m (inside
the 1 km approach ellipsoid).
"""
from __future__ import annotations

import logging

import numpy as np
import pytest

from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import (
    PARAMETERS, SIM_EPOCH0_NS, ClosedLoop, koz_switch_time_s,
)
from art_guidance.sim.faults import safety_duration_s
from art_guidance.sim.inprocess import InProcessGuidance
from art_guidance.sim.report import run_safety_model
from helpers import orbit_truth as truth

pytestmark = pytest.mark.slow
LOG = logging.getLogger("test_faults_truth")
SEED = 0


def _fly(chance: bool, **fault) -> ClosedLoop:
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path="", seed=SEED,
                  warm_start="cvx", chance_constrained=chance, **fault)
    loop = ClosedLoop(InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS), params, LOG,
                      settle_s=0.0)
    loop.summary, loop.code = loop.finish(loop.run(), 0.0)
    return loop


def _closest_node(loop: ClosedLoop) -> int:
    """1 + the node whose post-burn drift comes closest in the guidance's linear model."""
    switch = koz_switch_time_s(loop.scenario, loop.sim.chief_mean_oe0[0], loop.first_plan_t_s)
    model = run_safety_model(loop.sim, koz_switch_t_s=switch)
    t, _, _, roe_post = loop.sim.node_arrays()
    return 1 + int(np.argmin(model.evaluate(roe_post, np.zeros((t.size, 3))).margin_m))


def _truth_margin_m(loop: ClosedLoop, node: int, radius_m: float) -> float:
    """Smallest |r| - radius of the drift from the state at `node` (helpers, 0.25 s)."""
    state = loop.snapshots[node]
    duration = safety_duration_s(loop.scenario, loop.sim.chief_mean_oe0[0])
    return truth.sphere_clearance_m(state.chief_eci, state.deputy_eci, duration, radius_m, 0.25)


@pytest.mark.parametrize("chance, entered", [(True, False), (False, True)])
def test_loss_where_the_drift_passes_closest(chance, entered):
    nominal = _fly(chance)
    node = _closest_node(nominal)
    loop = _fly(chance, fault="loss", fault_node=node)
    f = loop.summary["fault"]
    assert f["hit"] and f["node"] == node and loop.summary["outcome"] == "fault_loss"
    radius = (loop.scenario.koz_semi_axes_m if f["zone"] == "keep_out_zone"
              else loop.scenario.ae_semi_axes_m)[0]
    ref = _truth_margin_m(loop, node, radius)
    assert f["min_margin_m"] == pytest.approx(ref, abs=0.05)
    assert f["entered"] is entered and (ref < 0) is entered
    assert loop.code == (1 if entered else 0)
    # the loss sweep of the nominal flight saw the same state at that node
    sweep = dict(nominal.loss_checks())[node]
    assert sweep.min_margin_m == pytest.approx(f["min_margin_m"], abs=1e-9)
