"""The summary of a contingency directory and its report: entry rates per configuration with
exact (Clopper-Pearson) one-sided upper bounds, the worst margins, the missed-burn outcomes, and
the markdown tables docs/fault_tolerance.md shows (regenerated with
`python -m art_guidance.sim.contingency <summary.json>`). Margins in [m], burns in [m/s].
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from art_guidance.sim.contingency_spec import KIND, read_rows, spec_of
from art_guidance.sim.faults import ZONES

CONFIDENCE = 0.95
DESIGN_RATE = 1e-3         # the chance constraint's probability per node
WORST_SHOWN = 10
HISTOGRAM_EDGES_M = (0, 10, 25, 50, 100, 200, 500, 1000)  # post-fault margin bins (+-inf added)
TABLE_BEGIN, TABLE_END = "<!-- contingency-table:begin -->", "<!-- contingency-table:end -->"


def upper_bound(entries: int, trials: int, confidence: float = CONFIDENCE) -> float | None:
    """One-sided exact (Clopper-Pearson) upper bound of a probability (None without trials)."""
    if trials <= 0:
        return None
    if entries >= trials:
        return 1.0
    from scipy.stats import beta

    return float(beta.ppf(confidence, entries + 1, trials - entries))


def summarize_directory(out: str | Path, this: dict | None = None,
                        runs: list[dict] | None = None) -> dict:
    """Entry rates, bounds, worst margins and missed-burn outcomes per configuration; `this`
    is the invocation that produced it, `runs` every invocation that flew flights."""
    head, rows = read_rows(out)
    spec = spec_of(head)
    per = []
    for c in range(len(spec.configs)):
        sel = rows["config"] == c if rows else np.zeros(0, bool)
        per.append({"config": spec.label(c), **_config_summary(rows, sel)})
    done = int(rows["index"].size) if rows else 0
    wall = float(rows["wall_s"].sum()) if rows else 0.0
    losses = sum(p["losses"]["n"] for p in per)
    identity = head["contingency"]
    return {"kind": KIND, "spec": identity["spec"], "models": identity["models"],
            "replan": identity.get("replan"), "flights_done": done, "flights": spec.n_flights,
            "complete": done == spec.n_flights, "design_rate_per_node": DESIGN_RATE,
            "confidence": CONFIDENCE, "cpu_s": wall,
            "losses_per_cpu_s": losses / wall if wall > 0 else None,
            "configs": per, **({"run": this} if this else {}),
            **({"runs": runs} if runs is not None else {})}


def _config_summary(rows: dict, sel: np.ndarray) -> dict:
    if not sel.any():
        return {"flights": 0, "losses": {"n": 0}, "missed": {"n": 0}}
    r = {k: v[sel] for k, v in rows.items()}  # this configuration's flights
    return {"flights": int(sel.sum()),
            "nominal": {"reached": int(r["reached"].sum()), "miss_m": _dist(r["miss_m"]),
                        "total_dv_mps": _dist(r["total_dv_mps"])},
            "losses": _loss_summary(r), "missed": _missed_summary(r)}


def _loss_summary(r: dict) -> dict:
    """Entries, bounds, margins and the worst losses of one configuration's flights."""
    node, margin_all = r["loss_node"], r["loss_margin_m"]
    valid = node >= 1
    margin = margin_all[valid]
    n, entries = int(valid.sum()), int((margin < 0).sum())
    flights_entered = int(np.any((margin_all < 0) & valid, axis=1).sum())
    worst = []
    for flat in np.argsort(margin_all, axis=None)[:WORST_SHOWN]:
        i, j = np.unravel_index(flat, node.shape)
        if valid[i, j]:
            worst.append({"seed": int(r["seed"][i]), "node": int(node[i, j]),
                          "min_margin_m": round(float(margin_all[i, j]), 3),
                          "zone": ZONES[int(r["loss_zone"][i, j])],
                          "lost_burn_mps": _round(r["loss_dv_cmd_mps"][i, j])})
    zones = r["loss_zone"][valid]
    edges = np.array([-np.inf, *HISTOGRAM_EDGES_M, np.inf])
    return {"n": n, "entries": entries, "per_1000": 1e3 * entries / max(n, 1),
            "upper_95_per_1000": _round(1e3 * (upper_bound(entries, n) or np.nan)),
            "flights_with_entry": flights_entered,
            "flights_upper_95": _round(upper_bound(flights_entered, len(node))),
            "min_margin_m": _dist(margin),
            "by_zone": {z: _dist(margin[zones == k]) for k, z in enumerate(ZONES)},
            "histogram_m": {"edges": ["-inf", *HISTOGRAM_EDGES_M, "inf"],
                            "counts": np.histogram(margin, bins=edges)[0].tolist()},
            "worst": worst}


