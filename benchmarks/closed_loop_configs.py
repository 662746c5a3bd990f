"""`bench closed_loop --configs`: configurations of the warm start (`cvx`, `auto`) and of the
replan (`fresh`, `carry`: `planning.carry`) flown on the same seeds, paired against
`cvx_fresh` (the module docstring of `bench_closed_loop`)."""
from __future__ import annotations

import dataclasses
import logging
import re
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.errors import InputError
from art_guidance.optim import ScpStatus
from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.guidance.replan import Action
from art_guidance.sim.inprocess import InProcessGuidance, default_settings
from common import warm_up

_LOG = logging.getLogger("bench_closed_loop")
ENDGAME_NODES = 5  # a replan with this many nodes left or fewer belongs to the end game
REFERENCE = "cvx_fresh"
TODAY = "auto_fresh"  # the shipped default before the end game (`auto_fresh_none`)
WARM_STARTS, REPLANS = ("cvx", "auto"), ("fresh", "carry")
# the third part of a name: the end-game policy (planning.yaml `endgame`, with its terminal
# tolerances appended where they are not the configuration's: position [m], velocity [mm/s],
# navigation sigmas, the nodes left over which they grow: keep3m, keep3m20v, keep3m20v4s,
# keep10m20vg10; then "t5": terminal_set_nodes 5 and "x0.3" terminal_set_share 0.3, "a":
# aim_within_tolerance, "f": first_plan_from_both: keep_capt5, keep_cap10m20vt99x0.3f), or a
# crude rule
# (node parameters only: `min_remaining_nodes` 6, and `replan_sigma_threshold` 5 or 8)
ENDGAMES = ("none", "keep", "keep_cap")
CRUDE = {"late6": {"min_remaining_nodes": 6},
         "late6s5": {"min_remaining_nodes": 6, "replan_sigma_threshold": 5.0},
         "late6s8": {"min_remaining_nodes": 6, "replan_sigma_threshold": 8.0}}
DEFAULT = "default"  # the shipped defaults: planning.yaml and guidance_node.yaml as they are
_NUM = r"(\d+(?:\.\d+)?)"
_ENDGAME = re.compile(
    rf"^(none|keep|keep_cap)(?:{_NUM}m)?(?:{_NUM}v)?(?:{_NUM}s)?(?:g(\d+))?(?:t(\d+))?"
    rf"(?:x{_NUM})?(a)?(f)?$")
_PIPELINES: dict[tuple, GuidancePipeline] = {}
_WARM_UPS: dict[tuple, float] = {}  # the warm-ups of this process not reported yet [ms]


@dataclass(frozen=True)
class FlightConfig:
    """What one configuration name flies: the warm start, the planning.yaml fields changed
    from the shipped ones (name, value) and the replan policy's settings changed from the
    node's defaults (name, value)."""

    warm_start: str
    planning: tuple[tuple[str, object], ...] = ()
    settings: tuple[tuple[str, float], ...] = ()


# the end game part's groups -> the planning.yaml fields they set (tolerance [mm/s] scaled)
_FIELDS = (("endgame", str), ("terminal_tolerance_m", float),
           ("terminal_tolerance_mps", lambda v: 1e-3 * float(v)),
           ("terminal_tolerance_sigma", float), ("tolerance_growth_nodes", int),
           ("terminal_set_nodes", int), ("terminal_set_share", float),
           ("aim_within_tolerance", bool),
           ("first_plan_from_both", bool))


def flight_config(name: str) -> FlightConfig:
    """The configuration a name flies (`parse_configs` validated it): `default`, or
    `WARMSTART_REPLAN[_ENDGAME]` (no end game part: `none`, every replan put in force)."""
    if name == DEFAULT:
        return FlightConfig("auto")
    ws, replan, *rest = name.split("_", 2)
    endgame = rest[0] if rest else "none"
    planning = [("replan_warm_start", replan)]
    if endgame in CRUDE:
        return FlightConfig(ws, (*planning, ("endgame", "none")),
                            tuple(sorted(CRUDE[endgame].items())))
    groups = _ENDGAME.match(endgame).groups()
    planning += [(field, kind(g)) for (field, kind), g in zip(_FIELDS, groups) if g]
    return FlightConfig(ws, tuple(planning))


