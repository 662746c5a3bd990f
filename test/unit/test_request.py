"""The plan request (`planning.request`): a field out of its domain is refused naming it, and a
malformed recorded request is an InputError saying what, never a KeyError or TypeError."""
from __future__ import annotations

import re

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import InputError
from art_guidance.planning import PlanRequest
from art_guidance.planning.request import RolloutContext

SCENARIO = ScenarioConfig()
CHIEF = np.array(SCENARIO.chief_oe)
ROE0 = roe_from_rtn_linear(CHIEF, np.array(SCENARIO.rtn0_nominal))
TARGET = np.array(SCENARIO.waypoints_rtn["plus_vbar"])


@pytest.mark.parametrize("field, value, message", [
    ("warm_start", "bogus", "warm_start: must be one of ('auto', 'cvx', 'art')"),
    ("n_nodes", 2, "n_nodes: must be in [3, 1000] (got 2)"),
    ("koz_switch_node", -1, "koz_switch_node: must be >= 0 (got -1)"),
    ("context", "the last steps", "context: must be a RolloutContext or None (got 'str')"),
    ("carry", [0.0, 1.0], "carry: must be a CarriedPlan or None (got 'list')"),
])
def test_a_request_field_out_of_its_domain_is_named(field, value, message):
    with pytest.raises(InputError, match=re.escape(message)) as exc:
        PlanRequest(CHIEF, ROE0, TARGET, **{field: value})
    assert exc.value.field == field


def test_a_context_with_an_undefined_reward_is_refused():
    roe = np.tile(ROE0, (2, 1))
    with pytest.raises(InputError, match="context reward0_mps: must be finite"):
        RolloutContext(roe, np.zeros((2, 6)), np.zeros((2, 3)), float("nan"))


@pytest.mark.parametrize("change", [
    lambda data: data.pop("target_rtn"),
    lambda data: data.update(roe0_m="six numbers"),
    lambda data: data.update(warm_start="bogus"),
    lambda data: data.update(context={"roe_m": [1.0]}),
])
def test_a_malformed_request_json_is_an_input_error(change):
    """`PlanRequest.from_json` (a recorded request, a replayed one): whatever is wrong with the
    JSON, an InputError on `request_json` that says what, never a KeyError or TypeError."""
    data = PlanRequest(CHIEF, ROE0, TARGET).to_json()
    change(data)
    with pytest.raises(InputError, match=r"request_json: malformed: \w+\(") as exc:
        PlanRequest.from_json(data)
    assert exc.value.field == "request_json"
