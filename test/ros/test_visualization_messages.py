"""The visualisation messages built from a real plan (no DDS): geometry, colours, ellipsoids."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("rclpy")
from visualization_msgs.msg import Marker  # noqa: E402

from art_guidance.dynamics import roe_from_rtn_linear  # noqa: E402
from art_guidance.plan_view import (  # noqa: E402
    ellipsoid_of, margin_rgb, nav_position, plan_view,
)
from art_guidance.planning import GuidancePipeline, PlanRequest  # noqa: E402
from art_guidance.ros import visualization as viz  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def planned():
    pipe = GuidancePipeline()
    sc = pipe.scenario
    chief = np.array(sc.chief_oe)
    req = PlanRequest(chief, roe_from_rtn_linear(chief, sc.rtn0_nominal),
                      np.asarray(sc.waypoints_rtn["plus_vbar"]), chance_constrained=True,
                      warm_start="cvx")
    result = pipe.plan(req)
    safety = pipe.safety_model(req)
    return result, safety, plan_view(result, safety, sc)


def test_view_follows_the_plan_and_its_safety_model(planned):
    result, safety, view = planned
    n = result.epochs_s.size
    np.testing.assert_array_equal(view.margin_m, safety.evaluate(result.roe_m,
                                                                 result.dv_rtn_mps).margin_m)
    assert view.margin_m.min() == pytest.approx(result.constraint_margin_m)
    assert view.zone.tolist() == [0] * 55 + [1] * (n - 55)  # AE, then KOZ from node 55
    # each drift starts at its node (linear map vs the plan's RTN: within 0.5 % of range)
    start = view.drift_m[:, 0]
    err = np.linalg.norm(start - view.position_m, axis=1)
    assert np.all(err <= 5e-3 * np.linalg.norm(view.position_m, axis=1) + 1.0)
    # post-burn velocity: the plan's velocity plus the burn (deputy-aware B vs Psi: 0.3 %)
    dv_rtn = view.velocity_post_mps - result.rtn[:, 3:]
    np.testing.assert_allclose(dv_rtn, result.dv_rtn_mps, atol=5e-3 * np.abs(
        result.dv_rtn_mps).max() + 1e-6)


def test_drift_colours_follow_the_margin_sign(planned):
    result, _, view = planned
    margins = view.margin_m.copy()
    margins[::3] = -np.abs(margins[::3]) - 1.0  # some nodes inside
    shown = dataclasses.replace(view, margin_m=margins)
    drift = [m for m in viz.plan_markers(shown, 10**18, "t").markers if m.ns == "drift"]
    for m, margin in zip(drift, margins):
        inside = bool(margin < 0)
        assert (m.color.r == 1.0 and m.color.g == 0.0) is inside
        assert (m.color.g > 0.5) is not inside
    assert margin_rgb(100.0) == (0.0, 1.0, 0.0) and margin_rgb(0.0)[0] == 1.0


def test_burn_arrows_and_path_orientation(planned):
    result, _, view = planned
    msgs = viz.plan_markers(view, 10**18, "t").markers
    arrows = [m for m in msgs if m.ns == "burns"]
    dv = np.linalg.norm(result.dv_rtn_mps, axis=1)
    assert [m.id for m in arrows] == np.flatnonzero(dv >= viz.BURN_MIN_MPS).tolist()
    for m in arrows:
        a, b = (np.array([p.x, p.y, p.z]) for p in m.points)
        assert m.type == Marker.ARROW
        np.testing.assert_allclose(b - a, viz.ARROW_M_PER_MPS * result.dv_rtn_mps[m.id])
    path = viz.path_msg(view, 10**18)
    q = path.poses[10].pose.orientation
    x_axis = np.array([1 - 2 * (q.y**2 + q.z**2), 2 * (q.x * q.y + q.z * q.w),
                       2 * (q.x * q.z - q.y * q.w)])
    v = view.velocity_post_mps[10]
    np.testing.assert_allclose(x_axis, v / np.linalg.norm(v), atol=1e-9)


def test_deputy_ellipsoid_is_three_sigma_of_the_position_covariance(planned):
    result, _, _ = planned
    chief = result.chief_oe
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    cov6 = a @ a.T + np.eye(6)
    pos, cov = nav_position(chief, result.roe_m[0], cov6)
    axes, quat = ellipsoid_of(cov)
    np.testing.assert_allclose(np.sort(axes), np.sort(3 * np.sqrt(np.linalg.eigvalsh(cov))))
    x, y, z, w = quat
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(rot @ np.diag((axes / 3) ** 2) @ rot.T, cov, rtol=1e-9,
                               atol=1e-9 * np.abs(cov).max())
    markers, pose = viz.deputy_msgs(pos, cov, 10**18)
    assert [m.ns for m in markers.markers] == ["deputy", "deputy_3sigma"]
    np.testing.assert_allclose(np.asarray(pose.pose.covariance).reshape(6, 6)[:3, :3], cov)


def test_truth_path_is_thinned_and_stamped_in_sim_time():
    t = np.linspace(0.0, 7000.0, 2501)
    rtn = np.column_stack([np.sin(t / 900.0) * 500, t, np.zeros_like(t), np.cos(t / 900.0),
                           np.ones_like(t), np.zeros_like(t)])
    msg = viz.truth_path_msg(t, rtn, 10**18)
    assert len(msg.poses) == viz.TRUTH_POSES and msg.header.frame_id == "chief_rtn"
    last = msg.poses[-1]
    assert last.header.stamp.sec == 10**9 + 7000 and last.pose.position.y == 7000.0
    assert len(viz.truth_path_msg(t[:5], rtn[:5], 0).poses) == 5
