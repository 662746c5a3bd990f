"""Continuous-time passive safety: closed-form drift arcs, certified minimum, fly-by, node API.

The references here are independent of `safety/drift.py`: drift positions from
`PassiveSafety.drift_maps` (dynamics.stm_j2 and psi_from_latitude at each instant) and margins
from a dense 1 s evaluation of those maps, with the covariance propagated explicitly (Phi X
Phi^T) for the chance margin.
"""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.safety.drift import CERT_TOL, CERT_TOL_REL, ArcPoints
from art_guidance.dynamics import (
    Horizon, propagate_mean_oe, roe_from_rtn_linear, stm_basis, stm_basis_orders, stm_j2,
    stm_j2_terms,
)
from art_guidance.errors import InputError
from art_guidance.optim import TransferProblem
from art_guidance.safety import PassiveSafety
from helpers.oracles import sign_only_violations

SC = ScenarioConfig()
UNC = UncertaintyConfig()
N = SC.n_nodes


@pytest.fixture(scope="module")
def models(horizon: Horizon) -> dict:
    return {"det": PassiveSafety(horizon, SC, None), "cc": PassiveSafety(horizon, SC, UNC)}


@pytest.fixture(scope="module")
def approach(horizon: Horizon) -> tuple[np.ndarray, np.ndarray]:
    x0 = np.linalg.solve(horizon.psi[0], np.array(SC.rtn0_nominal))
    dv = np.random.default_rng(10).normal(0.0, 0.05, (N, 3))
    return horizon.propagate(x0, dv), dv


@pytest.fixture(scope="module")
def plans(horizon: Horizon, models: dict) -> list:
    """Converged chance-constrained plans (seeds 3 and 11: fast fly-bys in the KOZ phase)."""
    out = []
    for seed in (3, 11):
        s = sample_scenario(SC, seed)
        x0 = np.linalg.solve(horizon.psi[0], s.rtn0)
        problem = TransferProblem.to_target(models["cc"], x0, s.target_rtn)
        cvx = problem.cvx()
        res = problem.scvx(ScpConfig.from_yaml(), samples_per_node=3).solve(cvx.dv_rtn_mps)
        out += [(cvx.roe_m, cvx.dv_rtn_mps), (res.roe_m, res.dv_rtn_mps)]
    return out


