"""Monte Carlo of the chance-constrained passive safety in the nonlinear truth, over whole arcs.

At an *active* node of a converged chance-constrained plan (margin d - 1 - q sigma within 3 %
of zero: the 1 % tightening and the plan's slack), N_MC post-burn states are drawn from the
paper's error models (written out here, independently of `art_guidance.uncertainty`): ARTMS
navigation (per-axis std s(rho) rho), Gates actuation in an explicit burn frame mapped through
B_i, and process noise N(0, Q). Each
sample's mean ROE is converted to osculating elements (the inverse orbit average of
`helpers.orbit_truth`, linearised about the planned state by central differences: the samples
differ by metres, the second-order error is < 1 mm), and its one-orbit free drift is integrated
in two-body + J2 with a fixed-step RK4 (T / 553 ~ 10 s; checked against DOP853 rtol 1e-11 to
1 cm here). An entry is any sample whose ellipsoidal distance, sampled every step and refined by
a parabola at every local minimum, drops below 1.

Nodes: seed 17 node 54 (approach ellipsoid, no burn) and seed 11 node 78 (keep-out zone after a
1.8 m/s burn), where a t* taken among the 20 drift samples gave 1.5e-3 and 0.90. The violation
probability must be below the design Delta = 1e-3 with 95 % confidence (one-sided exact
Clopper-Pearson upper bound), and the nominal state itself must stay outside.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import Horizon
from art_guidance.optim import TransferProblem
from art_guidance.safety import PassiveSafety
from helpers import orbit_truth as truth

pytestmark = pytest.mark.slow  # Monte Carlo / SCVx* plans integrated in the truth

SC = ScenarioConfig()
UNC = UncertaintyConfig()
N_MC = 20_000  # entries measured: 2 at each node (upper bounds 3.2e-4); a rate of 1.5e-3
# (t* among the drift samples, see above) gives ~30 entries, an upper bound ~2e-3: fails
DELTA = 1e-3
STEPS = 553  # RK4 steps per orbit (10 s; 5e-5 m from DOP853 on 1 km arcs)
CASES = ((17, 54), (11, 78))  # (scenario seed, node)


def _errors(rng: np.random.Generator, x_i: np.ndarray, dv_i: np.ndarray, b_i: np.ndarray,
            psi_i: np.ndarray, n: int) -> np.ndarray:
    """(n, 6) post-burn ROE errors [m]: navigation + B_i * Gates actuation + process noise."""
    rho = float(np.linalg.norm(psi_i[:3] @ x_i))
    s1, s2 = np.array(UNC.nav_s1), np.array(UNC.nav_s2)
    w = min(max((rho - UNC.nav_rho2_m) / (UNC.nav_rho1_m - UNC.nav_rho2_m), 0.0), 1.0)
    nav = rng.standard_normal((n, 6)) * ((w * s1 + (1.0 - w) * s2) * rho)
    mag = float(np.linalg.norm(dv_i))
    e1 = dv_i / mag if mag > 0 else np.array([1.0, 0.0, 0.0])
    e2 = np.cross(e1, np.eye(3)[np.argmin(np.abs(e1))])
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(e1, e2)
    std = [math.sqrt(UNC.sigma_r**2 + mag**2 * UNC.sigma_s**2),
           math.sqrt(UNC.sigma_a**2 + mag**2 * UNC.sigma_p**2),
           math.sqrt(UNC.sigma_a**2 + mag**2 * UNC.sigma_p**2)]
    g = rng.standard_normal((n, 3)) * std
    ddv = g[:, :1] * e1 + g[:, 1:2] * e2 + g[:, 2:] * e3  # (n, 3) RTN [m/s]
    proc = rng.standard_normal((n, 6)) * math.sqrt(UNC.process_noise_m2)
    return nav + ddv @ b_i.T + proc


def _osculating(chief_mean: np.ndarray, roe_m: np.ndarray, roe_nominal: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Inertial chief (6,) and deputies (n, 6) from mean elements, via the inverse orbit average
    at the nominal deputy and its central-difference Jacobian (nonsingular elements)."""
    dep_nom = truth.nonsingular_from_kep(truth.deputy_from_roe(chief_mean, roe_nominal))
    steps = np.array([1.0, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7])  # [m, -, -, rad, rad, rad]
    probes = np.vstack([dep_nom, dep_nom + np.diag(steps), dep_nom - np.diag(steps)])
    bodies = np.vstack([chief_mean, truth.kep_from_nonsingular(probes)])
    osc = truth.nonsingular_from_kep(truth.osculating_from_mean(bodies))
    jac = (osc[2:8] - osc[8:14]).T / (2.0 * steps)  # (6, 6) d osc / d mean
    mean = truth.nonsingular_from_kep(truth.deputy_from_roe(chief_mean, roe_m))
    delta = mean - dep_nom
    delta[:, 4:] = truth.wrap(delta[:, 4:])
    dep = truth.kep_from_nonsingular(osc[1] + delta @ jac.T)
    return truth.cart_from_kep(truth.kep_from_nonsingular(osc[0])), truth.cart_from_kep(dep)


