"""Benchmark: the ART proposal as the planner makes it, the fast path against the reference.

For chance-constrained `plan` scenarios (seeds FIRST.., held out from the shipped models'
training data) on which CVX is not passively safe (`auto` runs ART only there), the shipped
default model proposes a warm start (`ArtWarmStart.propose`: the conditioning sweep with the C
update at every step, then the judging of its candidates), on the default runtime
(`art_runtime` auto), one thread, in one process:

- `fast`: the planner's path (the speculative rollout: several steps decoded, then their
  violations searched at once, `rollout(speculate=True)`);
- `step`: the same with one step at a time (`speculate=False`, the speculative rollout's
  oracle), to measure what speculation saves;
- `reference`: the step-by-step proposal through the previous safety path, the K = 1 oracles
  of the fast one: every rollout step's violations decided by the certified sign-only minimum
  (`DriftArcs.minimum(sign_only=True)`, with its t* and candidate bookkeeping) instead of
  `DriftArcs.violated`, every candidate judged by its own full `PassiveSafety.evaluate`
  instead of one sign-only `violations_batch` over all of them.

The three alternate scenario by scenario; the proposals must be identical (controls and
constraint-to-go), and the numbers are medians of wall and CPU (process) time with the paired
ratios. The fast path's time is split into the C update (`violated`), the candidates'
terminal corrections, their safety search, and the rest (transformer, dynamics, bookkeeping),
and into the transformer (the decoder's `step_numpy`, decoded steps counted: speculation
decodes again the steps after a missed prediction) and the numerics (everything else);
`sweep_K_ms` times proposals with sweeps of K reward scales (the transformer's work grows
with the batch: at batch 8 it is arithmetic, not per-call overhead).

Before the first timed proposal the process is warmed up (`common.warm_up`: the kernels loaded,
the model run once on a canned transfer and once on the first scenario); its wall time is
`warm_up_ms`, apart from the timings.

    art-guidance bench proposal --repeats 40 --first-seed 20000 --json out/proposal.json
"""
from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np
import torch

import art_guidance.art.provider as provider_module
from art_guidance.art.provider import ArtWarmStart
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from common import StepTimer, unsafe_cases, warm_up

SWEEPS = {1: (1.0,), 2: (0.9, 1.1), 4: (0.85, 0.95, 1.05, 1.2)}  # and 8: the default


class _Reference:
    """A PassiveSafety whose rollout decisions and candidate judging take the reference path."""

    def __init__(self, safety) -> None:
        self._safety = safety

    def __getattr__(self, name: str):
        return getattr(self._safety, name)

    def violated(self, nodes, roe_m, dv_rtn_mps, z_m):  # the rollout loop's form
        s = self._safety
        items = s._items_at(nodes if np.ndim(nodes) else int(nodes), roe_m, dv_rtn_mps, z_m)
        return s.arcs.minimum(items, sign_only=True).margin < 0.0

    def violations_batch(self, roe_m, dv_rtn_mps):
        return np.stack([self._safety.evaluate(r, u).violation.astype(bool)
                         for r, u in zip(roe_m, dv_rtn_mps)])


class _Timed:
    """A PassiveSafety that adds up the time of the rollout's C update and of the judging's
    safety search."""

    def __init__(self, safety) -> None:
        self._safety, self.c_update_s, self.judge_eval_s = safety, 0.0, 0.0

    def __getattr__(self, name: str):
        return getattr(self._safety, name)

    def _timed(self, name: str, total: str, *args, **kwargs):
        t = time.perf_counter()
        out = getattr(self._safety, name)(*args, **kwargs)
        setattr(self, total, getattr(self, total) + time.perf_counter() - t)
        return out

    def violated(self, *args):
        return self._timed("violated", "c_update_s", *args)

    def violations_batch(self, *args):
        return self._timed("violations_batch", "judge_eval_s", *args)


def _scenarios(pipeline: GuidancePipeline, first: int, n: int) -> list:
    """(problem, cvx) of the first `n` chance-constrained `unsafe_cases`."""
    return [(t.problem, cvx) for t, cvx in unsafe_cases(pipeline, True, first, n)]


def _timed(fn) -> tuple[object, float, float]:
    """(result, wall ms, CPU ms) of fn()."""
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, 1e3 * (time.perf_counter() - w), 1e3 * (time.process_time() - c)


