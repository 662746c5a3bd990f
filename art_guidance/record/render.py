"""`art-guidance bag render`: the Foxglove layout's picture drawn from a recorded bag (matplotlib).

What `config/foxglove_layout.json` shows, from the same recorded topics, decoded with the
schemas embedded in the bag (`record.replay.read_log`): the 3D panel as its RT-plane projection
(x: along-track T, y: radial R; the plan's path, the approach ellipsoid and keep-out zone, the
drift arcs in their margin colours, the burn arrows, the navigated deputy with its 3-sigma
ellipse), the two plots (the plans' passive-safety margin and delta-v over time) and the status
text of the plan shown.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.errors import InputError
from art_guidance import topics
from art_guidance.record.replay import read_log

MARKERS, PATH, DEPUTY, PLAN = (topics.PLAN_MARKERS, topics.PLAN_PATH, topics.DEPUTY_MARKERS,
                               topics.MANEUVER_PLAN)
SPHERE, LINE_STRIP, ARROW = 2, 4, 0  # visualization_msgs/Marker types


def _stamp_s(header: object) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def _of(log: object, suffix: str) -> list:
    return [m for topic, m, _ in log.messages if topic.endswith(suffix)]


def _rgba(color: object) -> tuple:
    return (color.r, color.g, color.b, max(color.a, 0.15))


def _projected_ellipse(marker: object) -> tuple[float, float, float]:
    """Width (T), height (R) and angle [deg] of an oriented ellipsoid marker's RT projection."""
    q = marker.pose.orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    axes = np.array([marker.scale.x, marker.scale.y, marker.scale.z]) / 2
    cov = rot @ np.diag(axes**2) @ rot.T
    tr = cov[np.ix_([1, 0], [1, 0])]  # (T, R) block
    w_, v_ = np.linalg.eigh(tr)
    angle = float(np.degrees(np.arctan2(v_[1, 1], v_[0, 1])))
    return 2 * float(np.sqrt(max(w_[1], 0))), 2 * float(np.sqrt(max(w_[0], 0))), angle


def render_bag(path: str | Path, png: str | Path, plan: int = -1) -> dict:
    """Draw a recorded bag's visualisation topics into `png` (see the module docstring).

    Args:
        path: a bag folder or MCAP file written by the guidance node.
        png: output PNG path.
        plan: which recorded plan to draw (index among the plans put in force; -1 = last).

    Returns:
        What was drawn: counts of plans, drift arcs, burns and deputy fixes.

    Raises:
        InputError: no visualisation topics in the log, or `plan` out of range.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    log = read_log(path)
    marker_sets, paths = _of(log, MARKERS), _of(log, PATH)
    if not marker_sets:
        raise InputError("LOG", f"holds no {MARKERS} (recorded with visualization:=false?)",
                         str(path))
    if not -len(marker_sets) <= plan < len(marker_sets):
        raise InputError("--plan", f"the log has {len(marker_sets)} plans", plan)
    shown, shown_path = marker_sets[plan], paths[plan] if len(paths) == len(marker_sets) else None
    plans = [p for p in _of(log, PLAN) if p.epochs_s]
    deputies = [d for d in _of(log, DEPUTY) if d.markers]
    fig = Figure(figsize=(15.0, 7.5), dpi=100)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 2, width_ratios=[1.7, 1.0])
    ax = fig.add_subplot(grid[:, 0])
    counts = {"plans": len(marker_sets), "drift": 0, "burns": 0, "deputy_fixes": len(deputies)}
    status = ""
    for m in shown.markers:
        if m.type == SPHERE and m.ns in ("approach_ellipsoid", "keep_out_zone"):
            ax.add_patch(Ellipse((m.pose.position.y, m.pose.position.x), m.scale.y, m.scale.x,
                                 facecolor=_rgba(m.color), edgecolor=_rgba(m.color)[:3],
                                 lw=1.0, label=m.ns.replace("_", " ")))
        elif m.type == LINE_STRIP and m.ns == "drift":
            pts = np.array([[p.x, p.y] for p in m.points])
            ax.plot(pts[:, 1], pts[:, 0], color=_rgba(m.color)[:3], lw=0.6, alpha=0.7)
            counts["drift"] += 1
        elif m.type == ARROW and m.ns == "burns":
            a, b = m.points
            ax.annotate("", (b.y, b.x), (a.y, a.x),
                        arrowprops={"arrowstyle": "->", "color": _rgba(m.color)[:3]})
            counts["burns"] += 1
        elif m.ns == "status":
            status = m.text
    if shown_path is not None:
        pts = np.array([[p.pose.position.x, p.pose.position.y] for p in shown_path.poses])
        ax.plot(pts[:, 1], pts[:, 0], "--", color="tab:green", lw=1.2, label="plan (path)")
    for d in deputies:
        dot, ell = d.markers[0], d.markers[-1]
        ax.plot(dot.pose.position.y, dot.pose.position.x, ".", color="tab:blue", ms=3)
        width, height, angle = _projected_ellipse(ell)
        ax.add_patch(Ellipse((ell.pose.position.y, ell.pose.position.x), width, height,
                             angle=angle, fill=False, color="tab:blue", lw=0.5, alpha=0.6))
    ax.plot([], [], ".", color="tab:blue", label="navigated deputy, 3-sigma")
    ax.plot(0.0, 0.0, "k+", ms=10)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("along-track T [m] (frame chief_rtn, y)")
    ax.set_ylabel("radial R [m] (frame chief_rtn, x)")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title("3D panel, RT plane: drift arcs coloured by passive-safety margin "
                 "(red inside, green >= 50 m)", fontsize=9)
    t0 = _stamp_s(plans[0].header) if plans else 0.0
    t = np.array([_stamp_s(p.header) - t0 for p in plans])
    for row, (field, label) in enumerate((("constraint_margin_m", "margin [m]"),
                                          ("cost_mps", "delta-v [m/s]"))):
        pax = fig.add_subplot(grid[row, 1])
        pax.plot(t, [getattr(p, field) for p in plans], ".-", lw=0.8, ms=3)
        pax.set_ylabel(label)
        pax.grid(True, lw=0.3)
        pax.set_title(f"Plot: {PLAN}.{field}", fontsize=9)
    pax.set_xlabel("plan epoch since the first plan [s]")
    tax = fig.add_subplot(grid[2, 1])
    tax.axis("off")
    text = status or (plans[-1].status_text if plans else "")
    tax.text(0.0, 0.9, f"{PLAN}.status_text:\n{text}", fontsize=9, va="top", wrap=True,
             family="monospace")
    fig.tight_layout()
    out = Path(png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return counts
