"""`art-guidance generate`: the paper's 3-stage dataset, sharded and resumable."""
from __future__ import annotations

import argparse
from pathlib import Path

from art_guidance.config import MODES
from art_guidance.jobs import ENGINES
from art_guidance.scenarios import SEED_STRIDE


def run(args: argparse.Namespace) -> int:
    """Generate a trajectory dataset with the paper's 3-stage pipeline (resumable)."""
    from art_guidance.config import GuidanceConfig, ScenarioConfig
    from art_guidance.data.generate import generate
    from art_guidance.data.storage import SUMMARY

    config = GuidanceConfig.load()
    if args.scenario:
        config = config.replace(scenario=ScenarioConfig.from_yaml(args.scenario))
    summary = generate(args.out, args.n, args.mode, base_seed=args.seed, workers=args.workers,
                       engine=args.engine, shard_size=args.shard_size, config=config,
                       ray_address=args.ray_address, progress=not args.no_progress)
    if summary["status"] == "complete":
        print(f"summary -> {Path(args.out) / SUMMARY}")
    return 130 if summary["status"] == "interrupted" else 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser(
        "generate", help="generate a trajectory dataset (3-stage, resumable, parallel)",
        description=run.__doc__ + " Re-running the same command resumes an "
        "interrupted run and does nothing on a complete one. Exit 0 done, 130 interrupted, "
        "2 bad input or corrupt directory.")
    p.add_argument("--n", type=int, required=True, help="number of samples")
    p.add_argument("--mode", choices=MODES, required=True,
                   help="stage-3 passive safety: deterministic or chance-constrained")
    p.add_argument("--out", required=True, help="dataset directory (created or resumed)")
    p.add_argument("--seed", type=int, default=0,
                   help=f"dataset seed S >= 0; sample i uses scenario seed S * {SEED_STRIDE} + i")
    p.add_argument("--workers", type=int, default=None,
                   help="processes (local) or CPUs (local Ray instance); default: all CPUs")
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help="local process pool (default) or Ray ('pip install .[distributed]')")
    p.add_argument("--shard-size", type=int, default=32, help="samples per task and shard")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster address (default: start a local instance)")
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
