"""Standard visualisation messages of a plan and a navigation fix (RViz2, Foxglove).

Everything is stamped and in frame `chief_rtn` (`plan_view.FRAME_RTN`: origin at the chief,
x = R, y = T, z = N, metres); set it as the fixed / display frame. Topics (node-relative; the
plan topics are TRANSIENT_LOCAL depth 1, so a late subscriber gets the plan in force):

A plan is drawn when it is put in force, unless a newer solve is already queued (it would be
replaced at once; under a burst of fixes this keeps the callbacks responsive).

* `guidance/viz/plan_path` (nav_msgs/Path): one pose per node at the planned position, oriented
  along the post-burn relative velocity, stamped t0 + epoch.
* `guidance/viz/plan_markers` (visualization_msgs/MarkerArray): a DELETEALL, then namespace
  `approach_ellipsoid` and `keep_out_zone` (one translucent SPHERE each, scaled to the
  semi-axes; the one in force at the plan's first node more opaque), `drift` (one LINE_STRIP per
  node, `plan_view.DRIFT_SAMPLES` points: its one-orbit free drift, coloured by its
  passive-safety margin: red inside, yellow at 0 m, green from 50 m), `burns` (one ARROW per
  burn above 1 mm/s, from the node along the delta-v, 1 m per mm/s) and `status`
  (TEXT_VIEW_FACING: plan id, status, cost, margin).
* `guidance/viz/deputy` (visualization_msgs/MarkerArray): the navigated deputy position (SPHERE,
  15 m) and its 3-sigma position ellipsoid (translucent SPHERE along the covariance's axes).
* `guidance/viz/deputy_pose` (geometry_msgs/PoseWithCovarianceStamped): the same fix with its
  position covariance (orientation unknown: identity with zero covariance).

The simulator publishes `sim/viz/truth_path` (nav_msgs/Path): the truth trajectory so far.
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, Pose, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from art_guidance.plan_view import (
    FRAME_RTN, ZONES, PlanView, ellipsoid_of, margin_rgb, quaternion_of,
)
from art_guidance.ros.adapters import ns_to_stamp

TRUTH_POSES = 1000           # the truth path is thinned to at most this many poses
BURN_MIN_MPS = 1e-3          # burns drawn as arrows from this size [m/s]
ARROW_M_PER_MPS = 1000.0     # arrow length per delta-v [m per m/s]
LINE_WIDTH_M = 4.0
DEPUTY_SIZE_M = 15.0


def _header(stamp_ns: int, frame: str = FRAME_RTN) -> Header:
    header = Header(frame_id=frame)
    ns_to_stamp(header.stamp, int(stamp_ns))
    return header


def _point(p: np.ndarray) -> Point:
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _color(rgb: tuple[float, float, float], alpha: float = 1.0) -> ColorRGBA:
    return ColorRGBA(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))


def _orientation(direction: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning +x onto `direction` (identity for a zero vector)."""
    n = float(np.linalg.norm(direction))
    if n == 0.0:
        return 0.0, 0.0, 0.0, 1.0
    x = direction / n
    helper = np.eye(3)[int(np.argmin(np.abs(x)))]
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    return tuple(quaternion_of(np.column_stack([x, y, np.cross(x, y)])))


