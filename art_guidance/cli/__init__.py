"""`art-guidance`: one command-line entry point with subcommands.

Each subcommand is a module of this package with `add_parser(sub)` and `run(args) -> int`; what
a command needs is imported inside its `run`, and no module imports ROS at load time, so
`plan`, `generate`, `replay` and `bench` never import rclpy (tested). A command that needs an
extra of the install (torch and onnx: `[train]`) names the modules in its parser
(`set_defaults(needs=extras.TRAIN)`); `main` checks them before it runs the command, so a
flight install (no torch) answers with the extra to install, exit 2 (`art_guidance.extras`).
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from typing import Sequence

from art_guidance import __version__
from art_guidance.errors import GuidanceError
from art_guidance.extras import require

SUBCOMMANDS = ("demo", "plan", "generate", "train", "distill", "dagger", "evaluate", "export",
               "replay", "bag", "bench", "node", "sim", "kernels")


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="art-guidance",
        description="Onboard rendezvous guidance: ART warm start, post hoc check, robust SCP.",
    )
    parser.add_argument("--version", action="version", version=f"art-guidance {__version__}")
    parser.add_argument("--numerics", choices=("compiled", "numpy"), default=None,
                        help="the per-step numerics of every plan this command makes, chosen "
                        "once here: compiled (numba kernels, loaded from their cache; the "
                        "numpy path while a cold cache compiles) or numpy (default: "
                        "planning.yaml's numerics)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        importlib.import_module(f"art_guidance.cli.{name}").add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (2 for bad input, 1 for failures)."""
    args = build_parser().parse_args(argv)
    try:
        require(f"art-guidance {args.command}", getattr(args, "needs", ()))
        _choose_numerics(args.numerics)
        return int(args.func(args))
    except GuidanceError as exc:
        print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0


def _choose_numerics(mode: str | None) -> None:
    """The process's numerics, chosen once at its entry (`kernels.choose`; None: the packaged
    planning.yaml's); the kernels load at the first plan, or at a command's warm-up."""
    from art_guidance import kernels
    from art_guidance.config import PlanningConfig

    kernels.choose(mode or PlanningConfig.from_yaml().numerics)
