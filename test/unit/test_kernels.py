"""The compiled numerics (`art_guidance.kernels`) against their numpy oracles.

- The certified sign-only search (`DriftArcs.violated_at`): the same decision on every arc of
  held-out CVX trajectories and perturbations of them, both passive-safety modes, full
  trajectories and batches of 8 (the rollout's), where the numpy oracle decides by
  `violated(items(...))`.
- The full certified minimum (`DriftArcs.minimum`, SCVx*'s evaluation and linearisation
  instants): margins within MARGIN_TOL (sums in another order), the same t* and the same
  linearisation instants (`top_k`); SCVx* from CVX then ends with the same status in the same
  number of iterations, its cost within SCVX_COST_TOL_MPS (the subproblem solver amplifies
  1e-14 differences of the margins to 1e-6-1e-3 m/s: measured 1.4e-4 m/s at most on 16
  scenarios, docs/results.md "Compiled numerics").
- The deputy-aware propagation (`Horizon.propagate_nonlinear`): bit for bit.
- The learned proposal of the default model on held-out scenarios: bit for bit (controls,
  constraint-to-go and the judged terminal warm start).
- The path chosen and said: numba blocked in a fresh interpreter gives the numpy path with the
  reason; an unknown setting is refused; bad input keeps its refusal on either path.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.shipped import heldout_requests

from art_guidance import kernels
from art_guidance.art.provider import ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig, PlanningConfig, ScenarioConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import Trajectory
from art_guidance.planning import GuidancePipeline
from art_guidance.safety.drift import CERT_TOL, CERT_TOL_REL

ROOT = Path(__file__).resolve().parents[2]
N_SCENARIOS = 8  # held-out scenarios per mode for the arcs, and proposals compared
MARGIN_TOL = 1e-12  # |compiled - numpy| certified minimum margin [-] (measured 1.5e-14)
SCVX_COST_TOL_MPS = 1e-3  # |compiled - numpy| SCVx* cost [m/s] (measured 1.4e-4 at most)


@pytest.fixture(autouse=True)
def compiled_after():
    """Every test leaves the process on the default path."""
    yield
    kernels.choose("compiled")


def _both(fn):
    """fn() on the numpy path, then compiled."""
    kernels.choose("numpy")
    a = fn()
    kernels.choose("compiled")
    assert not kernels.error(), kernels.error()
    kernels.warm_up()  # loaded (or compiled) now: never the numpy path compared with itself
    assert kernels.compiled(), kernels.status()
    return a, fn()


@pytest.mark.parametrize("chance", [True, False])
def test_the_certified_search_decides_every_arc_as_its_oracle(chance):
    pipeline = GuidancePipeline()
    rng = np.random.default_rng(5)
    compared = violated = 0
    for request in heldout_requests(N_SCENARIOS):
        request = type(request)(request.chief_oe, request.roe0_m, request.target_rtn,
                                chance_constrained=chance)
        transfer = pipeline.transfer(request)
        safety, horizon = transfer.safety, transfer.horizon
        cvx = transfer.problem.cvx()
        for scale in (0.0, 30.0, 100.0):  # the plan, and perturbed states and burns
            x = cvx.roe_m + rng.normal(0.0, 1.0, cvx.roe_m.shape) * scale
            noise = rng.normal(0.0, 1.0, (horizon.n_nodes, 1))
            u = cvx.dv_rtn_mps * (1.0 + 0.01 * scale * noise)
            z = horizon.post_burn_nonlinear(x, u)
            nodes = np.arange(horizon.n_nodes)
            for sel in (slice(None), slice(0, 8), slice(50, 58)):
                a, b = _both(lambda: safety._violated_at(nodes[sel], x[sel], u[sel], z[sel]))
                np.testing.assert_array_equal(a, b)
                compared += a.size
                violated += int(a.sum())
    assert compared >= 2000 and 0 < violated < compared, (compared, violated)


@pytest.mark.parametrize("chance", [True, False])
def test_the_certified_minimum_is_its_oracle_to_rounding(chance):
    pipeline = GuidancePipeline()
    rng = np.random.default_rng(7)
    for request in heldout_requests(N_SCENARIOS // 2):
        request = type(request)(request.chief_oe, request.roe0_m, request.target_rtn,
                                chance_constrained=chance)
        transfer = pipeline.transfer(request)
        safety, horizon = transfer.safety, transfer.horizon
        cvx = transfer.problem.cvx()
        for scale in (0.0, 50.0):
            x = cvx.roe_m + rng.normal(0.0, 1.0, cvx.roe_m.shape) * scale
            u = cvx.dv_rtn_mps
            items = safety._items_at(np.arange(horizon.n_nodes), x, u,
                                     horizon.post_burn_nonlinear(x, u))
            for sign_only in (False, True):
                a, b = _both(lambda: safety.arcs.minimum(items, sign_only=sign_only))
                np.testing.assert_array_equal(a.margin < 0.0, b.margin < 0.0)
                if sign_only:
                    continue
                np.testing.assert_allclose(a.margin, b.margin, rtol=0.0, atol=MARGIN_TOL)
                # the smallest margin evaluated: within the certification tolerance of the
                # certified one on either path (where an arc has more than MAX_OPEN intervals
                # open at a level, the per-arc cap splits other intervals than the oracle's
                # batch cap, and the two evaluate other points); t* is a refined minimum:
                # rounding moves it by ~1e-12 s, and on a flat minimum it may pick another
                # point of the same margin
                tol = CERT_TOL + CERT_TOL_REL * np.abs(a.margin)
                assert np.all(np.abs(a.margin_at_t_star - b.margin_at_t_star) <= tol)
                moved = np.abs(a.tau_s - b.tau_s) > 1e-6
                assert moved.mean() <= 0.05, moved.mean()
                rows = np.abs(a.top_k(3) - b.top_k(3)).max(axis=1) > 1e-6
                assert rows.mean() <= 0.1, rows.mean()


def test_scvx_takes_the_same_path_to_rounding():
    pipeline = GuidancePipeline()
    for request in heldout_requests(3):
        transfer = pipeline.transfer(request)
        cvx = transfer.problem.cvx()
        a, b = _both(lambda: transfer.scvx(pipeline.config, pipeline.subproblem)
                     .solve(cvx.dv_rtn_mps))
        assert (a.status, a.iterations) == (b.status, b.iterations)
        assert abs(a.cost_mps - b.cost_mps) <= SCVX_COST_TOL_MPS


def test_the_propagation_is_bit_for_bit_its_oracle():
    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))
    rng = np.random.default_rng(1)
    for _ in range(50):
        x0 = rng.normal(0.0, 300.0, 6)
        burns = rng.random((horizon.n_nodes, 1)) < 0.3
        u = rng.normal(0.0, 0.05, (horizon.n_nodes, 3)) * burns
        a, b = _both(lambda: horizon.propagate_nonlinear(x0, u))
        np.testing.assert_array_equal(a, b)
    for mode in kernels.NUMERICS:  # bad input: the same refusal on either path
        kernels.choose(mode)
        with pytest.raises(InputError, match="roe0_m"):
            horizon.propagate_nonlinear(np.full(6, np.nan), np.zeros((horizon.n_nodes, 3)))


def test_proposals_are_bit_for_bit_those_of_the_numpy_path():
    provider = ArtWarmStart.load(default_model_path("chance"))
    planning = GuidanceConfig.load().planning
    pipeline = GuidancePipeline(provider=provider)
    proposed = 0
    for request in heldout_requests(N_SCENARIOS):
        transfer = pipeline.transfer(request)
        cvx = transfer.problem.cvx()
        if not cvx.status.feasible:
            continue
        a, b = _both(lambda: provider.propose(transfer.problem, cvx, planning))
        for name in ("dv_rtn_mps", "constraint_to_go", "reward_to_go_mps"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        for name in Trajectory._fields:
            np.testing.assert_array_equal(getattr(a.warm_start, name),
                                          getattr(b.warm_start, name), err_msg=name)
        proposed += 1
    assert proposed >= N_SCENARIOS // 2


def test_the_kernels_search_with_the_oracles_constants():
    """The kernel module imports only numpy and numba, so it states the search's constants
    again: they must be the oracle's."""
    from art_guidance.kernels import drift as kernel
    from art_guidance.safety import drift, drift_bounds

    for name in ("N_TERMS", "CERT_TOL", "CERT_TOL_REL", "SPLIT", "MAX_LEVELS", "MAX_OPEN",
                 "REFINE_ITERS"):
        assert getattr(kernel, name) == getattr(drift, name), name
    assert kernel.D_FLOOR == drift._D_FLOOR and kernel.N_SUB == drift_bounds.N_SUB


def test_the_setting_is_validated_and_numba_missing_takes_the_numpy_path(tmp_path):
    with pytest.raises(ValueError, match="numerics must be one of"):
        kernels.choose("jax")
    with pytest.raises(ConfigError, match="numerics"):
        PlanningConfig(numerics="fast")
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(
        "import sys\n"
        "class _Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'numba' or name.startswith('numba.'):\n"
        "            raise ImportError('numba is not installed here')\n"
        "sys.meta_path.insert(0, _Block())\n")
    code = ("from art_guidance import kernels\n"
            "from art_guidance.ros.node_status import prepare_numerics\n"
            "class Log:\n"
            "    def info(self, t): print('INFO', t)\n"
            "    def warning(self, t): print('WARN', t)\n"
            "print(prepare_numerics('compiled', Log()))\n"
            "print('compiled', kernels.compiled())\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "WARN numerics: numpy, the compiled kernels are not available: numba is not " \
           "usable (ImportError" in out.stdout, out.stdout
    assert "compiled False" in out.stdout and "Traceback" not in out.stderr
