"""What several benchmarks share: CPU timing, the alternated A/B loop, the decoder's step timer,
the screen of CVX-unsafe scenarios, the hard family's seeds (`hard_seeds`), the warm-up before
the first timed solve, and the tests' helpers (test/helpers) the node benchmarks drive a node
with.

Not a benchmark: `art-guidance bench` runs the `bench_*.py` modules only; this one is imported
by them (benchmarks/ is on the path: the bench command puts it there, pytest's `pythonpath`
too).
"""
from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from art_guidance.planning import GuidancePipeline

REPO = Path(__file__).resolve().parents[1]
TEST_HELPERS = REPO / "test" / "helpers"


def cpu_ms(fn: Callable[[], object]) -> tuple[object, float]:
    """(fn(), the CPU time of this process it took [ms])."""
    t = time.process_time()
    out = fn()
    return out, 1e3 * (time.process_time() - t)


def alternate(index: int, names: tuple[str, str], fn: Callable[[str], object],
              before: Callable[[str], object] | None = None) -> tuple[dict, dict]:
    """One round of an A/B comparison: `fn(name)` for both `names`, the first one first on an
    even `index` (the seed's or repeat's number), the second first on an odd one, so that the
    order and any drift of the machine fall on both alike. `before(name)` runs ahead of each
    call, outside its timing (e.g. resetting a timer, switching the numerics). Returns
    ({name: fn(name)}, {name: its CPU time [ms]})."""
    out, ms = {}, {}
    for name in (names if index % 2 == 0 else names[::-1]):
        if before is not None:
            before(name)
        out[name], ms[name] = cpu_ms(lambda: fn(name))
    return out, ms


class StepTimer:
    """Adds up the time and the count of a decoder's `step_numpy` calls (installed in its
    place: `decoder.step_numpy = StepTimer(decoder)`; `s` [s] and `n` are reset by the
    caller)."""

    def __init__(self, decoder) -> None:
        self.step, self.s, self.n = decoder.step_numpy, 0.0, 0

    def __call__(self, *args):
        t = time.perf_counter()
        out = self.step(*args)
        self.s += time.perf_counter() - t
        self.n += 1
        return out


def unsafe_cases(pipeline: GuidancePipeline, chance: bool, first: int, n: int) -> list:
    """(transfer, cvx) of the first `n` seeds from `first` (of at most 20 n screened) on which
    CVX is feasible and not passively safe: where `auto` runs ART. The requests are the
    `plan --seed S` ones (warm start auto)."""
    from art_guidance.config import ScenarioConfig
    from art_guidance.planning.learned import cvx_is_safe
    from art_guidance.planning.warm_up import seed_request

    sc = ScenarioConfig()
    out, seed = [], first
    while len(out) < n and seed < first + 20 * n:
        request = seed_request(sc, seed, chance_constrained=chance, warm_start="auto")
        seed += 1
        transfer = pipeline.transfer(request)
        cvx = transfer.problem.cvx()
        if cvx.status.feasible and not cvx_is_safe(cvx, transfer.safety):
            out.append((transfer, cvx))
    return out


def warm_up(pipeline: GuidancePipeline | None = None, *throwaway: Callable[[], object]
            ) -> float:
    """Pay this process's one-time costs before a benchmark's first timed solve, so that no
    timed plan, proposal or SCVx* run carries them: `pipeline.warm_up()` (the numba kernels
    loaded through `kernels.prepare(wait=True)`, compiled first on a cold cache, and the
    pipeline's learned provider run once on a canned transfer: its runtime's first
    inference), or without a pipeline `kernels.prepare(wait=True)` alone; then each
    `throwaway` call, untimed by the benchmark (e.g. one proposal of a provider that no
    pipeline holds, or a plan that starts a pipeline's proposal worker on its first job).
    Idempotent for the kernels. The wall time of it all [ms]: what a benchmark records as
    `warm_up_ms`."""
    t0 = time.perf_counter()
    if pipeline is not None:
        pipeline.warm_up(wait=True)
    else:
        from art_guidance import kernels

        kernels.prepare(wait=True)
    for call in throwaway:
        call()
    return 1e3 * (time.perf_counter() - t0)


def use_test_helpers() -> None:
    """Make test/helpers, the tests' modules the node benchmarks share with them (the DDS
    client `ros_client`, `processes`, the `fuzz_messages` and `kill_campaign` campaigns),
    importable as the package `helpers` without putting test/ on sys.path: registered from
    its folder unless it is imported already (as under pytest). The benchmark then imports
    what it needs by name (`from helpers.ros_client import Client`)."""
    if "helpers" not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            "helpers", TEST_HELPERS / "__init__.py", submodule_search_locations=[
                str(TEST_HELPERS)])
        package = importlib.util.module_from_spec(spec)
        sys.modules["helpers"] = package
        spec.loader.exec_module(package)


def hard_seeds(pipeline: GuidancePipeline, first: int, n: int, min_c: int
               ) -> tuple[list[int], list[int], int]:
    """The first `n` seeds from `first` whose initial transfer's CVX warm start has
    C_CVX >= `min_c`; (seeds, their C_CVX, seeds screened)."""
    import numpy as np

    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.planning import PlanRequest
    from art_guidance.scenarios import sample_scenario
    from art_guidance.sim.closed_loop import PARAMETERS

    scenario = pipeline.scenario
    chief = np.array(scenario.chief_oe)
    target = np.asarray(scenario.waypoints_rtn[PARAMETERS["waypoint"]], float)
    seeds, c_cvx, seed = [], [], first
    while len(seeds) < n and seed < first + 100 * n:
        rtn0 = sample_scenario(scenario, seed).rtn0
        request = PlanRequest(chief, roe_from_rtn_linear(chief, rtn0), target,
                              chance_constrained=True)
        transfer = pipeline.transfer(request)
        cvx = transfer.problem.cvx()
        if cvx.status.feasible:
            c = int(transfer.safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps).constraint_to_go[0])
            if c >= min_c:
                seeds.append(seed)
                c_cvx.append(c)
        seed += 1
    return seeds, c_cvx, seed - first
