"""Passive safety: ellipsoids, drift maps, linearisation (conservative), violation metric."""
from __future__ import annotations

import time

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import (
    Horizon,
    along_track_curvature_m,
    control_matrix_deputy,
    eci_from_oe,
    mean_motion,
    oe_from_roe,
    orbital_period_s,
    propagate_mean_oe,
    rtn_from_eci,
)
from art_guidance.errors import InputError
from art_guidance.safety import PassiveSafety

SC = ScenarioConfig()
UNC = UncertaintyConfig()
N = SC.n_nodes


@pytest.fixture(scope="module")
def ps_det(horizon: Horizon) -> PassiveSafety:
    return PassiveSafety(horizon, SC, None)


@pytest.fixture(scope="module")
def ps_cc(horizon: Horizon) -> PassiveSafety:
    return PassiveSafety(horizon, SC, UNC)


@pytest.fixture(scope="module")
def approach(horizon: Horizon) -> tuple[np.ndarray, np.ndarray]:
    """Paper nominal initial state with small random burns (a realistic reference)."""
    x0 = np.linalg.solve(horizon.psi[0], np.array(SC.rtn0_nominal))
    dv = np.random.default_rng(10).normal(0.0, 0.05, (N, 3))
    return horizon.propagate(x0, dv), dv


def _dist(ps: PassiveSafety, z: np.ndarray, i: int, tau_s: float) -> np.ndarray:
    """Ellipsoidal distance at node i, drift offset tau_s [s] of post-burn states z (K, 6)."""
    p = z @ ps.drift_maps(i, [tau_s])[1][0].T
    return np.sqrt(np.einsum("ki,ij,kj->k", p, ps.ellipsoid_p[i], p))


def _dense_min_dist(ps: PassiveSafety, z_i: np.ndarray, i: int, step_s: float = 1.0) -> float:
    """Minimum ellipsoidal distance of node i's drift from z_i (6,), sampled every step_s."""
    tau = np.linspace(0.0, ps.tau_s[-1], int(ps.tau_s[-1] / step_s) + 1)
    p = ps.drift_maps(i, tau)[1] @ z_i  # (K, 3)
    return float(np.sqrt(np.min(p * p @ np.diag(ps.ellipsoid_p[i]))))


# ---------------------------------------------------------------------------- set-up
def test_ellipsoid_switch_at_node_55(ps_det: PassiveSafety) -> None:
    assert ps_det.ellipsoid_p.shape == (N, 3, 3)
    np.testing.assert_allclose(ps_det.ellipsoid_p[:55],
                               np.broadcast_to(np.eye(3) / 1000.0**2, (55, 3, 3)))
    np.testing.assert_allclose(ps_det.ellipsoid_p[55:],
                               np.broadcast_to(np.eye(3) / 200.0**2, (N - 55, 3, 3)))
    assert np.all(ps_det.semi_axes_m[54] == 1000.0) and np.all(ps_det.semi_axes_m[55] == 200.0)


def test_drift_samples_and_maps(ps_det: PassiveSafety, horizon: Horizon) -> None:
    period = orbital_period_s(SC.chief_oe[0])
    assert ps_det.n_samples == 20 and ps_det.n_nodes == N
    np.testing.assert_allclose(ps_det.tau_s, np.linspace(0.0, period, 20))
    assert ps_det.drift_stms.shape == (N, 20, 6, 6)
    assert ps_det.drift_pos_maps.shape == (N, 20, 3, 6)
    np.testing.assert_allclose(ps_det.drift_stms[:, 0], np.broadcast_to(np.eye(6), (N, 6, 6)))
    np.testing.assert_allclose(ps_det.drift_pos_maps[:, 0], horizon.psi[:, :3], atol=1e-12)


