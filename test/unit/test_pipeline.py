"""The pipeline (`planning.pipeline`): the configuration it records is sealed."""
from __future__ import annotations

from art_guidance.planning import GuidancePipeline


def test_the_recorded_configuration_is_sealed():
    """`config_json` carries `record_sha256` over everything else it records; a record from
    before that seal is checked by its `config_sha256` over the bundle as recorded."""
    import json

    from art_guidance.planning.pipeline import recorded_config_problem

    data = json.loads(json.dumps(GuidancePipeline().config_json()))  # as the bag holds it
    assert recorded_config_problem(data) == ""
    for key, value in (("deadline_s", 9.0), ("scp_subproblem", {})):
        assert "record_sha256" in recorded_config_problem({**data, key: value})
    old = {k: v for k, v in data.items() if k != "record_sha256"}
    assert recorded_config_problem(old) == ""
    old["planning"] = {**old["planning"], "art_min_gain_mps": 0.5}
    assert "config_sha256" in recorded_config_problem(old)
    bare = {k: v for k, v in old.items() if k != "config_sha256"}
    assert recorded_config_problem(bare) == ""  # nothing to check it by
