"""Monte Carlo of thruster faults in the closed loop, checked in truth (`bench contingency`).

One *flight* per (configuration, seed): the in-process guidance (the node's replan policy and
pipeline, `sim.inprocess`) flies the closed loop with navigation and actuation errors in the
two-body + J2 truth, from the seed's initial state to the waypoint. A configuration is a
passive-safety mode (chance-constrained or deterministic) and a warm start ("auto": the shipped
model of that mode with the post hoc check; "cvx": CVX only).

* Losses: every node of the flight (K = 1 .. number of nodes, the last one being the drift
  after the final burn) is a loss: the truth state the flight reached at K drifts freely for
  T_safety and is checked densely against the ellipsoid in force (`ClosedLoop.loss_checks`,
  the same check `--fault loss --fault-node K` reports; the random draws before K are the
  same, so the state is the one that run ends in).
* Missed burns: `missed_per_seed` more flights of the same seed, each with burn K not executed,
  K drawn uniformly (seeded) among the flight's nodes that command at least `min_missed_dv_mps`
  (a missed zero burn changes nothing). Each reports whether the waypoint was still reached
  and the worst truth drift from the nodes flown after the fault.

Flights run as chunks on the local process pool or Ray (`jobs.run_missing`) and each
finished chunk is committed to the output directory, so an interrupted run resumes where it
stopped. `summarize_directory` turns the committed rows into entry rates with exact
(Clopper-Pearson) 95 % upper bounds, the worst margins, the missed-burn outcomes and the
figures.
The Monte Carlo's definition and directory format are `sim.contingency_spec`, the summary and
its tables `sim.contingency_summary`, the figures `sim.contingency_figures`.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.data.storage import DatasetWriter
from art_guidance.errors import ConfigError, InputError
from art_guidance.files import write_json_atomic
from art_guidance.jobs import check_run_options, run_missing
from art_guidance.guidance.replan import ReplanSettings
# the names below are also imported from here
from art_guidance.sim.contingency_figures import render
from art_guidance.sim.contingency_spec import (  # noqa: F401
    CONFIGS, FORMAT, KIND, NODES_MAX, ContingencySpec, config_fields, header, read_rows,
    spec_of,
)
from art_guidance.sim.contingency_summary import (  # noqa: F401
    CONFIDENCE, DESIGN_RATE, TABLE_BEGIN, TABLE_END, markdown_table, summarize_directory,
    table_in_doc, upper_bound,
)
from art_guidance.sim.faults import ZONES, Fault

_LOG = logging.getLogger("art_guidance.contingency")
_PIPELINES: dict[tuple[bool, str], object] = {}  # per worker process


def _pipeline(chance: bool, warm_start: str) -> object:
    """This process's pipeline for a configuration (the model loaded once)."""
    key = (chance, warm_start)
    if key not in _PIPELINES:
        from art_guidance.planning import GuidancePipeline

        provider = None
        if warm_start != "cvx":
            from art_guidance.art.provider import ArtWarmStart, resolve_model_path

            provider = ArtWarmStart.load(resolve_model_path(None, chance))
        _PIPELINES[key] = GuidancePipeline(provider=provider)
    return _PIPELINES[key]


def fly(spec: ContingencySpec, config: int, seed: int, fault: Fault | None = None
        ) -> tuple[object, dict]:
    """One closed-loop flight in-process; the finished `ClosedLoop` and its summary."""
    from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
    from art_guidance.sim.inprocess import InProcessGuidance, default_settings

    chance, warm, window = config_fields(spec.configs[config])
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path="", seed=int(seed),
                  waypoint=spec.waypoint, chance_constrained=chance, warm_start=warm,
                  errors=spec.errors, fault="" if fault is None else fault.kind,
                  fault_node=0 if fault is None else fault.node)
    pipeline = _pipeline(chance, warm)
    settings = dataclasses.replace(default_settings(pipeline.scenario),
                                   replan_window_nodes=window,
                                   terminal_target=spec.terminal_target)
    loop = ClosedLoop(InProcessGuidance(pipeline, SIM_EPOCH0_NS, settings), params, _LOG,
                      settle_s=0.0)
    summary, _ = loop.finish(loop.run(), 0.0)
    return loop, summary


def missed_nodes(dv_cmd_mps: np.ndarray, k: int, min_dv_mps: float, seed: int) -> list[int]:
    """`k` distinct nodes drawn (seeded) among those commanding >= `min_dv_mps` [m/s]."""
    burning = np.flatnonzero(np.linalg.norm(dv_cmd_mps, axis=1) >= min_dv_mps)
    rng = np.random.default_rng([int(seed), 0x6d15])
    return sorted(int(n) for n in rng.permutation(burning)[:k])