@pytest.mark.parametrize("node", [0, 37, 80])
def test_drift_maps_match_absolute_j2_propagation(ps_det: PassiveSafety, horizon: Horizon,
                                                  node: int) -> None:
    """Independent truth: propagate chief and deputy mean elements, exact RTN at each sample."""
    for z in (np.array([0.0, 0.0, 0.0, 1500.0, 0.0, 1500.0]),
              np.array([100.0, 2500.0, 300.0, -800.0, 500.0, -900.0])):
        chief = horizon.chief_oe[node]
        dep = oe_from_roe(chief, z)
        truth = np.array([
            rtn_from_eci(eci_from_oe(c), eci_from_oe(d))[:3]
            for c, d in zip(propagate_mean_oe(chief, ps_det.tau_s),
                            propagate_mean_oe(dep, ps_det.tau_s))
        ])
        # first-order (in separation and in e) maps: 5 m at 1-3 km separation
        np.testing.assert_allclose(ps_det.drift_pos_maps[node] @ z, truth, atol=5.0)


def test_post_burn(ps_det: PassiveSafety, horizon: Horizon,
                   approach: tuple[np.ndarray, np.ndarray]) -> None:
    """The drift starts from the post-burn state of the planner's (deputy-aware) model."""
    x = horizon.propagate_nonlinear(approach[0][0], approach[1])
    dv = approach[1]
    z = ps_det.post_burn(x, dv)
    b7 = control_matrix_deputy(horizon.chief_oe[7], x[7])
    np.testing.assert_allclose(z[7], x[7] + b7 @ dv[7], rtol=1e-14)
    assert np.abs(b7 - horizon.b[7]).max() > 1e-4 * np.abs(horizon.b[7]).max()  # not B(0)
    drift = along_track_curvature_m(horizon.chief_oe[7, 0], z[7, 0],
                                    horizon.epochs_s[8] - horizon.epochs_s[7])
    np.testing.assert_allclose(horizon.stm[7] @ z[7] + drift * np.eye(6)[1], x[8], rtol=1e-12)


def test_zero_safety_time_is_plain_collision_avoidance(horizon: Horizon,
                                                       approach: tuple) -> None:
    x, dv = approach
    for unc in (None, UNC):
        ps0 = PassiveSafety(horizon, SC, unc, t_safety_s=0.0, n_safety=20)
        assert ps0.n_samples == 1
        np.testing.assert_array_equal(ps0.tau_s, [0.0])
        z = ps0.post_burn(x, dv)
        r = horizon.to_rtn(z)[:, :3]
        p_diag = np.einsum("kii->ki", ps0.ellipsoid_p)
        d = np.sqrt(np.sum(r * r * p_diag, axis=1))
        g = np.einsum("kij,ki->kj", horizon.psi[:, :3], r * p_diag) / d[:, None]
        x_cov = ps0.covariance(x, dv)
        sigma = np.sqrt(np.einsum("ki,kij,kj->k", g, x_cov, g))
        q = 0.0 if unc is None else unc.q_sigma
        ev = ps0.evaluate(x, dv)
        np.testing.assert_allclose(ev.margin, d - 1.0 - q * sigma, rtol=1e-12)
        np.testing.assert_array_equal(ev.t_star_s, 0.0)
        lin = ps0.linearize(x, dv)
        np.testing.assert_allclose(lin.a, g, rtol=1e-12, atol=1e-18)
        np.testing.assert_allclose(lin.rhs, 1.0 + q * sigma, rtol=1e-12)


def test_default_safety_time_from_scenario(horizon: Horizon) -> None:
    ps = PassiveSafety(horizon, SC.replace(t_safety_orbits=0.5, n_safety=7), None)
    assert ps.n_samples == 7
    assert ps.tau_s[-1] == pytest.approx(0.5 * orbital_period_s(SC.chief_oe[0]), rel=1e-12)


