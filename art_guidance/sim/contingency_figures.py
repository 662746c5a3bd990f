"""The figures of a contingency directory: the histogram of the post-fault minimum distance
per configuration and the RT-plane drifts of the closest losses (recomputed in truth from the
stored states)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.sim.contingency_spec import read_rows, spec_of
from art_guidance.sim.faults import ZONES


def render(out: str | Path, n_worst: int = 6) -> list[str]:
    """contingency_margins.png (histogram of the post-fault minimum distance per
    configuration) and contingency_worst.png (RT plane: per configuration, the closest loss of
    each of the `n_worst` flights that came closest, its truth drift recomputed from the
    stored state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    from art_guidance.config import ScenarioConfig
    from art_guidance.sim.faults import free_drift_check, safety_duration_s

    out = Path(out)
    head, rows = read_rows(out)
    spec = spec_of(head)
    labels = [spec.label(c) for c in range(len(spec.configs))]
    scenario = ScenarioConfig.from_yaml(None)
    fig = Figure(figsize=(10, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    bins = np.linspace(-50.0, 1500.0, 63)
    for c, label in enumerate(labels):
        sel = rows["config"] == c
        m = rows["loss_margin_m"][sel][rows["loss_node"][sel] >= 1]
        if m.size:
            ax.hist(np.clip(m, bins[0], bins[-1]), bins=bins, histtype="step", lw=1.3,
                    label=f"{label}: {m.size} losses, {(m < 0).sum()} entries, "
                    f"min {m.min():.1f} m")
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("post-fault minimum distance to the ellipsoid in force, truth [m] "
                  "(clipped to the axis)")
    ax.set_ylabel("losses")
    ax.legend(fontsize=8)
    ax.set_title("thruster loss at every node of the flown closed loop (errors on), one-orbit "
                 "truth drift", fontsize=9)
    fig.tight_layout()
    paths = [str(out / "contingency_margins.png")]
    fig.savefig(paths[0])

    n_rows = (len(labels) + 1) // 2
    fig = Figure(figsize=(12, 5.5 * n_rows), dpi=100)
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(n_rows, 2)).ravel()
    for ax in axes[len(labels):]:
        ax.set_visible(False)
    a_m = float(np.linalg.norm(rows["loss_state"][0, 0, :3])) if rows else 6.9e6
    duration = safety_duration_s(scenario, a_m)
    for c, (ax, label) in enumerate(zip(axes, labels)):
        for axes_m, color in ((scenario.ae_semi_axes_m, "tab:orange"),
                              (scenario.koz_semi_axes_m, "tab:red")):
            ax.add_patch(Ellipse((0, 0), 2 * axes_m[1], 2 * axes_m[0], fill=False,
                                 color=color, lw=1.2))
        sel = np.flatnonzero(rows["config"] == c)
        margins = np.where(rows["loss_node"][sel] >= 1, rows["loss_margin_m"][sel], np.inf)
        worst_j = np.argmin(margins, axis=1)  # the closest loss of every flight
        worst = margins[np.arange(sel.size), worst_j]
        for i in np.argsort(worst)[:n_worst]:
            j = worst_j[i]
            if not np.isfinite(margins[i, j]):
                continue
            r = sel[i]
            state = rows["loss_state"][r, j]
            check = free_drift_check(state[:6], state[6:], rows["loss_t0_s"][r, j], duration,
                                     scenario, ZONES[int(rows["loss_zone"][r, j])])
            line, = ax.plot(check.rtn[:, 1], check.rtn[:, 0], lw=1.0,
                            label=f"seed {rows['seed'][r]} node {rows['loss_node'][r, j]}: "
                            f"{check.min_margin_m:.1f} m")
            ax.plot(check.closest_rtn_m[1], check.closest_rtn_m[0], "x",
                    color=line.get_color())
        ax.plot(0, 0, "k+")
        lim = 1.6 * max(scenario.ae_semi_axes_m)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.grid(True, lw=0.3)
        ax.set_xlabel("along-track T [m]")
        ax.set_ylabel("radial R [m]")
        ax.set_title(f"{label}: the closest post-fault drift of the {n_worst} closest "
                     "flights", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    paths.append(str(out / "contingency_worst.png"))
    fig.savefig(paths[1])
    return paths
