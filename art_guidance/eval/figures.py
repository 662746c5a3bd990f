"""PNG figures of a warm-start evaluation, shaped like the paper's (matplotlib, Agg backend).

Per model (one panel set per representation and mode), from summary.json alone:

- `warmstart-<k>-<repr>-<mode>.png`: the paper's warm-start analysis figure, against the
  cumulative C_CVX(t_1) bins (sample counts under the ticks): absolute suboptimality,
  improvement ratio, SCP iterations, median runtimes, infeasibility rate, and the histogram of
  J_SCP,CVX - J_SCP,ART with its min and max;
- `posthoc-maps-<k>-...png`: population, suboptimality improvement and iteration improvement
  over the (100 E_R, E_C) cells (gray: no data), with the acceptance region outlined;
- `posthoc-hist-<k>-...png`: the histogram with the post hoc check applied, over the one
  without it.

From the recomputed example (`eval.example`): `example-<k>-...png` (CVX, ART, PS-CVX, PS-ART in
the RT plane, PS-ART's free-drift arcs and q-sigma position ellipses) and
`example-constraints-<k>-...png` (passive-safety margin per node with and without the
uncertainty margin).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.eval.warmstart import BINS, EC_EDGES, ER_PCT_EDGES

_COLORS = {"cvx": "tab:gray", "art": "tab:orange", "ps_cvx": "tab:blue", "ps_art": "tab:red"}


def _figure(rows: int, cols: int, size: tuple[float, float]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=110)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(rows, cols, squeeze=False)


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path.name


def _suffix(m: dict) -> str:
    return "D" if m["mode"] == "deterministic" else "C"


def _series(m: dict, *keys: str) -> np.ndarray:
    """(len(BINS),) a nested per-bin value (NaN where missing or None)."""
    out = []
    for b in BINS:
        v = m["bins"].get(f">={b}", {})
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        out.append(np.nan if v is None else float(v))
    return np.array(out)


def plot_warmstart(path: Path, m: dict) -> str:
    """The paper's warm-start analysis figure for one model (see the module docstring)."""
    fig, ax = _figure(3, 2, (11.0, 11.5))
    s = _suffix(m)
    x = np.arange(len(BINS))
    ticks = [f">= {b}\nn={m['bins'].get(f'>={b}', {}).get('n', 0)}" for b in BINS]
    panels = [
        (ax[0, 0], "absolute suboptimality J_SCP - J_CVX (mean)", "[m/s]",
         [(f"PS-CVX-{s}", 1.0, ("subopt_cvx_mps", "mean")),
          (f"PS-ART-{s}", 1.0, ("subopt_art_mps", "mean"))]),
        (ax[0, 1], "suboptimality improvement ratio\n(J_SCP,CVX - J_SCP,ART) / "
         "(J_SCP,CVX - J_CVX)", "[%]",
         [("median of per-scenario ratios", 100.0, ("improvement_ratio", "median")),
          ("ratio of the sums", 100.0, ("improvement_ratio", "of_means"))]),
        (ax[1, 0], "SCP iterations (mean)", "[iterations]",
         [(f"PS-CVX-{s}", 1.0, ("iterations_cvx", "mean")),
          (f"PS-ART-{s}", 1.0, ("iterations_art", "mean"))]),
        (ax[1, 1], "runtime (median)", "[ms]",
         [("WS-CVX (CVX solve)", 1.0, ("runtime_ms_median", "ws_cvx")),
          ("WS-ART (rollout + post hoc)", 1.0, ("runtime_ms_median", "ws_art")),
          (f"PS-CVX-{s} total (CVX + SCP)", 1.0, ("runtime_ms_median", "total_cvx")),
          (f"PS-ART-{s} total (CVX + ART + SCP)", 1.0, ("runtime_ms_median", "total_art"))]),
        (ax[2, 0], "infeasibility rate (infeasible or not converged)", "[%]",
         [(f"PS-CVX-{s}", 100.0, ("infeasible_rate_cvx",)),
          (f"PS-ART-{s}", 100.0, ("infeasible_rate_art",))]),
    ]
    for a, title, unit, lines in panels:
        for label, scale, keys in lines:
            a.plot(x, scale * _series(m, *keys), "o-", label=label)
        a.set_title(title, fontsize=9)
        a.set_ylabel(unit)
        a.set_xticks(x, ticks, fontsize=7)
        a.set_xlabel("C_CVX(t_1) bin (cumulative: all scenarios >= value)", fontsize=8)
        a.grid(True, lw=0.3)
        a.legend(fontsize=7)
    _histogram(ax[2, 1], m.get("gain_histogram"), "J_SCP,CVX - J_SCP,ART [m/s] (> 0: ART better)",
               1.0, "tab:blue")
    fig.suptitle(f"Warm-start analysis, {m['label']}: SCP from CVX vs SCP from ART, "
                 f"{m['n']} held-out scenarios", fontsize=11)
    return _save(fig, path)


