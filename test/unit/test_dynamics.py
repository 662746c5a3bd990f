"""Unit tests of art_guidance.dynamics: conversions, maps, STM, B, Horizon, input checking.

Physics against an independently integrated truth lives in test_dynamics_truth.py; here the
checks are algebraic (round trips, invariants, Jacobians by central differences, structure).
All random draws use fixed seeds.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from art_guidance import dynamics as dyn
from art_guidance.config import ScenarioConfig
from art_guidance.errors import GuidanceError, InputError

MU = 3.986004415e14  # docs/design.md, Models and constants
R_E = 6378136.3
J2 = 1.082635819197e-3


@pytest.fixture(scope="module")
def chief() -> np.ndarray:
    """Paper chief orbit (Table I) from the packaged scenario.yaml, radians."""
    return np.array(ScenarioConfig.from_yaml().chief_oe, dtype=float)


@pytest.fixture(scope="module")
def circular_chief(chief: np.ndarray) -> np.ndarray:
    """Same orbit with e = 0, where Psi and B are the exact Jacobians of the Kepler maps."""
    out = chief.copy()
    out[1] = 0.0
    return out


def _random_oes(rng: np.random.Generator, count: int, e_max: float = 0.7) -> np.ndarray:
    """Elliptic, non-equatorial orbits with perigee above the Earth's surface."""
    a = rng.uniform(7.0e6, 4.2e7, count)
    e = rng.uniform(0.0, e_max, count)
    e = np.minimum(e, 1.0 - 6.6e6 / a)
    i = rng.uniform(0.05, math.pi - 0.05, count)
    return np.column_stack([a, e, i, rng.uniform(0.0, 2 * math.pi, (count, 3))])


def _wrap(x: np.ndarray) -> np.ndarray:
    return (np.asarray(x) + math.pi) % (2 * math.pi) - math.pi


def _angles_close(got: np.ndarray, want: np.ndarray, atol: float) -> bool:
    return bool(np.all(np.abs(_wrap(np.asarray(got) - np.asarray(want))) <= atol))


# --------------------------------------------------------------------------- constants, config
def test_constants_match_physics_reference() -> None:
    assert dyn.MU_M3PS2 == MU
    assert dyn.R_EARTH_M == R_E
    assert dyn.J2 == J2


def test_config_chief_orbit_is_table_one(chief: np.ndarray) -> None:
    """Table I: a = 6738 km, e = 5.58e-4, angles in degrees converted to radians; T = 1.528 h."""
    want = [6738e3, 5.58e-4] + [math.radians(v) for v in (51.64, 301.04, 26.18, 68.23)]
    assert chief == pytest.approx(want, rel=1e-12)
    assert np.array_equal(dyn.check_oe(chief), chief)
    assert dyn.orbital_period_s(chief[0]) / 3600.0 == pytest.approx(1.528, abs=1e-3)
    assert dyn.mean_motion(chief[0]) == pytest.approx(math.sqrt(MU / chief[0] ** 3), rel=1e-15)


# --------------------------------------------------------------------------- ROE <-> OE
@pytest.mark.parametrize("scale_m", [1.0, 1e3, 2e4, 5e4])
def test_roe_oe_round_trip(chief: np.ndarray, scale_m: float) -> None:
    """oe_from_roe inverts roe_from_oe exactly (angles wrapped), from 1 m to 50 km (sigma)."""
    rng = np.random.default_rng(11)
    for roe in scale_m * rng.standard_normal((20, 6)):
        deputy = dyn.oe_from_roe(chief, roe)
        assert dyn.roe_from_oe(chief, deputy) == pytest.approx(roe, abs=1e-6)
        again = dyn.oe_from_roe(chief, dyn.roe_from_oe(chief, deputy))
        assert again[:3] == pytest.approx(deputy[:3], rel=1e-12, abs=1e-15)
        assert _angles_close(again[3:], deputy[3:], 1e-12)


def test_roe_definition_and_angle_wrapping(chief: np.ndarray) -> None:
    """ROE match the definition in docs/design.md, across the 0/2 pi wrap of M and RAAN."""
    a, e, i, raan, w, m = chief
    deputy = chief.copy()
    deputy[0] += 100.0
    deputy[3] = raan + 1e-5
    deputy[5] = m + 2e-5 - 2 * math.pi  # same physical angle, other branch
    roe = dyn.roe_from_oe(chief, deputy)
    want = a * np.array([100.0 / a, 2e-5 + 1e-5 * math.cos(i), 0.0, 0.0, 0.0,
                         1e-5 * math.sin(i)])
    assert roe == pytest.approx(want, abs=1e-6)
    near_zero = chief.copy()
    near_zero[3], near_zero[5] = 2 * math.pi - 1e-6, 2 * math.pi - 1e-6
    dep = near_zero.copy()
    dep[3], dep[5] = 1e-6, 1e-6  # just past the wrap
    roe = dyn.roe_from_oe(near_zero, dep)
    assert roe[1] == pytest.approx(a * (2e-6 + 2e-6 * math.cos(i)), rel=1e-6)
    assert roe[5] == pytest.approx(a * 2e-6 * math.sin(i), rel=1e-6)


