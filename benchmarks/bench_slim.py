"""Benchmark: the distilled slim ART against its teacher, the shipped small model of its mode
(`provider.TEACHERS`; the chance-constrained default is itself a student now).

For chance-constrained `plan` scenarios (seeds FIRST.., held out from every training set) on
which CVX is not passively safe (where `auto` runs ART), the learned step as the pipeline makes
it (`planning.learned.learned_warm_start`: the sweep of 8 with the C update, the judging, the
post hoc check) with the teacher and with the distilled student
(`results/slim/art_slim_chance_rtn.pt`, not a default), both on ONNX Runtime (the default
runtime), alternated scenario by scenario, one thread, in one process; SCVx* from CVX on the
same scenario is timed beside them (the reference of the <= 0.25x target). Reported: medians
of CPU time per learned step and of the transformer alone, the paired ratios student / teacher
and learned step / SCVx* from CVX, and how often the two models' proposals are accepted by the
post hoc check.

What the student is worth as a warm start (the plans flown from it) is measured by the
warm-start analysis (`art-guidance evaluate` + `benchmarks/analyses/default_models.py`), not here.

Before the first timed step the process is warmed up (`common.warm_up`: the kernels loaded,
each model run once on the first scenario); its wall time is `warm_up_ms`, apart from the
timings.

    art-guidance bench slim --repeats 60 --first-seed 40000 --json out/slim.json
    art-guidance bench slim --model results/slim/art_slim1_chance_rtn.pt \
        --reference results/slim/art_slim_chance_rtn.pt     # one student against another
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.art.provider import TEACHERS, ArtWarmStart, models_dir
from art_guidance.config import GuidanceConfig
from art_guidance.planning import GuidancePipeline
from art_guidance.planning.learned import CvxSafety, learned_warm_start
from common import StepTimer, alternate, cpu_ms, unsafe_cases, warm_up

UNSAFE = CvxSafety.answered(False)  # the cases' CVX plans are not passively safe

SLIM_MODEL = Path(__file__).resolve().parent / "results" / "slim" / "art_slim_chance_rtn.pt"


def run(repeats: int = 30, first_seed: int = 40000, model: str | None = None,
        reference: str | None = None) -> dict:
    """Teacher and student alternated over `repeats` scenarios; medians [ms]. `model`: another
    student (e.g. `results/slim/art_slim_det_roe.pt`), measured against the teacher of its
    dataset's mode (`TEACHERS`) on scenarios of that mode; `reference`: a model measured in
    the teacher's place (e.g. another student, or the chance-constrained default)."""
    import torch

    torch.set_num_threads(1)
    config = GuidanceConfig.load()
    student = ArtWarmStart.load(model or SLIM_MODEL)
    mode = student.art.meta.get("dataset", {}).get("mode", "chance")
    models = {"teacher": ArtWarmStart.load(reference or models_dir() / TEACHERS[mode]),
              "student": student}
    timers = {}
    for name, provider in models.items():
        timers[name] = StepTimer(provider.art.decoder)
        provider.art.decoder.step_numpy = timers[name]
    pipeline = GuidancePipeline(config)
    warm_up_ms = warm_up(pipeline)  # the kernels
    cases = unsafe_cases(pipeline, mode == "chance", int(first_seed), max(int(repeats), 1))
    warm_up_ms += warm_up(None, lambda: [  # each model's first inference
        learned_warm_start(p, cases[0][0], cases[0][1], config.planning, cvx_safe=UNSAFE)
        for p in models.values()])
    cpu = {n: [] for n in models}
    net = {n: [] for n in models}
    accepted = {n: 0 for n in models}
    scvx_ms = []
    for i, (transfer, cvx) in enumerate(cases):
        out, ms = alternate(i, ("teacher", "student"), lambda name: learned_warm_start(
            models[name], transfer, cvx, config.planning, cvx_safe=UNSAFE),
            before=lambda name: setattr(timers[name], "s", 0.0))  # the transformer's time
        for name in models:
            cpu[name].append(ms[name])
            net[name].append(1e3 * timers[name].s)
            accepted[name] += int(out[name].posthoc is not None and out[name].posthoc.accepted)
        scvx_ms.append(cpu_ms(lambda: transfer.problem.scvx(
            config.scp, config.planning.samples_per_node).solve(cvx.dv_rtn_mps))[1])
    t, s, c = (np.array(x) for x in (cpu["teacher"], cpu["student"], scvx_ms))
    return {"scenarios": len(cases), "first_seed": int(first_seed), "mode": mode,
            "warm_up_ms": warm_up_ms,
            "student": Path(student.path).name, "runtime": models["student"].runtime,
            "teacher": Path(models["teacher"].path).name,
            "teacher_cpu_ms": float(np.median(t)), "student_cpu_ms": float(np.median(s)),
            "ratio_paired_cpu": float(np.median(s / t)),
            "teacher_transformer_ms": float(np.median(net["teacher"])),
            "student_transformer_ms": float(np.median(net["student"])),
            "scvx_from_cvx_cpu_ms": float(np.median(c)),
            "teacher_over_scvx": float(np.median(t / c)),
            "student_over_scvx": float(np.median(s / c)),
            "teacher_accepted": accepted["teacher"], "student_accepted": accepted["student"]}
