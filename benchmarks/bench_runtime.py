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

Before the first timed step the process is warmed up (`common.warm_up`: the kernels loaded,
each runtime run once on the first scenario); its wall time is `warm_up_ms` (per mode
`{mode}_warm_up_ms`), apart from the timings.

    art-guidance bench runtime --repeats 100 --first-seed 40000 --json out/runtime.json
"""
from __future__ import annotations

import numpy as np

from art_guidance.art.provider import DEFAULT_MODELS, ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from art_guidance.planning.learned import CvxSafety, learned_warm_start
from common import StepTimer, alternate, unsafe_cases, warm_up

UNSAFE = CvxSafety.answered(False)  # the cases' CVX plans are not passively safe


def _mode(mode: str, repeats: int, first_seed: int) -> dict:
    config = GuidanceConfig.load()
    path = default_model_path(mode)
    models = {rt: ArtWarmStart.load(path, runtime=rt) for rt in ("torch", "onnx")}
    timers = {}
    for rt, provider in models.items():
        timers[rt] = StepTimer(provider.art.decoder)
        provider.art.decoder.step_numpy = timers[rt]
    pipeline = GuidancePipeline(config)
    warm_up_ms = warm_up(pipeline)  # the kernels
    cases = unsafe_cases(pipeline, mode == "chance", first_seed, repeats)
    warm_up_ms += warm_up(None, lambda: [  # each runtime's first inference (sessions, caches)
        learned_warm_start(p, cases[0][0], cases[0][1], config.planning, cvx_safe=UNSAFE)
        for p in models.values()])
    cpu = {rt: [] for rt in models}
    net = {rt: [] for rt in models}
    same_c = same_decision = 0
    worst = 0.0
    for i, (transfer, cvx) in enumerate(cases):
        out, ms = alternate(i, ("torch", "onnx"), lambda rt: learned_warm_start(
            models[rt], transfer, cvx, config.planning, cvx_safe=UNSAFE),
            before=lambda rt: setattr(timers[rt], "s", 0.0))  # the transformer's time
        for rt in models:
            cpu[rt].append(ms[rt])
            net[rt].append(1e3 * timers[rt].s)
        a, b = out["torch"], out["onnx"]
        pa, pb = a.proposal, b.proposal
        if pa is not None and pb is not None:
            same_c += int(np.array_equal(pa.constraint_to_go, pb.constraint_to_go))
            worst = max(worst, float(np.abs(pa.dv_rtn_mps - pb.dv_rtn_mps).max()))
        same_decision += int(a.source is b.source and (a.posthoc is None) == (b.posthoc is None)
                             and (a.posthoc is None or a.posthoc.accepted == b.posthoc.accepted))
    t, o = np.array(cpu["torch"]), np.array(cpu["onnx"])
    return {f"{mode}_scenarios": len(cases), f"{mode}_warm_up_ms": warm_up_ms,
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
    out["warm_up_ms"] = sum(out[f"{mode}_warm_up_ms"] for mode in DEFAULT_MODELS)
    return out
