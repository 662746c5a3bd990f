"""`art-guidance train`: train the Autonomous Rendezvous Transformer on generated datasets."""
from __future__ import annotations

import argparse
import shlex
import sys

from art_guidance.extras import TRAIN

# art_guidance.art.config.PRESETS (import-free)
_PRESETS = ("small", "medium", "paper", "slim", "slim1", "tiny")
_DAGGER_REWARDS = ("hindsight", "fed")  # art_guidance.art.config.DAGGER_REWARDS (import-free)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `train` on the `art-guidance` subparsers (cheap: imports no torch)."""
    p = sub.add_parser(
        "train", help="train the ART model on dataset directories (resumable, data parallel)",
        description="Train the Autonomous Rendezvous Transformer on the train split of one or "
        "more datasets written by `art-guidance generate` (the test split is never read; a "
        "seeded share of the train split validates and early-stops). Writes OUT (best "
        "weights, config, normalisation, dataset checksums, this command) and OUT.state "
        "(resume state) atomically at every validation pass; re-running the same command "
        "resumes after a kill. Deterministic for a seed on CPU at a fixed thread count; uses "
        "CUDA when present. Data parallel: torchrun --standalone --nproc_per_node P -m "
        "art_guidance.cli train ... (gloo on CPU, NCCL on GPUs). Exit 0 done or stopped at a "
        "limit, 130 interrupted, 2 bad input.")
    p.add_argument("--data", action="append", required=True, metavar="DIR",
                   help="dataset directory (repeat for several of the same mode and config)")
    p.add_argument("--preset", choices=_PRESETS, default="small",
                   help="model size: small (default: 3 layers x 96, 0.35 M parameters, trains "
                   "on CPU), medium (6 x 192, 2.7 M), paper (6 x 384, 10.6 M, the paper's "
                   "appendix), slim (2 x 64), slim1 (2 x 64, one packed token a step instead "
                   "of five), tiny (tests)")
    p.add_argument("--repr", choices=("roe", "rtn"), default="roe", dest="representation",
                   help="state representation: ROE (a-scaled, m) or RTN (Psi x)")
    p.add_argument("--out", required=True, help="checkpoint path (OUT.state holds the resume "
                   "state)")
    p.add_argument("--seed", type=int, default=0, help="weights, validation split, batches")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this wall time (resumable); default: no limit")
    p.add_argument("--max-steps", type=int, default=None,
                   help="stop at this optimiser step (resumable; smoke runs)")
    p.add_argument("--epochs", type=int, default=None, dest="max_epochs",
                   help="maximum epochs (preset default 200; early stopping usually ends first)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="global batch (preset: 32, the paper's effective 4 x 8)")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate (preset)")
    p.add_argument("--eval-every", type=int, default=None,
                   help="steps between validation passes and checkpoints (default: 1 epoch)")
    p.add_argument("--patience", type=int, default=None,
                   help="validation passes without improvement before stopping (default 10)")
    p.add_argument("--min-lr-ratio", type=float, default=None,
                   help="final learning rate as a share of the peak (cosine decay over the "
                   "epochs; 1 keeps it constant; preset 0.1)")
    p.add_argument("--warmup-steps", type=int, default=None, help="linear warm-up steps")
    p.add_argument("--normalization", choices=("feature", "timestep"), default=None,
                   help="z-score states and controls per feature (default) or per time step "
                   "(the original ART)")
    p.add_argument("--burn-gate", action="store_true", default=None,
                   help="add a burn/no-burn gate to the control head (cross-entropy against "
                   "||u|| > --burn-threshold); rollouts coast where it says no burn")
    p.add_argument("--burn-threshold", type=float, default=None, dest="burn_threshold_mps",
                   help="what counts as a burn for the gate [m/s] (default 0.001)")
    p.add_argument("--gate-weight", type=float, default=None,
                   help="weight of the gate's cross-entropy in the loss (default 0.1)")
    p.add_argument("--max-train", type=int, default=None,
                   help="use at most this many training trajectories (learning curves)")
    p.add_argument("--dagger-max-cost-ratio", type=float, default=None,
                   help="skip DAgger rows whose expert costs more from its takeover node on "
                   "than this many times the scenario's J_CVX (default 0: keep all; the late "
                   "takeovers of a drifted rollout need recovery burns far outside the plans')")
    p.add_argument("--dagger-reward", choices=_DAGGER_REWARDS, default=None,
                   help="reward-to-go of the DAgger rows: hindsight (default: -the stitched "
                   "row's cost from each node on) or fed (-J_CVX plus what the row spent "
                   "before each node: the context the rollout was fed, the expert's suffix "
                   "following it)")
    p.add_argument("--precision", choices=("fp32", "bf16"), default=None,
                   help="bf16: autocast the forward pass on CUDA (default fp32)")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="default: CUDA when available")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per process (default: torch's choice)")
    p.add_argument("--init", default=None, metavar="MODEL",
                   help="fine-tune: start from this trained checkpoint's weights and keep its "
                   "normalisation (--preset, --repr, --normalization and --burn-gate must "
                   "describe it; the data must be of its mode and configuration); its "
                   "validation loss is the best to beat, so OUT is MODEL if no epoch improves")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run, needs=TRAIN)


def run(args: argparse.Namespace) -> int:
    """Train as asked; returns 0 when done or at a limit, 130 when interrupted.

    Raises:
        GuidanceError: bad input (InputError, ConfigError), a corrupt dataset or training
            state; the CLI's handler turns it into exit code 2.
    """
    import torch

    from art_guidance.art.train import TrainOptions, train
    from art_guidance.errors import InputError

    if args.threads is not None:
        if args.threads < 1:
            raise InputError("--threads", "must be >= 1", args.threads)
        torch.set_num_threads(args.threads)
    if args.max_steps is not None and args.max_steps < 1:
        raise InputError("--max-steps", "must be >= 1", args.max_steps)
    overrides = {k: getattr(args, k) for k in (
        "max_epochs", "batch_size", "lr", "eval_every", "patience", "min_lr_ratio",
        "warmup_steps", "burn_threshold_mps", "gate_weight", "max_train", "precision",
        "dagger_max_cost_ratio", "dagger_reward")}
    model_overrides = {"normalization": args.normalization, "burn_gate": args.burn_gate}
    opts = TrainOptions(data=tuple(args.data), out=args.out, preset=args.preset,
                        representation=args.representation, seed=args.seed,
                        max_minutes=args.max_minutes, max_steps=args.max_steps,
                        overrides={k: v for k, v in overrides.items() if v is not None},
                        model_overrides={k: v for k, v in model_overrides.items()
                                         if v is not None},
                        progress=not args.no_progress, device=args.device,
                        command=shlex.join(["art-guidance", *sys.argv[1:]]), init=args.init)
    summary = train(opts)
    return 130 if summary["stop_reason"] == "interrupted" else 0