# --------------------------------------------------------------------------- ECI <-> OE
def test_eci_oe_round_trip() -> None:
    """oe_from_eci inverts eci_from_oe for 200 random elliptic orbits (e up to 0.7)."""
    rng = np.random.default_rng(3)
    for oe in _random_oes(rng, 200):
        state = dyn.eci_from_oe(oe)
        back = dyn.oe_from_eci(state)
        assert back[0] == pytest.approx(oe[0], rel=1e-11)
        assert back[1] == pytest.approx(oe[1], abs=1e-11)
        assert back[2] == pytest.approx(oe[2], abs=1e-11)
        assert _angles_close(back[3], oe[3], 1e-10)
        if oe[1] > 1e-6:  # argument of perigee / M undefined for circular orbits, u is not
            assert _angles_close(back[4:], oe[4:], 1e-8 / oe[1])
        assert _angles_close(back[4] + back[5], oe[4] + oe[5], 1e-9)
        assert dyn.eci_from_oe(back) == pytest.approx(state, rel=1e-10, abs=1e-6)


def test_eci_from_oe_two_body_invariants() -> None:
    """Energy -mu/2a, |h| = sqrt(mu p), h direction from (i, RAAN), e vector from (e, w, i, RAAN).
    """
    rng = np.random.default_rng(5)
    for a, e, i, raan, w, m in _random_oes(rng, 50):
        s = dyn.eci_from_oe([a, e, i, raan, w, m])
        r, v = s[:3], s[3:]
        assert 0.5 * v @ v - MU / np.linalg.norm(r) == pytest.approx(-MU / (2 * a), rel=1e-12)
        h = np.cross(r, v)
        assert np.linalg.norm(h) == pytest.approx(math.sqrt(MU * a * (1 - e * e)), rel=1e-12)
        h_hat = [math.sin(raan) * math.sin(i), -math.cos(raan) * math.sin(i), math.cos(i)]
        assert h / np.linalg.norm(h) == pytest.approx(h_hat, abs=1e-12)
        e_vec = np.cross(v, h) / MU - r / np.linalg.norm(r)
        p_hat = [math.cos(raan) * math.cos(w) - math.sin(raan) * math.sin(w) * math.cos(i),
                 math.sin(raan) * math.cos(w) + math.cos(raan) * math.sin(w) * math.cos(i),
                 math.sin(w) * math.sin(i)]
        assert e_vec == pytest.approx(e * np.array(p_hat), abs=1e-10)
        # Kepler's equation: |r| = a (1 - e cos E)
        ecc = dyn.solve_kepler(float(_wrap(m)), e)
        assert ecc - e * math.sin(ecc) == pytest.approx(float(_wrap(m)), abs=1e-12)
        assert np.linalg.norm(r) == pytest.approx(a * (1 - e * math.cos(ecc)), rel=1e-12)


# --------------------------------------------------------------------------- RTN
def test_rtn_eci_round_trip_and_frame(chief: np.ndarray) -> None:
    """eci_from_rtn inverts rtn_from_eci; the basis is orthonormal and right-handed."""
    rng = np.random.default_rng(8)
    chief_eci = dyn.eci_from_oe(chief)
    basis, omega = dyn.rtn_frame(chief_eci)
    assert basis.T @ basis == pytest.approx(np.eye(3), abs=1e-15)
    assert np.linalg.det(basis) == pytest.approx(1.0, abs=1e-14)
    assert basis[:, 0] == pytest.approx(chief_eci[:3] / np.linalg.norm(chief_eci[:3]), abs=1e-15)
    assert omega[:2] == pytest.approx([0.0, 0.0])
    for rtn in np.column_stack([rng.normal(0, 5e3, (10, 3)), rng.normal(0, 5, (10, 3))]):
        deputy = dyn.eci_from_rtn(chief_eci, rtn)
        assert dyn.rtn_from_eci(chief_eci, deputy) == pytest.approx(rtn, abs=1e-7)