def run(repeats: int = 30, first_seed: int = 20000) -> dict:
    """Fast and reference proposals alternated over `repeats` scenarios; medians [ms]."""
    torch.set_num_threads(1)
    provider = ArtWarmStart.load()
    planning = GuidanceConfig.load().planning  # candidates ranked as the pipeline ranks them
    pipeline = GuidancePipeline(provider=provider)
    warm_up_ms = warm_up(pipeline)  # the kernels, the runtime's first inference
    cases = _scenarios(pipeline, int(first_seed), max(int(repeats), 1))
    problem, cvx = cases[0]
    warm_up_ms += warm_up(None, lambda: provider.propose(problem, cvx, planning))  # caches
    rows, same = [], 0
    parts = {"c_update": [], "judge_correction": [], "judge_search": [], "transformer": [],
             "numerics": [], "rest": []}
    original = provider_module.judged_trajectory
    decoder = provider.art.decoder
    timer = StepTimer(decoder)
    speculative = provider_module.rollout

    def one_step(fn):  # a proposal whose rollout goes one step at a time
        provider_module.rollout = functools.partial(speculative, speculate=False)
        try:
            return _timed(fn)
        finally:
            provider_module.rollout = speculative
    steps, decoded = [], []
    for problem, cvx in cases:
        reference = dataclasses.replace(problem, safety=_Reference(problem.safety))
        ref, ref_wall, ref_cpu = one_step(lambda: provider.propose(reference, cvx, planning))
        plain, step_wall, step_cpu = one_step(lambda: provider.propose(problem, cvx, planning))
        timed = _Timed(problem.safety)
        corr = [0.0]

        def corrected(*args, _f=original, _acc=corr):
            t = time.perf_counter()
            out = _f(*args)
            _acc[0] += time.perf_counter() - t
            return out

        provider_module.judged_trajectory = corrected
        decoder.step_numpy, timer.s, timer.n = timer, 0.0, 0
        try:
            fast, wall, cpu = _timed(lambda: provider.propose(
                dataclasses.replace(problem, safety=timed), cvx, planning))
        finally:
            provider_module.judged_trajectory = original
            decoder.step_numpy = timer.step
        same += int(all(np.array_equal(fast.dv_rtn_mps, p.dv_rtn_mps)
                        and np.array_equal(fast.constraint_to_go, p.constraint_to_go)
                        for p in (ref, plain)))
        rows.append((wall, cpu, ref_wall, ref_cpu))
        steps.append((step_wall, step_cpu))
        decoded.append(timer.n)
        parts["c_update"].append(1e3 * timed.c_update_s)
        parts["judge_correction"].append(1e3 * corr[0])
        parts["judge_search"].append(1e3 * timed.judge_eval_s)
        parts["rest"].append(wall - 1e3 * (timed.c_update_s + corr[0] + timed.judge_eval_s))
        parts["transformer"].append(1e3 * timer.s)  # the KV-cached decoder's steps
        parts["numerics"].append(wall - 1e3 * timer.s)  # everything but the transformer
    wall, cpu, ref_wall, ref_cpu = (np.array(x) for x in zip(*rows))
    step_wall, step_cpu = (np.array(x) for x in zip(*steps))
    out = {"scenarios": len(rows), "first_seed": int(first_seed), "warm_up_ms": warm_up_ms,
           "identical_proposals": same,
           "fast_ms": float(np.median(wall)), "reference_ms": float(np.median(ref_wall)),
           "fast_cpu_ms": float(np.median(cpu)), "reference_cpu_ms": float(np.median(ref_cpu)),
           "step_ms": float(np.median(step_wall)), "step_cpu_ms": float(np.median(step_cpu)),
           "speculation_paired_cpu": float(np.median(cpu / step_cpu)),
           "decoded_steps_per_proposal": float(np.mean(decoded)),
           "speedup_paired_cpu": float(np.median(ref_cpu / cpu)),
           "speedup_paired_wall": float(np.median(ref_wall / wall))}
    out.update({f"fast_{k}_ms": float(np.median(v)) for k, v in parts.items()})
    for k, scales in {**SWEEPS, 8: provider.reward_scales}.items():
        sweep = ArtWarmStart(provider.art, reward_scales=scales)
        cpu_ms = [_timed(lambda: sweep.propose(p, c, planning))[2] for p, c in cases]
        out[f"sweep_{k}_cpu_ms"] = float(np.median(cpu_ms))
    return out
