"""`art-guidance evaluate`: held-out evaluation of trained models against CVX."""
from __future__ import annotations

import argparse
import inspect
import sys
import time
from pathlib import Path

import numpy as np

from art_guidance.config import mode_name
from art_guidance.data.generate import ENGINES, default_workers
from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic


def _distribution(values: np.ndarray) -> dict:
    """min / quartiles / max / mean of a sample (JSON-ready)."""
    q = np.percentile(values, [0, 25, 50, 75, 100])
    return {"min": float(q[0]), "p25": float(q[1]), "median": float(q[2]), "p75": float(q[3]),
            "max": float(q[4]), "mean": float(np.mean(values))}


def _trained_on(art: object, data_dir: str) -> bool:
    """Whether the model's training data includes the dataset directory `data_dir`."""
    from art_guidance.art.data import manifest_digest, trained_manifests

    return manifest_digest(data_dir) in trained_manifests(art.meta)


def evaluate_model(data: dict, model_path: str, n: int | None, threads: int,
                   progress: bool = True, split: str = "test", data_dir: str | None = None,
                   oracle: bool = False, reward_scales: tuple[float, ...] = (1.0,)) -> dict:
    """Rollout suite of one model on the held-out scenarios of `data` (see `run`)."""
    import torch
    from tqdm import tqdm

    from art_guidance.art import build_safety, evaluate_rollouts, heldout_scenarios, load

    torch.set_num_threads(threads)
    art = load(model_path)
    if split == "all" and data_dir is not None and _trained_on(art, data_dir):
        raise InputError("--split", f"all scenarios of {data_dir} are not held out from "
                         f"{Path(model_path).name}: it was trained on that dataset")
    held = heldout_scenarios(data, ("cvx_roe_m", "cvx_dv_rtn_mps", "dv_rtn_mps", "feasible",
                                    "cost_mps", "constraint_to_go"), split)
    m = held["index"].size if n is None else min(n, held["index"].size)
    safety = build_safety(art)
    # C_CVX(t_1) again under the current safety model (the labels may come from an older
    # pipeline version), so both sides are judged by the same evaluation
    c_cvx_now = np.array([safety.evaluate(held["cvx_roe_m"][i], held["cvx_dv_rtn_mps"][i])
                          .constraint_to_go[0] for i in range(m)])
    report_oracle = _oracle(safety, held, m, c_cvx_now) if oracle else None
    t0 = time.perf_counter()
    parts, batch = [], 50
    for s in tqdm(range(0, m, batch), desc=f"rollouts {Path(model_path).name}", unit="batch",
                  disable=not progress):
        sl = slice(s, min(s + batch, m))
        parts.append(evaluate_rollouts(art, safety, held["roe0_m"][sl], held["target_rtn"][sl],
                                       held["cvx_cost_mps"][sl], c_cvx_now[sl],
                                       batch_size=batch, reward_scales=reward_scales))
    wall = time.perf_counter() - t0
    c_art = np.concatenate([p.c_art for p in parts])
    c_cvx = np.concatenate([p.c_cvx for p in parts])
    e_r = np.concatenate([p.e_r for p in parts])
    accepted = np.concatenate([p.accepted for p in parts])
    return {
        "model": Path(model_path).name, "model_sha256": art.sha256,
        "representation": art.config.representation, "n_scenarios": int(m),
        "scenario_indices": [int(held["index"][0]), int(held["index"][m - 1])],
        "mode": mode_name(safety.uncertainty is not None),
        "c_art_t1": _distribution(c_art), "c_cvx_t1": _distribution(c_cvx),
        "c_cvx_label_agreement": float(np.mean(c_cvx == held["cvx_constraint_to_go0"][:m])),
        "frac_c_art_zero": float(np.mean(c_art == 0)),
        "frac_c_cvx_zero": float(np.mean(c_cvx == 0)),
        "frac_c_art_below_cvx": float(np.mean(c_art < c_cvx)),
        "frac_c_art_le_cvx": float(np.mean(c_art <= c_cvx)),
        "e_r": _distribution(e_r), "e_r_pct_median_abs": float(np.median(np.abs(100 * e_r))),
        "e_r_pct_median": float(np.median(100 * e_r)),
        "e_r_pct_q90": float(np.percentile(100 * e_r, 90)),
        "frac_posthoc_accepted": float(np.mean(accepted)),
        "c_art_histogram": np.bincount(c_art, minlength=int(c_art.max()) + 1).tolist(),
        "wall_s": wall, "rollouts_per_s": m / wall, "threads": threads, "split": split,
        "reward_scales": list(reward_scales),
        "training": _training_summary(art),
        **({"oracle": report_oracle} if report_oracle is not None else {}),
    }