def contingency_chunk(spec: ContingencySpec, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """Fly the rows `indices` (the task the engines run); arrays stacked per row."""
    logging.getLogger("art_guidance.contingency").setLevel(logging.ERROR)
    rows = [_flight_row(spec, int(i)) for i in indices]
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


def _flight_row(spec: ContingencySpec, index: int) -> dict[str, np.ndarray]:
    t0 = time.perf_counter()
    config, seed = spec.flight(index)
    loop, summary = fly(spec, config, seed)
    checks = loop.loss_checks()
    n, m = NODES_MAX, spec.missed_per_seed
    row = {"index": np.int64(index), "config": np.int64(config), "seed": np.int64(seed),
           "reached": np.bool_(summary["reached"]), "miss_m": np.float64(summary["miss_m"]),
           "total_dv_mps": np.float64(summary["total_dv_mps"]),
           "n_nodes": np.int64(summary["n_burns"]),
           "loss_node": np.full(n, -1, np.int64), "loss_margin_m": np.full(n, np.nan),
           "loss_t0_s": np.full(n, np.nan), "loss_t_closest_s": np.full(n, np.nan),
           "loss_zone": np.full(n, -1, np.int8), "loss_state": np.full((n, 12), np.nan),
           "loss_dv_cmd_mps": np.full(n, np.nan)}
    dv_cmd = np.array([h.dv_cmd_mps for h in loop.sim.history]).reshape(-1, 3)
    states = dict(loop.loss_states())
    for j, (k, c) in enumerate(checks[:n]):
        row["loss_node"][j] = k
        row["loss_margin_m"][j] = c.min_margin_m
        row["loss_t0_s"][j] = c.t0_s
        row["loss_t_closest_s"][j] = c.t_closest_s
        row["loss_zone"][j] = ZONES.index(c.zone)
        row["loss_state"][j] = np.concatenate([states[k].chief_eci, states[k].deputy_eci])
        if k < dv_cmd.shape[0]:
            row["loss_dv_cmd_mps"][j] = np.linalg.norm(dv_cmd[k])
    nodes = missed_nodes(dv_cmd, m, spec.min_missed_dv_mps, seed)
    miss = {"missed_node": np.full(m, -1, np.int64), "missed_dv_cmd_mps": np.full(m, np.nan),
            "missed_reached": np.zeros(m, bool), "missed_miss_m": np.full(m, np.nan),
            "missed_margin_m": np.full(m, np.nan), "missed_entered": np.zeros(m, bool),
            "missed_replans_after": np.full(m, -1, np.int64),
            "missed_total_dv_mps": np.full(m, np.nan)}
    for j, node in enumerate(nodes):
        _, s = fly(spec, config, seed, Fault("missed", node))
        f = s["fault"]
        miss["missed_node"][j] = node
        miss["missed_dv_cmd_mps"][j] = np.linalg.norm(dv_cmd[node])
        miss["missed_reached"][j] = s["reached"]
        miss["missed_miss_m"][j] = s["miss_m"]
        miss["missed_margin_m"][j] = np.nan if f["min_margin_m"] is None else f["min_margin_m"]
        miss["missed_entered"][j] = bool(f["entered"])
        miss["missed_replans_after"][j] = f.get("replans_after_fault", 0)
        miss["missed_total_dv_mps"][j] = s["total_dv_mps"]
    row.update(miss)
    row["wall_s"] = np.float64(time.perf_counter() - t0)
    return row


def run(out: str | Path, spec: ContingencySpec | None = None, *, workers: int = 1,
        engine: str = "local", ray_address: str | None = None, progress: bool = True,
        figures: bool = True, log: Callable[[str], None] = print) -> dict:
    """Fly the Monte Carlo into `out` (resuming what is there) and summarise it.

    Args:
        out: output directory (created; resumed when it holds this Monte Carlo).
        spec: what to fly (default `ContingencySpec()`).
        workers: processes (local) or CPUs (local Ray instance).
        engine: "local" or "ray".
        ray_address: a Ray cluster to use instead of a local instance.
        progress: show a progress bar (flights).
        figures: write the histogram and the RT-plane figure of the worst losses.
        log: where progress lines go.

    Returns:
        The summary (also written to `out`/summary.json).

    Raises:
        InputError: bad options, or `out` holding something else.
    """
    from art_guidance.eval.runner import single_thread

    spec = spec or ContingencySpec()
    check_run_options({"--workers": workers, "--seeds": spec.n_seeds}, engine)
    if spec.missed_per_seed < 0:
        raise InputError("--missed-per-seed", "must be >= 0", spec.missed_per_seed)
    for config in spec.configs:
        chance, warm, window = config_fields(config)
        if warm not in ("auto", "cvx", "art"):
            raise InputError("configs", "warm start must be auto, art or cvx", warm)
        try:
            ReplanSettings(replan_window_nodes=window, terminal_target=spec.terminal_target)
        except ConfigError as exc:
            raise InputError("configs", str(exc), config) from exc
    single_thread()
    out = Path(out)
    head = header(spec, GuidanceConfig.load())
    with DatasetWriter(out, head, verify=False) as writer:
        def commit(arrays: dict) -> None:
            writer.write_shard(arrays, {"n": int(arrays["index"].size),
                                        "wall_s": float(arrays["wall_s"].sum())})

        status, wall, done0 = run_missing(
            writer, spec.n_flights, contingency_chunk, spec, commit, shard_size=1,
            workers=workers, engine=engine, ray_address=ray_address, unit="flight",
            desc="contingency", progress=progress, log=log, where=out, noun="flights")
    this = {"command": ["art-guidance", *sys.argv[1:]], "engine": engine, "workers": workers,
            "flights": int(writer.done_indices.size) - done0, "wall_s": wall, "status": status,
            "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    runs = _previous_runs(out) + ([this] if this["flights"] else [])
    summary = summarize_directory(out, this, runs)
    if figures and summary["complete"]:
        summary["figures"] = render(out)
    write_json_atomic(out / "summary.json", summary)
    if status == "interrupted":
        log("interrupted: re-run the same command to resume")
    return summary


def _previous_runs(out: Path) -> list[dict]:
    """The invocations that flew flights into `out` before (from its summary.json)."""
    try:
        return list(json.loads((out / "summary.json").read_text()).get("runs", []))
    except (OSError, ValueError):
        return []


if __name__ == "__main__":
    print(markdown_table(json.loads(Path(sys.argv[1]).read_text())), end="")
