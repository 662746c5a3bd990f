"""The guidance node's parameters as one typed, frozen object (no ROS needed)."""
from __future__ import annotations

import dataclasses

import pytest

from art_guidance.config import GuidanceConfig, node_parameter_defaults
from art_guidance.errors import ConfigError
from art_guidance.ros.parameters import (
    POLICY_PARAMETERS, SPECS, NodeParameters, check_table,
)


@pytest.fixture
def params() -> NodeParameters:
    defaults = node_parameter_defaults()
    check_table(defaults)
    planning = GuidanceConfig.load().planning
    return NodeParameters.from_values({**defaults,
                                       "samples_per_node": planning.samples_per_node,
                                       "numerics": planning.numerics,
                                       "replan_warm_start": planning.replan_warm_start})


def test_every_spec_is_a_typed_field_in_order(params):
    assert [f.name for f in dataclasses.fields(NodeParameters)] == list(SPECS)
    assert list(params.as_dict()) == list(SPECS)  # recorded in this order
    kinds = {"float": float, "int": int, "bool": bool, "str": str}
    for name, spec in SPECS.items():
        assert type(getattr(params, name)) is kinds[spec.kind], name
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.solve_deadline_s = 1.0


def test_a_run_time_change_is_applied_whole_or_refused(params):
    new = params.changed({"replan_period_s": 30, "stamp_check": "order"})
    assert new.replan_period_s == 30.0 and isinstance(new.replan_period_s, float)
    assert new.stamp_check == "order" and params.stamp_check != "order"  # a new object
    settings = new.replan_settings(ae_to_koz_node=40)
    assert {n: getattr(settings, n) for n in POLICY_PARAMETERS} == \
        {n: getattr(new, n) for n in POLICY_PARAMETERS} and settings.ae_to_koz_node == 40
    with pytest.raises(ConfigError, match="model_path is read-only"):
        params.changed({"replan_period_s": 1.0, "model_path": "x.pt"})
    with pytest.raises(ConfigError, match="replan_period_s must be >= 0"):
        params.changed({"replan_period_s": -1.0})
    with pytest.raises(ConfigError, match="stamp_check must be one of"):
        params.changed({"stamp_check": "sometimes"})
    with pytest.raises(ConfigError, match="nonexistent is read-only"):
        params.changed({"nonexistent": 1})