def _training_summary(art: object) -> dict:
    """What the model was trained on and how far (from its checkpoint's provenance)."""
    t = art.meta.get("training", {})
    d = art.meta.get("dataset", {})
    return {"preset": t.get("preset"), "config": art.config.to_dict(),
            "n_parameters": t.get("n_parameters"), "n_train": d.get("n_train"),
            "best_val_loss": t.get("best_val_loss"), "step": t.get("step"),
            "epoch": t.get("epoch"), "stop_reason": t.get("stop_reason"),
            "train_config": t.get("train_config")}


def _oracle(safety: object, held: dict, m: int, c_cvx_now: np.ndarray) -> dict:
    """A perfect model: the plans' own controls through the rollout machinery (`replay`)."""
    from art_guidance.art import evaluate_oracle

    ok = held["feasible"][:m]
    ev = evaluate_oracle(safety, held["roe0_m"][:m][ok], held["dv_rtn_mps"][:m][ok],
                         held["cvx_cost_mps"][:m][ok], c_cvx_now[ok])
    labels_c = held["constraint_to_go"][:m][ok][:, 0]
    labels_e_r = (held["cost_mps"][:m][ok] - held["cvx_cost_mps"][:m][ok]) \
        / held["cvx_cost_mps"][:m][ok]
    return {"n_scenarios": int(ok.sum()), "frac_c_zero": float(np.mean(ev.c_art == 0)),
            "frac_c_label_agreement": float(np.mean(ev.c_art == labels_c)),
            "e_r_pct_median": float(np.median(100 * ev.e_r)),
            "e_r_pct_q90": float(np.percentile(100 * ev.e_r, 90)),
            "e_r_max_abs_diff_to_labels": float(np.max(np.abs(ev.e_r - labels_e_r))),
            "frac_posthoc_accepted": float(np.mean(ev.accepted))}


