"""Benchmark: the windowed replan (receding horizon with a learned terminal target) in the
closed loop, against the full-horizon replan on the same seeds.

Every seed is flown in truth (two-body + J2, navigation and actuation errors, the in-process
guidance with the node's replan policy, chance-constrained, warm start `auto` with the shipped
default model) once per configuration: "full" (every replan re-optimises the whole remainder:
`replan_window_nodes` 0) and "H{h}_{target}" for each window h of `horizons` and each terminal
target of `targets` (`planning.window`). Paired on the seeds: the windowed configuration's
executed delta-v minus the full one's (mean and standard error), its replan times against the
full one's (median and p95 of every replan's wall time, one process per core).

`min_c_cvx` screens the seeds as `bench closed_loop` does (the first `repeats` seeds from
`first_seed` whose initial CVX plan violates passive safety at >= N nodes: the hard family).
`trigger` "sigma" replans on the node's deviation rule and, for a window, when fewer than h / 2
of its nodes are left; "every" replans at every node.

Every process's planner is warmed up before its first flight (`common.warm_up`: the kernels,
the model's first inference); `warm_up_ms` lists the warm-ups, one per process.
"""
from __future__ import annotations

import logging
import tempfile
import time

import numpy as np

from art_guidance.errors import InputError
from art_guidance.planning import GuidancePipeline
from art_guidance.guidance.replan import ReplanSettings
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance, default_settings
from common import warm_up

_LOG = logging.getLogger("bench_mpc")
_PIPELINE: GuidancePipeline | None = None
_WARM_UP_MS: list[float] = []  # this process's warm-up, until a flight reports it [ms]
SOURCES = ("art", "cvx", "scvx", "carry", "waypoint")  # where the windows' targets came from


def _pipeline(model: str | None) -> GuidancePipeline:
    """This process's planner, warmed up as it is made (`common.warm_up`: in a worker process,
    in its first flight, before that flight's first plan)."""
    global _PIPELINE
    if _PIPELINE is None:
        from art_guidance.art.provider import ArtWarmStart

        _PIPELINE = GuidancePipeline(provider=ArtWarmStart.load(model or None))
        _WARM_UP_MS.append(warm_up(_PIPELINE))
    return _PIPELINE


def fly(seed: int, window_nodes: int, target: str, model: str | None = None,
        trigger: str = "sigma", context: bool = False) -> dict:
    """One closed-loop flight of `seed` with a window of `window_nodes` (0: the full
    remainder) to `target`, the learned proposal given the flown steps with `context`; its
    figures (`warm_up_ms`: the planner's warm-up in this process, paid before the flight, in
    the process's first flight only, else None)."""
    pipeline = _pipeline(model)
    warm_up_ms = _WARM_UP_MS.pop() if _WARM_UP_MS else None
    settings = default_settings(pipeline.scenario)
    import dataclasses

    settings = dataclasses.replace(settings, replan_window_nodes=int(window_nodes),
                                   terminal_target=target, art_context=bool(context),
                                   replan_period_s=_every_node_s(pipeline) if trigger == "every"
                                   else settings.replan_period_s)
    with tempfile.TemporaryDirectory(prefix="bench_mpc_") as tmp:
        params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=f"{tmp}/s.json",
                      seed=int(seed), warm_start="auto", errors=True)
        guidance = InProcessGuidance(pipeline, SIM_EPOCH0_NS, settings)
        loop = ClosedLoop(guidance, params, _LOG, settle_s=0.0)
        summary, _ = loop.finish(loop.run(), 0.0)
    results = [r for _, r in guidance.results]
    windows = [r.window for r in results if r.window is not None]
    return {"seed": int(seed), "reached": bool(summary["reached"]), "warm_up_ms": warm_up_ms,
            "dv_mps": float(summary["total_dv_mps"]), "miss_m": float(summary["miss_m"]),
            "replan_ms": [float(r.timings.total) for r in results],
            "replans": len(results),
            "infeasible": sum(r.status.name == "INFEASIBLE" for r in results),
            "why_not_art": _why_not_art(windows),
            "targets": {s: sum(w.target_source == s for w in windows)
                        for s in SOURCES}}


def _why_not_art(windows: list) -> dict:
    """Why windows asked for an ART target ended at another: counts per reason."""
    reasons = {"CVX passively safe: ART not run": "passively safe (C_CVX",
               "rejected by the post hoc check": "rejected by the post hoc check",
               "the window to the ART target was infeasible": "the window to the ART target",
               "ART not run or its output refused": "ART not run"}
    out = {k: 0 for k in reasons}
    out["other"] = 0
    for w in windows:
        if w.target_source != "cvx" or w.reason == "terminal_target cvx":
            continue
        key = next((k for k, v in reasons.items() if v in w.reason), "other")
        out[key] += 1
    return out