def _histogram(a, h: dict | None, xlabel: str, scale: float, color: str,
               label: str | None = None, minmax: bool = True) -> None:
    """A stored histogram (edges, counts) with dotted min / max lines."""
    a.set_xlabel(xlabel, fontsize=8)
    a.set_ylabel("scenarios")
    a.grid(True, lw=0.3)
    if not h:
        a.text(0.5, 0.5, "no scenario with both SCP runs converged", ha="center",
               transform=a.transAxes, fontsize=8)
        return
    edges = scale * np.asarray(h["edges_mps"])
    a.stairs(h["counts"], edges, fill=True, alpha=0.6, color=color,
             label=label or f"n = {h['n']}")
    if minmax:
        for key, name in (("min_mps", "min"), ("max_mps", "max")):
            a.axvline(scale * h[key], color="red", ls=":", lw=1.2,
                      label=f"{name} {scale * h[key]:+.4g}")
    a.legend(fontsize=7)


def plot_posthoc_hist(path: Path, m: dict) -> str:
    """J_SCP,CVX - J_SCP,ART with the post hoc check applied, over the one without it."""
    fig, ax = _figure(1, 1, (8.0, 4.5))
    a = ax[0, 0]
    raw, ph = m.get("gain_histogram"), m.get("gain_histogram_posthoc")
    if raw:
        a.stairs(raw["counts"], 1e3 * np.asarray(raw["edges_mps"]), color="tab:gray",
                 label=f"without the check (n = {raw['n']})")
    _histogram(a, ph, "J_SCP,CVX - J_SCP,ART of the flown plan [mm/s] (> 0: ART better; "
               "rejected rollout: PS-CVX, 0)", 1e3, "tab:blue",
               label=f"with the post hoc check (n = {ph['n']})" if ph else None)
    a.set_yscale("symlog", linthresh=1.0)
    a.set_title(f"Post hoc acceptance check, {m['label']}: {m.get('accepted', 0)} of {m['n']} "
                "rollouts accepted", fontsize=10)
    return _save(fig, path)


def _cells(values: list) -> np.ma.MaskedArray:
    arr = np.array([[np.nan if v is None else v for v in row] for row in values], float)
    return np.ma.masked_invalid(arr)


def _interval(lo: float, hi: float) -> str:
    if not np.isfinite(lo):
        return f"<= {hi:g}"
    return f"> {lo:g}" if not np.isfinite(hi) else f"({lo:g}, {hi:g}]"


def plot_posthoc_maps(path: Path, m: dict, thresholds: dict) -> str:
    """The paper's post hoc figure: population and improvements over the (100 E_R, E_C) cells."""
    maps = m["posthoc_maps"]
    fig, ax = _figure(3, 1, (10.0, 12.0))
    er = [_interval(a, b) for a, b in zip(ER_PCT_EDGES[:-1], ER_PCT_EDGES[1:])]
    ec = ["0", "1", "2-4", "5-10", "11-20", "> 20"][:len(EC_EDGES) - 1]
    panels = ((maps["population"], "data population [scenarios]", "viridis", False),
              (maps["improvement_ratio_of_sums"],
               "suboptimality improvement: sum of (J_SCP,CVX - J_SCP,ART) / sum of "
               "(J_SCP,CVX - J_CVX) per cell [%] (red: ART better)",
               "RdBu_r", True),
              (maps["iterations_saved_mean"], "iteration improvement: mean of it_SCP,CVX - "
               "it_SCP,ART [iterations] (red: ART faster)", "RdBu_r", True))
    box = _acceptance_cells(thresholds)
    for a, (values, title, cmap, centred) in zip(ax[:, 0], panels):
        data = _cells(values)
        if "%" in title:
            data = 100.0 * data
        if not centred:
            data = np.ma.masked_where(data == 0, data)
        lim = float(np.nanmax(np.abs(data.filled(np.nan)))) if data.count() else 1.0
        kw = {"vmin": -lim, "vmax": lim} if centred else {}
        a.set_facecolor("lightgray")
        im = a.imshow(data, origin="lower", aspect="auto", cmap=cmap, **kw)
        fig.colorbar(im, ax=a)
        for (i, j), v in np.ndenumerate(data.filled(np.nan)):
            if np.isfinite(v):
                a.text(j, i, f"{v:.3g}", ha="center", va="center", fontsize=6)
        if box:
            from matplotlib.patches import Rectangle

            (r0, r1), (c0, c1) = box
            a.add_patch(Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0 + 1, r1 - r0 + 1, fill=False,
                                  ec="black", lw=2, ls="--",
                                  label="cells overlapping the acceptance region"))
            a.legend(fontsize=7, loc="lower left")
        a.set_xticks(range(len(er)), er, fontsize=7, rotation=30)
        a.set_yticks(range(len(ec)), ec, fontsize=7)
        a.set_xlabel("100 E_R = 100 (R_ART - R_des) / R_des [%]", fontsize=8)
        a.set_ylabel("E_C = C_ART(t_1) [nodes]", fontsize=8)
        a.set_title(title + " (gray: no data)", fontsize=9)
    fig.suptitle(f"ART rollouts by post hoc criterion, {m['label']}, {m['n']} scenarios\n"
                 f"(acceptance: {thresholds['e_r_pct_min']:g} <= 100 E_R <= "
                 f"{thresholds['e_r_pct_max']:g}, {thresholds['e_c_min']:g} <= E_C <= "
                 f"{thresholds['e_c_max']:g})", fontsize=10)
    return _save(fig, path)