def _missed_summary(r: dict) -> dict:
    """Outcomes of one configuration's missed-burn flights."""
    mm = r["missed_node"] >= 0
    if not mm.any():
        return {"n": 0}
    reached = r["missed_reached"][mm]
    seeds = np.broadcast_to(r["seed"][:, None], mm.shape)[mm]
    return {"n": int(mm.sum()), "reached": int(reached.sum()),
            "reached_share": float(reached.mean()),
            "entered": int(r["missed_entered"][mm].sum()),
            "min_post_fault_margin_m": _round(np.nanmin(r["missed_margin_m"][mm])),
            "missed_burn_mps": _dist(r["missed_dv_cmd_mps"][mm]),
            "miss_m": _dist(r["missed_miss_m"][mm]),
            "replanned_share": float((r["missed_replans_after"][mm] > 0).mean()),
            "not_reached": [{"seed": int(s), "node": int(k), "miss_m": _round(d)}
                            for s, k, d in zip(seeds, r["missed_node"][mm],
                                               r["missed_miss_m"][mm])
                            if d > 50.0][:WORST_SHOWN]}


def _round(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 4)


def _dist(x: np.ndarray) -> dict:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "min": _round(x.min()), "q01": _round(np.percentile(x, 1)),
            "median": _round(np.median(x)), "max": _round(x.max())}


# --------------------------------------------------------------------------- report
def markdown_table(summary: dict) -> str:
    """The results of a summary as two markdown tables (losses; missed burns)."""
    def num(x: object, fmt: str = "{:.1f}") -> str:
        return "-" if x is None else fmt.format(x)

    lines = ["| configuration | flights | losses | entries | per 1,000 (95 % upper) | flights "
             "with an entry | min margin AE [m] | min margin KOZ [m] | 1st pct. [m] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c in summary["configs"]:
        loss = c["losses"]
        if not loss["n"]:
            continue
        zone = loss["by_zone"]
        lines.append(
            f"| {c['config']} | {c['flights']} | {loss['n']:,} | {loss['entries']} | "
            f"{loss['per_1000']:.2f} ({num(loss['upper_95_per_1000'], '{:.2f}')}) | "
            f"{loss['flights_with_entry']} | "
            f"{num(zone['approach_ellipsoid'].get('min'))} | "
            f"{num(zone['keep_out_zone'].get('min'))} | {num(loss['min_margin_m']['q01'])} |")
    lines += ["", "| configuration | missed burns | missed burn median [m/s] | reached | "
              "replanned | post-fault entries | min post-fault margin [m] | miss median / max "
              "[m] |", "|---|---|---|---|---|---|---|---|"]
    for c in summary["configs"]:
        m = c["missed"]
        if not m["n"]:
            continue
        lines.append(
            f"| {c['config']} | {m['n']} | {m['missed_burn_mps']['median']:.3f} | "
            f"{m['reached']} ({100 * m['reached_share']:.1f} %) | "
            f"{100 * m['replanned_share']:.0f} % | {m['entered']} | "
            f"{num(m['min_post_fault_margin_m'])} | {m['miss_m']['median']:.1f} / "
            f"{m['miss_m']['max']:.1f} |")
    cpu = summary.get("cpu_s") or 0.0
    lines += ["", f"{summary['flights_done']} flights, {cpu / 3600:.2f} CPU hours, "
              f"{num(summary.get('losses_per_cpu_s'), '{:.2f}')} losses per CPU second "
              "(flights with their missed-burn repeats and checks)."]
    return "\n".join(lines) + "\n"


def table_in_doc(text: str) -> str:
    """The table between the contingency markers of a documentation page."""
    return text[text.index(TABLE_BEGIN) + len(TABLE_BEGIN):text.index(TABLE_END)].strip("\n") \
        + "\n"
