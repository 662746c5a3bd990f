"""`art-guidance bench`: the benchmarks in benchmarks/."""
from __future__ import annotations

import argparse
import sys

from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic


def run(args: argparse.Namespace) -> int:
    """Run benchmarks from benchmarks/ and print medians and ratios against references."""
    import importlib
    import inspect
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "benchmarks"
    names = sorted(p.stem[len("bench_"):] for p in root.glob("bench_*.py"))
    if not names:
        raise InputError("bench", "benchmarks/ not found (run from a source checkout)")
    chosen = names if args.name == "all" else [args.name]
    if str(root) not in sys.path:  # benchmarks share modules (e.g. the cvxpy reference)
        sys.path.insert(0, str(root))
    extra = {dest: getattr(args, dest) for dest in _PASSED if getattr(args, dest) is not None}
    report = {}
    for name in chosen:
        path = root / f"bench_{name}.py"
        if not path.is_file():
            raise InputError("bench", f"unknown benchmark; choose from {names + ['all']}", name)
        # imported as itself (benchmarks/ on the path): its workers import it by that name
        module = importlib.import_module(f"bench_{name}")
        kwargs = {"repeats": args.repeats} if args.repeats else {}
        accepted = inspect.signature(module.run).parameters
        for dest, value in extra.items():
            if dest in accepted:
                kwargs[dest] = value
            elif args.name != "all":
                raise InputError(_PASSED[dest], f"benchmark {name} does not take it", value)
        print(f"== {name}")
        report[name] = module.run(**kwargs)
        for key, value in report[name].items():
            print(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")
    if args.json:
        write_json_atomic(args.json, report)
    return 0


_PASSED = {"out": "--out", "workers": "--workers", "engine": "--engine",
           "ray_address": "--ray-address", "seeds": "--seeds",
           "missed_per_seed": "--missed-per-seed", "first_seed": "--first-seed",
           "model": "--model", "reference": "--reference", "min_c_cvx": "--min-c-cvx",
           "horizons": "--horizons", "targets": "--targets", "trigger": "--trigger",
           "context": "--context", "configs": "--configs"}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser(
        "bench", help="run benchmarks", description=run.__doc__ + " Options after --json go "
        "to the benchmarks that take them (contingency), e.g. "
        "`art-guidance bench contingency --workers 2 --out out/contingency`.")
    p.add_argument("name", nargs="?", default="all", help="benchmark name or 'all'")
    p.add_argument("--repeats", type=int, default=None, help="samples per benchmark")
    p.add_argument("--json", default=None, help="also write the numbers as JSON")
    p.add_argument("--out", default=None, help="output directory of a resumable benchmark "
                   "(re-run the same command to resume)")
    p.add_argument("--workers", type=int, default=None, help="worker processes (or Ray CPUs)")
    p.add_argument("--engine", choices=("local", "ray"), default=None,
                   help="local process pool (default) or Ray")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (--engine ray)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per configuration")
    p.add_argument("--first-seed", type=int, default=None,
                   help="first seed of a seed range (closed_loop: seeds FIRST..FIRST+repeats-1)")
    p.add_argument("--missed-per-seed", type=int, default=None,
                   help="missed-burn flights per configuration and seed")
    p.add_argument("--model", default=None, help="the model a benchmark flies instead of the "
                   "shipped default (plan_auto, closed_loop, node; slim: the student), e.g. "
                   "benchmarks/results/slim/art_slim_chance_rtn.pt")
    p.add_argument("--reference", default=None, help="slim: the model measured in the "
                   "teacher's place (default the shipped model of the student's mode), e.g. "
                   "another student")
    p.add_argument("--min-c-cvx", type=int, default=None, metavar="N",
                   help="closed_loop: fly the hard family, the first --repeats seeds from "
                   "--first-seed whose initial CVX warm start violates passive safety at N or "
                   "more nodes, with the learned warm start against CVX only (mpc: the same "
                   "screen)")
    p.add_argument("--horizons", default=None, metavar="H,H,...",
                   help="mpc: the replan windows to fly [nodes], e.g. 10,20,40")
    p.add_argument("--targets", default=None, metavar="T,T",
                   help="mpc: the windows' terminal targets, art, cvx and/or carry (the "
                   "plan in force's state: a tracking MPC)")
    p.add_argument("--trigger", default=None, choices=("sigma", "every"),
                   help="mpc: replan on the node's deviation rule (and when half a window is "
                   "flown) or at every node")
    p.add_argument("--context", default=None, choices=("off", "on", "both"),
                   help="mpc: give the learned proposal the steps flown since the target was "
                   "set (T-MPC's context): off, on, or both (each configuration both ways)")
    p.add_argument("--configs", default=None, metavar="C,C,...",
                   help="closed_loop: fly these configurations on the same seeds, each "
                   "WARMSTART_REPLAN with WARMSTART cvx or auto and REPLAN fresh (every replan "
                   "from scratch) or carry (from the plan in force), paired against cvx_fresh, "
                   "e.g. cvx_fresh,auto_fresh,cvx_carry,auto_carry")
    p.set_defaults(func=run)