def test_rtn_velocity_is_time_derivative_of_rtn_position(chief: np.ndarray) -> None:
    """rtn_from_eci velocity = d/dt of the RTN position along exact Keplerian motion.

    Independent of the omega x r formula: central differences (h = 0.5 s) of the RTN positions
    of a deputy 3 km away, both spacecraft propagated by Kepler's equation (M advanced by n t).
    Tolerance 1e-6 m/s: the O(h^2) difference error is ~ n^2 h^2 |dv| ~ 1e-7 m/s.
    """
    deputy_oe = dyn.oe_from_roe(chief, [300.0, -2000.0, 500.0, 800.0, -600.0, 1200.0])

    def rtn_at(t: float) -> np.ndarray:
        c, d = chief.copy(), deputy_oe.copy()
        c[5] += dyn.mean_motion(c[0]) * t
        d[5] += dyn.mean_motion(d[0]) * t
        return dyn.rtn_from_eci(dyn.eci_from_oe(c), dyn.eci_from_oe(d))

    for t in np.linspace(0.0, 5000.0, 7):
        fd = (rtn_at(t + 0.5)[:3] - rtn_at(t - 0.5)[:3]) / 1.0
        assert rtn_at(t)[3:] == pytest.approx(fd, abs=1e-6)


@pytest.mark.parametrize("scale_m", [10.0, 1e3, 2e4, 5e4])
def test_exact_rtn_roe_round_trip(chief: np.ndarray, scale_m: float) -> None:
    """roe_from_rtn_exact inverts rtn_from_roe_exact (and vice versa) from 10 m to 50 km."""
    rng = np.random.default_rng(17)
    n = dyn.mean_motion(chief[0])
    for roe in scale_m * rng.standard_normal((10, 6)):
        rtn = dyn.rtn_from_roe_exact(chief, roe)
        assert dyn.roe_from_rtn_exact(chief, rtn) == pytest.approx(roe, abs=1e-6 + 1e-9 * scale_m)
    for x in scale_m * rng.standard_normal((10, 6)):
        rtn = np.concatenate([x[:3], n * x[3:]])
        roe = dyn.roe_from_rtn_exact(chief, rtn)
        assert dyn.rtn_from_roe_exact(chief, roe) == pytest.approx(rtn, abs=1e-6 + 1e-9 * scale_m)


def test_linear_rtn_roe_maps_are_inverse(chief: np.ndarray) -> None:
    rng = np.random.default_rng(21)
    for roe in 1e3 * rng.standard_normal((10, 6)):
        rtn = dyn.rtn_from_roe_linear(chief, roe)
        assert rtn == pytest.approx(dyn.psi_matrix(chief) @ roe, rel=1e-14)
        assert dyn.roe_from_rtn_linear(chief, rtn) == pytest.approx(roe, abs=1e-8)