# ---------------------------------------------------------------------------- linearisation
def test_linearisation_exact_at_reference(ps_det: PassiveSafety, ps_cc: PassiveSafety,
                                          approach: tuple) -> None:
    x, dv = approach
    z = ps_det.post_burn(x, dv)
    for ps in (ps_det, ps_cc):
        lin = ps.linearize(x, dv)
        # d is homogeneous of degree one, so a @ z_ref = d(z_ref): tangent at the reference
        np.testing.assert_allclose(np.einsum("ki,ki->k", lin.a, z), lin.dist, rtol=1e-12)
        np.testing.assert_allclose(lin.rhs, 1.0 + lin.beta, rtol=0, atol=0)
    lin = ps_det.linearize(x, dv)
    np.testing.assert_array_equal(lin.beta, 0.0)
    # the paper's t* (minimum distance), now over the continuous arc: never above the samples,
    # and equal to a dense 1 s evaluation (tolerance: certification 1e-4 + 0.1 % of |margin|)
    sampled = np.stack([[_dist(ps_det, z[i:i + 1], i, t)[0] for t in ps_det.tau_s]
                        for i in range(0, N, 9)])
    dense = np.array([_dense_min_dist(ps_det, z[i], i) for i in range(0, N, 9)])
    assert np.all(lin.dist[::9] <= sampled.min(axis=1) + 1e-12)
    np.testing.assert_allclose(lin.dist[::9], dense, atol=1e-4, rtol=1e-3)
    assert np.all(ps_cc.linearize(x, dv).beta > 0)