def _rk4_min_distance(chief: np.ndarray, deputies: np.ndarray, axes_m: np.ndarray,
                      t_end: float, steps: int, keep: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Smallest ellipsoidal distance (n,) of every deputy over [0, t_end] (RK4, `steps` steps;
    parabola refinement at local minima) and the RTN positions of the first `keep` deputies."""
    h = t_end / steps
    y = np.vstack([chief, deputies])
    f = (lambda s: np.concatenate([s[:, 3:], truth.accel(s[:, :3])], axis=1))
    dist = lambda s: np.linalg.norm(truth.rtn_position(s[0], s[1:]) / axes_m, axis=1)  # noqa
    d_prev2, d_prev = None, dist(y)
    d_min = d_prev.copy()
    track = [truth.rtn_position(y[0], y[1:keep + 1])]
    for _ in range(steps):
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y = y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        d = dist(y)
        d_min = np.minimum(d_min, d)
        if d_prev2 is not None:
            curv = d_prev2 - 2.0 * d_prev + d
            local = (d_prev <= d_prev2) & (d_prev <= d) & (curv > 0)
            vertex = d_prev - (d_prev2 - d) ** 2 / (8.0 * np.where(local, curv, 1.0))
            d_min = np.where(local, np.minimum(d_min, vertex), d_min)
        d_prev2, d_prev = d_prev, d
        track.append(truth.rtn_position(y[0], y[1:keep + 1]))
    return d_min, np.stack(track, axis=1)


@pytest.fixture(scope="module")
def cases(horizon: Horizon) -> dict:
    ps = PassiveSafety(horizon, SC, UNC)
    out = {}
    for seed, node in CASES:
        s = sample_scenario(SC, seed)
        x0 = np.linalg.solve(horizon.psi[0], s.rtn0)
        problem = TransferProblem.to_target(ps, x0, s.target_rtn)
        res = problem.scvx(ScpConfig.from_yaml(), samples_per_node=3).solve(
            problem.cvx().dv_rtn_mps)
        assert res.feasible
        margin = ps.evaluate(res.roe_m, res.dv_rtn_mps).margin[node]
        z = ps.post_burn(res.roe_m, res.dv_rtn_mps)[node]
        err = _errors(np.random.default_rng(1000 + seed), res.roe_m[node], res.dv_rtn_mps[node],
                      horizon.b[node], horizon.psi[node], N_MC)
        chief, deps = _osculating(horizon.chief_oe[node], z + np.vstack([np.zeros(6), err]), z)
        t_end = float(ps.tau_s[-1])
        d_min, track = _rk4_min_distance(chief, deps, ps.semi_axes_m[node], t_end, STEPS, 8)
        out[(seed, node)] = {"margin": margin, "d_min": d_min, "track": track, "t_end": t_end,
                             "chief": chief, "deps": deps[:8]}
    return out


def test_rk4_matches_the_dop853_truth(cases: dict) -> None:
    """The fixed-step propagation agrees with DOP853 (rtol 1e-11) to 1 cm in relative position."""
    for res in cases.values():
        sol = truth.integrate(np.vstack([res["chief"], res["deps"]]), res["t_end"])
        t = np.linspace(0.0, res["t_end"], STEPS + 1)
        states = sol(t).T.reshape(t.size, -1, 6)
        ref = truth.rtn_position(states[:, :1], states[:, 1:])  # (K, 8, 3)
        assert np.max(np.abs(ref.transpose(1, 0, 2) - res["track"])) < 1e-2


def test_active_node_violation_probability_below_design(cases: dict) -> None:
    for (seed, node), res in cases.items():
        # the chance constraint is active: the 1 % tightening plus the slack a converged plan
        # may keep (measured 0.0098 at seed 17 node 54, 0.0233 at seed 11 node 78)
        assert 0.0 <= res["margin"] < 0.03
        assert res["d_min"][0] > 1.0  # the planned state itself drifts outside
        k = int(np.sum(res["d_min"][1:] < 1.0))
        upper95 = float(stats.beta.ppf(0.95, k + 1, N_MC - k))
        print(f"\nseed {seed} node {node}: {k}/{N_MC} entries, rate {k / N_MC:.2e}, "
              f"95 % upper bound {upper95:.2e} (design {DELTA:.0e})")
        assert upper95 <= DELTA