def parse_configs(text: str) -> list[str]:
    """The configurations named in `text` (comma-separated `WARMSTART_REPLAN[_ENDGAME]` or
    `default`), the reference first.

    Raises:
        InputError: an unknown name.
    """
    names = [c.strip() for c in str(text).split(",") if c.strip()]
    for name in names:
        if name == DEFAULT:
            continue
        ws, _, rest = name.partition("_")
        replan, _, endgame = rest.partition("_")
        if ws not in WARM_STARTS or replan not in REPLANS or (
                endgame and endgame not in CRUDE and not _ENDGAME.match(endgame)):
            raise InputError("--configs", f"each must be {DEFAULT!r} or "
                             f"WARMSTART_REPLAN[_ENDGAME] with WARMSTART in {WARM_STARTS}, "
                             f"REPLAN in {REPLANS} and ENDGAME one of {ENDGAMES} (optionally "
                             f"with a terminal tolerance, e.g. keep3m) or {tuple(CRUDE)}", name)
    return [REFERENCE] + [n for n in dict.fromkeys(names) if n != REFERENCE]


def pipeline_for(name: str, model: str | None) -> GuidancePipeline:
    """The planner of a configuration (one per process and configuration), warmed up as it is
    made (`common.warm_up`: in a worker process, in its first flight of the configuration,
    before that flight's first plan)."""
    fc = flight_config(name)
    key = (name, model)
    if key not in _PIPELINES:
        config = GuidanceConfig.load()
        config = config.replace(planning=dataclasses.replace(config.planning,
                                                             **dict(fc.planning)))
        provider = None
        if fc.warm_start == "auto":
            from art_guidance.art.provider import ArtWarmStart

            provider = ArtWarmStart.load(model or None)
        _PIPELINES[key] = GuidancePipeline(config, provider)
        _WARM_UPS[key] = warm_up(_PIPELINES[key])
    return _PIPELINES[key]


def fly(seed: int, name: str, model: str | None = None) -> dict:
    """One flight of `seed` under configuration `name`; its figures (`warm_up_ms`: the
    warm-up of its planner in this process, paid before the flight, in the process's first
    flight of the configuration only, else None)."""
    pipeline = pipeline_for(name, model)
    fc = flight_config(name)
    warm_up_ms = _WARM_UPS.pop((name, model), None)
    settings = dataclasses.replace(default_settings(pipeline.scenario), **dict(fc.settings))
    with tempfile.TemporaryDirectory(prefix="bench_closed_loop_") as tmp:
        params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=f"{tmp}/s.json",
                      seed=int(seed), warm_start=fc.warm_start, errors=True)
        guidance = InProcessGuidance(pipeline, SIM_EPOCH0_NS, settings)
        loop = ClosedLoop(guidance, params, _LOG, settle_s=0.0)
        summary, _ = loop.finish(loop.run(), 0.0)
    replans = [r for _, r in guidance.results][1:]  # the first plan: a fresh target
    core = guidance.core
    return {"seed": int(seed), "reached": bool(summary["reached"]), "warm_up_ms": warm_up_ms,
            "dv_mps": float(summary["total_dv_mps"]), "miss_m": float(summary["miss_m"]),
            "velocity_error_mps": float(summary["velocity_error_mps"]),
            "min_safety_margin_m": summary["min_safety_margin_m"],
            "replans": len(replans),
            "iterations": [int(r.scp_iterations_all) for r in replans],
            "replan_ms": [float(r.timings.total) for r in replans],
            "at_cap": sum(r.status is ScpStatus.MAX_ITERATIONS for r in replans),
            "carried": sum(bool(r.carry and r.carry.carried) for r in replans),
            "kept": sum(bool(r.carry and r.carry.kept) for r in replans),
            "guards": sum(bool(r.carry and r.carry.guard) for r in replans),
            "rescues": sum(bool(r.carry and r.carry.carried and not r.carry.guard
                                and r.discarded is not None) for r in replans),
            "kept_in_force": 0 if core is None else int(core.stats["kept"]),
            "capped": 0 if core is None else int(core.stats["capped"]),
            "aimed": 0 if core is None else int(core.stats["aimed"]),
            "in_set": 0 if core is None else int(core.stats["in_set"]),
            **growth(guidance.results, guidance.actions),
            "why_fresh": _why_fresh(replans)}


