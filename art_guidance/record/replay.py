"""Read recorded solves back (also from files cut short by a crash) and re-solve them.

`read_log` walks the MCAP records sequentially, so a file whose writer was killed (no summary,
a torn last record) yields every solve whose chunk was completed; it never modifies the files.
Messages are found by their type (the schema name), not by topic, so a node started in a
namespace or with remapped topics replays the same. `replay` rebuilds the pipeline from the
recorded configuration, solves each recorded request again (the request JSON in the
SolveRecord) and compares the plan.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Message, Metadata
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from art_guidance.errors import InputError
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.record.bag_metadata import bag_files
from art_guidance.record.recorder import PLAN_TYPE, REQUEST_TYPE, SOLVE_RECORD_TYPE

COST_REL_TOL = 1e-6     # relative cost agreement of a re-solve
DV_ABS_TOL_MPS = 1e-5   # largest delta-v component difference [m/s]


def _stamp_ns(stamp: object) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def request_stamp_ns(record: object) -> int:
    """SolveRecord.request_stamp in ns (0 = no request; logs older than the field give 0)."""
    stamp = getattr(record, "request_stamp", None)
    return 0 if stamp is None else _stamp_ns(stamp)


@dataclass
class RecordedLog:
    """Messages of one or more MCAP files, in file order."""

    metadata: dict = field(default_factory=dict)
    messages: list[tuple[str, object, int]] = field(default_factory=list)  # topic, msg, t_ns
    types: dict[str, str] = field(default_factory=dict)  # topic -> 'pkg/msg/Type'
    truncated: list[str] = field(default_factory=list)

    def of_type(self, msg_type: str) -> list[object]:
        """Every message of `msg_type` ('pkg/msg/Type'), whatever its topic, in file order."""
        return [msg for topic, msg, _ in self.messages if self.types.get(topic) == msg_type]

    def solves(self) -> list[tuple[object, object]]:
        """(SolveRecord, ManeuverPlan) pairs matched by plan id."""
        plans = {msg.plan_id: msg for msg in self.of_type(PLAN_TYPE)}
        records = {msg.plan_id: msg for msg in self.of_type(SOLVE_RECORD_TYPE)}
        return [(records[k], plans[k]) for k in records if k in plans]

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


def read_log(path: str | Path) -> RecordedLog:
    """Read every complete message of an MCAP file or bag folder (crash-truncated files too).

    Messages are decoded with the schemas embedded in the file, not the installed types.
    """
    log = RecordedLog()
    for file in _files(Path(path)):
        channels, schemas, factory = {}, {}, DecoderFactory()
        with open(file, "rb") as fh:
            try:
                for record in StreamReader(fh).records:
                    kind = type(record).__name__
                    if kind == "Schema":
                        schemas[record.id] = record
                    elif kind == "Channel":
                        schema = schemas.get(record.schema_id)
                        decoder = factory.decoder_for(record.message_encoding, schema)
                        channels[record.id] = (record.topic, decoder)
                        if schema is not None:
                            log.types[record.topic] = schema.name
                    elif isinstance(record, Metadata) and record.name == "art_guidance":
                        log.metadata = dict(record.metadata)
                    elif isinstance(record, Message) and record.channel_id in channels:
                        topic, decoder = channels[record.channel_id]
                        if decoder is None:
                            continue  # not a cdr/ros2msg channel: not ours
                        msg = decoder(record.data)
                        log.messages.append((topic, msg, record.log_time))
            except Exception as exc:  # torn tail after a crash: keep what was complete
                log.truncated.append(f"{file.name}: {type(exc).__name__}: {exc}")
    return log


def _plan_arrays(plan: object) -> tuple[float, np.ndarray]:
    return float(plan.cost_mps), np.asarray(plan.dv_rtn_mps, float).reshape(-1, 3)


def replay(path: str | Path) -> dict:
    """Re-solve every recorded request; returns a JSON-ready report with a per-solve verdict."""
    log = read_log(path)
    if "config" not in log.metadata:
        raise InputError("log", "no art_guidance configuration in the MCAP metadata", str(path))
    pipeline = GuidancePipeline.from_config_json(json.loads(log.metadata["config"]))
    pipeline.deadline_s = None  # replays are not time-boxed; timed-out solves are flagged
    rows = []
    for record, plan in log.solves():
        cost, dv = _plan_arrays(plan)
        row = {"plan_id": plan.plan_id, "status": plan.status_text, "cost_mps": cost,
               "request_stamp_ns": request_stamp_ns(record)}
        if plan.status_text == "TIMEOUT":
            row.update(match=None, reason="recorded solve hit its deadline")
            rows.append(row)
            continue
        result = pipeline.plan(PlanRequest.from_json(json.loads(record.request_json)))
        d_cost = abs(result.cost_mps - cost) / max(abs(cost), 1e-12)
        d_dv = (float(np.max(np.abs(result.dv_rtn_mps - dv)))
                if result.dv_rtn_mps.shape == dv.shape else float("inf"))
        row.update(replayed_cost_mps=result.cost_mps, cost_rel_diff=d_cost,
                   dv_max_abs_diff_mps=d_dv, replayed_status=result.status.name,
                   match=bool(d_cost <= COST_REL_TOL and d_dv <= DV_ABS_TOL_MPS))
        rows.append(row)
    compared = [r for r in rows if r["match"] is not None]
    return {"log": str(path), "solves": len(rows), "compared": len(compared),
            "matched": sum(r["match"] for r in compared),
            "mismatched": sum(not r["match"] for r in compared),
            "truncated": log.truncated, "tolerances": {"cost_rel": COST_REL_TOL,
                                                       "dv_abs_mps": DV_ABS_TOL_MPS},
            "per_solve": rows}
