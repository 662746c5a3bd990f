"""Plot of a simulated rendezvous in the RT plane (matplotlib, Agg backend)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import orbital_period_s
from art_guidance.plan_view import drift_rtn
from art_guidance.sim.simulator import RendezvousSim


def drift_arcs_rtn(sim: RendezvousSim, n_samples: int = 60,
                   duration_s: float | None = None) -> np.ndarray:
    """Linear free-drift arcs from every executed node's post-burn model ROE.

    Args:
        sim: the simulator.
        n_samples: samples per arc.
        duration_s: drift duration [s] (default: `scenario.t_safety_orbits` chief periods).

    Returns:
        (K, n_samples, 6) RTN states [m, m/s] along the K arcs (first-order map Psi).
    """
    t, _, _, roe_post = sim.node_arrays()
    if duration_s is None:
        duration_s = sim.scenario.t_safety_orbits * orbital_period_s(sim.chief_mean_oe0[0])
    return drift_rtn(sim.chief_mean_oe0, t, roe_post, duration_s, n_samples)


def plot_rendezvous(path: str | Path, sim: RendezvousSim, scenario: ScenarioConfig,
                    plan_rtn: object | None = None, *, target_rtn: object | None = None,
                    summary: dict | None = None, fault_drift: object | None = None) -> None:
    """Write a PNG of the run in the RT plane (x: along-track T [m], y: radial R [m]).

    Shows the approach-ellipsoid and keep-out-zone cross-sections (centred on the chief), the
    realised truth trajectory, the executed burns, the linear one-orbit free-drift arcs from
    the post-burn states, the start, the waypoint and optionally the last planned trajectory.

    Args:
        path: output PNG path (parent directories are created).
        sim: the simulator after the run.
        scenario: scenario (ellipsoid semi-axes [m]).
        plan_rtn: (N, 6) planned RTN trajectory [m, m/s], or None.
        target_rtn: (6,) waypoint [m, m/s], or None.
        summary: `run_outcome` output for the title, or None.
        fault_drift: a `sim.faults.DriftCheck`: the truth drift after a fault (drawn in red,
            with its closest approach), or None.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    fig = Figure(figsize=(13.0, 6.0), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.6, 1.0]})
    traj = np.array(sim.trajectory_rtn)
    arcs = drift_arcs_rtn(sim)
    _, rtn, dv, _ = sim.node_arrays()
    dv_norm = np.linalg.norm(dv, axis=1)
    plan = None if plan_rtn is None else as_finite_array("plan_rtn", plan_rtn, (None, 6))
    tgt = None if target_rtn is None else as_finite_array("target_rtn", target_rtn, (6,))
    zoom_m = 1.5 * max(scenario.ae_semi_axes_m)
    for ax, zoom in zip(axes, (False, True)):
        for axes_m, color, label in ((scenario.ae_semi_axes_m, "tab:orange",
                                      "approach ellipsoid"),
                                     (scenario.koz_semi_axes_m, "tab:red", "keep-out zone")):
            ax.add_patch(Ellipse((0.0, 0.0), 2 * axes_m[1], 2 * axes_m[0], fill=False,
                                 color=color, lw=1.5, label=label))
        for k, arc in enumerate(arcs):
            ax.plot(arc[:, 1], arc[:, 0], color="tab:gray", lw=0.5, alpha=0.3,
                    label="1-orbit free drift from post-burn states" if k == 0 else None)
        if plan is not None:
            ax.plot(plan[:, 1], plan[:, 0], "--", color="tab:green", lw=1.2, label="last plan")
        ax.plot(traj[:, 1], traj[:, 0], color="tab:blue", lw=1.4, label="truth", zorder=3)
        if dv_norm.size and dv_norm.max() > 0:
            ax.scatter(rtn[:, 1], rtn[:, 0], s=4 + 60 * dv_norm / dv_norm.max(),
                       color="tab:purple", alpha=0.6, zorder=4,
                       label="burns (area ~ |dv|)")
        if fault_drift is not None:
            f_rtn, f_min = fault_drift.rtn, fault_drift.closest_rtn_m
            ax.plot(f_rtn[:, 1], f_rtn[:, 0], color="tab:red", lw=1.4, zorder=4,
                    label=f"truth drift after the fault ({fault_drift.zone.replace('_', ' ')}"
                    f" margin {fault_drift.min_margin_m:.1f} m)")
            ax.plot(f_min[1], f_min[0], "x", color="tab:red", ms=9, zorder=5)
        ax.plot(traj[0, 1], traj[0, 0], "s", color="tab:blue", ms=6, label="start")
        if tgt is not None:
            ax.plot(tgt[1], tgt[0], "*", color="black", ms=12, label="waypoint", zorder=5)
        ax.plot(0.0, 0.0, "+", color="black", ms=10)
        ax.set_xlabel("along-track T [m]")
        ax.set_ylabel("radial R [m]")
        ax.grid(True, lw=0.3)
        if zoom:
            ax.set_xlim(-zoom_m, zoom_m)
            ax.set_ylim(-zoom_m, zoom_m)
            ax.set_aspect("equal", adjustable="box")
            ax.set_title(f"within {zoom_m:.0f} m of the chief (target spacecraft)", fontsize=9)
        else:
            ax.set_aspect("equal", adjustable="datalim")
            ax.legend(loc="best", fontsize=7)
    if summary:
        margin = summary.get("min_safety_margin_m")
        margin_txt = "n/a" if margin is None else f"{margin:.1f} m"
        axes[0].set_title(f"miss {summary['miss_m']:.1f} m, velocity error "
                          f"{1e3 * summary['velocity_error_mps']:.1f} mm/s, total dv "
                          f"{summary['total_dv_mps']:.3f} m/s, min passive-safety margin "
                          f"{margin_txt}, {summary['n_replans']} plans"
                          + _fault_title(summary.get("fault")), fontsize=9)
    else:
        axes[0].set_title(f"rendezvous at t = {sim.t_s:.0f} s, {len(sim.history)} burns",
                          fontsize=9)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png")


def _fault_title(fault: dict | None) -> str:
    """Second title line for a run with a fault."""
    if not fault:
        return ""
    if not fault["hit"]:
        return f"\nfault {fault['kind']} at node {fault['node']}: not reached"
    margin = fault["min_margin_m"]
    where = ("" if margin is None else f"; post-fault truth drift: min margin {margin:.1f} m "
             f"({'ENTERED' if fault['entered'] else 'outside'} the "
             f"{fault['zone'].replace('_', ' ')})")
    return f"\nfault {fault['kind']} at node {fault['node']}{where}"
