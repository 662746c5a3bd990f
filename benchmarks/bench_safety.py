"""Benchmark of the passive-safety evaluation and linearisation (paper scenario, N=100, S=20).

Times `PassiveSafety.evaluate`, `PassiveSafety.linearize` and
`PassiveSafety.linearize_samples` (k = 5 drift samples per node; chance-constrained, Table II
uncertainty; the one-entry cache is defeated by alternating two inputs) against a naive
reference: a per-node Python loop over a dense 1 s grid of the drift, with the covariance
propagated explicitly (Phi X Phi^T). The reference minimum is refined by a parabola through the
three grid points around it; `max_margin_diff` is the largest difference to `evaluate` (which
returns a certified lower bound within 1e-4 + 0.1 % of |margin|). Run directly
(`python benchmarks/bench_safety.py`) or call `run()`.
"""
from __future__ import annotations

import json
import time
from typing import Callable

import numpy as np

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.safety.drift import CERT_TOL, CERT_TOL_REL
from art_guidance.dynamics import Horizon, control_matrix_deputy, time_grid_s
from art_guidance.safety import PassiveSafety
from common import warm_up


def _scenario_trajectory(scenario: ScenarioConfig) -> tuple[Horizon, np.ndarray, np.ndarray]:
    """Paper nominal initial state with small seeded burns: horizon, (N, 6) ROE, (N, 3) dv."""
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    x0 = np.linalg.solve(horizon.psi[0], np.array(scenario.rtn0_nominal))
    dv = np.random.default_rng(0).normal(0.0, 0.05, (horizon.n_nodes, 3))
    return horizon, horizon.propagate(x0, dv), dv


def naive_margins(ps: PassiveSafety, roe_m: np.ndarray, dv_rtn_mps: np.ndarray,
                  step_s: float = 1.0) -> np.ndarray:
    """Reference: (N,) min over a dense grid of (d - 1 - q sigma), one node at a time."""
    unc = ps.uncertainty
    tau = np.linspace(0.0, ps.tau_s[-1], int(ps.tau_s[-1] / step_s) + 1)
    out = np.empty(ps.n_nodes)
    for i in range(ps.n_nodes):
        b = ps.horizon.b[i]  # the covariance maps the Gates error through B(0)
        z = roe_m[i] + control_matrix_deputy(ps.horizon.chief_oe[i], roe_m[i]) @ dv_rtn_mps[i]
        x_cov = np.zeros((6, 6))
        if unc is not None:
            rho = np.linalg.norm(ps.horizon.psi[i, :3] @ roe_m[i])
            w = min(max((rho - unc.nav_rho2_m) / (unc.nav_rho1_m - unc.nav_rho2_m), 0.0), 1.0)
            s = w * np.array(unc.nav_s1) + (1 - w) * np.array(unc.nav_s2)
            x_cov = np.diag((s * rho) ** 2) + unc.process_noise_m2 * np.eye(6)
            m = np.linalg.norm(dv_rtn_mps[i])
            v = np.diag([unc.sigma_r**2 + m**2 * unc.sigma_s**2,
                         unc.sigma_a**2 + m**2 * unc.sigma_p**2,
                         unc.sigma_a**2 + m**2 * unc.sigma_p**2])
            e1 = dv_rtn_mps[i] / m
            e2 = np.cross(e1, np.eye(3)[np.argmin(np.abs(e1))])
            e2 /= np.linalg.norm(e2)
            rot = np.column_stack([e1, e2, np.cross(e1, e2)])
            x_cov += b @ rot @ v @ rot.T @ b.T
        stm, pos = ps.drift_maps(i, tau)  # (K, 6, 6), (K, 3, 6)
        p = pos @ z  # (K, 3) [m]
        pp = p * np.diag(ps.ellipsoid_p[i])
        d = np.sqrt(np.sum(p * pp, axis=1))
        psi_pos = pos @ np.linalg.inv(stm)  # D Psi at t_i + tau
        h = np.einsum("kcj,kc->kj", psi_pos, pp) / d[:, None]  # gradient w.r.t. ROE at tau
        x_tau = stm @ x_cov @ np.swapaxes(stm, 1, 2)  # covariance along the drift
        sigma = np.sqrt(np.einsum("kj,kjl,kl->k", h, x_tau, h))
        margin = d - 1.0 - ps.q_sigma * sigma
        j = int(np.argmin(margin))
        out[i] = margin[j]
        if 0 < j < tau.size - 1:  # parabola through the interior minimum and its neighbours
            a, c, e = margin[j - 1:j + 2]
            out[i] = c - (a - e) ** 2 / (8 * (a - 2 * c + e))
    return out


def _time_ms(fn: Callable[[], object], repeats: int) -> dict:
    fn()  # warm-up
    samples = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples[k] = (time.perf_counter() - t0) * 1e3
    return {"median_ms": float(np.median(samples)), "p95_ms": float(np.percentile(samples, 95)),
            "repeats": repeats}


def run(repeats: int = 200) -> dict:
    """Time evaluate/linearize and the naive loop on the paper scenario.

    Args:
        repeats: timed calls per vectorised function (the naive loop uses repeats // 100, >= 3).

    Returns:
        dict with `n_nodes`, `n_samples`, `warm_up_ms` (the kernels loaded before anything
        is timed: `common.warm_up`), `init_ms`, timing dicts (`median_ms`, `p95_ms`,
        `repeats`) for `evaluate`, `linearize`, `linearize_samples_5`, `naive_evaluate` (dense
        1 s loop), the median speed-up `speedup_evaluate_vs_naive`, `max_margin_diff`
        (continuous vs dense) and `max_margin_diff_over_tolerance` (< 1: within the certified
        tolerance).
    """
    warm_up_ms = warm_up()  # the kernels, before the first timed construction and call
    scenario = ScenarioConfig.from_yaml()
    uncertainty = UncertaintyConfig.from_yaml()
    horizon, roe_m, dv = _scenario_trajectory(scenario)
    t0 = time.perf_counter()
    ps = PassiveSafety(horizon, scenario, uncertainty)
    init_ms = (time.perf_counter() - t0) * 1e3
    inputs = [(roe_m, dv), (roe_m * 1.001, dv)]  # alternate: no cache hits
    calls = iter(range(10**9))
    ev = _time_ms(lambda: ps.evaluate(*inputs[next(calls) % 2]), repeats)
    lin = _time_ms(lambda: ps.linearize(*inputs[next(calls) % 2]), repeats)
    lin5 = _time_ms(lambda: ps.linearize_samples(*inputs[next(calls) % 2], 5), repeats)
    naive = _time_ms(lambda: naive_margins(ps, roe_m, dv), max(3, repeats // 100))
    reference = naive_margins(ps, roe_m, dv)
    diff = ps.evaluate(roe_m, dv).margin - reference
    tolerance = CERT_TOL + CERT_TOL_REL * np.abs(reference)
    return {
        "n_nodes": ps.n_nodes, "n_samples": ps.n_samples, "warm_up_ms": warm_up_ms,
        "init_ms": init_ms,
        "evaluate": ev, "linearize": lin, "linearize_samples_5": lin5,
        "naive_evaluate": naive,
        "speedup_evaluate_vs_naive": naive["median_ms"] / ev["median_ms"],
        "max_margin_diff": float(np.max(np.abs(diff))),
        "max_margin_diff_over_tolerance": float(np.max(np.abs(diff) / tolerance)),
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
