"""The guidance node's recording: every solve to MCAP, with the messages it came from.

`SolveRecording` resolves the recorded topics (namespace and remapping applied, from the names:
it works before the endpoints exist, as in a lifecycle node's configure), opens the
`record.McapRecorder` with the run's metadata (configuration, versions, model, parameters) and
writes each solve: the fix, the replan request once (a request played back would reset a live
node's plan each time), the solve record and the plan, fsync'ed before the plan is published;
then the plan's visualisation, in a write of its own after the plan is out.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from art_guidance import topics
from art_guidance.planning import GuidancePipeline, PlanResult
from art_guidance.guidance.core import Job
from art_guidance.record.recorder import (
    NAV_TYPE, PLAN_TYPE, REQUEST_TYPE, SOLVE_RECORD_TYPE, McapRecorder, check_cap,
    check_record_dir, default_log_dir, free_bag_dir,
)
from art_guidance.ros.adapters import solve_record_msg, stamp_to_ns
from art_guidance.ros.node_outputs import VIZ_TYPE_NAMES, VIZ_TYPES
from art_guidance.ros.parameters import NodeParameters


def bag_folder(params: NodeParameters, again: bool = False) -> Path | None:
    """The folder the node's bag goes to (None when `record` is off), checked: the node asks
    before it loads a model or starts a worker, so a folder or size cap that cannot be used is
    refused at once.

    Args:
        again: this node run recorded before (a lifecycle configure after a cleanup): a bag
            folder that already holds a recording is not refused, the new bag goes beside it
            (`<record_dir>_2`, `_3`, ...: the first that holds none; a bag is never
            overwritten). On a node's first configure such a folder is refused.

    Raises:
        GuidanceError: a record directory or size cap that cannot be used.
    """
    if not params.record:
        return None
    check_cap(params.record_max_total_bytes, params.record_max_bytes)
    directory = Path(params.record_dir or str(default_log_dir()))
    return check_record_dir(free_bag_dir(directory) if again else directory)


class SolveRecording:
    """What the node records, and the recorder (None when `record` is off).

    Args:
        resolve: the node's `resolve_topic_name`.
        params: the node's parameters (`record*`, `visualization`; recorded).
        pipeline: the planner (its configuration is recorded).
        provider: the learned warm start, or None.
        model_status: the model in words (recorded).
        log: the node's logger.
        directory: the bag's folder (`bag_folder`; None: `record` is off).
        again: this node run recorded before (said in the log where the bag went beside the
            earlier one).
    """

    def __init__(self, resolve: Callable[[str], str], params: NodeParameters,
                 pipeline: GuidancePipeline, provider: Any, model_status: str,
                 log: Any, directory: Path | None, again: bool = False) -> None:
        # message type -> resolved topic; the solve record is recorded only, under the node's
        # own namespace
        self.topics = {NAV_TYPE: resolve(topics.NAV), REQUEST_TYPE: resolve(topics.REPLAN_REQUEST),
                       SOLVE_RECORD_TYPE: resolve(topics.SOLVE_RECORD),
                       PLAN_TYPE: resolve(topics.MANEUVER_PLAN)}
        self.viz_topics = ({topic: resolve(topic) for topic in VIZ_TYPES}
                           if params.visualization else {})
        self.model_load_ms = provider.load_ms if provider is not None else 0.0
        self._recorded_request: Any = None  # the last request written (worker thread only)
        self.recorder: McapRecorder | None = None
        if directory is None:
            return
        meta = {"config": pipeline.config_json(), "versions": versions(),
                "model_checksum": provider.sha256 if provider else "none",
                "art_runtime": provider.runtime if provider else "none",
                "art_runtime_checksum": provider.runtime_sha256 if provider else "none",
                "model": model_status, "parameters": params.as_dict()}
        log.info(f"recording every solve to {directory}" + (
            f" (a new bag: {params.record_dir} holds this node's earlier one)"
            if again and params.record_dir and directory != Path(params.record_dir) else ""))
        recorded = {t: msg_type for msg_type, t in self.topics.items()}
        recorded.update({self.viz_topics[t]: VIZ_TYPE_NAMES[t] for t in self.viz_topics})
        self.recorder = McapRecorder(directory, meta, max_bytes=params.record_max_bytes,
                                     topics=recorded,
                                     max_total_bytes=params.record_max_total_bytes)

    def record(self, job: Job, result: PlanResult, plan_id: str, plan_msg: Any) -> bool:
        """Write one solve: the fix, the request (once), the solve record and the plan, before
        the plan is published (True: written or not recording; False: see the recorder's
        `last_error`)."""
        if self.recorder is None:
            return True
        topic, request = self.topics, job.request_payload
        msgs = [(topic[NAV_TYPE], job.nav_payload)]
        # each request once (same stamp and content = same request): played back, every copy
        # would reset a live node's plan; the solve record links to it by stamp
        new_request = request is not None and request != self._recorded_request
        if new_request:
            msgs.append((topic[REQUEST_TYPE], request))
        request_ns = 0 if request is None else stamp_to_ns(request.header.stamp)
        msgs += [(topic[SOLVE_RECORD_TYPE], solve_record_msg(
                     result, job.nav.stamp_ns, plan_id, job.trigger, request_ns,
                     self.model_load_ms)),
                 (topic[PLAN_TYPE], plan_msg)]
        if not self.recorder.record_solve(msgs, time.time_ns()):
            return False
        if new_request:
            self._recorded_request = request
        return True

    def record_views(self, views: list[tuple[str, object]]) -> bool:
        """Write a published plan's visualisation messages (after the plan is out: derived
        data, drawn again from the recorded plan if lost); True as `record`."""
        if self.recorder is None or not views:
            return True
        return self.recorder.record_solve([(self.viz_topics[t], msg) for t, msg in views],
                                          time.time_ns(), solve=False)

    @property
    def directory(self) -> str:
        """The bag folder being written ("" when not recording)."""
        return "" if self.recorder is None else str(self.recorder.directory)

    def finish(self, log: Any) -> None:
        """Finish the recording (idempotent), saying where it went."""
        if self.recorder is not None:
            self.recorder.finish()
            log.info(f"recorded {self.recorder.solves} solves to {self.recorder.directory}")


def versions() -> dict:
    """The versions of the packages a recorded run depends on ("absent" if not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("art_guidance", "clarabel", "osqp", "numpy", "scipy", "mcap",
                "mcap-ros2-support", "torch", "onnxruntime", "numba", "rclpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "absent"
    return out