def test_gradient_matches_finite_differences(ps_det: PassiveSafety, approach: tuple) -> None:
    x, dv = approach
    z = ps_det.post_burn(x, dv)
    lin = ps_det.linearize(x, dv)
    h = 1e-3  # [m]; z is O(1e3-1e4) m
    for i in (3, 50, 90):
        tau = lin.t_star_s[i]
        zp = z[i] + h * np.eye(6)
        zm = z[i] - h * np.eye(6)
        fd = (_dist(ps_det, zp, i, tau) - _dist(ps_det, zm, i, tau)) / (2 * h)
        np.testing.assert_allclose(lin.a[i], fd, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("chance", [False, True])
def test_linearisation_is_conservative(ps_det: PassiveSafety, ps_cc: PassiveSafety,
                                       approach: tuple, chance: bool) -> None:
    """Random z with a_i @ z >= rhs_i are outside the ellipsoid at t* by at least beta."""
    ps = ps_cc if chance else ps_det
    x, dv = approach
    z_ref = ps.post_burn(x, dv)
    lin = ps.linearize(x, dv)
    rng = np.random.default_rng(11)
    checked = 0
    for i in range(0, N, 3):
        a, rhs, j = lin.a[i], lin.rhs[i], lin.t_star_s[i]
        scale = np.linalg.norm(z_ref[i])
        z = z_ref[i] + rng.normal(0.0, 1.0, (4000, 6)) * scale * rng.uniform(0.01, 3, (4000, 1))
        lhs = z @ a
        short = np.maximum(rhs - lhs, 0.0)  # project infeasible samples onto the half-space
        z = z + (short / (a @ a))[:, None] * a + rng.uniform(0, 0.2, (4000, 1)) * a / (a @ a)
        lhs = z @ a
        assert np.all(lhs >= rhs - 1e-12)
        d = _dist(ps, z, i, j)
        assert np.all(d >= lhs * (1 - 1e-12))  # Cauchy-Schwarz: d(z) >= a @ z
        assert np.all(d >= rhs * (1 - 1e-12))  # hence d >= 1 + beta: outside with the margin
        checked += z.shape[0]
    assert checked == 34 * 4000


# ---------------------------------------------------------------------------- evaluation
def _analytic_flags(horizon: Horizon, da_m: float, dlam0_m: float, tau_s: np.ndarray,
                    semi_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keplerian along-track drift r = da, t = dlam0 - 1.5 n da t (no J2): flags and margins."""
    n = mean_motion(SC.chief_oe[0])
    t = horizon.epochs_s[:, None] + tau_s[None, :]
    along = dlam0_m - 1.5 * n * da_m * t
    d = np.sqrt(da_m**2 + along**2) / semi_axis[:, None]
    margin = d.min(axis=1) - 1.0
    return (margin < 0).astype(int), margin


def test_safe_ei_separated_formation(ps_det: PassiveSafety, ps_cc: PassiveSafety,
                                     horizon: Horizon) -> None:
    """Parallel de and di of 1.5 km: radial and normal never vanish together."""
    x = horizon.propagate(np.array([0.0, 0.0, 0.0, 1500.0, 0.0, 1500.0]), np.zeros((N, 3)))
    for ps in (ps_det, ps_cc):
        ev = ps.evaluate(x, np.zeros((N, 3)))
        np.testing.assert_array_equal(ev.violation, 0)
        np.testing.assert_array_equal(ev.constraint_to_go, 0)
        assert ev.margin[:55].min() > 0.45 and ev.margin[55:].min() > 6.3
        np.testing.assert_allclose(ev.margin_m, ev.margin * np.where(np.arange(N) < 55,
                                                                     1000.0, 200.0))
    assert np.all(ps_cc.evaluate(x, np.zeros((N, 3))).margin
                  < ps_det.evaluate(x, np.zeros((N, 3))).margin)


def test_along_track_drift_through_target(ps_det: PassiveSafety, ps_cc: PassiveSafety,
                                          horizon: Horizon) -> None:
    """da = 100 m, dlambda = 2.5 km: the free drift crosses the AE from node ~46 on."""
    x = horizon.propagate(np.array([100.0, 2500.0, 0.0, 0.0, 0.0, 0.0]), np.zeros((N, 3)))
    ev = ps_det.evaluate(x, np.zeros((N, 3)))
    axis = np.where(np.arange(N) < 55, 1000.0, 200.0)
    flags, margin = _analytic_flags(horizon, 100.0, 2500.0, ps_det.tau_s, axis)
    clear = np.abs(margin) > 0.01  # away from the boundary, J2 cannot flip a flag
    np.testing.assert_array_equal(ev.violation[clear], flags[clear])
    np.testing.assert_allclose(ev.margin, margin, atol=0.01)
    np.testing.assert_array_equal(np.nonzero(ev.violation)[0], np.arange(46, 55))
    np.testing.assert_array_equal(ev.constraint_to_go,
                                  np.cumsum(ev.violation[::-1])[::-1])
    assert ev.constraint_to_go[0] == 9 and ev.constraint_to_go[55] == 0
    # the q-sigma margin can only add violations
    ev_cc = ps_cc.evaluate(x, np.zeros((N, 3)))
    assert np.all(ev_cc.violation >= ev.violation) and ev_cc.constraint_to_go[0] > 9


def test_collision_avoidance_through_origin(horizon: Horizon) -> None:
    """T_safety = 0: the nodal trajectory itself passes 100 m below the target."""
    ps0 = PassiveSafety(horizon, SC, None, t_safety_s=0.0)
    x = horizon.propagate(np.array([100.0, 600.0, 0.0, 0.0, 0.0, 0.0]), np.zeros((N, 3)))
    ev = ps0.evaluate(x, np.zeros((N, 3)))
    axis = np.where(np.arange(N) < 55, 1000.0, 200.0)
    flags, margin = _analytic_flags(horizon, 100.0, 600.0, ps0.tau_s, axis)
    np.testing.assert_array_equal(ev.violation, flags)
    np.testing.assert_array_equal(np.nonzero(ev.violation)[0], np.arange(0, 63))
    np.testing.assert_allclose(ev.margin, margin, atol=0.01)


# ---------------------------------------------------------------------------- bad input
def test_bad_inputs(ps_cc: PassiveSafety, horizon: Horizon) -> None:
    x = np.ones((N, 6))
    dv = np.zeros((N, 3))
    x_nan = x.copy()
    x_nan[4, 1] = np.nan
    for call in (ps_cc.evaluate, ps_cc.linearize, ps_cc.post_burn, ps_cc.covariance):
        with pytest.raises(InputError):
            call(x_nan, dv)
        with pytest.raises(InputError):
            call(x[:-1], dv)
        with pytest.raises(InputError):
            call(x, np.zeros((N, 2)))
    with pytest.raises(InputError):
        PassiveSafety(horizon, SC, None, t_safety_s=-1.0)
    with pytest.raises(InputError):
        PassiveSafety(horizon, SC, None, t_safety_s=float("nan"))
    with pytest.raises(InputError):
        PassiveSafety(horizon, SC, None, n_safety=0)


def test_reference_through_target_centre_is_finite(ps_cc: PassiveSafety) -> None:
    """d = 0 has no gradient: a = 0 (infeasible, left to the optimiser's slack), no NaN."""
    lin = ps_cc.linearize(np.zeros((N, 6)), np.zeros((N, 3)))
    assert np.all(np.isfinite(lin.a)) and np.all(lin.a == 0.0)
    ev = ps_cc.evaluate(np.zeros((N, 6)), np.zeros((N, 3)))
    np.testing.assert_array_equal(ev.violation, 1)
    np.testing.assert_array_equal(ev.constraint_to_go, np.arange(N, 0, -1))


def test_repeated_evaluation_hits_the_cache(ps_cc: PassiveSafety, approach: tuple,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """SCVx* evaluates an iterate and then linearises it: the arc minima are computed once
    (the minimum is not searched again for an equal copy of the iterate, and a linearisation
    from the cache costs at most half of one that computes them; CPU time of this process,
    median of 10 calls each). The speed of evaluate, linearize and linearize_samples itself is
    measured by `art-guidance bench safety` (benchmarks/bench_safety.py)."""
    x, dv = approach
    ev = ps_cc.evaluate(x, dv)
    searched = []
    minimum = ps_cc.arcs.minimum
    monkeypatch.setattr(ps_cc.arcs, "minimum",
                        lambda items, **kw: searched.append(1) or minimum(items, **kw))
    lin = ps_cc.linearize(x.copy(), dv.copy())
    assert searched == []
    np.testing.assert_array_equal(lin.t_star_s, ev.t_star_s)
    margin, t_star = ps_cc.minimum(np.arange(ps_cc.n_nodes), x, dv)  # the same cached body
    assert searched == []
    np.testing.assert_array_equal(margin, ev.margin)
    np.testing.assert_array_equal(t_star, ev.t_star_s)
    ps_cc.linearize(x * 1.001, dv)
    assert searched == [1]  # another iterate: searched
    monkeypatch.undo()

    def cpu_s(fn) -> float:
        times = []
        for _ in range(10):
            t0 = time.process_time()
            fn()
            times.append(time.process_time() - t0)
        return float(np.median(times))

    inputs = [(x, dv), (x * 1.001, dv)]
    calls = iter(range(100))
    fresh = cpu_s(lambda: ps_cc.linearize(*inputs[next(calls) % 2]))  # never a cache hit
    ps_cc.evaluate(x, dv)
    cached = cpu_s(lambda: ps_cc.linearize(x.copy(), dv.copy()))
    assert cached <= 0.5 * fresh, (cached, fresh)


def test_koz_switch_is_an_explicit_argument(horizon):
    """The AE -> KOZ switch node comes as an argument (a replan's own grid), not by changing
    the scenario; None keeps the scenario's."""
    sc = ScenarioConfig()
    default = PassiveSafety(horizon, sc, None)
    assert np.all(default.semi_axes_m[:sc.ae_to_koz_node] == sc.ae_semi_axes_m[0])
    assert np.all(default.semi_axes_m[sc.ae_to_koz_node:] == sc.koz_semi_axes_m[0])
    shifted = PassiveSafety(horizon, sc, None, koz_switch_node=10)
    assert np.all(shifted.semi_axes_m[:10] == 1000.0) and np.all(shifted.semi_axes_m[10:] == 200.0)
    assert np.all(PassiveSafety(horizon, sc, None, koz_switch_node=0).semi_axes_m == 200.0)
    assert sc == ScenarioConfig()  # untouched
    with pytest.raises(InputError, match="koz_switch_node"):
        PassiveSafety(horizon, sc, None, koz_switch_node=-1)