def _pose(position: np.ndarray, quat: tuple) -> Pose:
    pose = Pose()
    pose.position = _point(position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = map(
        float, quat)
    return pose


def path_msg(view: PlanView, t0_ns: int) -> Path:
    """The plan as a Path: one pose per node (position, post-burn velocity direction)."""
    msg = Path(header=_header(t0_ns))
    for k in range(view.epochs_s.size):
        pose = PoseStamped(header=_header(t0_ns + int(round(view.epochs_s[k] * 1e9))))
        pose.pose = _pose(view.position_m[k], _orientation(view.velocity_post_mps[k]))
        msg.poses.append(pose)
    return msg


def truth_path_msg(t_s: np.ndarray, rtn: np.ndarray, epoch0_ns: int) -> Path:
    """The simulator's truth trajectory (sim times (K,) [s], RTN (K, 6)) as a Path stamped
    `epoch0_ns` + t, thinned to TRUTH_POSES poses (the last one always kept)."""
    keep = np.unique(np.linspace(0, len(t_s) - 1, min(len(t_s), TRUTH_POSES)).astype(int))
    msg = Path(header=_header(epoch0_ns + int(round(t_s[-1] * 1e9))))
    for k in keep:
        pose = PoseStamped(header=_header(epoch0_ns + int(round(t_s[k] * 1e9))))
        pose.pose = _pose(rtn[k, :3], _orientation(rtn[k, 3:]))
        msg.poses.append(pose)
    return msg


def _marker(stamp_ns: int, ns: str, marker_id: int, kind: int) -> Marker:
    m = Marker(header=_header(stamp_ns), ns=ns, id=int(marker_id), type=kind,
               action=Marker.ADD, lifetime=Duration())
    m.pose.orientation.w = 1.0
    return m


def plan_markers(view: PlanView, t0_ns: int, status_text: str) -> MarkerArray:
    """Ellipsoids, drift arcs, burns and the status text of a plan (module docstring)."""
    out = MarkerArray()
    clear = Marker(header=_header(t0_ns), action=Marker.DELETEALL)
    out.markers.append(clear)
    in_force = ZONES[int(view.zone[0])] if view.zone.size else ZONES[0]
    for k, zone in enumerate(ZONES):
        m = _marker(t0_ns, zone, 0, Marker.SPHERE)
        axes = view.semi_axes_m[zone]
        m.scale.x, m.scale.y, m.scale.z = (float(2 * a) for a in axes)
        rgb = (1.0, 0.55, 0.0) if k == 0 else (0.85, 0.1, 0.1)
        m.color = _color(rgb, 0.25 if zone == in_force else 0.08)
        out.markers.append(m)
    for k in range(view.epochs_s.size):
        m = _marker(t0_ns, "drift", k, Marker.LINE_STRIP)
        m.scale.x = LINE_WIDTH_M
        m.color = _color(margin_rgb(view.margin_m[k]), 0.8)
        m.points = [_point(p) for p in view.drift_m[k]]
        out.markers.append(m)
    mags = np.linalg.norm(view.dv_rtn_mps, axis=1)
    for k in np.flatnonzero(mags >= BURN_MIN_MPS):
        m = _marker(t0_ns, "burns", int(k), Marker.ARROW)
        start = view.position_m[k]
        m.points = [_point(start), _point(start + ARROW_M_PER_MPS * view.dv_rtn_mps[k])]
        m.scale.x, m.scale.y, m.scale.z = LINE_WIDTH_M, 3 * LINE_WIDTH_M, 4 * LINE_WIDTH_M
        m.color = _color((0.55, 0.2, 0.8))
        out.markers.append(m)
    text = _marker(t0_ns, "status", 0, Marker.TEXT_VIEW_FACING)
    text.pose.position = _point(view.position_m[0] + np.array([150.0, 0.0, 0.0]))
    text.scale.z = 120.0
    text.color = _color((1.0, 1.0, 1.0))
    text.text = status_text
    out.markers.append(text)
    return out


def deputy_msgs(position_m: np.ndarray, cov_m2: np.ndarray, stamp_ns: int
                ) -> tuple[MarkerArray, PoseWithCovarianceStamped]:
    """The navigated deputy: markers (point and 3-sigma ellipsoid) and a pose with covariance."""
    dot = _marker(stamp_ns, "deputy", 0, Marker.SPHERE)
    dot.pose.position = _point(position_m)
    dot.scale.x = dot.scale.y = dot.scale.z = DEPUTY_SIZE_M
    dot.color = _color((0.1, 0.45, 0.95))
    axes, quat = ellipsoid_of(cov_m2, 3.0)
    ell = _marker(stamp_ns, "deputy_3sigma", 0, Marker.SPHERE)
    ell.pose = _pose(position_m, quat)
    ell.scale.x, ell.scale.y, ell.scale.z = (max(float(2 * a), 1e-3) for a in axes)
    ell.color = _color((0.1, 0.45, 0.95), 0.3)
    pose = PoseWithCovarianceStamped(header=_header(stamp_ns))
    pose.pose.pose = _pose(position_m, (0.0, 0.0, 0.0, 1.0))
    cov6 = np.zeros((6, 6))
    cov6[:3, :3] = cov_m2
    pose.pose.covariance = [float(c) for c in cov6.ravel()]
    return MarkerArray(markers=[dot, ell]), pose


def status_line(plan_id: str, result: object) -> str:
    """The status text of a plan marker."""
    return (f"{plan_id}: {result.status.name}, {result.cost_mps:.3f} m/s, "
            f"margin {result.constraint_margin_m:.1f} m, from {result.warm_start.label}")
