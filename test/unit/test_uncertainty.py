"""Uncertainty model (paper Table II): ARTMS navigation, Gates actuation, covariance history."""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.errors import InputError
from art_guidance.uncertainty import (
    gates_covariance,
    nav_covariance,
    post_burn_covariance,
    post_burn_covariance_checked,
    process_noise,
    propagate_covariance,
    state_covariance_history,
)

CFG = UncertaintyConfig()
S1 = np.array(CFG.nav_s1)
S2 = np.array(CFG.nav_s2)


def _radial_states(rho_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROE whose first-order RTN position is (rho, 0, 0) under an identity Psi."""
    roe = np.zeros((rho_m.size, 6))
    roe[:, 0] = rho_m
    return roe, np.broadcast_to(np.eye(6), (rho_m.size, 6, 6))


def _std(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))


@pytest.fixture(scope="module")
def horizon() -> Horizon:
    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    return Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))


# ---------------------------------------------------------------------------- navigation
def test_artms_far_and_near_values() -> None:
    rho = np.array([10_000.001, 20_000.0, 50_000.0, 999.999, 500.0, 1.0])
    roe, psi = _radial_states(rho)
    std = _std(nav_covariance(roe, psi, CFG))
    np.testing.assert_allclose(std[:3], S1 * rho[:3, None], rtol=1e-6)
    np.testing.assert_allclose(std[3:], S2 * rho[3:, None], rtol=1e-6)


def test_artms_linear_between_ranges() -> None:
    rho = np.linspace(1000.0, 10_000.0, 37)
    roe, psi = _radial_states(rho)
    s = _std(nav_covariance(roe, psi, CFG)) / rho[:, None]  # recovered s(rho)
    expected = (S1 * (rho[:, None] - 1000.0) + S2 * (10_000.0 - rho[:, None])) / 9000.0
    np.testing.assert_allclose(s, expected, rtol=1e-12, atol=1e-15)
    # affine in rho: second differences vanish; endpoints continuous with the plateaus
    np.testing.assert_allclose(np.diff(s, 2, axis=0), 0.0, atol=1e-15)
    np.testing.assert_allclose(s[0], S2, rtol=1e-12)
    np.testing.assert_allclose(s[-1], S1, rtol=1e-12)


def test_artms_covariance_is_diagonal_and_uses_position_rows(horizon: Horizon) -> None:
    rng = np.random.default_rng(1)
    roe = rng.normal(0.0, 3000.0, (horizon.n_nodes, 6))
    cov = nav_covariance(roe, horizon.psi, CFG)
    assert cov.shape == (horizon.n_nodes, 6, 6)
    off = cov - np.einsum("kii->ki", cov)[:, :, None] * np.eye(6)
    assert np.all(off == 0.0)
    rho = np.linalg.norm(horizon.to_rtn(roe)[:, :3], axis=1)
    w = np.clip((rho - 1000.0) / 9000.0, 0, 1)[:, None]
    np.testing.assert_allclose(_std(cov), (w * S1 + (1 - w) * S2) * rho[:, None], rtol=1e-12)


# ---------------------------------------------------------------------------- Gates
def _gates_reference(dv: np.ndarray, cfg: UncertaintyConfig) -> np.ndarray:
    """R V R^T with an explicit Gram-Schmidt burn frame (independent construction)."""
    e1 = dv / np.linalg.norm(dv)
    helper = np.eye(3)[np.argmin(np.abs(e1))]
    e2 = np.cross(e1, helper)
    e2 /= np.linalg.norm(e2)
    rot = np.column_stack([e1, e2, np.cross(e1, e2)])
    m2 = dv @ dv
    v = np.diag([cfg.sigma_r**2 + m2 * cfg.sigma_s**2, cfg.sigma_a**2 + m2 * cfg.sigma_p**2,
                 cfg.sigma_a**2 + m2 * cfg.sigma_p**2])
    return rot @ v @ rot.T


@pytest.mark.parametrize("cfg", [CFG, UncertaintyConfig(sigma_r=1e-3, sigma_a=2e-4),
                                 UncertaintyConfig(sigma_r=1e-4, sigma_a=5e-4)])
def test_gates_matches_rotated_v_and_is_psd(cfg: UncertaintyConfig) -> None:
    rng = np.random.default_rng(2)
    dv = rng.normal(0.0, 1.0, (200, 3)) * rng.uniform(1e-4, 3.0, (200, 1))
    u = gates_covariance(dv, cfg)
    ref = np.stack([_gates_reference(d, cfg) for d in dv])
    np.testing.assert_allclose(u, ref, rtol=1e-10, atol=1e-20)
    assert np.all(np.linalg.eigvalsh(u)[:, 0] >= -1e-18)
    np.testing.assert_array_equal(u, np.swapaxes(u, 1, 2))


def test_gates_eigen_structure() -> None:
    dv = np.array([0.3, -1.2, 0.5])
    m = np.linalg.norm(dv)
    e1 = dv / m
    u = gates_covariance(dv[None], CFG)[0]
    along = CFG.sigma_r**2 + m**2 * CFG.sigma_s**2
    across = CFG.sigma_a**2 + m**2 * CFG.sigma_p**2
    np.testing.assert_allclose(u @ e1, along * e1, rtol=1e-12)  # burn direction eigenvector
    w = np.cross(e1, [1.0, 0.0, 0.0])
    w /= np.linalg.norm(w)
    np.testing.assert_allclose(u @ w, across * w, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(np.linalg.eigvalsh(u), sorted([along, across, across]),
                               rtol=1e-12)


def test_gates_continuous_at_zero_for_table_ii() -> None:
    u0 = gates_covariance(np.zeros((1, 3)), CFG)[0]
    np.testing.assert_allclose(u0, CFG.sigma_a**2 * np.eye(3), rtol=1e-15)
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for eps in (1e-2, 1e-5, 1e-9, 1e-14):
        du = gates_covariance(eps * dirs, CFG) - u0
        # |U(eps e) - U(0)| = eps^2 * max(ss^2, sp^2) exactly when sr == sa
        assert np.max(np.abs(du)) <= 1.000001 * eps**2 * CFG.sigma_s**2


def test_gates_zero_dv_with_unequal_sigmas_is_conservative() -> None:
    cfg = UncertaintyConfig(sigma_r=1e-3, sigma_a=2e-4)
    u0 = gates_covariance(np.zeros((1, 3)), cfg)[0]
    np.testing.assert_allclose(u0, 1e-6 * np.eye(3))
    rng = np.random.default_rng(4)
    for d in rng.normal(size=(20, 3)):
        u_small = gates_covariance(1e-9 * d[None], cfg)[0]  # directional limit
        assert np.linalg.eigvalsh(u0 - u_small)[0] >= -1e-18  # U(0) dominates every limit


# ---------------------------------------------------------------------------- history
def test_process_noise() -> None:
    np.testing.assert_array_equal(process_noise(CFG), 1e-6 * np.eye(6))


def test_propagate_covariance_batched() -> None:
    rng = np.random.default_rng(5)
    a = rng.normal(size=(7, 6, 6))
    x = a @ np.swapaxes(a, 1, 2)
    phi = rng.normal(size=(7, 6, 6))
    out = propagate_covariance(x, phi)
    for k in range(7):
        np.testing.assert_allclose(out[k], phi[k] @ x[k] @ phi[k].T, rtol=1e-12)
    # broadcasting (N, 1, 6, 6) against (N, S, 6, 6)
    phis = rng.normal(size=(7, 3, 6, 6))
    np.testing.assert_allclose(propagate_covariance(x[:, None], phis)[2, 1],
                               phis[2, 1] @ x[2] @ phis[2, 1].T, rtol=1e-12)


def test_state_covariance_history(horizon: Horizon) -> None:
    n = horizon.n_nodes
    rng = np.random.default_rng(6)
    roe = rng.normal(0.0, 2000.0, (n, 6))
    dv = rng.normal(0.0, 0.2, (n, 3))
    dv[::7] = 0.0
    hist = state_covariance_history(roe, dv, horizon, CFG)
    assert hist.shape == (n, 6, 6)
    np.testing.assert_allclose(hist, np.swapaxes(hist, 1, 2), rtol=0, atol=0)
    assert np.all(np.linalg.eigvalsh(hist)[:, 0] >= 1e-6 * (1 - 1e-9))  # >= Q
    parts = (nav_covariance(roe, horizon.psi, CFG)
             + np.stack([b @ u @ b.T for b, u in zip(horizon.b, gates_covariance(dv, CFG))])
             + 1e-6 * np.eye(6))
    np.testing.assert_allclose(hist, parts, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(state_covariance_history(roe, dv, horizon, None),
                                  np.zeros((n, 6, 6)))
    # the rollout loop's unchecked form gives the same numbers, bit for bit, at one node
    i, m = 40, 9
    x, u = roe[:m], dv[:m]
    b_i, psi_i = horizon.b[i], horizon.psi[i]
    fast = post_burn_covariance_checked(x, u, np.broadcast_to(b_i, (m, 6, 3)),
                                        np.broadcast_to(psi_i, (m, 6, 6)), CFG)
    np.testing.assert_array_equal(fast, post_burn_covariance(x, u, b_i, psi_i, CFG))


# ---------------------------------------------------------------------------- bad input
def test_bad_inputs_raise_input_error(horizon: Horizon) -> None:
    n = horizon.n_nodes
    roe = np.ones((n, 6))
    dv = np.zeros((n, 3))
    bad = roe.copy()
    bad[3, 2] = np.nan
    with pytest.raises(InputError):
        nav_covariance(bad, horizon.psi, CFG)
    with pytest.raises(InputError):
        nav_covariance(np.ones((n, 5)), horizon.psi, CFG)
    with pytest.raises(InputError):
        nav_covariance(roe, horizon.psi[:-1], CFG)
    with pytest.raises(InputError):
        gates_covariance(np.ones((n, 2)), CFG)
    with pytest.raises(InputError):
        gates_covariance(np.array([[np.inf, 0.0, 0.0]]), CFG)
    with pytest.raises(InputError):
        state_covariance_history(roe[:-1], dv[:-1], horizon, CFG)
    with pytest.raises(InputError):
        state_covariance_history(roe, dv[:, :2], horizon, None)
    with pytest.raises(InputError):
        propagate_covariance(np.ones((4, 6, 5)), np.ones((4, 6, 6)))