def growth(results: list, actions: list) -> dict:
    """Where a flight's delta-v goes, over its plans (the first plan of the flight: a fresh
    target, its cost `first_plan_dv_mps`): every later plan put in force grows the flight by
    its cost minus what the plan in force it replaced still planned to spend from the fix
    (`CarriedPlan.remaining_mps` of its request), summed per flight with 5 or fewer nodes
    left (`endgame_growth_mps`) and with more (`midflight_growth_mps`); `replan_growth_mps`:
    each; `not_converged`: replans (put in force or not) whose plan did not converge, by
    nodes left (<= 5, > 5), and `replans_by_nodes_left` their counts."""
    first = float(results[0][1].cost_mps) if results else float("nan")
    end = mid = 0.0
    each = []
    not_converged, counts = [0, 0], [0, 0]
    for (_, r), action in list(zip(results, actions))[1:]:
        n_left = len(r.epochs_s)
        late = int(n_left > ENDGAME_NODES)
        counts[late] += 1
        not_converged[late] += int(r.status is not ScpStatus.CONVERGED)
        carry = None if r.request is None else r.request.carry
        if action is not Action.ACTIVATED or carry is None:
            continue
        g = float(r.cost_mps) - carry.remaining_mps
        each.append(g)
        if late:
            mid += g
        else:
            end += g
    return {"first_plan_dv_mps": first, "endgame_growth_mps": end,
            "midflight_growth_mps": mid, "replan_growth_mps": each,
            "not_converged": not_converged, "replans_by_nodes_left": counts}


def _why_fresh(replans: list) -> dict:
    """Why replans did not carry: counts per reason (its words before any figure)."""
    out: dict[str, int] = {}
    for r in replans:
        if r.carry is not None and not r.carry.carried:
            key = r.carry.reason.split(":")[0].split("(")[0].strip()
            out[key] = out.get(key, 0) + 1
    return out


def _fly_job(job: tuple) -> dict:
    return fly(*job)


def compare_configs(configs: str, repeats: int = 30, first_seed: int = 0,
                    min_c_cvx: int | None = None, model: str | None = None,
                    workers: int = 1, engine: str = "local",
                    ray_address: str | None = None) -> dict:
    """Every configuration of `configs` on the same seeds (the hard family with `min_c_cvx`),
    on `workers` local processes or Ray (`engine` "ray", `ray_address`: `flights.fly_all`)."""
    names = parse_configs(configs)
    t0 = time.perf_counter()
    n = max(int(repeats), 1)
    out: dict = {}
    if min_c_cvx is None:
        seeds = list(range(int(first_seed), int(first_seed) + n))
    else:
        from common import hard_seeds

        seeds, c_cvx, screened = hard_seeds(GuidancePipeline(), int(first_seed), n,
                                            int(min_c_cvx))
        out.update(min_c_cvx=int(min_c_cvx), c_cvx=c_cvx, screened_seeds=screened)
    # seed after seed, every configuration in turn: a load on the machine meanwhile falls on
    # all of them alike
    jobs = [(s, name, model) for s in seeds for name in names]
    from flights import fly_all  # benchmarks/ is on the path

    flights = fly_all(_fly_job, jobs, workers, "bench closed_loop", engine, ray_address)
    by = {name: flights[i::len(names)] for i, name in enumerate(names)}
    summaries = {name: summarise(runs, by[REFERENCE], name) for name, runs in by.items()}
    if TODAY in by:  # the default before the end game: every configuration paired against it
        for name, runs in by.items():
            summaries[name].update(paired(runs, by[TODAY], TODAY))
    out.update(seeds=seeds, configs=summaries,
               warm_up_ms={name: [r["warm_up_ms"] for r in runs if r["warm_up_ms"] is not None]
                           for name, runs in by.items()},
               per_seed_dv_mps={name: [round(r["dv_mps"], 4) for r in runs]
                                for name, runs in by.items()},
               wall_s=time.perf_counter() - t0)
    return out


