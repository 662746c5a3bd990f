"""`bench closed_loop --configs`: configurations of the warm start (`cvx`, `auto`) and of the
replan (`fresh`, `carry`: `planning.carry`) flown on the same seeds, paired against
`cvx_fresh` (the module docstring of `bench_closed_loop`)."""
from __future__ import annotations

import dataclasses
import logging
import tempfile
import time

import numpy as np

from art_guidance.config import GuidanceConfig
from art_guidance.errors import InputError
from art_guidance.optim import ScpStatus
from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
from art_guidance.sim.inprocess import InProcessGuidance
from common import warm_up

_LOG = logging.getLogger("bench_closed_loop")
REFERENCE = "cvx_fresh"
WARM_STARTS, REPLANS = ("cvx", "auto"), ("fresh", "carry")
_PIPELINES: dict[tuple, GuidancePipeline] = {}
_WARM_UPS: dict[tuple, float] = {}  # the warm-ups of this process not reported yet [ms]


def parse_configs(text: str) -> list[str]:
    """The configurations named in `text` (comma-separated `WARMSTART_REPLAN`), the reference
    first.

    Raises:
        InputError: an unknown name.
    """
    names = [c.strip() for c in str(text).split(",") if c.strip()]
    for name in names:
        ws, _, replan = name.partition("_")
        if ws not in WARM_STARTS or replan not in REPLANS:
            raise InputError("--configs", f"each must be WARMSTART_REPLAN with WARMSTART in "
                             f"{WARM_STARTS} and REPLAN in {REPLANS}", name)
    return [REFERENCE] + [n for n in dict.fromkeys(names) if n != REFERENCE]


def pipeline_for(name: str, model: str | None) -> GuidancePipeline:
    """The planner of a configuration (one per process and configuration), warmed up as it is
    made (`common.warm_up`: in a worker process, in its first flight of the configuration,
    before that flight's first plan)."""
    ws, _, replan = name.partition("_")
    key = (ws, replan, model)
    if key not in _PIPELINES:
        config = GuidanceConfig.load()
        config = config.replace(planning=dataclasses.replace(config.planning,
                                                             replan_warm_start=replan))
        provider = None
        if ws == "auto":
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
    ws, _, replan = name.partition("_")
    warm_up_ms = _WARM_UPS.pop((ws, replan, model), None)
    with tempfile.TemporaryDirectory(prefix="bench_closed_loop_") as tmp:
        params = dict(PARAMETERS, rtn0=None, png_path="", summary_path=f"{tmp}/s.json",
                      seed=int(seed), warm_start=name.partition("_")[0], errors=True)
        guidance = InProcessGuidance(pipeline, SIM_EPOCH0_NS)
        loop = ClosedLoop(guidance, params, _LOG, settle_s=0.0)
        summary, _ = loop.finish(loop.run(), 0.0)
    replans = [r for _, r in guidance.results][1:]  # the first plan: a fresh target
    return {"seed": int(seed), "reached": bool(summary["reached"]), "warm_up_ms": warm_up_ms,
            "dv_mps": float(summary["total_dv_mps"]), "miss_m": float(summary["miss_m"]),
            "replans": len(replans),
            "iterations": [int(r.scp_iterations_all) for r in replans],
            "replan_ms": [float(r.timings_ms["total"]) for r in replans],
            "at_cap": sum(r.status is ScpStatus.MAX_ITERATIONS for r in replans),
            "carried": sum(bool(r.carry and r.carry.carried) for r in replans),
            "kept": sum(bool(r.carry and r.carry.kept) for r in replans),
            "guards": sum(bool(r.carry and r.carry.guard) for r in replans),
            "rescues": sum(bool(r.carry and r.carry.carried and not r.carry.guard
                                and r.discarded is not None) for r in replans),
            "why_fresh": _why_fresh(replans)}


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
                    workers: int = 1) -> dict:
    """Every configuration of `configs` on the same seeds (the hard family with `min_c_cvx`)."""
    names = parse_configs(configs)
    t0 = time.perf_counter()
    n = max(int(repeats), 1)
    out: dict = {}
    if min_c_cvx is None:
        seeds = list(range(int(first_seed), int(first_seed) + n))
    else:
        from bench_closed_loop import hard_seeds

        seeds, c_cvx, screened = hard_seeds(GuidancePipeline(), int(first_seed), n,
                                            int(min_c_cvx))
        out.update(min_c_cvx=int(min_c_cvx), c_cvx=c_cvx, screened_seeds=screened)
    # seed after seed, every configuration in turn: a load on the machine meanwhile falls on
    # all of them alike
    jobs = [(s, name, model) for s in seeds for name in names]
    from flights import fly_all  # benchmarks/ is on the path

    flights = fly_all("closed_loop_configs", jobs, workers, "bench closed_loop")
    by = {name: flights[i::len(names)] for i, name in enumerate(names)}
    out.update(seeds=seeds, configs={name: summarise(runs, by[REFERENCE], name)
                                     for name, runs in by.items()},
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
    carry = name.endswith("_carry")
    return {
        "reached": int(sum(r["reached"] for r in runs)), "flights": len(runs),
        "dv_mps_mean": float(dv.mean()), "miss_m_max": float(max(r["miss_m"] for r in runs)),
        "replans_mean": float(np.mean([r["replans"] for r in runs])),
        "dv_minus_cvx_fresh_mps_mean": float(d.mean()),
        "dv_minus_cvx_fresh_mps_sem": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1
        else None,
        "dv_minus_cvx_fresh_mps_max": float(d.max()),
        "worst_seeds": [{"seed": runs[i]["seed"], "dv_minus_cvx_fresh_mps": float(d[i])}
                        for i in worst],
        "scvx_iterations_per_replan_mean": float(np.mean([i for r in runs
                                                          for i in r["iterations"]])),
        "replan_ms_median": float(np.median(ms)), "replan_ms_p95": float(np.percentile(ms, 95)),
        "max_iterations_share": sum(r["at_cap"] for r in runs) / max(replans, 1),
        "carried_kept_share": sum(r["kept"] for r in runs) / max(replans, 1) if carry
        else None,
        "carried_share": sum(r["carried"] for r in runs) / max(replans, 1) if carry else None,
        "guard_fired": int(sum(r["guards"] for r in runs)),
        "rescues": int(sum(r["rescues"] for r in runs)),
        "why_fresh": _merge([r["why_fresh"] for r in runs]),
    }


def _merge(counts: list[dict]) -> dict:
    out: dict[str, int] = {}
    for c in counts:
        for k, v in c.items():
            out[k] = out.get(k, 0) + v
    return out
