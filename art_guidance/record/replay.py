"""Read recorded solves back (also from damaged or crash-truncated files) and re-solve them.

`read_log` reads every file with `record.scan`: each chunk's CRC is checked, a damaged chunk is
named and skipped and the intact chunks after it are read; a file whose writer was killed inside
a write (a torn end) yields every solve whose chunk was completed. What was read is compared
with `metadata.yaml` (`record.loss`), and SolveRecords without their ManeuverPlan (and plans
without their record) are listed; the files are never modified. Messages are found by their
type (the schema name), not by topic, so a node started in a namespace or with remapped topics
replays the same. `replay` checks the run metadata it reads against its seal (`record.seal`;
every file's record), rebuilds the pipeline from the recorded configuration (and the learned
model, checked against the recorded checksum), solves each recorded request again (the request
JSON in the SolveRecord) and compares the ART rollout, the post hoc decision and the plan.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap_ros2.decoder import DecoderFactory

from art_guidance import kernels
from art_guidance.config import mode_name
from art_guidance.errors import GuidanceError, InputError
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.planning.pipeline import recorded_config_problem
from art_guidance.record.bag_metadata import bag_files
from art_guidance.record.loss import account
from art_guidance.record.recorder import PLAN_TYPE, REQUEST_TYPE, SOLVE_RECORD_TYPE
from art_guidance.record.replay_rows import (
    MIXED_NUMERICS, NO_COMPILED, ROLLOUT_ABS_TOL_MPS, art_rows, recorded_path, window_rows,
)
from art_guidance.record.scan import Damage, FileScan, lend_channels, scan_file
from art_guidance.record.seal import (
    SEAL_KEY, seal_problems, shown, shown_name, unknown_fields, writer_seals,
)

COST_REL_TOL = 1e-6     # relative cost agreement of a re-solve
DV_ABS_TOL_MPS = 1e-5   # largest delta-v component difference [m/s]
EXIT_OK = 0        # every compared solve matches, nothing lost or damaged
EXIT_MISMATCH = 1  # a compared solve does not match (whatever else)
EXIT_LOST = 3      # all compared solves match, but data was lost
EXIT_UNCOMPARED = 4  # no compared solve differs, but solves recorded with another model than
#                      the one replayed were not compared (without `allow_uncompared`)
OTHER_MODEL = "recorded with a different model"
DEADLINE_HIT = "recorded solve hit its deadline"
NOT_REPLAYED = "the recording was altered and no longer reads"


def _stamp_ns(stamp: object) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def request_stamp_ns(record: object) -> int:
    """SolveRecord.request_stamp in ns (0 = no request; logs older than the field give 0)."""
    stamp = getattr(record, "request_stamp", None)
    return 0 if stamp is None else _stamp_ns(stamp)


@dataclass
class RecordedLog:
    """Messages of one or more MCAP files, in file order, and what could not be read."""

    metadata: dict = field(default_factory=dict)  # the last file's record, which replay reads
    metadata_records: dict[str, dict] = field(default_factory=dict)  # file name -> its record
    writers: dict[str, str] = field(default_factory=dict)  # file name -> MCAP header library
    messages: list[tuple[str, object, int]] = field(default_factory=list)  # topic, msg, t_ns
    types: dict[str, str] = field(default_factory=dict)  # topic -> 'pkg/msg/Type'
    truncated: list[str] = field(default_factory=list)  # torn ends ("<file>: <why>")
    damaged: list[Damage] = field(default_factory=list)
    files: dict[str, int] = field(default_factory=dict)  # file name -> messages read
    notes: list[str] = field(default_factory=list)
    lost: dict = field(default_factory=dict)  # `record.loss.account`

    @property
    def data_lost(self) -> bool:
        """Damage that may have cost messages was found (not `Damage.no_loss`), messages are
        missing against metadata.yaml (or the damaged chunks' index), or a SolveRecord or plan
        lacks its partner."""
        unmatched = self.unmatched()
        return bool(any(d.lost_data for d in self.damaged) or self.lost.get("messages") is None
                    or self.lost.get("messages") or any(unmatched.values()))

    def metadata_check(self) -> tuple[str, list[str]]:
        """("sealed" | "unsealed" | "altered", problems): every file's run metadata record
        against its seal (`record.seal`; it must have one where its file's writer seals), and
        against the record replay reads (the last file's; the recorder writes the same one to
        every file). Each problem names the file, the field and its value. "unsealed":
        recorded before the seal, nothing to check by."""
        problems, unsealed = [], []
        last = next(reversed(self.metadata_records), None)
        for name, record in self.metadata_records.items():
            found = seal_problems(record, writer_seals(self.writers.get(name)))
            if found is None:
                unsealed.append(name)
            problems += [f"{name}: {problem}" for problem in found or []]
            if name != last:
                reads = self.metadata_records[last]
                problems += [f"{name}: {shown_name(key)} = {shown(str(record.get(key, '')))} "
                             f"differs from {last}'s {shown(str(reads.get(key, '')))}, which "
                             "replay reads"
                             for key in sorted(set(record) | set(reads))
                             if key != SEAL_KEY and record.get(key) != reads.get(key)]
        if unsealed and len(unsealed) < len(self.metadata_records):
            problems += [f"{name}: no {SEAL_KEY}, where the other files have one: removed "
                         "after recording" for name in unsealed]
        sealed = self.metadata_records and not unsealed
        state = "altered" if problems else "sealed" if sealed else "unsealed"
        return state, problems

    def of_type(self, msg_type: str) -> list[object]:
        """Every message of `msg_type` ('pkg/msg/Type'), whatever its topic, in file order."""
        return [msg for topic, msg, _ in self.messages if self.types.get(topic) == msg_type]

    def solves(self) -> list[tuple[object, object]]:
        """(SolveRecord, ManeuverPlan) pairs matched by plan id (see `unmatched`)."""
        plans = {msg.plan_id: msg for msg in self.of_type(PLAN_TYPE)}
        records = {msg.plan_id: msg for msg in self.of_type(SOLVE_RECORD_TYPE)}
        return [(records[k], plans[k]) for k in records if k in plans]

    def unmatched(self) -> dict[str, list[str]]:
        """Plan ids of SolveRecords without their ManeuverPlan and of plans without their
        SolveRecord (the recorder writes both with every solve)."""
        plans = {msg.plan_id for msg in self.of_type(PLAN_TYPE)}
        records = {msg.plan_id for msg in self.of_type(SOLVE_RECORD_TYPE)}
        return {"records_without_plan": sorted(records - plans),
                "plans_without_record": sorted(plans - records)}

    def request_for(self, record: object) -> object | None:
        """The ReplanRequest in force for a SolveRecord (matched by its header stamp), if any.

        Each request is recorded once, with the first solve made under it; later solves refer
        to it through `SolveRecord.request_stamp` (zero: no request, the node's default target).
        """
        stamp, latest = request_stamp_ns(record), None
        if stamp == 0:
            return None
        for topic, msg, _ in self.messages:  # the last such request recorded before the solve
            if msg is record:
                break
            if self.types.get(topic) == REQUEST_TYPE and _stamp_ns(msg.header.stamp) == stamp:
                latest = msg
        return latest


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        files = bag_files(path)
        if not files:
            raise InputError("log", "no .mcap files in the directory", str(path))
        return files
    if not path.is_file():
        raise InputError("log", "no such file", str(path))
    return [path]


def _decode(log: RecordedLog, scan: FileScan) -> None:
    """Append a file's messages (decoded with its embedded schemas) to `log`."""
    channels, factory = {}, DecoderFactory()
    for cid, channel in scan.channels.items():
        schema = scan.schemas.get(channel.schema_id)
        channels[cid] = (channel.topic, factory.decoder_for(channel.message_encoding, schema))
        if schema is not None:
            log.types[channel.topic] = schema.name
    if scan.header is not None:
        log.writers[scan.path.name] = scan.header.library
    for record in scan.metadata:
        if record.name == "art_guidance":
            log.metadata = dict(record.metadata)
            log.metadata_records[scan.path.name] = log.metadata
    count = 0
    for record in scan.messages:
        topic, decoder = channels[record.channel_id]
        if decoder is None:
            continue  # not a cdr/ros2msg channel: not ours
        try:
            msg = decoder(record.data)
        except Exception as exc:  # intact chunk, undecodable payload: damage all the same
            log.damaged.append(Damage(scan.path.name, None, -1, 0, f"a message on {topic} "
                                      f"(log time {record.log_time}) does not decode: "
                                      f"{type(exc).__name__}: {exc}", 1, {topic: 1}))
            continue
        log.messages.append((topic, msg, record.log_time))
        count += 1
    log.files[scan.path.name] = count


def read_log(path: str | Path) -> RecordedLog:
    """Read every intact message of an MCAP file or bag folder (see the module docstring).

    Messages are decoded with the schemas embedded in the file, not the installed types. The
    log's `damaged`, `truncated` (torn ends), `notes`, `lost` and `unmatched()` say what could
    not be read.
    """
    path = Path(path)
    scans = [scan_file(file) for file in _files(path)]
    lend_channels(scans)
    log = RecordedLog()
    for scan in scans:
        _decode(log, scan)
        log.damaged += scan.damaged
        log.notes += scan.notes
        if scan.torn:
            log.truncated.append(f"{scan.path.name}: {scan.torn}")
        scan.messages = []  # decoded: the raw copies are not needed any more
    read_topics: dict[str, int] = {}
    for topic, _, _ in log.messages:
        read_topics[topic] = read_topics.get(topic, 0) + 1
    log.lost = account(path, read_topics, log.files, log.types, log.damaged)
    return log


def _plan_arrays(plan: object) -> tuple[float, np.ndarray]:
    return float(plan.cost_mps), np.asarray(plan.dv_rtn_mps, float).reshape(-1, 3)


def recorded_mode(log: RecordedLog) -> str:
    """Passive-safety mode of a log's solves: "deterministic" when every recorded request
    planned deterministic passive safety, else "chance" (also for a log without solves)."""
    modes = set()
    for record, _ in log.solves():
        try:
            modes.add(bool(json.loads(record.request_json).get("chance_constrained", True)))
        except (ValueError, AttributeError):  # unreadable request: judged when it is replayed
            modes.add(True)
    return mode_name(modes != {False})


def _replay_provider(log: RecordedLog, model: str | Path | None) -> tuple[object | None, str]:
    """The warm-start provider to replay with, and a note on how it relates to the log's.

    A log recorded without a model replays CVX-only (a given model is ignored). A log recorded
    with a model replays with `model`, or else with the shipped model whose pinned checksum is
    the recorded one, or else with the shipped default of the log's passive-safety mode
    (`recorded_mode`); a different checksum is reported, never a silent mismatch.
    """
    recorded = str(log.metadata.get("model_checksum", "none") or "none")
    if recorded == "none":
        note = "recorded without a learned model: replayed CVX-only"
        return None, note + ("; the given model is not used" if model else "")
    from art_guidance.art.provider import (
        ArtWarmStart, default_model_path, shipped_model_with_sha256,
    )

    path = Path(model) if model else (shipped_model_with_sha256(recorded)
                                      or default_model_path(recorded_mode(log)))
    runtime = str(log.metadata.get("art_runtime", "torch") or "torch")  # older logs: torch
    try:
        provider = ArtWarmStart.load(path, runtime=runtime)
    except GuidanceError as exc:
        raise InputError("model", f"the log was recorded with model sha256 {recorded[:16]}..., "
                         f"which could not be loaded for replay: {exc}") from exc
    if provider.sha256 != recorded:
        return provider, (f"recorded with model sha256 {recorded[:16]}..., replayed with "
                          f"{path.name} sha256 {provider.sha256[:16]}...: solves that used "
                          "the learned warm start are not compared")
    ran = str(log.metadata.get("art_runtime_checksum", "") or "")
    if runtime == "onnx" and ran and provider.runtime_sha256 != ran:
        return provider, (f"replayed with the recorded model {path.name} on the onnx runtime, "
                          f"but the exported file differs (sha256 {ran[:16]}... recorded, "
                          f"{provider.runtime_sha256[:16]}... here)")
    return provider, (f"replayed with the recorded model {path.name} on the {runtime} runtime "
                      "(sha256 matches)")


def advice(path: str | Path, log: RecordedLog) -> list[str]:
    """What to do about what `read_log` found; `bag reindex` only where it helps."""
    out, folder = [], Path(path).is_dir()
    target = path if folder else Path(path).parent
    repairable = log.truncated or log.damaged or log.lost.get("files")
    if repairable and (folder or (target / "metadata.yaml").is_file()):
        out.append(f"`art-guidance bag reindex {target}` rebuilds the torn or damaged files "
                   "from their intact chunks and rewrites metadata.yaml to what is on disk, so "
                   "rosbag2 and rosbags read the folder; it cannot bring back lost data")
    elif repairable:
        out.append("a torn or damaged file outside a bag folder: put it in a folder of its own "
                   "for `art-guidance bag reindex` to rebuild it")
    if log.damaged:
        out.append("damaged chunks mean failing storage or a bad copy: check the medium, and "
                   "keep a copy of the folder as it is before repairing it")
    elif log.lost.get("messages") and not repairable:
        out.append("the files are intact but hold fewer messages than metadata.yaml counts: "
                   "files were cut or replaced after recording; no repair brings them back")
    return out


def _metadata_report(log: RecordedLog) -> tuple[str, list[str]]:
    """The report's `metadata_check` ("ok", "unsealed: ...", or "altered: ...") and its
    problems (`RecordedLog.metadata_check`). An unsealed record's fields that are not run
    metadata are named in its "unsealed: ..." (nothing tells whether they were added after
    recording)."""
    state, problems = log.metadata_check()
    if state == "unsealed":
        unknown = sorted({name for record in log.metadata_records.values()
                          for name in unknown_fields(record)})
        return ("unsealed: recorded before the metadata seal; model_checksum, art_runtime and "
                "art_runtime_checksum are taken as recorded (the configuration is sealed by its "
                "own record_sha256)" + "".join(
                    f"; {shown_name(name)} is not run metadata" for name in unknown)), []
    if problems:
        return f"altered: {len(problems)} value(s) do not match the seal", problems
    return "ok", []


def _recorded_config(log: RecordedLog, path: str | Path) -> dict:
    """The recorded configuration (`GuidancePipeline.config_json`).

    Raises:
        InputError: the log has none, or it is not a JSON object.
    """
    if "config" not in log.metadata:
        raise InputError("log", "no art_guidance configuration in the MCAP metadata", str(path))
    try:
        recorded = json.loads(log.metadata["config"])
    except ValueError as exc:
        raise InputError("config", f"recorded configuration is not JSON: {exc}") from exc
    if not isinstance(recorded, dict):
        raise InputError("config", "the recorded configuration is not a JSON object")
    return recorded


def replay(path: str | Path, model: str | Path | None = None,
           allow_uncompared: bool = False, numerics: str | None = None) -> dict:
    """Re-solve every recorded request; returns a JSON-ready report with a per-solve verdict.

    A solve matches when the replayed plan's cost agrees to COST_REL_TOL and every delta-v
    component to DV_ABS_TOL_MPS, and, where a learned warm start was proposed, the rollout
    agrees to ROLLOUT_ABS_TOL_MPS and the post hoc decision and the warm start kept are the
    same. A solve that used the learned warm start of another model than the one replayed is
    not compared (`uncompared`); nor is a solve that hit its deadline (`deadline_hit`: replays
    are not time-boxed, so it cannot be reproduced; the record's flag, or for records before
    it a TIMEOUT in the texts).

    Each solve is replayed on the numerics path it ran on (the record's `numerics`; the paths
    make the same decisions, not the same floats), the process's own path restored after it;
    one recorded while the kernels became ready (`mixed`), or compiled where they cannot be
    used here, is not compared. `numerics` replays every solve on that path; records before
    the field replay on the configuration's path.

    The report also says what could not be read (`damaged`, `truncated`: torn ends), what was
    lost against metadata.yaml (`lost`), which records or plans lack their partner
    (`unmatched`), `advice`, `config_check` ("ok", or why the recorded configuration cannot be
    trusted: its seal does not match, `planning.pipeline.recorded_config_problem`),
    `metadata_check` and `metadata_problems` (every run metadata value against its seal,
    `record.seal`: "ok", "unsealed: ..." for a recording from before the seal, or "altered:
    ..." with each altered field and value) and `exit_code`: EXIT_MISMATCH if a compared solve
    differs, the configuration or any run metadata value was altered; else EXIT_UNCOMPARED if
    solves went uncompared for another model (unless `allow_uncompared`); else EXIT_LOST if
    data was lost; else EXIT_OK. The seals are checked before the recorded values are used:
    where the recording was altered and the configuration or the model it names can no longer
    be read or loaded, no solve is replayed (NOT_REPLAYED, EXIT_MISMATCH).

    Args:
        path: an .mcap file or a bag folder.
        model: checkpoint to replay learned warm starts with (default: the shipped model if it
            is the recorded one; see the report's "model" note otherwise).
        allow_uncompared: solves left uncompared for another model do not set the exit code.
        numerics: "compiled" or "numpy", the path of every solve (None: each its own).

    Raises:
        InputError: no such log, no configuration in it, or a recorded value that cannot be
            used where nothing says it was altered (a record from before the seal).
    """
    log = read_log(path)
    metadata_check, metadata_problems = _metadata_report(log)
    config_problem, provider, pipeline = "", None, None
    try:
        recorded = _recorded_config(log, path)
        config_problem = recorded_config_problem(recorded)
        provider, model_note = _replay_provider(log, model)
        # the pipeline as recorded: configuration, ranking of the candidates, model; replays
        # are not time-boxed (timed-out solves are flagged)
        pipeline = GuidancePipeline.from_config_json(recorded, provider, time_boxed=False)
    except GuidanceError as exc:
        if not (metadata_problems or config_problem):
            raise  # nothing says it was altered: the log cannot be replayed as it is
        provider, model_note = None, f"not replayed, the recording was altered: {exc}"
    same_model = provider is None or provider.sha256 == log.metadata.get("model_checksum")
    rows = []
    for record, plan in log.solves():
        cost, dv = _plan_arrays(plan)
        row = {"plan_id": plan.plan_id, "status": plan.status_text.split(":")[0],
               "cost_mps": cost, "request_stamp_ns": request_stamp_ns(record)}
        reason = str(getattr(record, "warm_start_reason", ""))
        if bool(getattr(record, "deadline_hit", False)) or plan.status_text.startswith(
                "TIMEOUT") or "TIMEOUT" in reason:
            row.update(match=None, reason=DEADLINE_HIT)
            rows.append(row)
            continue
        path = numerics or recorded_path(record, None if pipeline is None
                                         else pipeline.config.planning.numerics)
        if path == MIXED_NUMERICS:
            row.update(match=None, reason=path)
            rows.append(row)
            continue
        if pipeline is None:
            row.update(match=None, reason=NOT_REPLAYED)
            rows.append(row)
            continue
        if not same_model and len(getattr(record, "warm_start_art_dv_rtn_mps", [])):
            row.update(match=None, reason=OTHER_MODEL)
            rows.append(row)
            continue
        row["numerics"] = path
        with kernels.using(path):  # the process's own choice again afterwards
            if path == "compiled" and not kernels.compiled():  # the kernels failed here
                rows.append({**row, "match": None, "reason": NO_COMPILED})
                continue
            result = pipeline.plan(PlanRequest.from_json(json.loads(record.request_json)))
        d_cost = abs(result.cost_mps - cost) / max(abs(cost), 1e-12)
        d_dv = (float(np.max(np.abs(result.dv_rtn_mps - dv)))
                if result.dv_rtn_mps.shape == dv.shape else float("inf"))
        row.update(replayed_cost_mps=result.cost_mps, cost_rel_diff=d_cost,
                   dv_max_abs_diff_mps=d_dv, replayed_status=result.status.name,
                   **art_rows(record, result))
        row.update(window_rows(record, result))
        row["match"] = bool(d_cost <= COST_REL_TOL and d_dv <= DV_ABS_TOL_MPS
                            and row["decision_match"] and row["window_match"])
        rows.append(row)
    compared = [r for r in rows if r["match"] is not None]
    mismatched = sum(not r["match"] for r in compared)
    uncompared = sum(r.get("reason") == OTHER_MODEL for r in rows)
    hints = []
    if metadata_problems:
        hints.append("the run metadata was altered after recording: what replay chose from it "
                     "(the configuration, the model) cannot be trusted; replay a copy of the "
                     "bag as recorded")
    elif uncompared and not allow_uncompared:
        hints.append(f"{uncompared} solve(s) that used the learned warm start of model sha256 "
                     f"{str(log.metadata.get('model_checksum'))[:16]}... were not compared: "
                     "replay with that model (`--model CKPT`) to compare them, or pass "
                     "`--allow-uncompared` to accept the replay without them")
    return {"log": str(path), "solves": len(rows), "compared": len(compared),
            "matched": sum(r["match"] for r in compared), "mismatched": mismatched,
            "uncompared": uncompared,
            "deadline_hit": sum(r.get("reason") == DEADLINE_HIT for r in rows),
            "exit_code": (EXIT_MISMATCH if mismatched or config_problem or metadata_problems
                          else EXIT_UNCOMPARED if uncompared and not allow_uncompared
                          else EXIT_LOST if log.data_lost else EXIT_OK),
            "config_check": config_problem or "ok",
            "metadata_check": metadata_check, "metadata_problems": metadata_problems,
            "model": model_note, "model_checksum": log.metadata.get("model_checksum", "none"),
            "truncated": log.truncated,
            "damaged": [d.as_dict() for d in log.damaged],
            "lost": log.lost, "unmatched": log.unmatched(), "notes": log.notes,
            "advice": hints + advice(path, log),
            "tolerances": {"cost_rel": COST_REL_TOL, "dv_abs_mps": DV_ABS_TOL_MPS,
                           "rollout_abs_mps": ROLLOUT_ABS_TOL_MPS},
            "per_solve": rows}