def summarise(runs: list[dict], reference: list[dict], name: str) -> dict:
    """A configuration's figures, paired against the reference's flights of the same seeds."""
    dv = np.array([r["dv_mps"] for r in runs])
    d = dv - np.array([r["dv_mps"] for r in reference])
    ms = np.array([t for r in runs for t in r["replan_ms"]])
    replans = sum(r["replans"] for r in runs)
    worst = np.argsort(-d)[:5]
    carry = "_carry" in name or (name == DEFAULT and GuidanceConfig.load().planning
                                 .replan_warm_start == "carry")
    out = {
        "reached": int(sum(r["reached"] for r in runs)), "flights": len(runs),
        "dv_mps_mean": float(dv.mean()), "miss_m_max": float(max(r["miss_m"] for r in runs)),
        "replans_mean": float(np.mean([r["replans"] for r in runs])),
        "dv_minus_cvx_fresh_mps_mean": float(d.mean()),
        "dv_minus_cvx_fresh_mps_sem": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1
        else None,
        "dv_minus_cvx_fresh_mps_max": float(d.max()),
        "worst_seeds": [{"seed": runs[i]["seed"], "dv_minus_cvx_fresh_mps": float(d[i])}
                        for i in worst],
        "scvx_iterations_per_replan_mean": _mean([i for r in runs for i in r["iterations"]]),
        "scvx_iterations_per_replan_p95": _p95([i for r in runs for i in r["iterations"]]),
        "replan_ms_median": float(np.median(ms)) if ms.size else None,
        "replan_ms_p95": float(np.percentile(ms, 95)) if ms.size else None,
        "max_iterations_share": sum(r["at_cap"] for r in runs) / max(replans, 1),
        "carried_kept_share": sum(r["kept"] for r in runs) / max(replans, 1) if carry
        else None,
        "carried_share": sum(r["carried"] for r in runs) / max(replans, 1) if carry else None,
        "guard_fired": int(sum(r["guards"] for r in runs)),
        "rescues": int(sum(r["rescues"] for r in runs)),
        "why_fresh": _merge([r["why_fresh"] for r in runs]),
    }
    return {**where_dv_goes(runs), **out}


def where_dv_goes(runs: list[dict]) -> dict:
    """Where the flights' delta-v goes (`growth`), their accuracy in truth and their realised
    passive safety, as means over the flights unless named otherwise [m/s, m]."""
    each = [g for r in runs for g in r["replan_growth_mps"]]
    margins = [r["min_safety_margin_m"] for r in runs if r["min_safety_margin_m"] is not None]
    counts = np.sum([r["replans_by_nodes_left"] for r in runs], axis=0)
    failed = np.sum([r["not_converged"] for r in runs], axis=0)
    return {
        "first_plan_dv_mps_mean": float(np.mean([r["first_plan_dv_mps"] for r in runs])),
        "flown_minus_first_mps_mean": float(np.mean([r["dv_mps"] - r["first_plan_dv_mps"]
                                                     for r in runs])),
        "endgame_growth_mps_mean": float(np.mean([r["endgame_growth_mps"] for r in runs])),
        "midflight_growth_mps_mean": float(np.mean([r["midflight_growth_mps"] for r in runs])),
        "largest_replan_growth_mps": float(max(each)) if each else 0.0,
        "miss_m_mean": float(np.mean([r["miss_m"] for r in runs])),
        "velocity_error_mps_mean": float(np.mean([r["velocity_error_mps"] for r in runs])),
        "velocity_error_mps_max": float(max(r["velocity_error_mps"] for r in runs)),
        "min_safety_margin_m_min": float(min(margins)) if margins else None,
        "not_converged_share_endgame": float(failed[0] / max(counts[0], 1)),
        "not_converged_share_midflight": float(failed[1] / max(counts[1], 1)),
        "replans_kept_in_force_mean": float(np.mean([r["kept_in_force"] for r in runs])),
        "replans_capped": int(sum(r["capped"] for r in runs)),
        "replans_aimed_mean": float(np.mean([r["aimed"] for r in runs])),
        "replans_in_terminal_set_mean": float(np.mean([r["in_set"] for r in runs])),
    }


def paired(runs: list[dict], reference: list[dict], name: str) -> dict:
    """Delta-v of `runs` minus the `reference` flights of the same seeds, named after it [m/s]:
    mean, sem, the largest and its seed."""
    d = np.array([r["dv_mps"] for r in runs]) - np.array([r["dv_mps"] for r in reference])
    i = int(np.argmax(d))
    return {f"dv_minus_{name}_mps_mean": float(d.mean()),
            f"dv_minus_{name}_mps_sem": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1
            else None,
            f"dv_minus_{name}_mps_max": float(d[i]),
            f"dv_minus_{name}_worst_seed": runs[i]["seed"]}


def _mean(x: list) -> float | None:
    return float(np.mean(x)) if len(x) else None


def _p95(x: list) -> float | None:
    return float(np.percentile(x, 95)) if len(x) else None


def _merge(counts: list[dict]) -> dict:
    out: dict[str, int] = {}
    for c in counts:
        for k, v in c.items():
            out[k] = out.get(k, 0) + v
    return out