def _exact_map_jacobian(chief_oe: np.ndarray, h: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobian of the exact ROE -> RTN map at 0, and the (1, 1/n) scaling."""
    jac = np.zeros((6, 6))
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        jac[:, k] = (dyn.rtn_from_roe_exact(chief_oe, step)
                     - dyn.rtn_from_roe_exact(chief_oe, -step)) / (2 * h)
    n = dyn.mean_motion(chief_oe[0])
    return jac, np.diag([1, 1, 1, 1 / n, 1 / n, 1 / n])


def test_psi_is_jacobian_of_exact_map_for_circular_chief(circular_chief: np.ndarray) -> None:
    """For e = 0 the first-order map is exactly the Jacobian of the exact ROE -> RTN map at 0.

    Central differences with h = 10 m (truncation O(h^2/a^2) ~ 1e-12, rounding ~ 1e-9).
    Tolerance 1e-8 on entries of size 1 (positions) and n (velocities, compared after / n).
    """
    jac, scale = _exact_map_jacobian(circular_chief)
    assert scale @ jac == pytest.approx(scale @ dyn.psi_matrix(circular_chief), abs=1e-8)


def test_psi_near_circular_error_is_first_order_in_e(chief: np.ndarray) -> None:
    """For the paper's e = 5.58e-4, Psi differs from the exact Jacobian by O(e): <= 4 e."""
    jac, scale = _exact_map_jacobian(chief)
    err = np.max(np.abs(scale @ (jac - dyn.psi_matrix(chief))))
    assert 1e-2 * chief[1] < err <= 4 * chief[1]


# --------------------------------------------------------------------------- control matrix
def test_control_matrix_is_jacobian_for_circular_chief(circular_chief: np.ndarray) -> None:
    """For e = 0, B is exactly d(ROE)/d(dv) of an impulse at the chief's position.

    Central differences of roe_from_rtn_exact with a pure velocity offset (h = 1 mm/s).
    Tolerance 1e-7 / n on entries of size <= 2 / n.
    """
    h = 1e-3
    jac = np.zeros((6, 3))
    for k in range(3):
        dv = np.zeros(6)
        dv[3 + k] = h
        jac[:, k] = (dyn.roe_from_rtn_exact(circular_chief, dv)
                     - dyn.roe_from_rtn_exact(circular_chief, -dv)) / (2 * h)
    n = dyn.mean_motion(circular_chief[0])
    assert n * jac == pytest.approx(n * dyn.control_matrix(circular_chief), abs=1e-7)


def test_control_matrix_structure(chief: np.ndarray) -> None:
    """Radial dv: no da; tangential: da = 2 dv / n; normal dv only moves the inclination vector."""
    b = dyn.control_matrix(chief)
    n = dyn.mean_motion(chief[0])
    u = chief[4] + chief[5]
    assert b.shape == (6, 3)
    assert b[:, 0] == pytest.approx([0, -2 / n, math.sin(u) / n, -math.cos(u) / n, 0, 0])
    assert b[:, 1] == pytest.approx([2 / n, 0, 2 * math.cos(u) / n, 2 * math.sin(u) / n, 0, 0])
    assert b[:, 2] == pytest.approx([0, 0, 0, 0, math.cos(u) / n, math.sin(u) / n])


# --------------------------------------------------------------------------- STM, mean elements
def test_stm_is_identity_at_zero_and_keplerian_without_j2_terms(chief: np.ndarray) -> None:
    """Phi(0) = I; da and dix are J2 invariants (rows 1 and 5 are unit rows)."""
    assert dyn.stm_j2(chief, 0.0) == pytest.approx(np.eye(6), abs=1e-15)
    tau = dyn.orbital_period_s(chief[0])
    phi = dyn.stm_j2(chief, tau)
    assert phi[0] == pytest.approx(np.eye(6)[0], abs=0)
    assert phi[4] == pytest.approx(np.eye(6)[4], abs=0)
    # along-track drift: -3/2 n tau plus a J2 correction of O(kappa tau) ~ 1e-3 relative
    n = dyn.mean_motion(chief[0])
    assert phi[1, 0] == pytest.approx(-1.5 * n * tau, rel=5e-3)
    assert phi[1, 0] != pytest.approx(-1.5 * n * tau, rel=1e-6)


@pytest.mark.parametrize("ecc", [5.58e-4, 0.01, 0.1])
def test_stm_composition(chief: np.ndarray, ecc: float) -> None:
    """Phi(t0 + t1 + t2, t0) = Phi(t2; oe(t1)) Phi(t1; oe(t0)) with mean elements propagated.

    The secular J2 STM composes exactly (the e-vector cross terms cancel because the middle
    eccentricity vector is the rotated initial one); tolerance 1e-12 of max |Phi|.
    """
    oe = chief.copy()
    oe[1] = ecc
    period = dyn.orbital_period_s(oe[0])
    for t1, t2 in [(0.3 * period, 0.5 * period), (period, 2.5 * period)]:
        whole = dyn.stm_j2(oe, t1 + t2)
        chained = dyn.stm_j2(dyn.propagate_mean_oe(oe, t1), t2) @ dyn.stm_j2(oe, t1)
        assert np.max(np.abs(whole - chained)) <= 1e-12 * np.max(np.abs(whole))


def test_propagate_mean_oe_shapes_and_rates(chief: np.ndarray) -> None:
    """Scalar tau -> (6,), (K,) -> (K, 6); a, e, i constant; angles linear in tau."""
    assert dyn.propagate_mean_oe(chief, 0.0) == pytest.approx(chief, abs=0)
    one = dyn.propagate_mean_oe(chief, 100.0)
    assert one.shape == (6,)
    taus = np.linspace(0.0, 1e4, 5)
    many = dyn.propagate_mean_oe(chief, taus)
    assert many.shape == (5, 6)
    assert np.all(many[:, :3] == chief[:3])
    raan_dot, argp_dot, m_dot = dyn.j2_secular_rates(chief)
    assert many[:, 3] == pytest.approx(chief[3] + raan_dot * taus, rel=1e-14)
    assert many[:, 4] == pytest.approx(chief[4] + argp_dot * taus, rel=1e-14)
    assert many[:, 5] == pytest.approx(chief[5] + m_dot * taus, rel=1e-14)
    assert many[2] == pytest.approx(dyn.propagate_mean_oe(chief, taus[2]), rel=1e-15)
    # prograde orbit below 63.4 deg: node regresses, perigee advances, M faster than Kepler
    assert raan_dot < 0 < argp_dot
    assert m_dot > dyn.mean_motion(chief[0])


# --------------------------------------------------------------------------- Horizon
@pytest.fixture(scope="module")
def horizon(chief: np.ndarray) -> dyn.Horizon:
    return dyn.Horizon.build(chief, dyn.time_grid_s(chief[0], 1.29, 100))


def test_time_grid(chief: np.ndarray) -> None:
    grid = dyn.time_grid_s(chief[0], 1.29, 100)
    assert grid.shape == (100,)
    assert grid[0] == 0.0
    assert grid[-1] == pytest.approx(1.29 * dyn.orbital_period_s(chief[0]), rel=1e-14)
    assert np.allclose(np.diff(grid), grid[1])
    for bad in [(1.29, 1), (0.0, 10), (-1.0, 10), (float("nan"), 10)]:
        with pytest.raises(InputError):
            dyn.time_grid_s(chief[0], *bad)


def test_horizon_build_shapes_and_contents(chief: np.ndarray, horizon: dyn.Horizon) -> None:
    t = horizon.epochs_s
    assert horizon.n_nodes == 100
    assert horizon.chief_oe.shape == (100, 6)
    assert horizon.stm.shape == (99, 6, 6)
    assert horizon.b.shape == (100, 6, 3)
    assert horizon.psi.shape == (100, 6, 6)
    for k in (0, 37, 98):
        oe_k = dyn.propagate_mean_oe(chief, t[k])
        assert horizon.chief_oe[k] == pytest.approx(oe_k, rel=1e-14)
        assert horizon.stm[k] == pytest.approx(dyn.stm_j2(oe_k, t[k + 1] - t[k]), rel=1e-12)
        assert horizon.b[k] == pytest.approx(dyn.control_matrix(oe_k), rel=1e-12, abs=1e-9)
        assert horizon.psi[k] == pytest.approx(dyn.psi_matrix(oe_k), rel=1e-12, abs=1e-15)


def test_horizon_propagate_shape_and_consistency(chief: np.ndarray,
                                                 horizon: dyn.Horizon) -> None:
    """Rollout = explicit loop x_{k+1} = Phi_k (x_k + B_k u_k); linear; coasting = one STM."""
    rng = np.random.default_rng(31)
    x0 = dyn.roe_from_rtn_linear(chief, [-4000.0, -17500.0, 0.0, 0.0, 6.849, 0.0])
    u = rng.normal(0.0, 0.05, (100, 3))
    out = horizon.propagate(x0, u)
    assert out.shape == (100, 6)
    assert out[0] == pytest.approx(x0, abs=0)
    x = x0.copy()
    for k in range(99):
        x = horizon.stm[k] @ (x + horizon.b[k] @ u[k])
        assert out[k + 1] == pytest.approx(x, rel=1e-12, abs=1e-9)
    coast = horizon.propagate(x0, np.zeros((100, 3)))
    whole = dyn.stm_j2(chief, horizon.epochs_s[-1]) @ x0
    assert coast[-1] == pytest.approx(whole, rel=1e-10, abs=1e-6)
    burns_only = horizon.propagate(np.zeros(6), u)
    assert out == pytest.approx(coast + burns_only, rel=1e-10, abs=1e-6)
    rtn = horizon.to_rtn(out)
    assert rtn.shape == (100, 6)
    assert rtn[42] == pytest.approx(horizon.psi[42] @ out[42], rel=1e-14)


def test_horizon_rejects_bad_input(chief: np.ndarray, horizon: dyn.Horizon) -> None:
    with pytest.raises(InputError):
        dyn.Horizon.build(chief, [0.0, 10.0, 10.0])
    with pytest.raises(InputError):
        dyn.Horizon.build(chief, [0.0, 20.0, 10.0])
    with pytest.raises(InputError):
        dyn.Horizon.build(chief, [0.0])
    with pytest.raises(InputError):
        dyn.Horizon.build(chief, [[0.0, 1.0]])
    with pytest.raises(InputError):
        horizon.propagate(np.zeros(6), np.zeros((99, 3)))
    with pytest.raises(InputError):
        horizon.propagate(np.zeros(5), np.zeros((100, 3)))
    with pytest.raises(InputError):
        horizon.propagate(np.full(6, np.nan), np.zeros((100, 3)))


# --------------------------------------------------------------------------- deputy-aware model
def _deputy_case(horizon: dyn.Horizon) -> tuple[np.ndarray, np.ndarray]:
    """A 17 km approach with 0.3 m/s burns (seeded): initial ROE (6,) [m], dv (N, 3) [m/s]."""
    rng = np.random.default_rng(7)
    x0 = np.array([-4000.0, -17500.0, 300.0, 2000.0, 50.0, -80.0])
    return x0, rng.normal(0.0, 0.3, (horizon.n_nodes, 3))


def test_propagate_nonlinear_is_its_definition(horizon: dyn.Horizon) -> None:
    """x_{k+1} = Phi_k z_k + curvature(z_k) e_dlambda, z_k = x_k + B_d(x_k) u_k, step by step."""
    x0, dv = _deputy_case(horizon)
    out = horizon.propagate_nonlinear(x0, dv)
    x = x0
    for k in range(horizon.n_nodes - 1):
        z = x + dyn.control_matrix_deputy(horizon.chief_oe[k], x) @ dv[k]
        x = horizon.stm[k] @ z
        x[1] += dyn.along_track_curvature_m(horizon.chief_oe[0, 0], z[0],
                                            horizon.epochs_s[k + 1] - horizon.epochs_s[k])
        np.testing.assert_allclose(out[k + 1], x, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(horizon.post_burn_nonlinear(out, dv)[-1],
                               horizon.final_post_burn_nonlinear(out, dv), atol=1e-9)
    np.testing.assert_allclose(horizon.post_burn_at(5, out[5:6], dv[5:6])[0],
                               horizon.post_burn_nonlinear(out, dv)[5], atol=1e-9)
    # without burns and at zero separation it is the linear model
    zero = np.zeros((horizon.n_nodes, 3))
    np.testing.assert_allclose(horizon.propagate_nonlinear(np.zeros(6), zero), 0.0)
    curv = horizon.propagate_nonlinear(x0, zero) - horizon.propagate(x0, zero)
    # only dlambda, by ~15/8 n t (a da)^2 / a: 28 m per orbit at a da = -4 km
    assert np.allclose(np.delete(curv, 1, axis=1), 0.0, atol=1e-6)
    a_m = horizon.chief_oe[0, 0]
    expect = 15 / 8 * dyn.mean_motion(a_m) * horizon.epochs_s[-1] * x0[0] ** 2 / a_m
    assert curv[-1, 1] == pytest.approx(expect, rel=0.01)
    # the curvature term: 175 m per orbit at a da = -10 km
    t_orbit = dyn.orbital_period_s(horizon.chief_oe[0, 0])
    assert dyn.along_track_curvature_m(horizon.chief_oe[0, 0], -1e4, t_orbit) == pytest.approx(
        175.0, rel=0.01)


def test_post_burn_at_is_one_door_for_every_shape(horizon: dyn.Horizon) -> None:
    """`post_burn_at` of K trajectories, of single nodes and of any mix of nodes, and its
    adapters (a trajectory, its last node): the same numbers, bit for bit."""
    x0, dv = _deputy_case(horizon)
    n = horizon.n_nodes
    roe = np.stack([horizon.propagate_nonlinear(x0 * s, dv * s) for s in (1.0, 0.5, -0.3)])
    u = np.stack([dv, 0.5 * dv, -0.3 * dv])
    each = np.stack([horizon.post_burn_nonlinear(r, v) for r, v in zip(roe, u)])
    np.testing.assert_array_equal(horizon.post_burn_at(np.arange(n), roe, u), each)
    for k in (0, 41, n - 1):
        np.testing.assert_array_equal(horizon.post_burn_at(k, roe[:, k], u[:, k]), each[:, k])
    b, k = np.divmod(np.random.default_rng(2).permutation(3 * n)[:50], n)
    np.testing.assert_array_equal(horizon.post_burn_at(k, roe[b, k], u[b, k]), each[b, k])
    np.testing.assert_array_equal(horizon.final_post_burn_nonlinear(roe[1], u[1]), each[1, -1])
    with pytest.raises(InputError):
        horizon.post_burn_nonlinear(roe, u)


def test_deputy_linearization_matches_finite_differences(horizon: dyn.Horizon) -> None:
    """E = dz/dx, B = dz/du, P = dx_{k+1}/dz and the terminal sensitivity by central differences.

    Tolerance 1e-7 relative: the model is smooth on the scale of the orbit (a); steps of 1 m and
    1 mm/s leave truncation errors ~ (step / a)^2.
    """
    x0, dv = _deputy_case(horizon)
    roe = horizon.propagate_nonlinear(x0, dv)
    lin = horizon.linearize_nonlinear(roe, dv)
    eye = np.eye(6)
    num_e = np.stack([(horizon.post_burn_nonlinear(roe + eye[j], dv)
                       - horizon.post_burn_nonlinear(roe - eye[j], dv)) / 2.0
                      for j in range(6)], axis=-1)
    np.testing.assert_allclose(lin.e, num_e, rtol=0.0, atol=1e-7)
    h_u = 1e-3
    num_b = np.stack([(horizon.post_burn_nonlinear(roe, dv + h_u * np.eye(3)[j])
                       - horizon.post_burn_nonlinear(roe, dv - h_u * np.eye(3)[j])) / (2 * h_u)
                      for j in range(3)], axis=-1)
    np.testing.assert_allclose(lin.b, num_b, rtol=1e-7, atol=1e-7 * np.abs(lin.b).max())
    np.testing.assert_allclose(lin.e @ roe[:, :, None] + lin.b @ dv[:, :, None]
                               - lin.jx[:, :, None], lin.z[:, :, None], atol=1e-6)
    # one step: x_{k+1} = P_k z_k (+ a term constant in z near the reference)
    k = 10

    def next_state(z: np.ndarray) -> np.ndarray:
        xz = horizon.stm[k] @ z
        xz[1] += dyn.along_track_curvature_m(horizon.chief_oe[0, 0], z[0],
                                             horizon.epochs_s[k + 1] - horizon.epochs_s[k])
        return xz

    num_p0 = (next_state(lin.z[k] + eye[0]) - next_state(lin.z[k] - eye[0])) / 2.0
    np.testing.assert_allclose(lin.p[k][:, 0], num_p0, atol=1e-7)
    g = lin.terminal_sensitivity  # (6, 3N)
    for col in (0, 3 * 40 + 1, 3 * horizon.n_nodes - 1):
        du = np.zeros(3 * horizon.n_nodes)
        du[col] = h_u
        ends = [horizon.final_post_burn_nonlinear(horizon.propagate_nonlinear(x0, u), u)
                for u in ((dv.ravel() + du).reshape(-1, 3), (dv.ravel() - du).reshape(-1, 3))]
        np.testing.assert_allclose(g[:, col], (ends[0] - ends[1]) / (2 * h_u), rtol=1e-6,
                                   atol=1e-6 * np.abs(g).max())


# --------------------------------------------------------------------------- input checking
def _bad_oes(chief: np.ndarray) -> list:
    nan = chief.copy()
    nan[2] = np.nan
    inf = chief.copy()
    inf[5] = np.inf
    parabolic = chief.copy()
    parabolic[1] = 1.0
    hyperbolic = chief.copy()
    hyperbolic[1] = 1.5
    neg_e = chief.copy()
    neg_e[1] = -0.1
    neg_a = chief.copy()
    neg_a[0] = -6738e3
    sub_surface = chief.copy()
    sub_surface[0] = 6000e3
    return [nan, inf, parabolic, hyperbolic, neg_e, neg_a, sub_surface, chief[:5],
            np.append(chief, 0.0), chief.reshape(6, 1), chief.reshape(2, 3), "chief", None]


_OE_FUNCTIONS = {
    "check_oe": lambda oe, c: dyn.check_oe(oe),
    "eci_from_oe": lambda oe, c: dyn.eci_from_oe(oe),
    "psi_matrix": lambda oe, c: dyn.psi_matrix(oe),
    "control_matrix": lambda oe, c: dyn.control_matrix(oe),
    "stm_j2": lambda oe, c: dyn.stm_j2(oe, 100.0),
    "propagate_mean_oe": lambda oe, c: dyn.propagate_mean_oe(oe, 100.0),
    "roe_from_oe_chief": lambda oe, c: dyn.roe_from_oe(oe, c),
    "roe_from_oe_deputy": lambda oe, c: dyn.roe_from_oe(c, oe),
    "oe_from_roe": lambda oe, c: dyn.oe_from_roe(oe, np.zeros(6)),
    "rtn_from_roe_exact": lambda oe, c: dyn.rtn_from_roe_exact(oe, np.zeros(6)),
    "Horizon.build": lambda oe, c: dyn.Horizon.build(oe, [0.0, 10.0]),
}


@pytest.mark.parametrize("name", sorted(_OE_FUNCTIONS))
def test_bad_orbit_elements_raise_input_error(chief: np.ndarray, name: str) -> None:
    """NaN/inf, wrong shapes, e >= 1, e < 0, a < 0, a < R_E: InputError (a GuidanceError)."""
    for bad in _bad_oes(chief):
        with pytest.raises(InputError) as info:
            _OE_FUNCTIONS[name](bad, chief)
        assert isinstance(info.value, GuidanceError)
        assert isinstance(info.value, ValueError)
        assert info.value.field


@pytest.mark.parametrize("bad", [[np.nan] * 6, [0.0] * 5, [[0.0] * 6], "x"])
def test_bad_state_vectors_raise_input_error(chief: np.ndarray, bad: object) -> None:
    chief_eci = dyn.eci_from_oe(chief)
    calls = [
        lambda: dyn.roe_from_rtn_linear(chief, bad),
        lambda: dyn.rtn_from_roe_linear(chief, bad),
        lambda: dyn.oe_from_roe(chief, bad),
        lambda: dyn.roe_from_rtn_exact(chief, bad),
        lambda: dyn.rtn_from_eci(chief_eci, bad),
        lambda: dyn.rtn_from_eci(bad, chief_eci),
        lambda: dyn.eci_from_rtn(chief_eci, bad),
        lambda: dyn.oe_from_eci(bad),
    ]
    for call in calls:
        with pytest.raises(GuidanceError):
            call()
        with pytest.raises(InputError):
            call()


def test_domain_errors_raise_input_error(chief: np.ndarray) -> None:
    """Unbound state; equatorial orbit (node / ROE inclination vector undefined); a_d <= 0."""
    r = dyn.eci_from_oe(chief)[:3]
    v_escape = math.sqrt(2 * MU / np.linalg.norm(r))
    escape = np.concatenate([r, 1.1 * v_escape * r / np.linalg.norm(r)])
    with pytest.raises(InputError):
        dyn.oe_from_eci(escape)
    equatorial = chief.copy()
    equatorial[2] = 0.0
    with pytest.raises(InputError):
        dyn.oe_from_roe(equatorial, np.zeros(6))
    with pytest.raises(InputError):  # node undefined: an error, never a silent NaN
        dyn.oe_from_eci(dyn.eci_from_oe(equatorial))
    with pytest.raises(InputError):
        dyn.oe_from_roe(chief, [-chief[0], 0, 0, 0, 0, 0])
    with pytest.raises(InputError):
        dyn.oe_from_roe(chief, [0, 0, chief[0], 0, 0, 0])  # deputy e >= 1


def test_stm_and_psi_vectorised_match_scalar_calls():
    """Array inputs give exactly the stacked scalar results (used by the drift precompute)."""
    chief = np.array(ScenarioConfig().chief_oe)
    tau = np.linspace(0.0, 5400.0, 7)
    batch = dyn.stm_j2(chief, tau)
    assert batch.shape == (7, 6, 6)
    for k, t in enumerate(tau):
        np.testing.assert_array_equal(batch[k], dyn.stm_j2(chief, float(t)))
    u = np.linspace(0.0, 6.0, 5)
    n = dyn.mean_motion(chief[0])
    psis = dyn.psi_from_latitude(u, n)
    for k, uk in enumerate(u):
        np.testing.assert_array_equal(psis[k], dyn.psi_from_latitude(float(uk), n))


def test_the_deputy_post_burn_in_floats_is_the_batch_form():
    """The deputy-aware post-burn state has two speeds of one definition: `post_burn_batch`
    (``x + B_d(x) u`` with `control_matrix_deputy`, every array caller) and
    `deputy_post_burn` (the same in floats, the single-trajectory loop); they agree to
    1e-9 m on random states."""
    from art_guidance.dynamics import control_matrix_deputy
    from art_guidance.dynamics.deputy import deputy_post_burn, post_burn_batch
    from art_guidance.dynamics.elements import mean_arg_latitude, mean_motion

    chief = np.array(ScenarioConfig().chief_oe)
    rng = np.random.default_rng(5)
    x = rng.normal(0.0, [3e3, 1e4, 500.0, 500.0, 300.0, 300.0], (16, 6))
    u = rng.normal(0.0, 0.5, (16, 3))
    lat, n, a, inc = float(mean_arg_latitude(chief)), mean_motion(chief[0]), chief[0], chief[2]
    batch = post_burn_batch(lat, n, a, inc, x, u)
    floats = np.array([deputy_post_burn(lat, n, a, inc, xi.tolist(), ui.tolist())
                       for xi, ui in zip(x, u)])
    np.testing.assert_array_equal(
        batch, x + (control_matrix_deputy(chief, x) @ u[:, :, None])[:, :, 0])
    np.testing.assert_allclose(batch, floats, rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(post_burn_batch(lat, n, a, inc, x[0], u[0]), batch[0])
