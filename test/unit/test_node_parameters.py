"""The guidance node's parameters as one typed, frozen object (no ROS needed)."""
from __future__ import annotations

import dataclasses

import pytest

from art_guidance.config import GuidanceConfig, node_parameter_defaults
from art_guidance.errors import ConfigError
from art_guidance.ros.parameters import (
    PLANNING_PARAMETERS, POLICY_PARAMETERS, SPECS, NodeParameters, check_table, shown_value,
)


@pytest.fixture
def params() -> NodeParameters:
    defaults = node_parameter_defaults()
    check_table(defaults)
    planning = GuidanceConfig.load().planning
    return NodeParameters.from_values({**defaults, **{name: getattr(planning, name)
                                                      for name in PLANNING_PARAMETERS}})


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


def test_a_refused_value_is_shown_cut(params):
    """A refused value is echoed cut to SHOWN_CHARS characters with its length (as a recorded
    value is in `record.seal`), whatever its size: the reason stays one short line."""
    for name, value in (("terminal_target", "x" * 100_000), ("stamp_check", "y" * 5_000)):
        with pytest.raises(ConfigError) as refused:
            params.changed({name: value})
        reason = str(refused.value)
        assert len(reason) < 300 and f"({len(value)} characters)" in reason, reason
        assert reason.startswith(f"{name} must be one of"), reason
    with pytest.raises(ConfigError) as refused:
        params.changed({"replan_period_s": list(range(50_000))})
    assert len(str(refused.value)) < 300 and "characters)" in str(refused.value)
    assert shown_value("cvx") == "'cvx'" and shown_value(7) == "7"


@pytest.mark.parametrize("name, value, expected", [
    ("numerics", 7, "numerics must be a string (one of: compiled, numpy), got 7 (an integer)"),
    ("replan_window_nodes", "abc",
     "replan_window_nodes must be an integer (>= 0), got 'abc' (a string)"),
    ("art_context", "maybe", "art_context must be a boolean (true or false), got 'maybe' "
     "(a string)"),
    ("min_remaining_nodes", 3.5, "min_remaining_nodes must be an integer (>= 2), got 3.5 "
     "(a floating-point number)"),
    ("record", [1, 2], "record must be a boolean (true or false), got [1, 2] (an array)"),
])
def test_a_value_of_the_wrong_type_is_refused_in_words(name, value, expected):
    """What the node says of a start-up value of another type than the parameter's (rclpy's
    InvalidParameterTypeException at declaration): the parameter, its type and constraints,
    the value given and its type."""
    assert str(SPECS[name].type_refusal(name, value)) == expected


def test_an_unquoted_yaml_boolean_for_a_string_says_how_to_quote_it():
    """`-p stamp_check:=off` reaches the node as False (YAML): the refusal says so."""
    reason = str(SPECS["stamp_check"].type_refusal("stamp_check", False))
    assert reason.startswith("stamp_check must be a string (one of: wallclock, order, off), "
                             "got False (a boolean); YAML reads an unquoted")
    assert "-p stamp_check:=\"'...'\"" in reason
    long = str(SPECS["numerics"].type_refusal("numerics", list(range(100_000))))
    assert len(long) < 300 and "characters) (an array)" in long
