"""`art-guidance dagger`: DAgger data aggregation for ART (expert re-solves from its rollouts)."""
from __future__ import annotations

import argparse
from pathlib import Path

from art_guidance.extras import TRAIN
from art_guidance.jobs import ENGINES


def run(args: argparse.Namespace) -> int:
    """Roll a trained ART model out on the train-split scenarios of a dataset and, at a random
    node k of each rollout (1..N-3, drawn from the seed and the sample index), re-solve the
    3-stage expert (CVX, collision avoidance, passive safety) from the state the model reached
    over the remaining horizon. Each sample is stored as a full row: the rollout's states and
    controls before k, the expert's from k on, with R, C and margins recomputed over the whole
    row and train_from = k, so that training learns only the expert's controls (the prefix is
    context). The output is a dataset directory of the source's mode and configuration with no
    test split: train on both with `art-guidance train --data SRC --data OUT --out CKPT`."""
    from art_guidance.data.dagger import dagger

    summary = dagger(args.out, args.model, args.data, args.n, seed=args.seed,
                     workers=args.workers, engine=args.engine, shard_size=args.shard_size,
                     batch=args.batch, ray_address=args.ray_address,
                     progress=not args.no_progress)
    if summary["status"] == "complete":
        from art_guidance.data.storage import SUMMARY

        print(f"summary -> {Path(args.out) / SUMMARY}")
    return 130 if summary["status"] == "interrupted" else 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser(
        "dagger", help="DAgger: expert re-solves from a model's rollouts (resumable, parallel)",
        description=run.__doc__ + " Every row depends on the model, the source dataset, "
        "--seed, --batch and its index alone: the engines, --workers and --shard-size give "
        "the same data. Re-running the same command resumes an interrupted run and does "
        "nothing on a complete one. Exit 0 done, 130 interrupted, 2 bad input or corrupt "
        "directory.")
    p.add_argument("--model", required=True, help="checkpoint to roll out (trained on data of "
                   "the source's mode and configuration)")
    p.add_argument("--data", required=True, help="source dataset directory (complete; only "
                   "its feasible train-split scenarios are used)")
    p.add_argument("--out", required=True, help="DAgger dataset directory (created or resumed)")
    p.add_argument("--n", type=int, required=True,
                   help="number of DAgger samples (the scenarios are cycled through if needed)")
    p.add_argument("--seed", type=int, default=0, help="seeds the takeover nodes k (>= 0)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes (local) or CPUs (local Ray instance); default: all CPUs")
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help="local process pool (default) or Ray ('pip install .[distributed]')")
    p.add_argument("--shard-size", type=int, default=32,
                   help="samples per task and shard (best a multiple of --batch)")
    p.add_argument("--batch", type=int, default=32,
                   help="rollouts per batch: samples gB..gB+B-1 are rolled out together (part "
                   "of the data's identity; a resume must keep it)")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster address (default: start a local instance; --model and "
                   "--data must be readable from every node)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run, needs=TRAIN)