def _acceptance_cells(t: dict) -> tuple | None:
    """((first row, last row), (first col, last col)) of the cells the region overlaps."""
    cols = [j for j in range(len(ER_PCT_EDGES) - 1)
            if ER_PCT_EDGES[j] < t["e_r_pct_max"] and ER_PCT_EDGES[j + 1] >= t["e_r_pct_min"]]
    rows = [i for i in range(len(EC_EDGES) - 1)
            if EC_EDGES[i] < t["e_c_max"] and EC_EDGES[i + 1] >= t["e_c_min"]]
    return ((rows[0], rows[-1]), (cols[0], cols[-1])) if rows and cols else None


def _ellipse(cov_rt: np.ndarray, centre_tr: np.ndarray, q: float, **kw):
    """q-sigma ellipse of an RT position covariance, drawn with x = T, y = R."""
    from matplotlib.patches import Ellipse

    c = cov_rt[np.ix_([1, 0], [1, 0])]  # (T, R) order
    val, vec = np.linalg.eigh(c)
    val = np.maximum(val, 0.0)
    angle = np.degrees(np.arctan2(vec[1, 1], vec[0, 1]))
    return Ellipse(tuple(centre_tr), 2 * q * np.sqrt(val[1]), 2 * q * np.sqrt(val[0]),
                   angle=angle, **kw)


def plot_example(path: Path, ex: dict, m: dict) -> str:
    """The paper's sample-trajectory figure (RT plane, x: along-track T, y: radial R)."""
    from matplotlib.patches import Ellipse

    s = _suffix(m)
    fig, ax = _figure(1, 2, (14.0, 6.5))
    names = {"cvx": "CVX", "art": "ART (warm start)", "ps_cvx": f"PS-CVX-{s}",
             "ps_art": f"PS-ART-{s}"}
    axes_m = ex["semi_axes_m"]
    koz = np.all(axes_m == axes_m[-1], axis=1)
    arcs, cov = ex.get("arc_rtn_m"), ex.get("arc_cov_m2")
    q = float(ex["q_sigma"])
    zoom = 1.5 * float(axes_m.max())
    for a, zoomed in zip(ax[0], (False, True)):
        for sel, color, label in ((~koz, "tab:green", "approach ellipsoid (AE)"),
                                  (koz, "dimgray", "keep-out zone (KOZ)")):
            if sel.any():
                r = axes_m[np.flatnonzero(sel)[0]]
                a.add_patch(Ellipse((0.0, 0.0), 2 * r[1], 2 * r[0], fill=False, color=color,
                                    lw=1.5, label=label))
        if arcs is not None:
            for i in range(arcs.shape[0]):
                color = "dimgray" if koz[i] else "tab:green"
                a.plot(arcs[i, :, 1], arcs[i, :, 0], color=color, lw=0.4, alpha=0.35,
                       label=(f"PS-ART-{s} free drift ({'KOZ' if koz[i] else 'AE'} phase)"
                              if i in (0, int(np.argmax(koz))) else None))
                if q > 0 and i % 5 == 0:
                    for k in range(0, arcs.shape[1], 10):
                        a.add_patch(_ellipse(cov[i, k, :2, :2], arcs[i, k, [1, 0]], q,
                                             fill=False, color=color, lw=0.4, alpha=0.5))
        for key, name in names.items():
            rtn = ex[f"{key}_rtn"]
            a.plot(rtn[:, 1], rtn[:, 0], "--" if key in ("cvx", "art") else "-",
                   color=_COLORS[key], lw=1.4,
                   label=f"{name}: dv_tot {float(ex[f'{key}_cost_mps']):.4f} m/s")
        a.plot(ex["cvx_rtn"][0, 1], ex["cvx_rtn"][0, 0], "s", color="black", label="start")
        a.plot(ex["target_rtn"][1], ex["target_rtn"][0], "*", color="black", ms=12,
               label="target")
        a.set(xlabel="along-track T [m]", ylabel="radial R [m]")
        a.grid(True, lw=0.3)
        if zoomed:
            a.axis((-zoom, zoom, -zoom, zoom))
            a.set_aspect("equal", adjustable="box")
            a.set_title(f"within {zoom:.0f} m of the target spacecraft", fontsize=9)
        else:
            a.set_aspect("equal", adjustable="datalim")
            a.legend(fontsize=7, loc="best")
    unc = f", drift ellipses {q:g}-sigma" if q > 0 else ""
    fig.suptitle(f"Largest ART gain, {m['label']}: J_CVX {float(ex['j_cvx']):.4f}, "
                 f"PS-CVX {float(ex['j_scp_cvx']):.4f}, PS-ART {float(ex['j_scp_art']):.4f} m/s"
                 f"; post hoc 100 E_R {100 * float(ex['e_r']):+.2f} %, E_C "
                 f"{float(ex['e_c']):g} ({'accepted' if ex['accepted'] else 'rejected'}){unc}",
                 fontsize=9)
    return _save(fig, path)


