"""The seal of a recorded configuration (`GuidancePipeline.config_json`): its fingerprint and
the check replay makes before it trusts it."""
from __future__ import annotations

import hashlib
import json

_RECORD_EXTRAS = ("deadline_s", "config_sha256", "scp_subproblem", "record_sha256")


def _canonical_sha256(data: dict) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def config_json_sha256(data: dict) -> str:
    """Fingerprint of a recorded configuration (`GuidancePipeline.config_json`): the sha256 of
    its canonical JSON without the `record_sha256` entry itself."""
    return _canonical_sha256({k: v for k, v in data.items() if k != "record_sha256"})


def recorded_config_problem(data: dict) -> str:
    """Why a recorded configuration cannot be trusted ("" = it can): its `record_sha256` does
    not match its content, or, in a record from before that seal, the configuration bundle as
    recorded does not match its `config_sha256` (`GuidanceConfig.sha256`, computed on the
    bundle as it was written, so a field added since does not count as a change)."""
    sealed, bundle = data.get("record_sha256"), data.get("config_sha256")
    if sealed is not None:
        ok, name = sealed == config_json_sha256(data), "record_sha256"
    elif bundle is not None:
        recorded = {k: v for k, v in data.items() if k not in _RECORD_EXTRAS}
        ok, name = bundle == _canonical_sha256(recorded), "config_sha256"
    else:
        return ""
    return "" if ok else (f"the recorded configuration does not match its {name}: it was "
                          "altered after recording")
