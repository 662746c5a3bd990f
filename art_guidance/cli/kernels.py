"""`art-guidance kernels`: compile the numba kernels into their cache, or say what is there."""
from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    """Compile the kernels into the cache the node will use (or load them from it: nothing to
    do), and say where it is; the build step of a flight image, so that no flight computer
    compiles. Exit 0 when the compiled path is ready from the cache, 1 when the numpy path is
    taken (numba missing or failing) or the cache cannot be written (a full disk, a quota, a
    read-only file system: the kernels are compiled in memory and the cache left as it is);
    the reason is printed."""
    from art_guidance.kernels.__main__ import main

    return main(["--status"] if args.status else [])


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("kernels", help="compile the numba kernels into their cache (the build "
                       "step of a flight image)", description=run.__doc__)
    p.add_argument("--status", action="store_true",
                   help="say where the cache is and whether it holds the kernels (warm, cold "
                   "or damaged); compile nothing, exit 0")
    p.set_defaults(func=run)
