"""Benchmark: the learned warm start on its two runtimes, torch (the checkpoint) against ONNX
Runtime (the exported file beside it, `art-guidance export`), per passive-safety mode.

For `plan` scenarios of each mode (seeds FIRST.., held out from the shipped models' training
data) on which CVX is not passively safe (where `auto` runs ART), the shipped default model of
the mode makes the learned step as the pipeline makes it (`planning.learned.learned_warm_start`:
the conditioning sweep with the C update at every step, the judging of the candidates, the post
hoc check), once on each runtime, alternated scenario by scenario, one thread each, in one
process. Reported per mode:

- agreement: the proposals whose constraint-to-go and post hoc decision (accepted or not, and
  the warm start chosen) are the same on both runtimes, and the largest difference of the
  proposed controls [m/s] (torch is the oracle; the graph computes in float32 as torch does,
  in another order);
- time: medians of CPU time per learned step on each runtime and the paired ratio onnx/torch,
  and the transformer alone (the decoder's steps) on each.

    art-guidance bench runtime --repeats 100 --first-seed 40000 --json out/runtime.json
"""
from __future__ import annotations

import time

import numpy as np

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from art_guidance.planning.learned import learned_warm_start
from bench_proposal import StepTimer, unsafe_cases


def _mode(mode: str, repeats: int, first_seed: int) -> dict:
    config = GuidanceConfig.load()
    path = default_model_path(mode)
    models = {rt: ArtWarmStart.load(path, runtime=rt) for rt in ("torch", "onnx")}
    timers = {}
    for rt, provider in models.items():
        timers[rt] = StepTimer(provider.art.decoder)
        provider.art.decoder.step_numpy = timers[rt]
    pipeline = GuidancePipeline(config)
    cases = unsafe_cases(pipeline, mode == "chance", first_seed, repeats)
    for provider in models.values():  # warm-up (sessions, caches)
        learned_warm_start(provider, cases[0][0], cases[0][1], config.planning, cvx_unsafe=True)
    cpu = {rt: [] for rt in models}
    net = {rt: [] for rt in models}
    same_c = same_decision = 0
    worst = 0.0
    for i, (transfer, cvx) in enumerate(cases):
        out = {}
        for rt in (("torch", "onnx") if i % 2 == 0 else ("onnx", "torch")):
            timers[rt].s = 0.0
            t = time.process_time()
            out[rt] = learned_warm_start(models[rt], transfer, cvx, config.planning,
                                         cvx_unsafe=True)
            cpu[rt].append(1e3 * (time.process_time() - t))
            net[rt].append(1e3 * timers[rt].s)
        a, b = out["torch"], out["onnx"]
        pa, pb = a.proposal, b.proposal
        if pa is not None and pb is not None:
            same_c += int(np.array_equal(pa.constraint_to_go, pb.constraint_to_go))
            worst = max(worst, float(np.abs(pa.dv_rtn_mps - pb.dv_rtn_mps).max()))
        same_decision += int(a.source is b.source and (a.posthoc is None) == (b.posthoc is None)
                             and (a.posthoc is None or a.posthoc.accepted == b.posthoc.accepted))
    t, o = np.array(cpu["torch"]), np.array(cpu["onnx"])
    return {f"{mode}_scenarios": len(cases),
            f"{mode}_same_constraint_to_go": same_c,
            f"{mode}_same_decision": same_decision,
            f"{mode}_max_dv_difference_mps": worst,
            f"{mode}_torch_cpu_ms": float(np.median(t)),
            f"{mode}_onnx_cpu_ms": float(np.median(o)),
            f"{mode}_ratio_paired_cpu": float(np.median(o / t)),
            f"{mode}_torch_transformer_ms": float(np.median(net["torch"])),
            f"{mode}_onnx_transformer_ms": float(np.median(net["onnx"])),
            f"{mode}_ratio_paired_transformer": float(np.median(np.array(net["onnx"])
                                                                / np.array(net["torch"])))}


def run(repeats: int = 30, first_seed: int = 40000) -> dict:
    """Both runtimes alternated over `repeats` scenarios per mode; medians [ms]."""
    import torch

    torch.set_num_threads(1)
    out: dict = {"first_seed": int(first_seed)}
    for mode in sorted(DEFAULT_MODELS):
        out.update(_mode(mode, max(int(repeats), 1), int(first_seed)))
    return out
