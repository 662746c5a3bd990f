"""`art-guidance distill`: a slim ART that imitates a trained teacher as the planner flies it."""
from __future__ import annotations

import argparse
import json
import shlex
import sys

from art_guidance.extras import TRAIN


def run(args: argparse.Namespace) -> int:
    """Distil a student (preset --student, default slim: 2 x 64) from a teacher checkpoint:
    the teacher rolls out its conditioning sweep on fresh scenarios (C update included) and
    the student learns its controls, conditioned the same way (art_guidance.art.distill)."""
    from art_guidance.art.distill import distill

    summary = distill(args.teacher, args.out, student=args.student, scenarios=args.scenarios,
                      first_seed=args.first_seed, epochs=args.epochs,
                      batch_size=args.batch_size, lr=args.lr, workers=args.workers,
                      threads=args.threads, seed=args.seed, progress=not args.no_progress,
                      command="art-guidance " + shlex.join(sys.argv[1:]))
    print(json.dumps(summary))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    from art_guidance.art.config import DISTILL_FIRST_SEED  # torch-free (--help, plan)

    p = sub.add_parser("distill", help="distil a slim ART from a trained one",
                       description=run.__doc__ + " The teacher's rollouts are kept beside the "
                       "output (<out>.sequences.npz) and reused by a re-run. Exit 0 done, 2 bad "
                       "input (an existing output, a teacher that does not load).")
    p.add_argument("teacher", help="the teacher checkpoint (.pt)")
    p.add_argument("--out", required=True, help="the student checkpoint to write (new file)")
    p.add_argument("--student", default="slim", help="the student's preset (default slim: 2 x "
                   "64, five tokens a step; slim1: the same with one packed token a step)")
    p.add_argument("--scenarios", type=int, default=1500,
                   help="fresh scenarios the teacher rolls out on (8 sequences each)")
    p.add_argument("--first-seed", type=int, default=DISTILL_FIRST_SEED,
                   help="first scenario seed (default apart from every dataset and benchmark)")
    p.add_argument("--epochs", type=int, default=8, help="passes over the sequences")
    p.add_argument("--batch-size", type=int, default=32, help="sequences per step")
    p.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (AdamW, cosine)")
    p.add_argument("--workers", type=int, default=2, help="processes for the teacher rollouts")
    p.add_argument("--threads", type=int, default=2, help="torch threads for the training")
    p.add_argument("--seed", type=int, default=0, help="training seed (split, order, init)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run, needs=TRAIN)
