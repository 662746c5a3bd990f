"""`art-guidance evaluate`: held-out evaluation of trained models against CVX."""
from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

from art_guidance.jobs import ENGINES, default_workers
from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic


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
    from art_guidance.eval.runner import run_evaluation

    summary = run_evaluation(args.out, args.data, args.model, n=args.n,
                             workers=args.workers or default_workers(), engine=args.engine,
                             ray_address=args.ray_address, shard_size=args.shard_size,
                             figures=not args.no_figures, progress=not args.no_progress,
                             command=["art-guidance", *sys.argv[1:]], split=args.split,
                             single_rollout=args.single_rollout)
    print(f"summary -> {Path(args.out) / 'summary.json'}")
    return 130 if summary["status"] == "interrupted" else 0


def _figures_only(args: argparse.Namespace) -> int:
    from art_guidance.data.storage import MANIFEST
    from art_guidance.eval.results import rerender

    if not (Path(args.out) / MANIFEST).is_file():
        raise InputError("--out", "holds no evaluation to render", args.out)
    rerender(args.out)
    return 0


def _rollouts(args: argparse.Namespace) -> int:
    from art_guidance.eval.suite import evaluate_model
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
                   "was trained on, or one of a seed whose scenarios it was trained on where "
                   "its provenance records the seeds)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
