"""`art-guidance`: one command-line entry point with subcommands."""
from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

import numpy as np

from art_guidance import __version__
from art_guidance.errors import GuidanceError

Handler = Callable[[argparse.Namespace], int]


def _cmd_demo(args: argparse.Namespace) -> int:
    """Free-drift propagation of the paper's nominal initial state (no maneuvers)."""
    from art_guidance.config import ScenarioConfig
    from art_guidance.dynamics import Horizon, time_grid_s

    scenario = ScenarioConfig.from_yaml(args.scenario)
    chief = np.array(scenario.chief_oe)
    horizon = Horizon.build(chief, time_grid_s(chief[0], scenario.n_orbits, scenario.n_nodes))
    roe0 = np.linalg.solve(horizon.psi[0], np.array(scenario.rtn0_nominal))
    roe = horizon.propagate(roe0, np.zeros((horizon.n_nodes, 3)))
    rtn = horizon.to_rtn(roe)
    rng = np.linalg.norm(rtn[:, :3], axis=1)
    print(f"free drift over {scenario.n_orbits} orbits, {horizon.n_nodes} nodes")
    print(f"{'t [s]':>9} {'r_R [m]':>10} {'r_T [m]':>10} {'r_N [m]':>10} {'range [m]':>10}")
    for k in range(0, horizon.n_nodes, max(1, horizon.n_nodes // 10)):
        t = horizon.epochs_s[k]
        print(f"{t:9.1f} {rtn[k, 0]:10.1f} {rtn[k, 1]:10.1f} {rtn[k, 2]:10.1f} {rng[k]:10.1f}")
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main demonstration",
                       description=_cmd_demo.__doc__)
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.set_defaults(func=_cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="art-guidance",
        description="Onboard rendezvous guidance: ART warm start, post hoc check, robust SCP.",
    )
    parser.add_argument("--version", action="version", version=f"art-guidance {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_demo]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (2 for bad input, 1 for failures)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except GuidanceError as exc:
        print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