def run(args: argparse.Namespace) -> int:
    """Evaluate trained models on the held-out (test) split of their datasets.

    --suite warmstart (the paper's warm-start analysis, section V): every model is evaluated on
    the test split of each --data dataset of its own mode (the mode of its training data: a
    deterministic model gives PS-CVX-D / PS-ART-D, a chance-constrained one PS-CVX-C /
    PS-ART-C). Per scenario: CVX, the ART rollout conditioned on R(t1) = -J_CVX, C(t1) = 0 and
    its post hoc check (E_R, E_C), SCVx* from CVX and from ART. OUT/summary.json gives per model
    and per cumulative bin of C_CVX(t1) (>= 0, 10, 20, 30, 40) the absolute suboptimality
    J_SCP - J_CVX, the improvement ratio (J_SCP,CVX - J_SCP,ART) / (J_SCP,CVX - J_CVX), SCP
    iterations, median runtimes (warm start + SCP, measured in the same worker), the
    infeasibility rate (infeasible or not converged); the histogram of J_SCP,CVX - J_SCP,ART
    with its min and max, without and with the post hoc check; the (E_R, E_C) maps; checksums,
    sizes and throughput (scenarios/s). OUT/figures/*.png are the paper's figures, including
    the scenario with the largest ART gain (solved once more). Scenarios run on --workers
    processes (1 torch thread each) or Ray, and are committed to OUT in shards: re-running the
    same command resumes an interrupted run; another command on the same OUT is refused.
    --figures-only re-renders summary.json and the figures from OUT without solving.

    --suite rollouts: each model is rolled out from every held-out scenario and its realised
    C(t1) and E_R are compared with the CVX solution of the same scenario (its C(t1)
    evaluated again by the current safety model; the share agreeing with the dataset's label
    is reported), with the median and q90 of 100 E_R, the share with C(t1) = 0 and the share
    inside the post hoc region. The oracle row drives the same machinery with the plans' own
    controls (a perfect model). One --data; writes OUT/rollouts.json.
    """
    try:
        if args.figures_only:
            return _figures_only(args)
        if not args.data or not args.model:
            raise InputError("--data/--model", "both are required (except with --figures-only)")
        if args.suite == "warmstart":
            return _warmstart(args)
        return _rollouts(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _warmstart(args: argparse.Namespace) -> int:
    from art_guidance.eval.runner import evaluate

    summary = evaluate(args.out, args.data, args.model, n=args.n,
                       workers=args.workers or default_workers(), engine=args.engine,
                       ray_address=args.ray_address, shard_size=args.shard_size,
                       figures=not args.no_figures, progress=not args.no_progress,
                       command=["art-guidance", *sys.argv[1:]], split=args.split,
                       single_rollout=args.single_rollout)
    print(f"summary -> {Path(args.out) / 'summary.json'}")
    return 130 if summary["status"] == "interrupted" else 0


def _figures_only(args: argparse.Namespace) -> int:
    from art_guidance.data.storage import MANIFEST
    from art_guidance.eval.runner import rerender

    if not (Path(args.out) / MANIFEST).is_file():
        raise InputError("--out", "holds no evaluation to render", args.out)
    rerender(args.out)
    return 0


def _rollouts(args: argparse.Namespace) -> int:
    from art_guidance.data.storage import load_dataset

    if len(args.data) != 1:
        raise InputError("--data", "the rollouts suite takes one dataset", args.data)
    data = load_dataset(args.data[0])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scales = (1.0,)
    if args.sweep:
        from art_guidance.art.provider import DEFAULT_REWARD_SCALES as scales
    report = {"data": str(args.data[0]), "suite": args.suite, "split": args.split,
              "models": [evaluate_model(data, m, args.n, args.threads, not args.no_progress,
                                        args.split, args.data[0], oracle=i == 0,
                                        reward_scales=tuple(scales))
                         for i, m in enumerate(args.model)]}
    o = report["models"][0]["oracle"]
    print(f"oracle (the plans' own controls through the rollout) on {o['n_scenarios']} "
          f"scenarios: C(t1) = 0 in {100 * o['frac_c_zero']:.1f} %, agreeing with the labels in "
          f"{100 * o['frac_c_label_agreement']:.1f} %; median 100 E_R "
          f"{o['e_r_pct_median']:.2f} % (q90 {o['e_r_pct_q90']:.2f} %), equal to the labels' "
          f"within {o['e_r_max_abs_diff_to_labels']:.1e}")
    write_json_atomic(out / "rollouts.json", report)
    for r in report["models"]:
        print(f"{r['model']} ({r['representation']}) on {r['n_scenarios']} held-out scenarios: "
              f"C(t1) median {r['c_art_t1']['median']:.0f} (CVX {r['c_cvx_t1']['median']:.0f}), "
              f"mean {r['c_art_t1']['mean']:.2f} (CVX {r['c_cvx_t1']['mean']:.2f}); "
              f"C(t1) = 0 in {100 * r['frac_c_art_zero']:.1f} % (CVX "
              f"{100 * r['frac_c_cvx_zero']:.1f} %); 100 E_R median {r['e_r_pct_median']:.2f} "
              f"% (q90 {r['e_r_pct_q90']:.2f} %); inside the post hoc region "
              f"{100 * r['frac_posthoc_accepted']:.1f} %; "
              f"{r['rollouts_per_s']:.1f} rollouts/s")
    print(f"report -> {out / 'rollouts.json'}")
    return 0


_EPILOG = """\
examples:
  art-guidance evaluate --data data/chance --data data/deterministic \\
      --model roe_c.pt --model rtn_c.pt --model roe_d.pt --model rtn_d.pt \\
      --n 1000 --workers 8 --out eval/paper     (Ctrl-C, then the same command resumes)
  art-guidance evaluate --figures-only --out eval/paper
  art-guidance evaluate --suite rollouts --data data/chance --model roe_c.pt --out eval/rollouts
  art-guidance evaluate --suite rollouts --sweep --data data/fresh --split all \\
      --model roe_c.pt --out eval/inflight     (what the node proposes, on a never-seen seed)

exit codes: 0 done, 130 interrupted (re-run the same command to resume), 2 bad input (e.g. a
model whose mode matches no dataset, an OUT holding another evaluation or a dataset, a corrupt
dataset or checkpoint).
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("evaluate", help="held-out evaluation of trained models against CVX",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description=inspect.cleandoc(run.__doc__), epilog=_EPILOG)
    p.add_argument("--data", action="append", default=[],
                   help="dataset directory, its test split is used (repeat: e.g. a chance and "
                   "a deterministic dataset; each model uses those of its mode)")
    p.add_argument("--model", action="append", default=[],
                   help="checkpoint (repeat for several models, e.g. ROE and RTN, -C and -D)")
    p.add_argument("--suite", choices=["rollouts", "warmstart"], default="warmstart",
                   help="warmstart (default): the paper's warm-start analysis (CVX, PS-CVX, "
                   "PS-ART per scenario; resumable, parallel; OUT/summary.json, OUT/figures); "
                   "rollouts: ART rollouts against the CVX labels (OUT/rollouts.json)")
    p.add_argument("--n", type=int, default=None, help="at most this many held-out scenarios "
                   "per model and dataset (the first by sample index); default: all")
    p.add_argument("--out", required=True, help="output directory (warmstart: created, or "
                   "resumed if it holds the same evaluation)")
    p.add_argument("--workers", type=int, default=None,
                   help="warmstart: processes (local; 1 = in this process) or CPUs (local Ray "
                   "instance), 1 torch thread each; default: all CPUs")
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help="warmstart: local process pool (default) or Ray "
                   "('pip install .[distributed]')")
    p.add_argument("--ray-address", default=None,
                   help="warmstart: Ray cluster address (default: start a local instance)")
    p.add_argument("--shard-size", type=int, default=4,
                   help="warmstart: scenarios per task and per committed shard")
    p.add_argument("--figures-only", action="store_true",
                   help="warmstart: rebuild OUT/summary.json and OUT/figures from the stored "
                   "results without solving (no --data/--model needed)")
    p.add_argument("--no-figures", action="store_true",
                   help="warmstart: skip the figures and the example scenario")
    p.add_argument("--threads", type=int, default=2, help="rollouts: torch threads")
    p.add_argument("--sweep", action="store_true",
                   help="rollouts: judge the candidate the in-flight provider proposes (one "
                   "rollout per R(t_1) = -s J_CVX of its conditioning sweep, the best by the "
                   "post hoc criteria) instead of the model's single rollout at s = 1")
    p.add_argument("--single-rollout", action="store_true",
                   help="warmstart: the paper's single rollout at R(t_1) = -J_CVX instead of the "
                   "in-flight provider's conditioning sweep (the default, as the node flies)")
    p.add_argument("--split", choices=("test", "all"), default="test",
                   help="the datasets' test split (default), or all their scenarios (datasets "
                   "generated with a seed the models never saw; refused for a dataset a model "
                   "was trained on)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
