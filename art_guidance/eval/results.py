"""What an evaluation directory holds and shows: its committed rows, summary.json, report.md,
the recomputed largest-gain example per model and the figures (`eval.figures` draws).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from art_guidance import __version__
from art_guidance.config import GuidanceConfig
from art_guidance.data.storage import SUMMARY, load_dataset, read_manifest
from art_guidance.errors import DatasetError
from art_guidance.eval import example as ex_io
from art_guidance.eval.warmstart import columns, gains, standard_error, summarize
from art_guidance.eval.inputs import FORMAT, KIND, ModelInfo, load_model, problem_of


EXAMPLES = "examples"
FIGURES = "figures"
ID_FIELDS = ("index", "model", "dataset", "sample")


def read_results(out: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and the committed rows of an evaluation directory, sorted by pair index.

    Raises:
        DatasetError: not an evaluation directory, or corrupt shards.
    """
    head = read_manifest(out)[0]
    if head.get("mode") != KIND:
        raise DatasetError(f"{out}: holds a dataset, not an evaluation")
    return head, load_dataset(out, require_complete=False)


def model_summaries(head: dict, cols: dict[str, np.ndarray]) -> list[dict]:
    """Per model: what it is, how far the run is, its throughput and `summarize` of its rows."""
    ev = head["evaluation"]
    out = []
    for k, m in enumerate(ev["models"]):
        sel = cols["model"] == k if cols else np.zeros(0, bool)
        rows = {f: v[sel] for f, v in cols.items()}
        worker_s = float(rows["ms_task"].sum()) / 1e3 if cols else 0.0
        info = ModelInfo(**m)
        entry = {"k": k, "label": info.label, "name": Path(info.path).name, **m,
                 "datasets": sorted({int(d) for d in rows.get("dataset", [])}),
                 "n_done": int(sel.sum()), "worker_s": worker_s,
                 "scenarios_per_worker_s": int(sel.sum()) / worker_s if worker_s else None}
        entry.update(summarize(rows) if sel.any() else {"n": 0, "bins": {}})
        out.append(entry)
    return out


def flown_pairs(head: dict, cols: dict[str, np.ndarray]) -> list[dict]:
    """Every two models of one mode, paired on the scenarios both ran: the per-scenario
    difference of what they fly (what `benchmarks/analyses/default_models.py` takes its
    interval from).

    For models a and b (a listed first) over the scenarios (dataset, sample) where each one's
    flown plan (`warm_start auto`) and SCVx* from CVX are feasible, the flown saving of a over
    CVX alone minus b's: (J_auto,b - J_SCP,CVX) - (J_auto,a - J_SCP,CVX) per scenario; its mean
    "saving_a_minus_b_mmps", standard error "sem_mmps" [mm/s] and the scenario count "n".
    """
    if not cols:
        return []
    data = columns(cols)
    flown = []
    for k in range(len(head["evaluation"]["models"])):
        ok = ((cols["model"] == k) & data["ok_auto"].astype(bool)
              & data["ok_scp_cvx"].astype(bool))
        keys = zip(cols["dataset"][ok].tolist(), cols["sample"][ok].tolist())
        flown.append(dict(zip(keys, (data["j_auto"][ok] - data["j_scp_cvx"][ok]).tolist())))
    models = [ModelInfo(**m) for m in head["evaluation"]["models"]]
    out = []
    for a, ma in enumerate(models):
        for b in range(a + 1, len(models)):
            mb = models[b]
            common = sorted(set(flown[a]) & set(flown[b]))
            if ma.mode != mb.mode or not common:
                continue
            diff = 1e3 * np.array([flown[b][s] - flown[a][s] for s in common])
            out.append({"mode": ma.mode, "a": Path(ma.path).name, "b": Path(mb.path).name,
                        "sha256_a": ma.sha256, "sha256_b": mb.sha256, "n": int(diff.size),
                        "saving_a_minus_b_mmps": float(diff.mean()),
                        "sem_mmps": standard_error(diff)})
    return out


