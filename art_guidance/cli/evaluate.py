"""`art-guidance evaluate`: held-out evaluation of trained models against CVX."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from art_guidance.files import write_json_atomic


def _distribution(values: np.ndarray) -> dict:
    """min / quartiles / max / mean of a sample (JSON-ready)."""
    q = np.percentile(values, [0, 25, 50, 75, 100])
    return {"min": float(q[0]), "p25": float(q[1]), "median": float(q[2]), "p75": float(q[3]),
            "max": float(q[4]), "mean": float(np.mean(values))}


def evaluate_model(data: dict, model_path: str, n: int | None, threads: int,
                   progress: bool = True) -> dict:
    """Rollout suite of one model on the held-out split of `data` (see `run`)."""
    import torch
    from tqdm import tqdm

    from art_guidance.art import build_safety, evaluate_rollouts, heldout_scenarios, load

    torch.set_num_threads(threads)
    art = load(model_path)
    held = heldout_scenarios(data, ("cvx_roe_m", "cvx_dv_rtn_mps"))
    m = held["index"].size if n is None else min(n, held["index"].size)
    safety = build_safety(art)
    # C_CVX(t_1) again under the current safety model (the labels may come from an older
    # pipeline version), so both sides are judged by the same evaluation
    c_cvx_now = np.array([safety.evaluate(held["cvx_roe_m"][i], held["cvx_dv_rtn_mps"][i])
                          .constraint_to_go[0] for i in range(m)])
    t0 = time.perf_counter()
    parts, batch = [], 50
    for s in tqdm(range(0, m, batch), desc=f"rollouts {Path(model_path).name}", unit="batch",
                  disable=not progress):
        sl = slice(s, min(s + batch, m))
        parts.append(evaluate_rollouts(art, safety, held["roe0_m"][sl], held["target_rtn"][sl],
                                       held["cvx_cost_mps"][sl], c_cvx_now[sl],
                                       batch_size=batch))
    wall = time.perf_counter() - t0
    c_art = np.concatenate([p.c_art for p in parts])
    c_cvx = np.concatenate([p.c_cvx for p in parts])
    e_r = np.concatenate([p.e_r for p in parts])
    accepted = np.concatenate([p.accepted for p in parts])
    return {
        "model": Path(model_path).name, "model_sha256": art.sha256,
        "representation": art.config.representation, "n_scenarios": int(m),
        "scenario_indices": [int(held["index"][0]), int(held["index"][m - 1])],
        "mode": "chance" if safety.uncertainty is not None else "deterministic",
        "c_art_t1": _distribution(c_art), "c_cvx_t1": _distribution(c_cvx),
        "c_cvx_label_agreement": float(np.mean(c_cvx == held["cvx_constraint_to_go0"][:m])),
        "frac_c_art_zero": float(np.mean(c_art == 0)),
        "frac_c_cvx_zero": float(np.mean(c_cvx == 0)),
        "frac_c_art_below_cvx": float(np.mean(c_art < c_cvx)),
        "frac_c_art_le_cvx": float(np.mean(c_art <= c_cvx)),
        "e_r": _distribution(e_r), "e_r_pct_median_abs": float(np.median(np.abs(100 * e_r))),
        "frac_posthoc_accepted": float(np.mean(accepted)),
        "c_art_histogram": np.bincount(c_art, minlength=int(c_art.max()) + 1).tolist(),
        "wall_s": wall, "rollouts_per_s": m / wall, "threads": threads,
    }


def evaluate_warmstart(data: dict, model_path: str, n: int | None, threads: int,
                       progress: bool = True) -> dict:
    """Warm-start suite of one model on the held-out split (`art_guidance.eval.warmstart`)."""
    import torch
    from tqdm import tqdm

    from art_guidance.art import build_safety, heldout_scenarios
    from art_guidance.art.provider import ArtWarmStart
    from art_guidance.config import GuidanceConfig
    from art_guidance.eval.warmstart import compare, summarize
    from art_guidance.planning import PlanRequest

    torch.set_num_threads(threads)
    provider = ArtWarmStart.load(model_path, threads=threads)
    safety = build_safety(provider.art)
    config = GuidanceConfig.load()
    held = heldout_scenarios(data)
    m = held["index"].size if n is None else min(n, held["index"].size)
    chief = safety.horizon.chief_oe[0]
    rows = []
    t0 = time.perf_counter()
    for i in tqdm(range(m), desc=f"warm starts {Path(model_path).name}", unit="scenario",
                  disable=not progress):
        req = PlanRequest(chief, held["roe0_m"][i], held["target_rtn"][i],
                          chance_constrained=safety.uncertainty is not None)
        rows.append(compare(req, safety, provider, config))
    wall = time.perf_counter() - t0
    return {"model": Path(model_path).name, "model_sha256": provider.sha256,
            "n_scenarios": m, "wall_s": wall, "scenarios_per_s": m / wall,
            **summarize(rows)}


def run(args: argparse.Namespace) -> int:
    """Evaluate trained models on the held-out (test) split of a dataset: each model is rolled
    out from every held-out scenario conditioned on R(t_1) = -J_CVX and C(t_1) = 0, and its
    realised C(t_1) and E_R are compared with the CVX solution of the same scenario (its C(t_1)
    evaluated again by the current safety model; the share agreeing with the dataset's label
    is reported). Writes OUT/rollouts.json."""
    from art_guidance.data.storage import load_dataset

    data = load_dataset(args.data)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.suite == "warmstart":
        report = {"data": str(args.data), "suite": args.suite,
                  "models": [evaluate_warmstart(data, m, args.n, args.threads,
                                                not args.no_progress) for m in args.model]}
        write_json_atomic(out / "warmstart.json", report)
        for r in report["models"]:
            d = r["auto_minus_scp_cvx_mps"]
            print(f"{r['model']} on {r['n_scenarios']} held-out scenarios: ART accepted "
                  f"{r['accepted']}; auto - PS-CVX cost [mm/s] min {1e3 * d['min']:.2f} median "
                  f"{1e3 * d['median']:.2f} max {1e3 * d['max']:.2f}; SCP iterations auto "
                  f"{r['iterations_auto_mean']:.1f} vs CVX {r['iterations_cvx_mean']:.1f}")
        print(f"report -> {out / 'warmstart.json'}")
        return 0
    report = {"data": str(args.data), "suite": args.suite,
              "models": [evaluate_model(data, m, args.n, args.threads, not args.no_progress)
                         for m in args.model]}
    write_json_atomic(out / "rollouts.json", report)
    for r in report["models"]:
        print(f"{r['model']} ({r['representation']}) on {r['n_scenarios']} held-out scenarios: "
              f"C(t1) median {r['c_art_t1']['median']:.0f} (CVX {r['c_cvx_t1']['median']:.0f}), "
              f"mean {r['c_art_t1']['mean']:.2f} (CVX {r['c_cvx_t1']['mean']:.2f}); "
              f"C(t1) = 0 in {100 * r['frac_c_art_zero']:.1f} % (CVX "
              f"{100 * r['frac_c_cvx_zero']:.1f} %); mean 100 E_R {100 * r['e_r']['mean']:.2f} "
              f"%; inside the post hoc region {100 * r['frac_posthoc_accepted']:.1f} %; "
              f"{r['rollouts_per_s']:.1f} rollouts/s")
    print(f"report -> {out / 'rollouts.json'}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("evaluate", help="held-out evaluation of trained models",
                       description=run.__doc__ + " Exit 0 done, 2 bad input.")
    p.add_argument("--data", required=True, help="dataset directory (its test split is used)")
    p.add_argument("--model", action="append", required=True,
                   help="checkpoint (repeat for several models)")
    p.add_argument("--suite", choices=["rollouts", "warmstart"], default="rollouts",
                   help="rollouts: ART rollouts against the CVX labels (OUT/rollouts.json); "
                   "warmstart: SCVx* from CVX and from ART per scenario, the post hoc "
                   "decision and the auto plan, by C_CVX(t1) bin (OUT/warmstart.json)")
    p.add_argument("--n", type=int, default=None, help="at most this many held-out scenarios "
                   "(the first by sample index)")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
