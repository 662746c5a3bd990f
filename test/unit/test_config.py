"""One configuration: the YAML files are the source; code defaults and tables agree with them."""
from __future__ import annotations

import argparse
import dataclasses

import pytest

from art_guidance.config import (
    GuidanceConfig, PlanningConfig, PosthocThresholds, ScenarioConfig, ScpConfig,
    UncertaintyConfig, node_parameter_defaults,
)
from art_guidance.errors import ConfigError


def test_dataclass_defaults_equal_the_packaged_yaml():
    loaded = GuidanceConfig.load()
    assert loaded == GuidanceConfig()
    assert loaded.scenario == ScenarioConfig() and loaded.scp == ScpConfig()
    assert loaded.uncertainty == UncertaintyConfig() and loaded.planning == PlanningConfig()


def test_bundle_round_trips_and_fingerprints():
    cfg = GuidanceConfig.load()
    assert GuidanceConfig.from_json(cfg.to_json()) == cfg
    assert len(cfg.sha256()) == 64 and cfg.sha256() == GuidanceConfig.load().sha256()
    changed = cfg.replace(planning=dataclasses.replace(cfg.planning, samples_per_node=2))
    assert changed.sha256() != cfg.sha256()


@pytest.mark.parametrize("bad", [{"samples_per_node": 0}, {"samples_per_node": True},
                                 {"posthoc": {"e_c_min": 3.0, "e_c_max": 2.0}},
                                 {"posthoc": {"e_r_pct_max": float("nan")}},
                                 {"posthoc": {"bogus": 1.0}}, {"art_min_gain_mps": -0.001},
                                 {"art_min_gain_mps": True}, {"art_min_gain_mps": float("nan")},
                                 {"art_min_gain_mps": float("inf")},
                                 {"art_min_gain_mps": "1 mm/s"},
                                 {"skip_art_when_cvx_safe": 1}])
def test_bad_planning_config_is_refused(bad):
    with pytest.raises(ConfigError):
        PlanningConfig(**bad)


def test_planning_yaml_holds_the_papers_posthoc_region():
    assert PlanningConfig.from_yaml().posthoc == PosthocThresholds(-1.5, 3.5, 0.0, 2.0)


def test_node_parameter_table_is_the_params_file():
    params = node_parameter_defaults()
    assert params["default_waypoint"] == "plus_vbar" and params["stamp_check"] == "wallclock"
    assert "samples_per_node" not in params  # one default: planning.yaml's
    from art_guidance.guidance.replan import ReplanSettings

    # the switch node and the horizon's length are the scenario's, not parameters
    scenario_fields = {"ae_to_koz_node", "horizon_nodes"}
    names = {f.name for f in dataclasses.fields(ReplanSettings)} - scenario_fields
    settings = ReplanSettings(**{k: params[k] for k in names})
    assert settings == ReplanSettings(ae_to_koz_node=settings.ae_to_koz_node)


def test_simulator_cli_defaults_match_its_parameters():
    from art_guidance.cli.sim import add_parser
    from art_guidance.sim.closed_loop import PARAMETERS

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["sim"])
    assert args.waypoint == PARAMETERS["waypoint"] and args.seed == PARAMETERS["seed"]
    assert args.step_timeout == PARAMETERS["step_timeout_s"]
    assert args.max_steps == PARAMETERS["max_steps"]
    assert args.miss_tolerance == PARAMETERS["miss_tolerance_m"]
    assert args.png == PARAMETERS["png_path"] and args.summary_json == PARAMETERS["summary_path"]


def test_a_recorded_configuration_from_before_the_flight_rules_keeps_its_behaviour():
    """A log recorded before `art_min_gain_mps` and `skip_art_when_cvx_safe` existed replays
    with the behaviour it was flown with (no margin, ART always run)."""
    cfg = GuidanceConfig.load()
    old = cfg.to_json()
    for key in ("art_min_gain_mps", "skip_art_when_cvx_safe"):
        del old["planning"][key]
    before = GuidanceConfig.from_json(old)
    assert before.planning.art_min_gain_mps == 0.0
    assert before.planning.skip_art_when_cvx_safe is False
    assert GuidanceConfig.from_json(cfg.to_json()) == cfg


def test_yaml_loads_as_pyyaml_s_safe_load_with_and_without_libyaml(tmp_path, monkeypatch):
    """`files.load_yaml` (libyaml's parser where PyYAML has it, ~20x faster) gives the objects
    of `yaml.safe_load` for every packaged config file and a recorder's bag metadata, and
    without libyaml falls back to PyYAML's parser; a malformed file is still refused as a
    ConfigError naming it."""
    import yaml

    from art_guidance.config import _load_yaml, default_config_dir
    from art_guidance.files import load_yaml
    from art_guidance.record.bag_metadata import FileInfo, TopicInfo, write_bag_metadata

    bag = write_bag_metadata(tmp_path, [FileInfo("bag_0.mcap", 1, 2_000_000_001, 3)],
                             [TopicInfo("/guidance/maneuver_plan", "pkg/msg/T", 3, "RIHS01_0")],
                             {"config": '{"a": 1e-3, "b": "yes", "c": null}'})
    texts = [p.read_text() for p in sorted(default_config_dir().glob("*.yaml"))]
    texts.append(bag.read_text())
    assert len(texts) >= 6
    for text in texts:
        assert repr(load_yaml(text)) == repr(yaml.safe_load(text))
    monkeypatch.delattr(yaml, "CSafeLoader", raising=False)
    for text in texts:
        assert repr(load_yaml(text)) == repr(yaml.safe_load(text))
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\nb: 3\n")
    with pytest.raises(ConfigError, match="cannot read config .*bad.yaml"):
        _load_yaml(bad)


def test_bag_metadata_is_emitted_as_pyyaml_s_safe_dump_and_loads_back(tmp_path, monkeypatch):
    """`files.dump_yaml` (libyaml's emitter where PyYAML has it) writes a recorder's
    metadata.yaml as `yaml.safe_dump` does, to the byte, and a document with awkward strings
    (quotes, colons, newlines, non-ASCII, a long error message) loads back to itself, with and
    without libyaml."""
    import yaml

    from art_guidance.files import dump_yaml
    from art_guidance.record.bag_metadata import FileInfo, TopicInfo, bag_metadata

    files = [FileInfo(f"bag_{k}.mcap", 10 + k, 2_000_000_000 + k, 3 + k) for k in range(4)]
    topics = [TopicInfo(f"/ns/guidance/t{k}", "art_guidance_msgs/msg/ManeuverPlan", k,
                        "RIHS01_" + "ab" * 32) for k in range(8)]
    plain = bag_metadata(files, topics, {"art_guidance.writer": "McapRecorder",
                                         "art_guidance.state": "recording"})
    assert dump_yaml(plain) == yaml.safe_dump(plain, sort_keys=False, default_flow_style=False)
    awkward = bag_metadata(files, topics, {
        "art_guidance.last_error": "OSError: [Errno 28] No space left: '/data/x: y' \"q\"\n"
        + "é ✓ " * 40, "art_guidance.write_errors": 3, "key: with colon": "- dash",
        "empty": "", "yes": "no", "number_like": "1e-3"})
    for libyaml in (True, False):
        if not libyaml:
            monkeypatch.delattr(yaml, "CSafeDumper", raising=False)
        for doc in (plain, awkward):
            assert yaml.safe_load(dump_yaml(doc)) == doc