def _every_node_s(pipeline: GuidancePipeline) -> float:
    """The node spacing of the scenario's horizon [s] (replan period of trigger "every")."""
    from art_guidance.dynamics import orbital_period_s

    sc = pipeline.scenario
    return 0.999 * sc.n_orbits * orbital_period_s(sc.chief_oe[0]) / (sc.n_nodes - 1)


def _fly_job(job: tuple) -> dict:
    return fly(*job)


def run(repeats: int = 30, first_seed: int = 1000, min_c_cvx: int | None = None,
        horizons: str = "10,20", targets: str = "art,cvx", model: str | None = None,
        workers: int = 1, trigger: str = "sigma", context: str = "off") -> dict:
    """Per seed, the full remainder and each (window, target); paired figures (module
    docstring). `context` "off", "on" (the learned proposal given the flown steps: T-MPC's
    context) or "both" (every configuration both ways, "_ctx" naming the one with it; the
    full-horizon reference is flown without it)."""
    t0 = time.perf_counter()
    hs = [int(h) for h in str(horizons).split(",") if h.strip()]
    ts = [t.strip() for t in str(targets).split(",") if t.strip()]
    for h in hs:
        ReplanSettings(replan_window_nodes=h)  # refused with the reason
    for t in ts:
        ReplanSettings(terminal_target=t)
    n = max(int(repeats), 1)
    if min_c_cvx is None:
        seeds = list(range(int(first_seed), int(first_seed) + n))
        out: dict = {}
    else:
        from common import hard_seeds

        seeds, c_cvx, screened = hard_seeds(GuidancePipeline(), int(first_seed), n,
                                            int(min_c_cvx))
        out = {"min_c_cvx": int(min_c_cvx), "c_cvx": c_cvx, "screened_seeds": screened}
    if context not in ("off", "on", "both"):
        raise InputError("--context", "must be off, on or both", context)
    ctx = {"off": (False,), "on": (True,), "both": (False, True)}[context]
    configs = [("full", 0, "cvx", False)] + [("full_ctx", 0, "cvx", True)] * ("both" == context)
    configs += [(f"H{h}_{t}{'_ctx' * c}", h, t, c) for h in hs for t in ts for c in ctx]
    if context == "on":
        configs[0] = ("full", 0, "cvx", True)
    jobs = [(s, h, t, model, trigger, c) for _, h, t, c in configs for s in seeds]
    from flights import fly_all  # benchmarks/ is on the path

    flights = fly_all(_fly_job, jobs, workers, "bench mpc")
    by = {name: flights[i * len(seeds):(i + 1) * len(seeds)]
          for i, (name, *_) in enumerate(configs)}
    full = by["full"]
    table = {name: summarise(runs, None if name == "full" else full)
             for name, runs in by.items()}
    out.update(seeds=seeds, trigger=trigger, context=context, configs=table,
               warm_up_ms=[r["warm_up_ms"] for r in flights if r["warm_up_ms"] is not None],
               per_seed_dv_mps={name: [round(r["dv_mps"], 4) for r in runs]
                                for name, runs in by.items()},
               wall_s=time.perf_counter() - t0)
    return out


def summarise(runs: list[dict], full: list[dict] | None) -> dict:
    """A configuration's figures; paired against `full` (same seeds) when given."""
    dv = np.array([r["dv_mps"] for r in runs])
    ms = np.array([t for r in runs for t in r["replan_ms"]])
    out = {"reached": int(sum(r["reached"] for r in runs)), "flights": len(runs),
           "dv_mps_mean": float(dv.mean()), "miss_m_max": float(max(r["miss_m"] for r in runs)),
           "replan_ms_median": float(np.median(ms)), "replan_ms_p95": float(np.percentile(ms, 95)),
           "replans_mean": float(np.mean([r["replans"] for r in runs])),
           "infeasible_share": sum(r["infeasible"] for r in runs)
           / max(sum(r["replans"] for r in runs), 1),
           "targets": {k: int(sum(r["targets"][k] for r in runs))
                       for k in SOURCES},
           "why_not_art": {k: int(sum(r["why_not_art"][k] for r in runs))
                           for k in runs[0]["why_not_art"]}}
    if full is not None:
        full_dv = np.array([r["dv_mps"] for r in full])
        d = dv - full_dv
        sem = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
        f_ms = np.array([t for r in full for t in r["replan_ms"]])
        out.update(dv_minus_full_mps_mean=float(d.mean()), dv_minus_full_mps_sem=sem,
                   dv_minus_full_pct_mean_plus_2sem=float(
                       100 * (d.mean() + 2 * (sem if d.size > 1 else 0.0)) / full_dv.mean()),
                   replan_ms_median_vs_full=float(np.median(ms) / np.median(f_ms)),
                   replan_ms_p95_vs_full=float(np.percentile(ms, 95)
                                               / np.percentile(f_ms, 95)))
    return out