def example_index(cols: dict[str, np.ndarray], k: int) -> int | None:
    """Pair index of model k's scenario with the largest J_SCP,CVX - J_SCP,ART (None: none
    with both SCVx* runs converged)."""
    sel = np.flatnonzero(cols["model"] == k) if cols else np.zeros(0, int)
    if not sel.size:
        return None
    gain = gains(columns({f: v[sel] for f, v in cols.items()}))["gain_mps"]
    if not np.isfinite(gain).any():
        return None
    return int(cols["index"][sel[int(np.nanargmax(gain))]])


def build_summary(out: Path, this: dict | None, held: list[dict] | None = None) -> dict:
    """summary.json from the committed rows; `this` (the run's numbers) is appended to the
    runs recorded in an existing summary.json."""
    head, cols = read_results(out)
    previous = _read_summary(out)
    runs = previous.get("runs", []) + ([this] if this else [])
    datasets = head["evaluation"]["datasets"]
    for j, d in enumerate(datasets):
        d = dict(d, **(held[j] if held else previous.get("datasets", [{}] * len(datasets))[j]))
        d["n_evaluated"] = int(np.sum(cols["dataset"] == j)) if cols else 0
        datasets[j] = d
    n_done = int(cols["index"].size) if cols else 0
    _, shards, _ = read_manifest(out)
    return {
        "out": str(out), "kind": KIND, "format": FORMAT, "n_scenarios": head["n"],
        "n_done": n_done, "complete": n_done == head["n"],
        "status": this["status"] if this else previous.get("status", "complete"),
        "this_run": this or previous.get("this_run"), "runs": runs,
        "wall_s_total": float(sum(r.get("wall_s", 0.0) for r in runs)),
        "datasets": datasets, "models": model_summaries(head, cols),
        "flown_pairs": flown_pairs(head, cols),
        "sizes": {"shards": len(shards), "bytes": int(sum(e["bytes"] for e in shards))},
        "config_sha256": head["config_sha256"], "art_guidance_version": __version__,
        "definitions": DEFINITIONS, "figures": previous.get("figures", []),
    }


DEFINITIONS = {
    "bins": "cumulative: scenarios with C_CVX(t_1) >= the bin value (paper section V)",
    "subopt_*_mps": "J_SCP - J_CVX over the scenarios where both SCVx* runs converged [m/s]",
    "improvement_ratio": "(J_SCP,CVX - J_SCP,ART) / (J_SCP,CVX - J_CVX): per-scenario mean and "
                         "median (where J_SCP,CVX - J_CVX > 1e-6 m/s), and the ratio of sums",
    "iterations_*": "convex subproblems solved by SCVx* from that warm start",
    "runtime_ms_median": "ws_cvx: CVX solve; ws_art: ART rollout + post hoc check; total_cvx: "
                         "CVX + SCP from CVX; total_art: CVX (J_CVX conditions the rollout) + "
                         "rollout + SCP from ART; measured in the same worker",
    "infeasible_rate_*": "share of scenarios whose SCVx* run did not converge (infeasible, "
                         "solver error or iteration limit)",
    "gain_histogram": "J_SCP,CVX - J_SCP,ART [m/s], both converged; > 0: ART better",
    "gain_histogram_posthoc": "the same for the plan flown with the post hoc check (rejected "
                              "rollout: PS-CVX, difference 0)",
    "posthoc_maps": "cells of (100 E_R [%], E_C): population, mean improvement ratio, mean "
                    "SCP iterations saved by ART",
    "auto_minus_scp_cvx_mps": "the plan flown (warm_start auto) minus SCVx* from CVX alone, "
                              "both feasible [m/s]: mean, its standard error (sem), extremes",
    "flown_pairs": "two models of one mode on the scenarios both ran: the flown saving of a "
                   "minus b's per scenario, mean and standard error [mm/s]",
}


def _read_summary(out: Path) -> dict:
    try:
        data = json.loads((out / SUMMARY).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) and data.get("kind") == KIND else {}


def write_summary(out: str | Path, summary: dict) -> None:
    """Atomically (re)write OUT/summary.json and OUT/report.md."""
    from art_guidance.files import write_atomic

    write_atomic(Path(out) / SUMMARY, json.dumps(summary, indent=1, sort_keys=True).encode())
    write_report(out, summary)


