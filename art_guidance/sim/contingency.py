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
"""
from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.config import MODES, GuidanceConfig
from art_guidance.data.storage import DatasetWriter, load_dataset, read_manifest, sha256_bytes
from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic
from art_guidance.jobs import check_run_options, run_missing
from art_guidance.sim.faults import ZONES, Fault

KIND = "contingency"
FORMAT = 1
NODES_MAX = 128            # per-flight loss columns (a flight has n_nodes + 1 losses at most)
CONFIDENCE = 0.95
DESIGN_RATE = 1e-3         # the chance constraint's probability per node
WORST_SHOWN = 10
HISTOGRAM_EDGES_M = (0, 10, 25, 50, 100, 200, 500, 1000)  # post-fault margin bins (+-inf added)
CONFIGS = ((True, "auto"), (True, "cvx"), (False, "auto"), (False, "cvx"))
_LOG = logging.getLogger("art_guidance.contingency")
_PIPELINES: dict[tuple[bool, str], object] = {}  # per worker process


@dataclass(frozen=True)
class ContingencySpec:
    """What a Monte Carlo flies (picklable; sent once to every worker).

    Attributes:
        configs: (chance_constrained, warm_start) per configuration.
        n_seeds: seeds per configuration: base_seed .. base_seed + n_seeds - 1.
        base_seed: the first seed.
        missed_per_seed: missed-burn flights per (configuration, seed).
        min_missed_dv_mps: smallest commanded burn a missed fault is drawn on [m/s].
        waypoint: the terminal waypoint.
        errors: navigation and actuation errors on.
    """

    configs: tuple[tuple[bool, str], ...] = CONFIGS
    n_seeds: int = 24
    base_seed: int = 0
    missed_per_seed: int = 3
    min_missed_dv_mps: float = 0.01
    waypoint: str = "plus_vbar"
    errors: bool = True

    @property
    def n_flights(self) -> int:
        """Rows of the output: one per (configuration, seed)."""
        return len(self.configs) * self.n_seeds

    def flight(self, index: int) -> tuple[int, int]:
        """(configuration index, seed) of row `index`."""
        return index // self.n_seeds, self.base_seed + index % self.n_seeds

    def label(self, config: int) -> str:
        """"chance/auto", "deterministic/cvx", ..."""
        chance, warm = self.configs[config]
        return f"{'chance' if chance else 'deterministic'}/{warm}"


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
    from art_guidance.sim.inprocess import InProcessGuidance

    chance, warm = spec.configs[config]
    params = dict(PARAMETERS, rtn0=None, png_path="", summary_path="", seed=int(seed),
                  waypoint=spec.waypoint, chance_constrained=chance, warm_start=warm,
                  errors=spec.errors, fault="" if fault is None else fault.kind,
                  fault_node=0 if fault is None else fault.node)
    loop = ClosedLoop(InProcessGuidance(_pipeline(chance, warm), SIM_EPOCH0_NS), params, _LOG,
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


# --------------------------------------------------------------------------- driver
def header(spec: ContingencySpec, config: GuidanceConfig) -> dict:
    """The output directory's manifest header; a resume with other options is refused."""
    from art_guidance.art.provider import default_model_path, pinned_sha256
    from art_guidance.sim.inprocess import default_settings

    models = {mode: pinned_sha256(default_model_path(mode))
              for mode in MODES}
    identity = {"format": FORMAT, "spec": asdict(spec), "models": models,
                "guidance_config_sha256": config.sha256(),
                "replan": asdict(default_settings(config.scenario))}  # what `fly` replans by
    return {"mode": KIND, "base_seed": spec.base_seed, "n": spec.n_flights,
            "seed_rule": "row i: configs[i // n_seeds], seed base_seed + i % n_seeds",
            "config_sha256": sha256_bytes(json.dumps(identity, sort_keys=True).encode()),
            "contingency": identity, "art_guidance_version": __version__,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


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
    for chance, warm in spec.configs:
        if warm not in ("auto", "cvx", "art"):
            raise InputError("configs", "warm start must be auto, art or cvx", warm)
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


# --------------------------------------------------------------------------- summary
def upper_bound(entries: int, trials: int, confidence: float = CONFIDENCE) -> float | None:
    """One-sided exact (Clopper-Pearson) upper bound of a probability (None without trials)."""
    if trials <= 0:
        return None
    if entries >= trials:
        return 1.0
    from scipy.stats import beta

    return float(beta.ppf(confidence, entries + 1, trials - entries))


def spec_of(head: dict) -> ContingencySpec:
    """The `ContingencySpec` a contingency directory's header records."""
    stored = head["contingency"]["spec"]
    return ContingencySpec(**dict(stored, configs=tuple(tuple(c) for c in stored["configs"])))


def read_rows(out: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and the committed rows of a contingency directory."""
    head = read_manifest(out)[0]
    if head.get("mode") != KIND:
        raise InputError("--out", "does not hold a contingency Monte Carlo", str(out))
    return head, load_dataset(out, require_complete=False)


def _previous_runs(out: Path) -> list[dict]:
    """The invocations that flew flights into `out` before (from its summary.json)."""
    try:
        return list(json.loads((out / "summary.json").read_text()).get("runs", []))
    except (OSError, ValueError):
        return []


def summarize_directory(out: str | Path, this: dict | None = None,
                        runs: list[dict] | None = None) -> dict:
    """Entry rates, bounds, worst margins and missed-burn outcomes per configuration; `this`
    is the invocation that produced it, `runs` every invocation that flew flights."""
    head, rows = read_rows(out)
    spec = spec_of(head)
    per = []
    for c in range(len(spec.configs)):
        sel = rows["config"] == c if rows else np.zeros(0, bool)
        per.append({"config": spec.label(c), **_config_summary(rows, sel)})
    done = int(rows["index"].size) if rows else 0
    wall = float(rows["wall_s"].sum()) if rows else 0.0
    losses = sum(p["losses"]["n"] for p in per)
    identity = head["contingency"]
    return {"kind": KIND, "spec": identity["spec"], "models": identity["models"],
            "replan": identity.get("replan"), "flights_done": done, "flights": spec.n_flights,
            "complete": done == spec.n_flights, "design_rate_per_node": DESIGN_RATE,
            "confidence": CONFIDENCE, "cpu_s": wall,
            "losses_per_cpu_s": losses / wall if wall > 0 else None,
            "configs": per, **({"run": this} if this else {}),
            **({"runs": runs} if runs is not None else {})}


def _config_summary(rows: dict, sel: np.ndarray) -> dict:
    if not sel.any():
        return {"flights": 0, "losses": {"n": 0}, "missed": {"n": 0}}
    r = {k: v[sel] for k, v in rows.items()}  # this configuration's flights
    return {"flights": int(sel.sum()),
            "nominal": {"reached": int(r["reached"].sum()), "miss_m": _dist(r["miss_m"]),
                        "total_dv_mps": _dist(r["total_dv_mps"])},
            "losses": _loss_summary(r), "missed": _missed_summary(r)}


def _loss_summary(r: dict) -> dict:
    """Entries, bounds, margins and the worst losses of one configuration's flights."""
    node, margin_all = r["loss_node"], r["loss_margin_m"]
    valid = node >= 1
    margin = margin_all[valid]
    n, entries = int(valid.sum()), int((margin < 0).sum())
    flights_entered = int(np.any((margin_all < 0) & valid, axis=1).sum())
    worst = []
    for flat in np.argsort(margin_all, axis=None)[:WORST_SHOWN]:
        i, j = np.unravel_index(flat, node.shape)
        if valid[i, j]:
            worst.append({"seed": int(r["seed"][i]), "node": int(node[i, j]),
                          "min_margin_m": round(float(margin_all[i, j]), 3),
                          "zone": ZONES[int(r["loss_zone"][i, j])],
                          "lost_burn_mps": _round(r["loss_dv_cmd_mps"][i, j])})
    zones = r["loss_zone"][valid]
    edges = np.array([-np.inf, *HISTOGRAM_EDGES_M, np.inf])
    return {"n": n, "entries": entries, "per_1000": 1e3 * entries / max(n, 1),
            "upper_95_per_1000": _round(1e3 * (upper_bound(entries, n) or np.nan)),
            "flights_with_entry": flights_entered,
            "flights_upper_95": _round(upper_bound(flights_entered, len(node))),
            "min_margin_m": _dist(margin),
            "by_zone": {z: _dist(margin[zones == k]) for k, z in enumerate(ZONES)},
            "histogram_m": {"edges": ["-inf", *HISTOGRAM_EDGES_M, "inf"],
                            "counts": np.histogram(margin, bins=edges)[0].tolist()},
            "worst": worst}


def _missed_summary(r: dict) -> dict:
    """Outcomes of one configuration's missed-burn flights."""
    mm = r["missed_node"] >= 0
    if not mm.any():
        return {"n": 0}
    reached = r["missed_reached"][mm]
    seeds = np.broadcast_to(r["seed"][:, None], mm.shape)[mm]
    return {"n": int(mm.sum()), "reached": int(reached.sum()),
            "reached_share": float(reached.mean()),
            "entered": int(r["missed_entered"][mm].sum()),
            "min_post_fault_margin_m": _round(np.nanmin(r["missed_margin_m"][mm])),
            "missed_burn_mps": _dist(r["missed_dv_cmd_mps"][mm]),
            "miss_m": _dist(r["missed_miss_m"][mm]),
            "replanned_share": float((r["missed_replans_after"][mm] > 0).mean()),
            "not_reached": [{"seed": int(s), "node": int(k), "miss_m": _round(d)}
                            for s, k, d in zip(seeds, r["missed_node"][mm],
                                               r["missed_miss_m"][mm])
                            if d > 50.0][:WORST_SHOWN]}


def _round(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 4)


def _dist(x: np.ndarray) -> dict:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "min": _round(x.min()), "q01": _round(np.percentile(x, 1)),
            "median": _round(np.median(x)), "max": _round(x.max())}


# --------------------------------------------------------------------------- figures
def render(out: str | Path, n_worst: int = 6) -> list[str]:
    """contingency_margins.png (histogram of the post-fault minimum distance per
    configuration) and contingency_worst.png (RT plane: per configuration, the closest loss of
    each of the `n_worst` flights that came closest, its truth drift recomputed from the
    stored state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    from art_guidance.config import ScenarioConfig
    from art_guidance.sim.faults import free_drift_check, safety_duration_s

    out = Path(out)
    head, rows = read_rows(out)
    spec = spec_of(head)
    labels = [spec.label(c) for c in range(len(spec.configs))]
    scenario = ScenarioConfig.from_yaml(None)
    fig = Figure(figsize=(10, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    bins = np.linspace(-50.0, 1500.0, 63)
    for c, label in enumerate(labels):
        sel = rows["config"] == c
        m = rows["loss_margin_m"][sel][rows["loss_node"][sel] >= 1]
        if m.size:
            ax.hist(np.clip(m, bins[0], bins[-1]), bins=bins, histtype="step", lw=1.3,
                    label=f"{label}: {m.size} losses, {(m < 0).sum()} entries, "
                    f"min {m.min():.1f} m")
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("post-fault minimum distance to the ellipsoid in force, truth [m] "
                  "(clipped to the axis)")
    ax.set_ylabel("losses")
    ax.legend(fontsize=8)
    ax.set_title("thruster loss at every node of the flown closed loop (errors on), one-orbit "
                 "truth drift", fontsize=9)
    fig.tight_layout()
    paths = [str(out / "contingency_margins.png")]
    fig.savefig(paths[0])

    n_rows = (len(labels) + 1) // 2
    fig = Figure(figsize=(12, 5.5 * n_rows), dpi=100)
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(n_rows, 2)).ravel()
    for ax in axes[len(labels):]:
        ax.set_visible(False)
    a_m = float(np.linalg.norm(rows["loss_state"][0, 0, :3])) if rows else 6.9e6
    duration = safety_duration_s(scenario, a_m)
    for c, (ax, label) in enumerate(zip(axes, labels)):
        for axes_m, color in ((scenario.ae_semi_axes_m, "tab:orange"),
                              (scenario.koz_semi_axes_m, "tab:red")):
            ax.add_patch(Ellipse((0, 0), 2 * axes_m[1], 2 * axes_m[0], fill=False,
                                 color=color, lw=1.2))
        sel = np.flatnonzero(rows["config"] == c)
        margins = np.where(rows["loss_node"][sel] >= 1, rows["loss_margin_m"][sel], np.inf)
        worst_j = np.argmin(margins, axis=1)  # the closest loss of every flight
        worst = margins[np.arange(sel.size), worst_j]
        for i in np.argsort(worst)[:n_worst]:
            j = worst_j[i]
            if not np.isfinite(margins[i, j]):
                continue
            r = sel[i]
            state = rows["loss_state"][r, j]
            check = free_drift_check(state[:6], state[6:], rows["loss_t0_s"][r, j], duration,
                                     scenario, ZONES[int(rows["loss_zone"][r, j])])
            line, = ax.plot(check.rtn[:, 1], check.rtn[:, 0], lw=1.0,
                            label=f"seed {rows['seed'][r]} node {rows['loss_node'][r, j]}: "
                            f"{check.min_margin_m:.1f} m")
            ax.plot(check.closest_rtn_m[1], check.closest_rtn_m[0], "x",
                    color=line.get_color())
        ax.plot(0, 0, "k+")
        lim = 1.6 * max(scenario.ae_semi_axes_m)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.grid(True, lw=0.3)
        ax.set_xlabel("along-track T [m]")
        ax.set_ylabel("radial R [m]")
        ax.set_title(f"{label}: the closest post-fault drift of the {n_worst} closest "
                     "flights", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    paths.append(str(out / "contingency_worst.png"))
    fig.savefig(paths[1])
    return paths


# --------------------------------------------------------------------------- report
TABLE_BEGIN, TABLE_END = "<!-- contingency-table:begin -->", "<!-- contingency-table:end -->"


def markdown_table(summary: dict) -> str:
    """The results of a summary as two markdown tables (losses; missed burns)."""
    def num(x: object, fmt: str = "{:.1f}") -> str:
        return "-" if x is None else fmt.format(x)

    lines = ["| configuration | flights | losses | entries | per 1,000 (95 % upper) | flights "
             "with an entry | min margin AE [m] | min margin KOZ [m] | 1st pct. [m] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c in summary["configs"]:
        loss = c["losses"]
        if not loss["n"]:
            continue
        zone = loss["by_zone"]
        lines.append(
            f"| {c['config']} | {c['flights']} | {loss['n']:,} | {loss['entries']} | "
            f"{loss['per_1000']:.2f} ({num(loss['upper_95_per_1000'], '{:.2f}')}) | "
            f"{loss['flights_with_entry']} | "
            f"{num(zone['approach_ellipsoid'].get('min'))} | "
            f"{num(zone['keep_out_zone'].get('min'))} | {num(loss['min_margin_m']['q01'])} |")
    lines += ["", "| configuration | missed burns | missed burn median [m/s] | reached | "
              "replanned | post-fault entries | min post-fault margin [m] | miss median / max "
              "[m] |", "|---|---|---|---|---|---|---|---|"]
    for c in summary["configs"]:
        m = c["missed"]
        if not m["n"]:
            continue
        lines.append(
            f"| {c['config']} | {m['n']} | {m['missed_burn_mps']['median']:.3f} | "
            f"{m['reached']} ({100 * m['reached_share']:.1f} %) | "
            f"{100 * m['replanned_share']:.0f} % | {m['entered']} | "
            f"{num(m['min_post_fault_margin_m'])} | {m['miss_m']['median']:.1f} / "
            f"{m['miss_m']['max']:.1f} |")
    cpu = summary.get("cpu_s") or 0.0
    lines += ["", f"{summary['flights_done']} flights, {cpu / 3600:.2f} CPU hours, "
              f"{num(summary.get('losses_per_cpu_s'), '{:.2f}')} losses per CPU second "
              "(flights with their missed-burn repeats and checks)."]
    return "\n".join(lines) + "\n"


def table_in_doc(text: str) -> str:
    """The table between the contingency markers of a documentation page."""
    return text[text.index(TABLE_BEGIN) + len(TABLE_BEGIN):text.index(TABLE_END)].strip("\n") \
        + "\n"


if __name__ == "__main__":
    print(markdown_table(json.loads(Path(sys.argv[1]).read_text())), end="")
