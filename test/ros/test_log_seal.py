"""The run metadata of a recording is sealed: every value the recorder writes into the MCAP
metadata record (configuration, model and runtime checksums, runtime, parameters, versions) is
checked by replay against its seal, and a value altered in any file is named (file, field,
value) with exit 1. A bag from before the seal replays, said to be unsealed; solves it leaves
uncompared for another model exit 4 unless --allow-uncompared. A seal whose key was altered, or
that is missing where the file's writer seals, is an alteration, and so is a value altered past
reading: exit 1, whatever the value has become."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from mcap.records import Header, Metadata

from art_guidance.cli import main as cli_main
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.record.recorder import McapRecorder
from art_guidance.record.reindex import rebuild
from art_guidance.record.replay import (
    EXIT_MISMATCH, EXIT_OK, EXIT_UNCOMPARED, NOT_REPLAYED, OTHER_MODEL, read_log, replay,
)
from art_guidance.record.scan import scan_file
from art_guidance.record.seal import SEAL_KEY, SEALING_LIBRARY, seal, seal_problems
from art_guidance.ros.adapters import plan_to_msg, solve_record_msg
from art_guidance.scenarios import sample_scenario

STAMP0 = 1_800_000_000_000_000_000
UNSEALING_LIBRARY = "art_guidance"  # the MCAP header's library of the writers before the seal


@pytest.fixture(scope="module")
def flown():
    """The shipped default model, the run metadata the node records with it, and two solves:
    one warm-started by the model, one by CVX."""
    from art_guidance.art.provider import ArtWarmStart, default_model_path

    provider = ArtWarmStart.load(default_model_path("chance"))
    scenario = ScenarioConfig.from_yaml()
    pipeline = GuidancePipeline(GuidanceConfig.load(), provider=provider)
    chief = np.array(scenario.chief_oe)
    solves = []
    for k, (seed, warm_start) in enumerate(((7, "art"), (9, "cvx"))):
        s = sample_scenario(scenario, seed)
        result = pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0),
                                           s.target_rtn, warm_start=warm_start))
        assert (result.proposal is None) == (warm_start == "cvx")
        stamp = STAMP0 + k * 1_000_000_000
        solves.append((stamp, [
            ("/guidance/solve_record", solve_record_msg(result, stamp, f"plan-{k}", "test")),
            ("/guidance/maneuver_plan", plan_to_msg(result, stamp, f"plan-{k}"))]))
    meta = {"config": pipeline.config_json(), "versions": {"art_guidance": "test"},
            "model_checksum": provider.sha256, "art_runtime": provider.runtime,
            "art_runtime_checksum": provider.runtime_sha256, "model": "loaded (test)",
            "parameters": {"record": True, "warm_start": "auto"}}
    return meta, solves


def _bag(tmp_path: Path, flown) -> Path:
    """A finished bag of two files (one solve each), recorded with the fixture's metadata."""
    meta, solves = flown
    bag = tmp_path / "bag"
    with McapRecorder(bag, meta, max_bytes=1) as rec:
        for stamp, msgs in solves:
            assert rec.record_solve(msgs, stamp)
    assert [p.name for p in sorted(bag.glob("*.mcap"))] == ["guidance_0.mcap", "guidance_1.mcap"]
    return bag


def _rewrite(bag: Path, change: Callable[[dict], dict], names: tuple[str, ...] = (),
             library: str | None = None) -> None:
    """Rewrite the art_guidance metadata record of the bag's files (of `names` only, when
    given) through `change`, as an edit after recording would; with `library`, the files'
    MCAP header says that writer made them."""
    for path in sorted(bag.glob("*.mcap")):
        if names and path.name not in names:
            continue
        scan = scan_file(path)
        scan.metadata = [Metadata(name=r.name, metadata=change(dict(r.metadata)))
                         if r.name == "art_guidance" else r for r in scan.metadata]
        if library is not None:
            scan.header = Header(profile=scan.header.profile, library=library)
        rebuild(path, scan)


def _unsealed(metadata: dict) -> dict:
    return {k: v for k, v in metadata.items() if k != SEAL_KEY}


def _stored(value: object) -> str:
    """A run metadata value as the recorder stores it."""
    return value if isinstance(value, str) else json.dumps(value)


def _one_digit_off(sha: str) -> str:
    return sha[:10] + ("0" if sha[10] != "0" else "1") + sha[11:]


def test_every_recorded_value_is_sealed_and_a_clean_bag_replays(tmp_path, flown):
    bag = _bag(tmp_path, flown)
    for name, record in read_log(bag).metadata_records.items():
        assert set(json.loads(record[SEAL_KEY])["fields"]) == set(flown[0]), name
        assert seal_problems(record) == []
    report = replay(bag)
    assert report["metadata_check"] == "ok" and report["metadata_problems"] == []
    assert report["compared"] == report["matched"] == 2 and report["uncompared"] == 0
    assert report["exit_code"] == EXIT_OK, report