def write_report(out: str | Path, summary: dict) -> None:
    """Atomically (re)write OUT/report.md (`eval.report`: our numbers beside the paper's)."""
    from art_guidance.eval.report import REPORT, report_markdown
    from art_guidance.files import write_atomic

    write_atomic(Path(out) / REPORT, report_markdown(summary).encode())


def rerender(out: str | Path, log: Callable[[str], None] = print) -> dict:
    """Rebuild summary.json and the figures from the stored rows and examples (no solving).

    Raises:
        DatasetError: not an evaluation directory.
    """
    out = Path(out)
    summary = build_summary(out, None)
    summary["figures"] = render(out, summary, recompute=False)
    write_summary(out, summary)
    log(f"{len(summary['figures'])} figures -> {out / FIGURES}")
    return summary


def log_run(summary: dict, log: Callable[[str], None]) -> None:
    this = summary["this_run"]
    rate = this.get("scenarios_per_s")
    log(f"evaluated {this['scenarios']} scenarios in {this['wall_s']:.1f} s"
        + (f" ({rate:.3f} scenarios/s, {this['engine']} engine, {this['workers']} workers)"
           if rate else "")
        + f"; {summary['n_done']} of {summary['n_scenarios']} done")
    for m in summary["models"]:
        b = m["bins"].get(">=0")
        if not b:
            continue
        h = m.get("gain_histogram") or {}
        log(f"{m['label']}: {m['n']} scenarios, ART accepted {m['accepted']}, "
            f"J_SCP,CVX - J_SCP,ART [mm/s] min {1e3 * h.get('min_mps', np.nan):.1f} "
            f"median {1e3 * h.get('median_mps', np.nan):.1f} max "
            f"{1e3 * h.get('max_mps', np.nan):.1f}; iterations CVX "
            f"{b['iterations_cvx']['mean']:.1f} ART {b['iterations_art']['mean']:.1f}; "
            f"not converged CVX {100 * b['infeasible_rate_cvx']:.0f} % ART "
            f"{100 * b['infeasible_rate_art']:.0f} %")


def _example(out: Path, head: dict, cols: dict, m: dict, recompute: bool) -> dict | None:
    """Model k's example: stored, or recomputed (and stored) when asked and missing."""
    k = m["k"]
    i = example_index(cols, k)
    if i is None:
        return None
    path = example_path(out, k)
    ex = ex_io.load(path)
    if (ex is None or int(ex["index"]) != i) and recompute:
        info = ModelInfo(**head["evaluation"]["models"][k])
        provider, safety = load_model(info)
        pos = int(np.flatnonzero(cols["index"] == i)[0])
        config = GuidanceConfig.from_json(head["evaluation"]["config"])
        problem = problem_of(cols["roe0_m"][pos], cols["target_rtn"][pos], safety)
        ex = ex_io.recompute(problem, provider, config,
                             {f: cols[f][pos] for f in cols})
        ex_io.save(path, ex, i)
        ex = ex_io.load(path)
    if ex is None or int(ex["index"]) != i:
        return None
    pos = int(np.flatnonzero(cols["index"] == i)[0])
    m["example"] = {"pair_index": i, "dataset": int(cols["dataset"][pos]),
                    "sample": int(cols["sample"][pos]),
                    "gain_mps": float(ex["j_scp_cvx"] - ex["j_scp_art"]),
                    "reproduced": bool(ex["reproduced"]),
                    "file": str(path.relative_to(out))}
    return ex


def render(out: str | Path, summary: dict, recompute: bool = True) -> list[str]:
    """Write every figure of an evaluation directory (`eval.figures`); returns the file names.

    Args:
        out: the evaluation directory (its figures go to `out/figures`).
        summary: its summary (`build_summary`); each model's "example" entry is set.
        recompute: solve the example scenarios that are not stored yet (else skip them).
    """
    from art_guidance.eval.figures import render_model

    out = Path(out)
    head, cols = read_results(out)
    thresholds = head["evaluation"]["config"]["planning"]["posthoc"]
    names = []
    for m in summary["models"]:
        if m.get("n"):
            ex = _example(out, head, cols, m, recompute)
            names += render_model(out / FIGURES, m, thresholds, ex)
    return names


def example_path(out: str | Path, k: int) -> Path:
    """Where model k's recomputed example is stored."""
    return Path(out) / EXAMPLES / f"example-{k}.npz"
