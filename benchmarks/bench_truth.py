"""Benchmark: the truth's derivative in Python floats (`sim.truth._rhs_scalar`, what
`integrate_truth` uses for the simulator's two spacecraft) against its array form
(`_rhs_array`, the oracle and the form used before), one thread.

Two measures, alternated A/B (`common.alternate`), CPU time, paired medians:
- the truth alone: the paper scenario's chief and deputy integrated together over one orbit
  (DOP853, rtol 1e-11, dense output, as the fault check integrates a free drift), `repeats`
  times; whether both give the same bits;
- a closed-loop flight in this process (`sim.closed_loop.ClosedLoop` over
  `InProcessGuidance`, seed 0, CVX warm start, 100 nodes: the truth between fixes, the
  planner at each replan), `flights` times each way; whether both end in the same state, bit
  for bit, and the share of the flight's CPU the truth took on each path.
"""
from __future__ import annotations

import contextlib
import logging
import tempfile
import time
from typing import Iterator

import numpy as np
from scipy.integrate import solve_ivp
from tqdm import tqdm

from art_guidance import dynamics as dyn
from art_guidance.config import ScenarioConfig
from art_guidance.sim import truth
from common import alternate

FORMS = ("scalar", "array")


@contextlib.contextmanager
def _form(name: str) -> Iterator[None]:
    """`integrate_truth` with the derivative `name` for the block."""
    chosen = truth._rhs
    truth._rhs = truth._rhs_scalar if name == "scalar" else truth._rhs_array
    try:
        yield
    finally:
        truth._rhs = chosen


def _orbit(y0: np.ndarray, period_s: float, name: str):
    with _form(name):
        return truth.integrate_truth(y0, period_s, dense=True)


def _fly(name: str) -> tuple[dict, float]:
    """A closed-loop flight's summary, and the CPU its truth integration took [ms]."""
    from art_guidance.planning import GuidancePipeline
    from art_guidance.sim.closed_loop import PARAMETERS, SIM_EPOCH0_NS, ClosedLoop
    from art_guidance.sim import faults, mean_elements, simulator
    from art_guidance.sim.inprocess import InProcessGuidance

    spent = [0.0]
    inner = truth.integrate_truth

    def timed(*args, **kwargs):
        t = time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            spent[0] += time.process_time() - t

    users = [m for m in (simulator, faults, mean_elements) if hasattr(m, "integrate_truth")]
    with tempfile.TemporaryDirectory() as out, _form(name):
        params = dict(PARAMETERS, rtn0=None, png_path="", seed=0, warm_start="cvx",
                      summary_path=f"{out}/s.json")
        link = InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS)
        loop = ClosedLoop(link, params, logging.getLogger("bench_truth"), settle_s=0.0)
        for module in users:  # imported by name there
            module.integrate_truth = timed
        try:
            summary, _ = loop.finish(loop.run(), 0.0)
        finally:
            for module in users:
                module.integrate_truth = inner
    return summary, 1e3 * spent[0]


def run(repeats: int = 30, flights: int = 2) -> dict:
    """Paired medians [ms CPU] and ratios of the two forms; whether they agree bit for bit."""
    scenario = ScenarioConfig.from_yaml()
    chief = dyn.eci_from_oe(scenario.chief_oe)
    y0 = np.concatenate([chief, dyn.eci_from_rtn(chief, [-4000.0, -17500.0, 0.0, 0.0, 6.849,
                                                         0.0])])
    period_s = 2.0 * np.pi * np.sqrt(scenario.chief_oe[0] ** 3 / dyn.MU_M3PS2)
    solve_ivp(truth._rhs_array, (0.0, 10.0), y0, method="DOP853")  # scipy's first call
    rows, same = [], 0
    for k in tqdm(range(max(int(repeats), 1)), desc="bench truth: orbits", unit="orbit"):
        out, ms = alternate(k, FORMS, lambda name: _orbit(y0, period_s, name))
        a, b = out["scalar"], out["array"]
        same += bool(np.array_equal(a.t, b.t) and np.array_equal(a.y, b.y))
        rows.append(ms)
    flown, same_flight = [], 0
    for k in tqdm(range(max(int(flights), 1)), desc="bench truth: flights", unit="pair"):
        out, ms = alternate(k, FORMS, _fly)
        (sa, ta), (sb, tb) = out["scalar"], out["array"]
        same_flight += sa == sb
        flown.append({"scalar": ms["scalar"], "array": ms["array"], "truth_scalar": ta,
                      "truth_array": tb})
    col = {key: np.array([r[key] for r in rows]) for key in FORMS}
    fly = {key: np.array([r[key] for r in flown]) for key in flown[0]}
    return {
        "orbits": len(rows), "orbit_scalar_ms_median": float(np.median(col["scalar"])),
        "orbit_array_ms_median": float(np.median(col["array"])),
        "orbit_scalar_over_array_paired_median": float(np.median(col["scalar"]
                                                                 / col["array"])),
        "orbits_bit_for_bit": f"{same}/{len(rows)}",
        "flights": len(flown), "flight_scalar_ms_median": float(np.median(fly["scalar"])),
        "flight_array_ms_median": float(np.median(fly["array"])),
        "flight_scalar_over_array_paired_median": float(np.median(fly["scalar"]
                                                                  / fly["array"])),
        "flight_truth_share_scalar": float(np.median(fly["truth_scalar"] / fly["scalar"])),
        "flight_truth_share_array": float(np.median(fly["truth_array"] / fly["array"])),
        "flights_same_summary": f"{same_flight}/{len(flown)}",
    }