def test_a_tampered_model_checksum_is_named_and_replay_exits_1(tmp_path, flown, capsys):
    """One hex digit of model_checksum changed in every file: replay falls back to the
    default model, leaves the ART solve uncompared, names the field and exits 1."""
    bag = _bag(tmp_path, flown)
    sha = flown[0]["model_checksum"]
    tampered = _one_digit_off(sha)
    _rewrite(bag, lambda m: {**m, "model_checksum": tampered})
    assert cli_main(["replay", str(bag), "--json", str(tmp_path / "r.json")]) == EXIT_MISMATCH
    out = capsys.readouterr().out
    for name in ("guidance_0.mcap", "guidance_1.mcap"):
        assert (f"METADATA: {name}: model_checksum = '{tampered}' does not match its seal"
                in out), out
    assert "altered after recording" in out and "1/1 matched" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["metadata_check"].startswith("altered: 2 value(s)")
    assert report["uncompared"] == 1 and report["exit_code"] == EXIT_MISMATCH
    assert [r["reason"] for r in report["per_solve"] if r["match"] is None] == [OTHER_MODEL]


def test_another_value_altered_in_one_file_is_named(tmp_path, flown):
    """art_runtime_checksum altered in the first file only (replay reads the last file's
    record): both the broken seal and the difference from the record replay reads are named,
    every solve still matches, and replay exits 1."""
    bag = _bag(tmp_path, flown)
    _rewrite(bag, lambda m: {**m, "art_runtime_checksum": "f" * 64}, ("guidance_0.mcap",))
    report = replay(bag)
    problems = report["metadata_problems"]
    assert len(problems) == 2, problems
    assert problems[0].startswith(f"guidance_0.mcap: art_runtime_checksum = '{'f' * 64}' "
                                  "does not match its seal")
    assert "differs from guidance_1.mcap's" in problems[1] and "which replay reads" in problems[1]
    assert report["matched"] == 2 and report["exit_code"] == EXIT_MISMATCH