def plot_example_constraints(path: Path, ex: dict, m: dict) -> str:
    """The paper's constraint-history figure: passive-safety margin per node."""
    s = _suffix(m)
    fig, ax = _figure(1, 1, (10.0, 5.0))
    a = ax[0, 0]
    chance = bool(ex["chance"])
    names = {"cvx": "CVX", "art": "ART", "ps_cvx": f"PS-CVX-{s}", "ps_art": f"PS-ART-{s}"}
    for key, name in names.items():
        node = np.arange(ex[f"{key}_margin_m"].size)
        a.plot(node, ex[f"{key}_margin_m"], color=_COLORS[key], lw=1.4,
               label=f"{name}" + (f" with the {float(ex['q_sigma']):g}-sigma margin"
                                  if chance else ""))
        if chance:
            a.plot(node, ex[f"{key}_margin_mean_m"], color=_COLORS[key], lw=1.0, alpha=0.35,
                   label=f"{name}, mean state (no uncertainty margin)")
    a.axhspan(-1e9, 0.0, color="tab:red", alpha=0.08, label="constraint violated (< 0)")
    a.axhline(0.0, color="black", lw=0.8)
    a.set_yscale("symlog", linthresh=10.0)
    finite = np.concatenate([ex[f"{k}_margin_m"] for k in names])
    finite = finite[np.isfinite(finite)]
    if finite.size:
        a.set_ylim(min(finite.min(), -1.0) * 1.5, max(finite.max(), 1.0) * 1.5)
    a.set_xlabel("node i")
    a.set_ylabel("passive-safety margin over the free drift [m] (>= 0: safe)")
    a.set_title(f"Passive-safety constraint history, {m['label']}", fontsize=10)
    a.grid(True, lw=0.3)
    a.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def render_model(figs: Path, m: dict, thresholds: dict, ex: dict | None) -> list[str]:
    """Draw one model's figures into `figs` (the directory); returns the file names.

    Args:
        figs: output directory.
        m: the model's summary entry (`results.build_summary`).
        thresholds: the post hoc region (the evaluation's planning.posthoc configuration).
        ex: its largest-gain example (`eval.example`), or None to skip its two figures.
    """
    slug = f"{m['k']}-{m['representation']}-{m['mode']}"
    names = [plot_warmstart(figs / f"warmstart-{slug}.png", m),
             plot_posthoc_maps(figs / f"posthoc-maps-{slug}.png", m, thresholds),
             plot_posthoc_hist(figs / f"posthoc-hist-{slug}.png", m)]
    if ex is not None:
        names.append(plot_example(figs / f"example-{slug}.png", ex, m))
        names.append(plot_example_constraints(figs / f"example-constraints-{slug}.png", ex, m))
    return names
