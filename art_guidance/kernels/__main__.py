"""`python -m art_guidance.kernels`: compile the kernels into their cache (or load them from
it) and say where; exit 0 when the compiled path is ready from the cache, 1 when the numpy path
is taken or the cache is not filled (it cannot be written: a full disk, a quota, read-only;
or another filler held its lock too long, named by its pid).

The node and the one-shot commands start it in the background on a cold cache; a flight image
runs it once at build time, so that no flight computer ever compiles (`art-guidance kernels`
is the same step with the command-line's help)."""
from __future__ import annotations

import argparse
import sys

from art_guidance import kernels


def main(argv: list[str] | None = None) -> int:
    """Fill the cache (or, with --status, only say what is there); returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m art_guidance.kernels",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--status", action="store_true",
                        help="say where the cache is and whether it holds the kernels; compile "
                        "nothing")
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    args = parser.parse_args(argv)
    if args.status:
        text = kernels.cache_status()
    else:
        text = kernels.prepare("compiled", wait=True)
    if not args.quiet:
        print(text)
    if args.status:
        return 0
    # the cache not filled (a full disk, a read-only folder, a stalled filler holding its lock)
    # fails the build step, though this process compiled in memory
    return 0 if kernels.ready_s() is not None and not kernels.cache_problem() else 1


if __name__ == "__main__":
    sys.exit(main())