def test_an_unsealed_bag_replays_and_uncompared_solves_exit_4(tmp_path, flown, capsys):
    """A bag from before the seal replays (said to be unsealed, a field that is not run
    metadata named, exit 0). With its model_checksum altered nothing can tell, but the ART
    solve it leaves uncompared makes replay exit 4, unless --allow-uncompared."""
    bag = _bag(tmp_path, flown)
    _rewrite(bag, lambda m: {**_unsealed(m), "operator": "x"}, library=UNSEALING_LIBRARY)
    assert cli_main(["replay", str(bag)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "note: metadata unsealed: recorded before the metadata seal" in out, out
    assert "; operator is not run metadata" in out
    assert "2/2 matched" in out and "METADATA" not in out
    _rewrite(bag, lambda m: {**m, "model_checksum": _one_digit_off(m["model_checksum"])})
    assert cli_main(["replay", str(bag)]) == EXIT_UNCOMPARED
    out = capsys.readouterr().out
    assert "1/1 matched (2 solves, 1 UNCOMPARED (another model)" in out, out
    assert "UNCOMPARED" in out.splitlines()[2] and "--allow-uncompared" in out
    assert cli_main(["replay", str(bag), "--allow-uncompared"]) == EXIT_OK


def test_seal_problems_name_the_field_and_its_value():
    record = seal({"config": '{"a": 1}', "model_checksum": "ab" * 32, "versions": "{}"})
    assert seal_problems(record) == [] and seal_problems({"config": "{}"}) is None
    assert seal(record) == record  # sealing again seals the same values
    altered = {**record, "model_checksum": "ac" + "ab" * 31}
    [problem] = seal_problems(altered)
    assert problem.startswith(f"model_checksum = '{'ac' + 'ab' * 31}' does not match its seal")
    removed = {k: v for k, v in record.items() if k != "versions"}
    assert seal_problems(removed) == ["versions is sealed but missing from the record: removed "
                                      "after recording"]
    [added] = seal_problems({**record, "extra": "x" * 100})
    assert added.startswith(f"extra = '{'x' * 72}'... (100 characters) is not in the seal")
    [added] = seal_problems({**record, "y" * 100: "1"})  # a long name is cut as a value is
    assert added == (f"'{'y' * 72}'... (100 characters) = '1' is not in the seal: added after "
                     "recording")
    body = json.loads(record[SEAL_KEY])
    body["fields"]["config"] = "0" * 64  # a seal edited to fit an altered value
    [problem] = seal_problems({**record, SEAL_KEY: json.dumps(body)})
    assert "metadata_seal does not match its own sha256" in problem
    [problem] = seal_problems({**record, SEAL_KEY: record[SEAL_KEY][:-3]})
    assert problem.startswith("metadata_seal = ") and "does not read" in problem


@pytest.mark.parametrize("library", [SEALING_LIBRARY, UNSEALING_LIBRARY])
def test_a_seal_under_an_altered_key_is_an_alteration(tmp_path, flown, capsys, library):
    """The key metadata_seal altered to metadata_seam (also in a file sealed before its header
    said that its writer seals) and art_runtime_checksum and parameters altered: the seal is
    found under the other key, the altered values are checked against it, replay exits 1."""
    bag = _bag(tmp_path, flown)
    _rewrite(bag, lambda m: {**_unsealed(m), "metadata_seam": m[SEAL_KEY],
                             "art_runtime_checksum": "f" * 64, "parameters": "{}"},
             library=library)
    assert cli_main(["replay", str(bag)]) == EXIT_MISMATCH
    out = capsys.readouterr().out
    for name in ("guidance_0.mcap", "guidance_1.mcap"):
        assert (f"METADATA: {name}: no metadata_seal, but metadata_seam holds a seal: its key "
                "was altered after recording\n") in out, out
        assert (f"METADATA: {name}: art_runtime_checksum = '{'f' * 64}' does not match its "
                "seal") in out
        assert f"METADATA: {name}: parameters = '{{}}' does not match its seal" in out
    assert "unsealed" not in out


def test_a_seal_missing_where_the_writer_seals_is_an_alteration(tmp_path, flown):
    """The seal removed from files whose header says their writer seals, and a field that is
    not run metadata added (its long name shown cut): both are named, replay exits 1."""
    bag = _bag(tmp_path, flown)
    _rewrite(bag, lambda m: {**_unsealed(m), "k" * 100: "1"})
    report = replay(bag)
    assert report["exit_code"] == EXIT_MISMATCH and report["matched"] == 2
    assert report["metadata_check"].startswith("altered: 4 value(s)")
    assert report["metadata_problems"][:2] == [
        "guidance_0.mcap: no metadata_seal, though the file's writer seals every record: "
        "removed after recording",
        f"guidance_0.mcap: '{'k' * 72}'... (100 characters) = '1' is not run metadata: added "
        "after recording"]


@pytest.mark.parametrize("field, change", [
    ("config", lambda text: text.replace('"q_sigma"', '"q_sigm0"')),
    ("config", lambda text: text[:-1]),
    ("art_runtime", lambda text: "onny"),
])
def test_a_value_altered_past_reading_exits_1_not_2(tmp_path, flown, capsys, field, change):
    """A sealed value altered so that it no longer reads (a configuration key renamed, the
    configuration cut, an unknown runtime) is an alteration: named, no solve replayed, exit 1
    (not 2, bad input)."""
    bag = _bag(tmp_path, flown)
    altered = change(_stored(flown[0][field]))
    _rewrite(bag, lambda m: {**m, field: altered})
    assert cli_main(["replay", str(bag), "--json", str(tmp_path / "r.json")]) == EXIT_MISMATCH
    out = capsys.readouterr().out
    for name in ("guidance_0.mcap", "guidance_1.mcap"):
        assert f"METADATA: {name}: {field} = '{altered[:72]}'" in out, out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["compared"] == 0 and report["model"].startswith("not replayed")
    assert [r["reason"] for r in report["per_solve"]] == [NOT_REPLAYED] * 2


def test_an_unsealed_bag_is_checked_by_its_configuration_seal_first(tmp_path, flown, capsys):
    """In a bag from before the seal, a configuration key renamed is caught by the
    configuration's own record_sha256 (exit 1); a runtime that does not read, with nothing to
    check it by, is bad input (exit 2)."""
    bag = _bag(tmp_path, flown)
    config = _stored(flown[0]["config"])
    renamed = config.replace('"q_sigma"', '"q_sigm0"')
    _rewrite(bag, lambda m: {**_unsealed(m), "config": renamed}, library=UNSEALING_LIBRARY)
    assert cli_main(["replay", str(bag)]) == EXIT_MISMATCH
    out = capsys.readouterr().out
    assert ("CONFIGURATION: the recorded configuration does not match its record_sha256: it was "
            "altered after recording") in out, out
    assert "METADATA" not in out
    _rewrite(bag, lambda m: {**m, "config": config, "art_runtime": "onny"})
    assert cli_main(["replay", str(bag)]) == 2
    assert "onny" in capsys.readouterr().err


def test_three_damages_outside_any_crc_do_not_unseal_a_sealed_bag(tmp_path, flown, capsys):
    """One character of the MCAP header's library, one of the key metadata_seal and one of a
    key inside the seal's JSON, together: the seal is still known by its shape (and the writer
    by its library, one character off), so the bag is altered, not unsealed: exit 1, naming
    the seal."""
    bag = _bag(tmp_path, flown)

    def damage(m: dict) -> dict:
        inner = m[SEAL_KEY].replace('"fields"', '"fieldz"')
        return {**_unsealed(m), "metadata_seaX": inner}

    _rewrite(bag, damage, library=SEALING_LIBRARY.replace("writes", "wrltes"))
    assert cli_main(["replay", str(bag)]) == EXIT_MISMATCH
    out = capsys.readouterr().out
    assert "unsealed" not in out
    for name in ("guidance_0.mcap", "guidance_1.mcap"):
        assert (f"METADATA: {name}: no metadata_seal, but metadata_seaX holds a seal: its key "
                "was altered after recording") in out, out
        assert f"METADATA: {name}: metadata_seal = " in out and "does not read" in out
