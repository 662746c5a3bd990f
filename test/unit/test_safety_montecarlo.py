"""Monte Carlo validation of the chance-constrained passive-safety linearisation.

For a few nodes of a realistic reference, the post-burn state is made *tight* for the linearised
chance constraint (``a_i @ z_i == rhs_i``, found by scaling (x_i, u_i) to a fixed point of
`linearize`, which keeps the reference on the normal of the ellipsoid at t*). Errors are then
drawn from the model, each built independently of `art_guidance.uncertainty`:

* navigation: per-axis ROE error with std s(rho) rho (ARTMS piecewise law written out here),
* actuation: Gates magnitude / pointing errors in an explicit burn frame, mapped through B_i,
* process noise: N(0, Q).

Each sample is propagated with the drift map to the continuous t* (the margin's minimiser;
`test_safety_montecarlo_truth.py` checks the whole arc in the nonlinear truth). With q = 3.09
the probability of entering the ellipsoid must not exceed Phi(-q) = 1.0008e-3 (the constraint
is tight, so the rate is close to it, not far below); with q = 0 a tight reference enters about
half of the time. Sample size:
N_MC = 250,000 per node, 4 nodes (1,000,000 pooled), seed 2024. Clopper-Pearson bounds are
exact binomial bounds.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon
from art_guidance.safety import PassiveSafety

SC = ScenarioConfig()
UNC = UncertaintyConfig()
N = SC.n_nodes
N_MC = 250_000
NODES = (8, 30, 62, 88)  # AE phase (approach reference) and KOZ phase (drift reference)
P_TAIL = float(stats.norm.sf(UNC.q_sigma))  # Phi(-3.09) = 1.0008e-3


def clopper_pearson(k: int, n: int, conf: float, side: str) -> float:
    """Exact one-sided binomial bound on the rate (side 'upper' or 'lower') at level conf."""
    if side == "upper":
        return 1.0 if k == n else float(stats.beta.ppf(conf, k + 1, n - k))
    return 0.0 if k == 0 else float(stats.beta.ppf(1.0 - conf, k, n - k + 1))


@pytest.fixture(scope="module")
def reference(horizon: Horizon) -> dict:
    """Node -> (roe_m, dv_rtn_mps) reference; t* is a drift sample (> 0) at every MC node.

    AE nodes: the paper's nominal approach with small random burns. KOZ nodes: an along-track
    drift towards the target (da = 100 m, dlambda = 2.5 km) with one burn per node.
    """
    x0 = np.linalg.solve(horizon.psi[0], np.array(SC.rtn0_nominal))
    dv = np.random.default_rng(10).normal(0.0, 0.05, (N, 3))
    approach = (horizon.propagate(x0, dv), dv)
    drift = (horizon.propagate(np.array([100.0, 2500.0, 0.0, 0.0, 0.0, 0.0]), np.zeros((N, 3))),
             np.tile([0.01, -0.02, 0.005], (N, 1)))
    return {8: approach, 30: approach, 62: drift, 88: drift}


def _tight(ps: PassiveSafety, x: np.ndarray, dv: np.ndarray, i: int):
    """Scale (x_i, u_i) until a_i @ z_i == rhs_i at the linearisation of the scaled state."""
    x, dv = x.copy(), dv.copy()
    for _ in range(100):
        lin = ps.linearize(x, dv)
        c = lin.rhs[i] / lin.dist[i]  # a @ (c z) = c d(z) since d is 1-homogeneous
        x[i] *= c
        dv[i] *= c
        if abs(c - 1.0) < 1e-14:
            break
    lin = ps.linearize(x, dv)
    z = ps.post_burn(x, dv)[i]
    assert abs(lin.a[i] @ z - lin.rhs[i]) < 1e-10 * lin.rhs[i]
    return x, dv, z, lin


def _sample_errors(rng: np.random.Generator, horizon: Horizon, x_i: np.ndarray,
                   dv_i: np.ndarray, i: int, cfg: UncertaintyConfig, n: int) -> np.ndarray:
    """(n, 6) post-burn ROE errors [m]: navigation + B_i * actuation + process noise."""
    rho = float(np.linalg.norm(horizon.psi[i, :3] @ x_i))
    s1, s2 = np.array(cfg.nav_s1), np.array(cfg.nav_s2)
    if rho > cfg.nav_rho1_m:
        s = s1
    elif rho < cfg.nav_rho2_m:
        s = s2
    else:
        s = (s1 * (rho - cfg.nav_rho2_m) + s2 * (cfg.nav_rho1_m - rho)) / (
            cfg.nav_rho1_m - cfg.nav_rho2_m)
    nav = rng.standard_normal((n, 6)) * (s * rho)
    mag = float(np.linalg.norm(dv_i))
    e1 = dv_i / mag
    e2 = np.cross(e1, np.eye(3)[np.argmin(np.abs(e1))])
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(e1, e2)
    std_along = math.sqrt(cfg.sigma_r**2 + mag**2 * cfg.sigma_s**2)  # magnitude error
    std_across = math.sqrt(cfg.sigma_a**2 + mag**2 * cfg.sigma_p**2)  # pointing error
    w = rng.standard_normal((n, 3)) * [std_along, std_across, std_across]
    ddv = w[:, :1] * e1 + w[:, 1:2] * e2 + w[:, 2:] * e3  # (n, 3) RTN [m/s]
    proc = rng.standard_normal((n, 6)) * math.sqrt(cfg.process_noise_m2)
    return nav + ddv @ horizon.b[i].T + proc


def _run_node(ps: PassiveSafety, horizon: Horizon, reference: dict, i: int, seed: int) -> dict:
    x, dv, z, lin = _tight(ps, *reference[i], i)
    rng = np.random.default_rng(seed)
    err = _sample_errors(rng, horizon, x[i], dv[i], i, ps.uncertainty, N_MC)
    tau = lin.t_star_s[i]
    zs = z + err
    p = zs @ ps.drift_maps(i, [tau])[1][0].T  # (n, 3) RTN position at the continuous t*
    d = np.sqrt(np.sum(p * p * np.diag(ps.ellipsoid_p[i]), axis=1))
    return {"x": x, "dv": dv, "err": err, "lin": lin, "tau": tau,
            "enter": d < 1.0, "lin_viol": zs @ lin.a[i] < 1.0}


@pytest.fixture(scope="module")
def mc_chance(horizon: Horizon, reference: dict) -> dict:
    ps = PassiveSafety(horizon, SC, UNC)
    return {i: _run_node(ps, horizon, reference, i, 2024 + i) for i in NODES} | {"ps": ps}


def test_tight_chance_constraint_enters_at_most_delta(mc_chance: dict) -> None:
    k_tot = 0
    for i in NODES:
        res = mc_chance[i]
        # every sample inside the ellipsoid also violates the linear constraint (C-S)
        assert not np.any(res["enter"] & ~res["lin_viol"])
        k_lin = int(res["lin_viol"].sum())
        assert clopper_pearson(k_lin, N_MC, 0.9995, "lower") <= P_TAIL
        assert clopper_pearson(k_lin, N_MC, 0.9995, "upper") >= P_TAIL  # sigma is the right std
        assert res["tau"] > 0  # the error is propagated over a drift arc
        k = int(res["enter"].sum())
        assert clopper_pearson(k, N_MC, 0.999, "lower") <= P_TAIL
        k_tot += k
    n_tot = N_MC * len(NODES)
    rate = k_tot / n_tot
    upper95 = clopper_pearson(k_tot, n_tot, 0.95, "upper")
    print(f"\npooled entry rate {rate:.3e} ({k_tot}/{n_tot}), CP 95% upper {upper95:.3e}")
    assert rate <= 1.05e-3 and upper95 <= 1.1e-3
    assert clopper_pearson(k_tot, n_tot, 0.999, "lower") <= P_TAIL


def test_without_margin_tight_reference_violates_half_the_time(
        horizon: Horizon, reference: dict) -> None:
    ps0 = PassiveSafety(horizon, SC, UncertaintyConfig(q_sigma=0.0))
    for i in NODES:
        res = _run_node(ps0, horizon, reference, i, 77 + i)
        assert np.all(res["lin"].beta == 0.0)
        rate = res["enter"].mean()
        assert 0.45 <= rate <= 0.55, (i, rate)


def test_covariance_recursion_matches_sample_covariance(mc_chance: dict) -> None:
    """X_i, Phi X_i Phi^T at t* and sigma^2 against sample statistics of the same errors.

    Per-entry tolerance: 6 standard errors of a Gaussian sample covariance,
    sqrt((X_kk X_ll + X_kl^2) / n) (about 0.85 % of the scale at n = 250,000).
    """
    ps = mc_chance["ps"]
    for i in NODES:
        res = mc_chance[i]
        x_cov = ps.covariance(res["x"], res["dv"])[i]
        drift = ps.drift_covariance(res["x"], res["dv"], res["lin"].t_star_s)[i]
        phi = ps.drift_maps(i, [res["tau"]])[0][0]
        for err, model in ((res["err"], x_cov), (res["err"] @ phi.T, drift)):
            sample = np.cov(err, rowvar=False)
            var = np.diag(model)
            tol = 6.0 * np.sqrt((np.outer(var, var) + model**2) / N_MC)
            assert np.all(np.abs(sample - model) <= tol), i
        lin = res["lin"]
        sigma2 = (lin.beta[i] / UNC.q_sigma) ** 2
        emp = np.var(res["err"] @ lin.a[i])
        assert abs(emp / sigma2 - 1.0) <= 6.0 * math.sqrt(2.0 / N_MC)