def _dense_margins(ps: PassiveSafety, roe_m: np.ndarray, dv: np.ndarray, i: int,
                   step_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Margins d - 1 - q sigma of node i's drift every step_s [s]: offsets (K,), margins (K,)."""
    tau = np.linspace(0.0, ps.tau_s[-1], int(ps.tau_s[-1] / step_s) + 1)
    z = ps.post_burn(roe_m, dv)[i]
    stm, pos = ps.drift_maps(i, tau)
    p = pos @ z  # (K, 3) [m]
    pp = p / ps.semi_axes_m[i] ** 2
    d = np.sqrt(np.sum(p * pp, axis=1))
    if ps.uncertainty is None:
        return tau, d - 1.0
    x_cov = stm @ ps.covariance(roe_m, dv)[i] @ np.swapaxes(stm, 1, 2)  # X(tau), (K, 6, 6)
    psi_pos = pos @ np.linalg.inv(stm)  # D Psi at t_i + tau
    h = np.einsum("kcj,kc->kj", psi_pos, pp) / d[:, None]  # gradient w.r.t. ROE at tau
    sigma = np.sqrt(np.einsum("kj,kjl,kl->k", h, x_cov, h))
    return tau, d - 1.0 - ps.q_sigma * sigma


def _refined_dense_min(tau: np.ndarray, m: np.ndarray) -> float:
    """Dense minimum refined by the parabola through the three samples around it."""
    j = int(np.argmin(m))
    if 0 < j < m.size - 1:
        a, b, c = m[j - 1:j + 2]
        if a - 2 * b + c > 0:
            return float(b - (a - c) ** 2 / (8 * (a - 2 * b + c)))
    return float(m[j])


# ---------------------------------------------------------------------------- closed form
def test_stm_terms_and_basis_derivatives() -> None:
    """Phi = sum_b s_b(tau) terms[b] (the STM's one definition) and s', s'' by differences."""
    chief = np.array(SC.chief_oe)
    terms, wdot = stm_j2_terms(chief)
    tau = np.array([0.0, 100.0, 2500.0, 7000.0])
    np.testing.assert_allclose(np.einsum("kb,bij->kij", stm_basis(wdot, tau), terms),
                               stm_j2(chief, tau), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(stm_basis(wdot, tau, axis=0), stm_basis(wdot, tau).T)
    h = 1e-2
    for order in (1, 2):
        fd = (stm_basis(wdot, tau + h, order - 1) - stm_basis(wdot, tau - h, order - 1)) / (2 * h)
        np.testing.assert_allclose(stm_basis(wdot, tau, order), fd, rtol=1e-5, atol=1e-15)
    together = stm_basis_orders(wdot, tau, (0, 1, 2))  # one cos/sin evaluation, same numbers
    for order in (0, 1, 2):
        np.testing.assert_array_equal(together[order], stm_basis(wdot, tau, order))
    with pytest.raises(InputError):
        stm_basis(wdot, tau, 3)
    with pytest.raises(InputError):
        stm_basis_orders(wdot, tau, (0, 3))


@pytest.mark.parametrize("node", [0, 33, 54, 55, 99])
def test_closed_form_matches_direct_maps(models: dict, node: int) -> None:
    """y(tau) = b(tau) @ G z equals P^{1/2} D Psi Phi z at arbitrary instants (1e-9 relative)."""
    ps = models["det"]
    rng = np.random.default_rng(node)
    z = rng.normal(0.0, 3000.0, 6)
    tau = np.sort(rng.uniform(0.0, ps.tau_s[-1], 37))
    it = ps.arcs.items(np.array([node]), z[None], None, 0.0)
    b0, _ = ps.arcs.basis(np.array([node]), tau[None])
    closed = (b0 @ it.coef)[0] * ps.semi_axes_m[node]
    direct = ps.drift_maps(node, tau)[1] @ z
    np.testing.assert_allclose(closed, direct, rtol=0, atol=1e-9 * np.abs(direct).max())


@pytest.mark.parametrize("kind", ["det", "cc"])
def test_margin_slopes_match_finite_differences(models: dict, approach: tuple,
                                                kind: str) -> None:
    ps = models[kind]
    x, dv = approach
    z, x_cov = ps.post_burn(x, dv), ps.covariance(x, dv) if kind == "cc" else None
    nodes = np.arange(0, N, 7)
    it = ps.arcs.items(nodes, z[nodes], None if x_cov is None else x_cov[nodes], ps.q_sigma)
    tau = np.random.default_rng(1).uniform(10.0, ps.tau_s[-1] - 10.0, (nodes.size, 9))
    sel = np.arange(nodes.size)
    p = ps.arcs.points(it, sel, tau)
    h = 1e-3  # [s]
    fd = (ps.arcs.points(it, sel, tau + h).m - ps.arcs.points(it, sel, tau - h).m) / (2 * h)
    np.testing.assert_allclose(p.dm, fd, rtol=1e-5, atol=1e-9)


# ---------------------------------------------------------------------------- certified minimum
@pytest.mark.parametrize("kind", ["det", "cc"])
def test_certified_minimum_matches_dense_evaluation(models: dict, approach: tuple, plans: list,
                                                    kind: str) -> None:
    """On CVX and converged plans (seeds 3, 11) and a random approach, at every 4th node: the
    reported minimum (a certified lower bound) is never above the dense (1 s, refined) one by
    more than 1e-6 and never below it by more than the certification tolerance."""
    ps = models[kind]
    worst_miss = 0.0
    for roe_m, dv in plans + [approach]:
        ev = ps.evaluate(roe_m, dv)
        for i in range(0, N, 4):
            tau, m = _dense_margins(ps, roe_m, dv, i)
            dense = _refined_dense_min(tau, m)
            tol = CERT_TOL + CERT_TOL_REL * abs(dense)
            assert dense - tol <= ev.margin[i] <= dense + 1e-6, (i, ev.margin[i], dense)
            sampled = m[np.searchsorted(tau, ps.tau_s).clip(0, tau.size - 1)].min()
            worst_miss = max(worst_miss, sampled - dense)
    assert worst_miss > 0.1  # the drift samples alone are off by more than 10 % of the axis


@pytest.mark.parametrize("kind", ["det", "cc"])
def test_interval_bounds_are_below_the_dense_minimum(models: dict, plans: list,
                                                     kind: str) -> None:
    """Every stage of the certified bound on random intervals (1 s .. 2 samples long)."""
    ps = models[kind]
    rng = np.random.default_rng(7)
    roe_m, dv = plans[0]
    z, x_cov = ps.post_burn(roe_m, dv), ps.covariance(roe_m, dv) if kind == "cc" else None
    nodes = np.arange(N)
    it = ps.arcs.items(nodes, z, x_cov, ps.q_sigma)
    item = rng.integers(0, N, 400)
    length = np.exp(rng.uniform(np.log(1.0), np.log(580.0), item.size))
    a = rng.uniform(0.0, ps.tau_s[-1] - length)
    grid = a[:, None] + length[:, None] * np.linspace(0.0, 1.0, 401)  # (I, 401)
    dense = ps.arcs.points(it, item, grid).m.min(axis=1)
    ends = ps.arcs.points(it, item, np.column_stack([a, a + length]))
    lo, hi = ends.take((slice(None), 0)), ends.take((slice(None), 1))
    lb = ps.arcs.lower_bound(it, item, lo, hi)
    assert np.all(lb <= dense + 1e-12)
    assert np.mean(dense - lb < 1e-2) > 0.5  # and useful: mostly within 1 % of the axis


def test_a_fast_flyby_between_samples_is_found(horizon: Horizon, models: dict) -> None:
    """A 2 m/s pass 50 m from the target half-way between two drift samples (290 s apart): the
    samples see 1.4 KOZ radii, the old sampled evaluation calls the node safe; the continuous
    evaluation finds the pass (margin -0.75) at the right instant, as the dense evaluation."""
    node = 70
    ps = models["det"]
    tau_c = 0.5 * (ps.tau_s[9] + ps.tau_s[10])
    oe_c = propagate_mean_oe(ps.horizon.chief_oe[node], tau_c)  # chief at t_i + tau_c
    x_c = roe_from_rtn_linear(oe_c, [50.0, 0.0, 0.0, 0.0, 2.0, 0.0])  # RTN [m, m/s] at t*
    z = np.linalg.solve(ps.drift_maps(node, [tau_c])[0][0], x_c)  # post-burn ROE at the node
    roe = horizon.propagate(z, np.zeros((N, 3)))  # any trajectory through z at `node`
    roe[node] = z
    dv = np.zeros((N, 3))
    sampled = np.linalg.norm(ps.drift_pos_maps[node] @ z / ps.semi_axes_m[node], axis=1)
    assert sampled.min() - 1.0 > 0.4  # the old evaluation: safe by 0.4 radii
    for kind, ps_k in models.items():
        ev = ps_k.evaluate(roe, dv)
        tau, m = _dense_margins(ps_k, roe, dv, node)
        assert ev.margin[node] < -0.7
        dense = _refined_dense_min(tau, m)
        assert dense - CERT_TOL - CERT_TOL_REL * abs(dense) <= ev.margin[node] <= dense + 1e-6
        # deterministic: the closest approach itself; chance: where d - q sigma is smallest,
        # 36 s earlier (sigma grows as the direction turns towards the along-track axis)
        assert abs(ev.t_star_s[node] - tau_c) < (1.0 if kind == "det" else 60.0)
        assert tau[np.argmin(m)] == pytest.approx(ev.t_star_s[node], abs=3.0)  # flat minimum
        assert ps_k.linearize(roe, dv).t_star_s[node] == ev.t_star_s[node]


# ---------------------------------------------------------------------------- node API
@pytest.mark.parametrize("kind", ["det", "cc"])
def test_minimum_at_a_node_equals_evaluate(models: dict, approach: tuple, plans: list,
                                           kind: str) -> None:
    """minimum(i, x_i, u_i) is evaluate(...).margin[i], for single states and batches."""
    ps = models[kind]
    for roe_m, dv in (approach, plans[1]):
        ev = ps.evaluate(roe_m, dv)
        for i in range(0, N, 3):
            got = ps.minimum(i, roe_m[i:i + 1], dv[i:i + 1])[0]
            np.testing.assert_allclose(got, ev.margin[i:i + 1], rtol=0, atol=1e-12)
    # a batch of different candidates at one node: each equals a full evaluation with it
    rng = np.random.default_rng(3)
    roe_m, dv = plans[1]
    i = 60
    xs = roe_m[i] + rng.normal(0.0, 50.0, (6, 6))
    us = dv[i] + rng.normal(0.0, 0.05, (6, 3))
    batch = ps.minimum(i, xs, us)[0]
    for b in range(6):
        x_full, u_full = roe_m.copy(), dv.copy()
        x_full[i], u_full[i] = xs[b], us[b]
        assert batch[b] == pytest.approx(ps.evaluate(x_full, u_full).margin[i], abs=1e-12)


@pytest.mark.parametrize("kind", ["det", "cc"])
def test_the_sign_only_minimum_decides_the_sign_of_minimum(models: dict, approach: tuple,
                                                           plans: list, kind: str) -> None:
    """The sign-only search gives minimum(...) < 0 for every candidate whose margin is
    outside the certification tolerance of zero: 3 trajectories x 100 nodes and 400 random
    candidates around a converged plan's active nodes (fly-bys, near misses, clear arcs)."""
    ps = models[kind]
    rng = np.random.default_rng(7)
    checked = {True: 0, False: 0}
    cases = [(np.arange(N), roe_m, dv) for roe_m, dv in (approach, plans[0], plans[1])]
    roe_m, dv = plans[1]
    for i in (20, 55, 60, 78):
        xs = roe_m[i] + rng.normal(0.0, 30.0, (100, 6))
        us = dv[i] + rng.normal(0.0, 0.1, (100, 3))
        cases.append((np.full(100, i), xs, us))
    for nodes, xs, us in cases:
        for i in np.unique(nodes):
            sel = nodes == i
            margin = ps.minimum(i, xs[sel], us[sel])[0]
            violated = sign_only_violations(ps, i, xs[sel], us[sel])
            assert violated.dtype == bool and violated.shape == margin.shape
            clear = np.abs(margin) > 2.0 * (CERT_TOL + CERT_TOL_REL * np.abs(margin))
            np.testing.assert_array_equal(violated[clear], margin[clear] < 0.0)
            for v in (True, False):
                checked[v] += int(np.sum(clear & (violated == v)))
    assert checked[True] > 50 and checked[False] > 50, checked  # both outcomes exercised
    with pytest.raises(InputError):
        sign_only_violations(ps, N, np.ones((1, 6)), np.zeros((1, 3)))


@pytest.mark.parametrize("kind", ["det", "cc"])
def test_violated_is_the_sign_only_minimum(models: dict, plans: list, kind: str) -> None:
    """The rollout's fast C update (`DriftArcs.violated`, through `violated`) makes the
    decision of its oracle, the sign-only certified minimum, on every arc: candidates around a
    converged plan at nodes with fly-bys, near misses and clear arcs, and whole plans."""
    ps = models[kind]
    rng = np.random.default_rng(11)
    roe_m, dv = plans[1]
    decided = {True: 0, False: 0}
    for i in (0, 20, 55, 60, 78, 99):
        xs = roe_m[i] + rng.normal(0.0, 30.0, (64, 6))
        us = dv[i] + rng.normal(0.0, 0.1, (64, 3))
        z = ps.horizon.post_burn_at(i, xs, us)
        fast = ps.violated(i, xs, us, z)
        oracle = ps.arcs.minimum(ps._items_at(i, xs, us, z), sign_only=True).margin < 0.0
        np.testing.assert_array_equal(fast, oracle)
        np.testing.assert_array_equal(fast, sign_only_violations(ps, i, xs, us))
        np.testing.assert_array_equal(fast, ps.violated(i, xs, us))  # validated, z its own
        for v in (True, False):
            decided[v] += int(np.sum(fast == v))
    assert decided[True] > 20 and decided[False] > 20, decided
    for roe_m, dv in plans:
        items = ps.arcs.items(np.arange(N), ps.post_burn(roe_m, dv),
                              None if kind == "det" else ps.covariance(roe_m, dv), ps.q_sigma)
        np.testing.assert_array_equal(ps.arcs.violated(items),
                                      ps.arcs.minimum(items, sign_only=True).margin < 0.0)


@pytest.mark.parametrize("kind", ["det", "cc"])
def test_minimum_of_trajectories_equals_evaluate(models: dict, approach: tuple, plans: list,
                                                 kind: str) -> None:
    """`minimum` of K trajectories (K, N, 6) is `evaluate` of each (its K = 1 oracle), and its
    sign-only violations are the certified ones outside the tolerance of zero; `violated` and
    its adapter `violations_batch` (what the candidates are ranked by) decide every arc as the
    sign-only `minimum` does."""
    ps = models[kind]
    trajs = [approach, *plans]
    roe = np.stack([t[0] for t in trajs])
    dv = np.stack([t[1] for t in trajs])
    nodes = np.arange(N)
    margin, t_star = ps.minimum(nodes, roe, dv)
    signs = sign_only_violations(ps, nodes, roe, dv)
    assert margin.shape == t_star.shape == signs.shape == (len(trajs), N)
    for k, (roe_m, dv_k) in enumerate(trajs):
        one = ps.evaluate(roe_m, dv_k)
        np.testing.assert_allclose(margin[k], one.margin, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t_star[k], one.t_star_s, rtol=0, atol=1e-12)
        clear = np.abs(one.margin) > 2.0 * (CERT_TOL + CERT_TOL_REL * np.abs(one.margin))
        np.testing.assert_array_equal(signs[k][clear], one.violation[clear].astype(bool))
    # the rollout's sign-only search over the same arcs: the same decisions, every arc
    np.testing.assert_array_equal(ps.violated(nodes, roe, dv), signs)
    np.testing.assert_array_equal(ps.violations_batch(roe, dv), signs)
    with pytest.raises(InputError):
        ps.minimum(nodes, roe[:, :-1], dv)
    with pytest.raises(InputError):
        ps.violated(nodes, roe[:, :-1], dv[:, :-1])
    with pytest.raises(InputError):
        ps.violations_batch(roe[:, :-1], dv)


def test_minimum_bad_inputs(models: dict) -> None:
    ps = models["cc"]
    for node in (-1, N, 2.5, True, np.array([3, N])):
        with pytest.raises(InputError):
            ps.minimum(node, np.ones((2, 6)), np.zeros((2, 3)))
    with pytest.raises(InputError):
        ps.minimum(3, np.ones((2, 6)), np.zeros((3, 3)))
    with pytest.raises(InputError):
        ps.minimum(3, np.full((1, 6), np.nan), np.zeros((1, 3)))
    with pytest.raises(InputError):  # nodes that are not broadcast against the pairs
        ps.minimum(np.arange(3), np.ones((2, 6)), np.zeros((2, 3)))


def test_degenerate_arc_through_the_centre_is_bounded(models: dict) -> None:
    """z = 0: no certificate is possible (sigma is 0/0); the search stops at its work cap and
    reports its (finite, conservative) bound."""
    for ps in models.values():
        ev = ps.evaluate(np.zeros((N, 6)), np.zeros((N, 3)))
        assert np.all(ev.margin <= -1.0) and np.all(np.isfinite(ev.margin))
        assert np.all(np.isfinite(ev.t_star_s))


def test_arc_points_take_and_where() -> None:
    a = ArcPoints(*(np.arange(6.0).reshape(2, 3) + k for k in range(7)))
    b = a.take((slice(None), 0))
    assert b.m.shape == (2,) and b.tau[1] == 3.0
    w = ArcPoints.where(np.array([True, False]), b, a.take((slice(None), 1)))
    np.testing.assert_array_equal(w.tau, [0.0, 4.0])
